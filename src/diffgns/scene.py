"""Declarative 2D scenes: domain, grid, bodies, walls, obstacles, gravity.

A :class:`Scene` is static and hashable; it is validated when constructed, so
nothing invalid reaches jitted code. ``Scene.effects`` lists the physics the
scene declares; the MPM step is assembled from exactly those pieces.

Geometry is in m, velocities in m/s, gravity in m/s^2, times in s.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import SceneError
from .materials import Fluid, Material, Sand
from .shapes import Polygon, Rectangle, Shape

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


@dataclass(frozen=True)
class Scene:
    """A 2D MPM scene.

    Args:
        domain: ((xmin, xmax), (ymin, ymax)), m: the box the walls enclose.
        dx: grid cell size, m; the domain extents must be multiples of dx.
        bodies: the bodies.
        gravity: gravity vector, m/s^2.
        walls: conditions of the four box walls.
        obstacles: static rigid boxes.
        frame_dt: time between output frames, s.
        padding: grid cells outside the domain on every side (>= 2).
        cfl: Courant number of the automatic substep (0 < cfl <= 0.5).
        dt: optional substep, s; rejected if above the CFL limit.
        max_speed: speed bound used by the CFL limit, m/s; default is the largest initial
            speed plus the free-fall speed over the domain diagonal.
        damping: grid velocity damping rate, 1/s (0 = none; for quasi-static problems).
    """

    domain: tuple = ((0.0, 1.0), (0.0, 1.0))
    dx: float = 0.02
    bodies: tuple[Body, ...] = ()
    gravity: tuple[float, float] = (0.0, -9.81)
    walls: Walls = Walls()
    obstacles: tuple[BoxObstacle, ...] = ()
    frame_dt: float = 2.5e-3
    padding: int = 3
    cfl: float = 0.4
    dt: float | None = None
    max_speed: float | None = None
    damping: float = 0.0
    _cache: dict = field(default_factory=dict, compare=False, hash=False, repr=False)

    def __post_init__(self):
        object.__setattr__(self, "bodies", tuple(self.bodies))
        object.__setattr__(self, "obstacles", tuple(self.obstacles))
        object.__setattr__(self, "gravity", tuple(float(g) for g in self.gravity))
        dom = tuple(tuple(float(v) for v in ax) for ax in self.domain)
        object.__setattr__(self, "domain", dom)
        from .scene_checks import validate_scene

        validate_scene(self)

    # ------------------------------------------------------------------ grid
    @property
    def n_cells(self) -> tuple[int, int]:
        """Cells of the domain box along x and y (without padding)."""
        return tuple(int(round((hi - lo) / self.dx)) for lo, hi in self.domain)

    @property
    def grid_shape(self) -> tuple[int, int]:
        """Grid nodes along x and y, padding included."""
        return tuple(n + 2 * self.padding + 1 for n in self.n_cells)

    @property
    def grid_origin(self) -> tuple[float, float]:
        """Position of grid node (0, 0), m."""
        return tuple(lo - self.padding * self.dx for lo, _ in self.domain)

    # --------------------------------------------------------------- effects
    @property
    def effects(self) -> frozenset[str]:
        """The physics this scene declares; the MPM step traces exactly these."""
        fx = {b.material.effect for b in self.bodies}
        if any(g != 0.0 for g in self.gravity):
            fx.add("gravity")
        for w in self.walls:
            fx.add(f"{w.kind}_walls")
        if self.obstacles:
            fx.add("obstacles")
        if self.damping > 0:
            fx.add("damping")
        return frozenset(fx)

    # ------------------------------------------------------------- particles
    def particles(self) -> dict[str, np.ndarray]:
        """Particles of all bodies, grouped by material effect (static order).

        Returns a dict of numpy arrays: ``x`` (N, 2) m, ``v`` (N, 2) m/s, ``vol`` (N,) m^2,
        ``body`` (N,) int body index. Particles are ordered by material group
        (see :meth:`material_groups`) and within a group by body declaration order.
        """
        if "particles" not in self._cache:
            xs, vs, vols, ids = [], [], [], []
            for b in self.body_order():
                x, vol = self.bodies[b].shape.fill(self.dx, self.bodies[b].particles_per_cell)
                xs.append(x)
                vs.append(np.broadcast_to(np.array(self.bodies[b].velocity), x.shape))
                vols.append(vol)
                ids.append(np.full(len(x), b, np.int32))
            self._cache["particles"] = dict(
                x=np.concatenate(xs), v=np.concatenate(vs), vol=np.concatenate(vols),
                body=np.concatenate(ids),
            )
        return self._cache["particles"]

    def body_order(self) -> list[int]:
        """Body indices sorted by material group then declaration order."""
        order = {e: i for i, e in enumerate(EFFECT_ORDER)}
        return sorted(range(len(self.bodies)),
                      key=lambda b: (order[self.bodies[b].material.effect], b))

    def material_groups(self) -> dict[str, slice]:
        """Static particle slices per material effect, e.g. {"sand": slice(0, 1200)}."""
        body = self.particles()["body"]
        groups, start = {}, 0
        for eff in EFFECT_ORDER:
            n = int(sum((body == b).sum() for b in range(len(self.bodies))
                        if self.bodies[b].material.effect == eff))
            if n:
                groups[eff] = slice(start, start + n)
                start += n
        return groups

    @property
    def n_particles(self) -> int:
        return len(self.particles()["x"])

    # ------------------------------------------------------------- time step
    def wave_speed(self) -> float:
        """Largest material wave speed, m/s."""
        return max(b.material.wave_speed() for b in self.bodies)

    def speed_bound(self) -> float:
        """Speed bound used for the CFL condition, m/s."""
        if self.max_speed is not None:
            return float(self.max_speed)
        v0 = max(math.hypot(*b.velocity) for b in self.bodies)
        (x0, x1), (y0, y1) = self.domain
        g = math.hypot(*self.gravity)
        return v0 + math.sqrt(2.0 * g * math.hypot(x1 - x0, y1 - y0))

    def stable_dt(self) -> float:
        """Largest stable substep, s: cfl*dx/(c_p + v_max), and the viscous limit for fluids."""
        dt = self.cfl * self.dx / (self.wave_speed() + self.speed_bound())
        for b in self.bodies:
            if isinstance(b.material, Fluid) and b.material.viscosity > 0:
                dt = min(dt, 0.25 * b.material.rho * self.dx**2 / b.material.viscosity)
        return dt

    @property
    def substeps(self) -> int:
        """Substeps per frame."""
        dt = self.dt if self.dt is not None else self.stable_dt()
        return max(1, math.ceil(self.frame_dt / dt * (1 - 1e-9)))

    @property
    def substep_dt(self) -> float:
        """The substep actually taken, s (frame_dt / substeps)."""
        return self.frame_dt / self.substeps

    def replace(self, **kw) -> Scene:
        from dataclasses import replace

        return replace(self, _cache={}, **kw)


EFFECT_ORDER = ("elastic_linear", "elastic_corotated", "sand", "fluid")

__all__ = [
    "Wall", "Walls", "BoxObstacle", "Body", "Scene", "Rectangle", "Polygon", "Sand",
    "WALL_KINDS", "WALL_NAMES", "EFFECT_ORDER",
]
