"""Body shapes and particle filling (m): Rectangle and Polygon in 2D, Box and Cylinder in 3D.

Every shape has ``dim``, ``lower``/``upper`` (bounding-box corners), ``fill(dx, ppc)`` ->
(positions (n, dim) m, volumes (n,) m^dim) and ``contains(points (n, dim))``. In 3D, y is
vertical: a Cylinder stands on the y axis.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from diffgns.errors import SceneError


def _lattice(lo: float, hi: float, h: float) -> np.ndarray:
    """Cell-centred lattice of spacing ~h filling [lo, hi] exactly."""
    n = max(1, int(round((hi - lo) / h)))
    return lo + (np.arange(n) + 0.5) * (hi - lo) / n


@dataclass(frozen=True)
class Rectangle:
    """Axis-aligned rectangle [x0, x1] x [y0, y1], m."""

    x0: float
    y0: float
    x1: float
    y1: float

    dim = 2

    def __post_init__(self):
        vals = (self.x0, self.y0, self.x1, self.y1)
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in vals):
            raise SceneError(f"Rectangle corners must be finite numbers, got {vals}")
        if not (self.x1 > self.x0 and self.y1 > self.y0):
            raise SceneError(f"Rectangle needs x1 > x0 and y1 > y0, got {vals}")

    @property
    def bbox(self) -> tuple[float, float, float, float]:
        return (self.x0, self.y0, self.x1, self.y1)

    @property
    def lower(self) -> tuple[float, ...]:
        return (self.x0, self.y0)

    @property
    def upper(self) -> tuple[float, ...]:
        return (self.x1, self.y1)

    @property
    def area(self) -> float:
        return (self.x1 - self.x0) * (self.y1 - self.y0)

    def fill(self, dx: float, ppc: int) -> tuple[np.ndarray, np.ndarray]:
        """Particles on a regular sub-lattice: positions (n, 2) m and volumes (n,) m^2."""
        h = dx / math.isqrt(ppc)
        xs, ys = _lattice(self.x0, self.x1, h), _lattice(self.y0, self.y1, h)
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        x = np.stack([X.ravel(), Y.ravel()], 1)
        return x, np.full(len(x), self.area / len(x))

    def contains(self, p: np.ndarray) -> np.ndarray:
        return (p[:, 0] > self.x0) & (p[:, 0] < self.x1) & (p[:, 1] > self.y0) & (p[:, 1] < self.y1)


@dataclass(frozen=True)
class Polygon:
    """Simple polygon given by its vertices ((x, y), ...), m, in either orientation."""

    vertices: tuple

    dim = 2

    def __post_init__(self):
        v = tuple(tuple(float(c) for c in p) for p in self.vertices)
        if len(v) < 3 or any(len(p) != 2 for p in v):
            raise SceneError("Polygon needs at least 3 vertices given as (x, y) pairs")
        object.__setattr__(self, "vertices", v)
        if self.area <= 0:
            raise SceneError(f"Polygon {v} has zero area")

    @property
    def bbox(self) -> tuple[float, float, float, float]:
        a = np.array(self.vertices)
        return (a[:, 0].min(), a[:, 1].min(), a[:, 0].max(), a[:, 1].max())

    @property
    def lower(self) -> tuple[float, ...]:
        return self.bbox[:2]

    @property
    def upper(self) -> tuple[float, ...]:
        return self.bbox[2:]

    @property
    def area(self) -> float:
        a = np.array(self.vertices)
        x, y = a[:, 0], a[:, 1]
        return abs(0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))

    def contains(self, p: np.ndarray) -> np.ndarray:
        """Even-odd rule point-in-polygon test for points (n, 2)."""
        a = np.array(self.vertices)
        inside = np.zeros(len(p), bool)
        x, y = p[:, 0], p[:, 1]
        for (xa, ya), (xb, yb) in zip(a, np.roll(a, -1, axis=0)):
            crosses = (ya > y) != (yb > y)
            with np.errstate(divide="ignore", invalid="ignore"):
                xc = xa + (y - ya) * (xb - xa) / (yb - ya)
            inside ^= crosses & (x < xc)
        return inside

    def fill(self, dx: float, ppc: int) -> tuple[np.ndarray, np.ndarray]:
        h = dx / math.isqrt(ppc)
        x0, y0, x1, y1 = self.bbox
        xs = (np.floor(x0 / h) + 0.5 + np.arange(int(np.ceil((x1 - x0) / h)) + 2)) * h
        ys = (np.floor(y0 / h) + 0.5 + np.arange(int(np.ceil((y1 - y0) / h)) + 2)) * h
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        p = np.stack([X.ravel(), Y.ravel()], 1)
        p = p[self.contains(p)]
        if len(p) == 0:
            raise SceneError(f"Polygon {self.vertices} is too small to hold a particle at dx={dx}")
        return p, np.full(len(p), self.area / len(p))


def _check_numbers(owner: str, vals: tuple) -> None:
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
               for v in vals):
        raise SceneError(f"{owner} needs finite numbers, got {vals}")


def _side(ppc: int) -> int:
    """Particles per cell along one axis in 3D (ppc a perfect cube)."""
    return round(ppc ** (1.0 / 3.0))


@dataclass(frozen=True)
class Box:
    """Axis-aligned box [x0, x1] x [y0, y1] x [z0, z1], m (3D)."""

    x0: float
    y0: float
    z0: float
    x1: float
    y1: float
    z1: float

    dim = 3

    def __post_init__(self):
        _check_numbers("Box", (self.x0, self.y0, self.z0, self.x1, self.y1, self.z1))
        if not (self.x1 > self.x0 and self.y1 > self.y0 and self.z1 > self.z0):
            raise SceneError(f"Box needs x1 > x0, y1 > y0 and z1 > z0, got {self.lower} to "
                             f"{self.upper}")

    @property
    def lower(self) -> tuple[float, ...]:
        return (self.x0, self.y0, self.z0)

    @property
    def upper(self) -> tuple[float, ...]:
        return (self.x1, self.y1, self.z1)

    @property
    def volume(self) -> float:
        return (self.x1 - self.x0) * (self.y1 - self.y0) * (self.z1 - self.z0)

    def fill(self, dx: float, ppc: int) -> tuple[np.ndarray, np.ndarray]:
        """Particles on a regular sub-lattice: positions (n, 3) m and volumes (n,) m^3."""
        h = dx / _side(ppc)
        axes = [_lattice(lo, hi, h) for lo, hi in zip(self.lower, self.upper)]
        x = np.stack([g.ravel() for g in np.meshgrid(*axes, indexing="ij")], 1)
        return x, np.full(len(x), self.volume / len(x))

    def contains(self, p: np.ndarray) -> np.ndarray:
        return np.all((p > np.array(self.lower)) & (p < np.array(self.upper)), axis=1)


@dataclass(frozen=True)
class Cylinder:
    """Upright circular cylinder (axis along y, the vertical): centre (cx, cz) in the
    horizontal plane, ``radius``, from y0 to y1, m (3D). The axisymmetric granular column."""

    cx: float
    cz: float
    radius: float
    y0: float
    y1: float

    dim = 3

    def __post_init__(self):
        _check_numbers("Cylinder", (self.cx, self.cz, self.radius, self.y0, self.y1))
        if not (self.radius > 0 and self.y1 > self.y0):
            raise SceneError(f"Cylinder needs radius > 0 and y1 > y0, got radius "
                             f"{self.radius}, y0 {self.y0}, y1 {self.y1}")

    @property
    def lower(self) -> tuple[float, ...]:
        return (self.cx - self.radius, self.y0, self.cz - self.radius)

    @property
    def upper(self) -> tuple[float, ...]:
        return (self.cx + self.radius, self.y1, self.cz + self.radius)

    @property
    def volume(self) -> float:
        return math.pi * self.radius**2 * (self.y1 - self.y0)

    def contains(self, p: np.ndarray) -> np.ndarray:
        r2 = (p[:, 0] - self.cx) ** 2 + (p[:, 2] - self.cz) ** 2
        return (r2 < self.radius**2) & (p[:, 1] > self.y0) & (p[:, 1] < self.y1)

    def fill(self, dx: float, ppc: int) -> tuple[np.ndarray, np.ndarray]:
        """Particles of a regular sub-lattice (spacing dx / ppc^(1/3), centred on the axis)
        inside the cylinder: positions (n, 3) m; volumes (n,) m^3 share the exact volume."""
        h = dx / _side(ppc)
        k = int(np.ceil(self.radius / h))
        ring = (np.arange(-k, k) + 0.5) * h
        ys = _lattice(self.y0, self.y1, h)
        X, Y, Z = np.meshgrid(self.cx + ring, ys, self.cz + ring, indexing="ij")
        p = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
        p = p[(p[:, 0] - self.cx) ** 2 + (p[:, 2] - self.cz) ** 2 <= self.radius**2]
        if len(p) == 0:
            raise SceneError(f"Cylinder of radius {self.radius} is too thin for a particle at "
                             f"dx={dx}")
        return p, np.full(len(p), self.volume / len(p))


Shape = Rectangle | Polygon | Box | Cylinder
SHAPES_2D = (Rectangle, Polygon)
SHAPES_3D = (Box, Cylinder)
