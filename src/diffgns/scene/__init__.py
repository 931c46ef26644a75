"""Scenes: the declarative input of every simulator (shapes, materials, elements, checks,
TOML files, builders of common scene families)."""
from diffgns.scene.core import EFFECT_ORDER, Scene
from diffgns.scene.elements import WALL_KINDS, WALL_NAMES, Body, BoxObstacle, Wall, Walls
from diffgns.scene.materials import Elastic, Fluid, Material, Sand
from diffgns.scene.shapes import Polygon, Rectangle, Shape

__all__ = [
    "EFFECT_ORDER", "WALL_KINDS", "WALL_NAMES", "Body", "BoxObstacle", "Elastic", "Fluid",
    "Material", "Polygon", "Rectangle", "Sand", "Scene", "Shape", "Wall", "Walls",
]
