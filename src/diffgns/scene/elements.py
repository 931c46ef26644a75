"""Scene elements: walls, box obstacles and bodies (frozen, validated on construction).

Geometry in m, velocities in m/s. In 3D, y is vertical (as in 2D) and z the depth axis:
the box has two more walls, ``back`` (z min) and ``front`` (z max).
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
WALL_NAMES_3D = WALL_NAMES + ("back", "front")


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
    """The walls of the domain box: four in 2D; in 3D also ``back`` (z min) and ``front``
    (z max), slip when not given. Iterating gives the four 2D walls; :meth:`of` gives the
    walls of a dimension."""

    left: Wall = Wall()
    right: Wall = Wall()
    bottom: Wall = Wall()
    top: Wall = Wall()
    back: Wall | None = None
    front: Wall | None = None

    def __iter__(self):
        return iter((self.left, self.right, self.bottom, self.top))

    def of(self, dim: int) -> tuple[Wall, ...]:
        """The 2 ``dim`` walls in the order of :data:`WALL_NAMES_3D` (unset back/front: slip)."""
        if dim == 2:
            return tuple(self)
        return (*self, self.back or Wall(), self.front or Wall())

    @property
    def depth_walls_set(self) -> bool:
        """True if back or front was given and differs from the four others (an error in 2D:
        a 2D box has no depth walls)."""
        same = all(w == self.left for w in self)
        return any(w is not None and not (same and w == self.left)
                   for w in (self.back, self.front))

    @staticmethod
    def all(kind: str = "slip", mu: float = 0.0) -> Walls:
        """Every wall (four in 2D, six in 3D) of the given kind."""
        w = Wall(kind, mu)
        return Walls(w, w, w, w, w, w)


@dataclass(frozen=True)
class BoxObstacle:
    """A static rigid axis-aligned box [x0, x1] x [y0, y1] (m) with a surface condition;
    in 3D also [z0, z1] (give both z0 and z1)."""

    x0: float
    y0: float
    x1: float
    y1: float
    surface: Wall = Wall("sticky")
    z0: float | None = None
    z1: float | None = None

    def __post_init__(self):
        if not (self.x1 > self.x0 and self.y1 > self.y0):
            raise SceneError(
                f"BoxObstacle needs x1 > x0 and y1 > y0, got ({self.x0}, {self.y0}, "
                f"{self.x1}, {self.y1})"
            )
        if (self.z0 is None) != (self.z1 is None):
            raise SceneError("BoxObstacle: give both z0 and z1 (3D) or neither (2D)")
        if self.z0 is not None and self.z1 is not None and not self.z1 > self.z0:
            raise SceneError(f"BoxObstacle needs z1 > z0, got ({self.z0}, {self.z1})")

    @property
    def dim(self) -> int:
        return 2 if self.z0 is None else 3

    @property
    def lower(self) -> tuple[float, ...]:
        """Lowest corner (x0, y0[, z0]), m."""
        return (self.x0, self.y0) if self.z0 is None else (self.x0, self.y0, self.z0)

    @property
    def upper(self) -> tuple[float, ...]:
        """Highest corner (x1, y1[, z1]), m."""
        return (self.x1, self.y1) if self.z1 is None else (self.x1, self.y1, self.z1)

    def contains(self, p: np.ndarray) -> np.ndarray:
        """Points (n, d) strictly inside."""
        return np.all((p > np.array(self.lower)) & (p < np.array(self.upper)), axis=1)


@dataclass(frozen=True)
class Body:
    """A body filled with particles.

    Args:
        shape: a Rectangle or Polygon (2D), Box or Cylinder (3D), m.
        material: Elastic, Sand or Fluid.
        velocity: initial velocity (vx, vy[, vz]), m/s; default at rest.
        particles_per_cell: particles per grid cell, a perfect square in 2D (1, 4, 9, 16,
            ...), a perfect cube in 3D (1, 8, 27, ...); default 4 in 2D, 8 in 3D.
        name: optional label.
    """

    shape: Shape
    material: Material
    velocity: tuple[float, ...] | None = None
    particles_per_cell: int | None = None
    name: str = ""

    def __post_init__(self):
        d = self.shape.dim
        if self.particles_per_cell is None:
            object.__setattr__(self, "particles_per_cell", 4 if d == 2 else 8)
        ppc = self.particles_per_cell
        side = round(ppc ** (1.0 / d)) if isinstance(ppc, int) and ppc >= 1 else 0
        if not (isinstance(ppc, int) and ppc >= 1 and side ** d == ppc):
            kind, ex = ("square", "1, 4, 9, 16") if d == 2 else ("cube", "1, 8, 27, 64")
            raise SceneError(
                f"Body {self.name!r}: particles_per_cell = {ppc!r} must be a perfect {kind} "
                f"({ex}, ...) in {d}D so particles sit on a regular sub-lattice"
            )
        v = (0.0,) * d if self.velocity is None else self.velocity
        if (not isinstance(v, tuple | list) or len(v) != d
                or not all(isinstance(c, int | float) and math.isfinite(c) for c in v)):
            raise SceneError(f"Body {self.name!r}: velocity must be {d} finite numbers (m/s) "
                             f"for a {d}D shape, got {v!r}")
        object.__setattr__(self, "velocity", tuple(float(c) for c in v))
