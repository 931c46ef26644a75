"""Scenes: the declarative input of every simulator (shapes, materials, elements, checks,
TOML files, builders of common scene families)."""
from diffgns.scene.core import EFFECT_ORDER, Scene
from diffgns.scene.elements import (
    WALL_KINDS,
    WALL_NAMES,
    WALL_NAMES_3D,
    Body,
    BoxObstacle,
    Wall,
    Walls,
)
from diffgns.scene.materials import Elastic, Fluid, Material, Sand
from diffgns.scene.shapes import Box, Cylinder, Polygon, Rectangle, Shape

__all__ = [
    "EFFECT_ORDER", "WALL_KINDS", "WALL_NAMES", "WALL_NAMES_3D", "Body", "Box", "BoxObstacle",
    "Cylinder", "Elastic", "Fluid", "Material", "Polygon", "Rectangle", "Sand", "Scene", "Shape",
    "Wall", "Walls",
]
