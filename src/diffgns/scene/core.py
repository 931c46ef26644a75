"""Declarative 2D and 3D scenes: domain, grid, bodies, walls, obstacles, gravity.

The dimension is the domain's: two (x, y) or three (x, y, z) axes; y is vertical in both
(default gravity (0, -9.81[, 0])), z the depth axis of 3D.

A :class:`Scene` is static and hashable; it is validated when constructed, so
nothing invalid reaches jitted code. ``Scene.effects`` lists the physics the
scene declares; the MPM step is assembled from exactly those pieces.

Geometry is in m, velocities in m/s, gravity in m/s^2, times in s.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from diffgns.scene.checks import validate_scene
from diffgns.scene.elements import (
    WALL_KINDS,
    WALL_NAMES,
    WALL_NAMES_3D,
    Body,
    BoxObstacle,
    Wall,
    Walls,
)
from diffgns.scene.materials import Fluid, Sand
from diffgns.scene.shapes import Box, Cylinder, Polygon, Rectangle


@dataclass(frozen=True)
class Scene:
    """A 2D or 3D MPM scene.

    Args:
        domain: ((xmin, xmax), (ymin, ymax)) or, in 3D, ((xmin, xmax), (ymin, ymax),
            (zmin, zmax)), m: the box the walls enclose; its length is the dimension.
        dx: grid cell size, m; the domain extents must be multiples of dx.
        bodies: the bodies (2D shapes in 2D, 3D shapes in 3D).
        gravity: gravity vector, m/s^2 (default (0, -9.81) in 2D, (0, -9.81, 0) in 3D).
        walls: conditions of the box walls (four in 2D, six in 3D).
        obstacles: static rigid boxes.
        frame_dt: time between output frames, s.
        padding: grid cells outside the domain on every side (>= 2).
        cfl: Courant number of the automatic substep (0 < cfl <= 0.5).
        dt: optional substep, s; rejected if above the CFL limit.
        max_speed: speed bound used by the CFL limit, m/s; default is the largest initial
            speed plus the free-fall speed over the domain diagonal.
        damping: grid velocity damping rate, 1/s (0 = none; for quasi-static problems).
        flip: fraction in [0, 1] of FLIP in the particle velocity update (0, the default:
            APIC alone). APIC smooths every velocity field finer than affine once per
            particle-grid round trip, so it damps a flow more the more substeps a second
            has; ``flip`` = 0.99 keeps the particle's own velocity plus the grid's change
            and loses far less (docs/validation.md, "The answer depends on the substep
            too"). Positions always move with the grid velocity.
    """

    domain: tuple = ((0.0, 1.0), (0.0, 1.0))
    dx: float = 0.02
    bodies: tuple[Body, ...] = ()
    gravity: tuple[float, ...] | None = None
    walls: Walls = Walls()
    obstacles: tuple[BoxObstacle, ...] = ()
    frame_dt: float = 2.5e-3
    padding: int = 3
    cfl: float = 0.4
    dt: float | None = None
    max_speed: float | None = None
    damping: float = 0.0
    flip: float = 0.0
    # init=False: dataclasses.replace gives the copy a fresh cache (a shared one returned the
    # first scene's particles for the other)
    _cache: dict = field(default_factory=dict, init=False, compare=False, hash=False,
                         repr=False)

    def __post_init__(self):
        object.__setattr__(self, "bodies", tuple(self.bodies))
        object.__setattr__(self, "obstacles", tuple(self.obstacles))
        dom = tuple(tuple(float(v) for v in ax) for ax in self.domain)
        object.__setattr__(self, "domain", dom)
        g = self.gravity
        if g is None:
            g = (0.0, -9.81) + (0.0,) * max(0, len(dom) - 2)
        object.__setattr__(self, "gravity", tuple(float(c) for c in g))
        validate_scene(self)

    # ------------------------------------------------------------------ grid
    @property
    def dim(self) -> int:
        """Spatial dimension, 2 or 3 (the number of domain axes)."""
        return len(self.domain)

    @property
    def wall_list(self) -> tuple[Wall, ...]:
        """The 2 dim walls in the order of :data:`WALL_NAMES_3D` (left, right, bottom, top
        [, back, front])."""
        return self.walls.of(self.dim)

    @property
    def wall_names(self) -> tuple[str, ...]:
        return WALL_NAMES_3D[: 2 * self.dim]

    @property
    def n_cells(self) -> tuple[int, ...]:
        """Cells of the domain box along each axis (without padding)."""
        return tuple(int(round((hi - lo) / self.dx)) for lo, hi in self.domain)

    @property
    def grid_shape(self) -> tuple[int, ...]:
        """Grid nodes along each axis, padding included."""
        return tuple(n + 2 * self.padding + 1 for n in self.n_cells)

    @property
    def grid_origin(self) -> tuple[float, ...]:
        """Position of grid node (0, 0), m."""
        return tuple(lo - self.padding * self.dx for lo, _ in self.domain)

    # --------------------------------------------------------------- effects
    @property
    def effects(self) -> frozenset[str]:
        """The physics this scene declares; the MPM step traces exactly these."""
        fx = {b.material.effect for b in self.bodies}
        if any(g != 0.0 for g in self.gravity):
            fx.add("gravity")
        for w in self.wall_list:
            fx.add(f"{w.kind}_walls")
        if self.obstacles:
            fx.add("obstacles")
        if self.damping > 0:
            fx.add("damping")
        if self.flip > 0:
            fx.add("flip")
        return frozenset(fx)

    # ------------------------------------------------------------- particles
    def particles(self) -> dict[str, np.ndarray]:
        """Particles of all bodies, grouped by material effect (static order).

        Returns a dict of numpy arrays: ``x`` (N, d) m, ``v`` (N, d) m/s, ``vol`` (N,) m^d,
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
        g = math.hypot(*self.gravity)
        return v0 + math.sqrt(2.0 * g * math.hypot(*(hi - lo for lo, hi in self.domain)))

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

        return replace(self, **kw)


EFFECT_ORDER = ("elastic_linear", "elastic_corotated", "sand", "fluid")

__all__ = [
    "Wall", "Walls", "BoxObstacle", "Body", "Scene", "Rectangle", "Polygon", "Box", "Cylinder",
    "Sand", "WALL_KINDS", "WALL_NAMES", "WALL_NAMES_3D", "EFFECT_ORDER",
]
