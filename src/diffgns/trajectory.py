"""Trajectory pytree: particle states sampled at frames.

Every simulator (MPM, GNS, hybrid) returns a :class:`Trajectory`, so downstream
code (metrics, datasets, plots) never cares which simulator produced it.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from diffgns.clamp import clamp_summary

# Particle types, following the convention of the published GNS datasets.
KINEMATIC = 3
FLUID = 5
SAND = 6
ELASTIC = 7


@struct.dataclass
class Trajectory:
    """Particle states at frames.

    Attributes:
        positions: (T, N, d) particle positions in m (d = 2 or 3, y vertical).
        velocities: (T, N, d) particle velocities in m/s.
        particle_type: (N,) int32 particle type (SAND, FLUID, ELASTIC, KINEMATIC).
        material: (N,) float material feature, tan(friction angle) for sand, 0 otherwise.
        frame_dt: time between frames in s (static).
        bounds: ((xmin, xmax), (ymin, ymax)[, (zmin, zmax)]) of the domain in m (static).
        clamped: (T,) int32 positions a domain clamp moved in each frame (the simulator's
            :class:`~diffgns.clamp.ClampCount`), or None when the trajectory was not made by a
            simulator (a dataset, a reference file).
        clamp_shift: (T,) largest distance a clamp moved a position in each frame, m, or None.
        obstacles: box obstacles ``((x0, y0, x1, y1), ...)`` (3D: ``(x0, y0, z0, x1, y1,
            z1)``) of the scene, m (static; empty when the trajectory records none).
    """

    positions: jax.Array
    velocities: jax.Array
    particle_type: jax.Array
    material: jax.Array
    frame_dt: float = struct.field(pytree_node=False, default=2.5e-3)
    bounds: tuple = struct.field(pytree_node=False, default=((0.0, 1.0), (0.0, 1.0)))
    clamped: jax.Array | None = None
    clamp_shift: jax.Array | None = None
    obstacles: tuple = struct.field(pytree_node=False, default=())

    @property
    def n_frames(self) -> int:
        return self.positions.shape[0]

    @property
    def n_particles(self) -> int:
        return self.positions.shape[1]

    def clamp_summary(self) -> dict | None:
        """:func:`diffgns.clamp.clamp_summary` of the recorded clamps (None if none recorded)."""
        if self.clamped is None:
            return None
        shift = self.clamp_shift if self.clamp_shift is not None else jnp.zeros(self.n_frames)
        return clamp_summary(self.clamped, shift)

    @property
    def times(self) -> jax.Array:
        """(T,) time of each frame in s."""
        return jnp.arange(self.n_frames) * self.frame_dt
