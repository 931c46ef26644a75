"""Scene elements: walls, box obstacles and bodies (frozen, validated on construction).

Geometry in m, velocities in m/s.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from diffgns.errors import SceneError
from diffgns.scene.materials import Material
from diffgns.scene.shapes import Shape

WALL_KINDS = ("sticky", "slip", "friction")
WALL_NAMES = ("left", "right", "bottom", "top")


@dataclass(frozen=True)
class Wall:
    """Boundary condition of a wall or obstacle face.

    kind: "sticky" (no motion), "slip" (no penetration, no friction) or "friction"
    (no penetration, Coulomb friction with coefficient ``mu`` >= 0).
    """

    kind: str = "slip"
    mu: float = 0.0

    def __post_init__(self):
        if self.kind not in WALL_KINDS:
            raise SceneError(f"Wall.kind = {self.kind!r} is unknown; use one of {WALL_KINDS}")
        if not (isinstance(self.mu, (int, float)) and math.isfinite(self.mu) and self.mu >= 0):
            raise SceneError(f"Wall.mu = {self.mu!r} must be a finite number >= 0")
        if self.kind != "friction" and self.mu != 0:
            raise SceneError(
                f"Wall.mu = {self.mu} given for a {self.kind!r} wall; set kind='friction' "
                "to use a friction coefficient"
            )


@dataclass(frozen=True)
class Walls:
    """The four walls of the domain box."""

    left: Wall = Wall()
    right: Wall = Wall()
    bottom: Wall = Wall()
    top: Wall = Wall()

    def __iter__(self):
        return iter((self.left, self.right, self.bottom, self.top))

    @staticmethod
    def all(kind: str = "slip", mu: float = 0.0) -> Walls:
        w = Wall(kind, mu)
        return Walls(w, w, w, w)


@dataclass(frozen=True)
class BoxObstacle:
    """A static rigid axis-aligned box [x0, x1] x [y0, y1] (m) with a surface condition."""

    x0: float
    y0: float
    x1: float
    y1: float
    surface: Wall = Wall("sticky")

    def __post_init__(self):
        if not (self.x1 > self.x0 and self.y1 > self.y0):
            raise SceneError(
                f"BoxObstacle needs x1 > x0 and y1 > y0, got ({self.x0}, {self.y0}, "
                f"{self.x1}, {self.y1})"
            )

    def contains(self, p: np.ndarray) -> np.ndarray:
        return (p[:, 0] > self.x0) & (p[:, 0] < self.x1) & (p[:, 1] > self.y0) & (p[:, 1] < self.y1)


@dataclass(frozen=True)
class Body:
    """A body filled with particles.

    Args:
        shape: a Rectangle or Polygon (m).
        material: Elastic, Sand or Fluid.
        velocity: initial velocity (vx, vy), m/s.
        particles_per_cell: particles per grid cell, a perfect square (1, 4, 9, 16, ...).
        name: optional label.
    """

    shape: Shape
    material: Material
    velocity: tuple[float, float] = (0.0, 0.0)
    particles_per_cell: int = 4
    name: str = ""

    def __post_init__(self):
        ppc = self.particles_per_cell
        if not (isinstance(ppc, int) and ppc >= 1 and int(round(math.sqrt(ppc))) ** 2 == ppc):
            raise SceneError(
                f"Body {self.name!r}: particles_per_cell = {ppc!r} must be a perfect square "
                "(1, 4, 9, 16, ...) so particles sit on a regular sub-lattice"
            )
        if len(self.velocity) != 2 or not all(math.isfinite(v) for v in self.velocity):
            raise SceneError(f"Body {self.name!r}: velocity must be two finite numbers (m/s)")
        object.__setattr__(self, "velocity", tuple(float(v) for v in self.velocity))
