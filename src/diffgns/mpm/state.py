"""MPM state and parameter pytrees.

Layout is component-major so that the substep is a chain of fused elementwise kernels:
vectors are (d, N), matrices (d, d, N), d = 2 or 3 the scene's dimension.
:class:`diffgns.trajectory.Trajectory` holds the user-facing (T, N, d) layout.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from diffgns.clamp import ClampCount
from diffgns.scene.materials import Elastic, Fluid, Sand


@struct.dataclass
class MPMState:
    """Particle state.

    Attributes:
        x: (d, N) positions, m.
        v: (d, N) velocities, m/s.
        C: (d, d, N) APIC affine velocity field (velocity gradient), 1/s.
        F: (d, d, N) elastic deformation gradient.
        vol: (N,) initial particle volumes (areas in 2D, m^2; volumes in 3D, m^3).
        clamp: :class:`~diffgns.clamp.ClampCount` of the current frame: positions the domain
            clamp moved in its substeps so far (counted, never silent).
    """

    x: jax.Array
    v: jax.Array
    C: jax.Array
    F: jax.Array
    vol: jax.Array
    clamp: ClampCount

    @property
    def n_particles(self) -> int:
        return self.x.shape[1]

    @staticmethod
    def from_particles(x: np.ndarray, v: np.ndarray, vol: np.ndarray, dtype) -> MPMState:
        """Build a state at rest-deformation (F = I, C = 0) from (N, d) positions/velocities."""
        n, d = np.shape(x)
        eye = np.zeros((d, d, n))
        for i in range(d):
            eye[i, i] = 1.0
        return MPMState(
            x=jnp.asarray(np.asarray(x).T, dtype), v=jnp.asarray(np.asarray(v).T, dtype),
            C=jnp.zeros((d, d, n), dtype), F=jnp.asarray(eye, dtype),
            vol=jnp.asarray(vol, dtype), clamp=ClampCount.zero(dtype),
        )


@struct.dataclass
class MPMParams:
    """Differentiable physical parameters (all leaves).

    Per-body arrays have shape (B,) in the scene's body declaration order; entries of a
    field that does not apply to a body's material are unused.

    Attributes:
        E: Young's modulus, Pa.  nu: Poisson's ratio.  rho: density, kg/m^3.
        friction_angle: degrees (sand).  cohesion: Pa (sand).
        bulk_modulus: Pa (fluid).  viscosity: Pa s (fluid).  gamma: Tait exponent (fluid).
        wall_mu: (2d,) Coulomb coefficients of the left, right, bottom, top (and in 3D back,
            front) walls.
        obstacle_mu: (K,) Coulomb coefficients of the obstacles.
        gravity: (d,) m/s^2.
        damping: () grid velocity damping rate, 1/s.
    """

    E: jax.Array
    nu: jax.Array
    rho: jax.Array
    friction_angle: jax.Array
    cohesion: jax.Array
    bulk_modulus: jax.Array
    viscosity: jax.Array
    gamma: jax.Array
    wall_mu: jax.Array
    obstacle_mu: jax.Array
    gravity: jax.Array
    damping: jax.Array

    @staticmethod
    def from_scene(scene, dtype) -> MPMParams:
        rows = []
        for b in scene.bodies:
            m = b.material
            if isinstance(m, Sand):
                rows.append((m.E, m.nu, m.rho, m.friction_angle, m.cohesion, 1.0, 0.0, 7.0))
            elif isinstance(m, Elastic):
                rows.append((m.E, m.nu, m.rho, 30.0, 0.0, 1.0, 0.0, 7.0))
            elif isinstance(m, Fluid):
                rows.append((1.0, 0.3, m.rho, 30.0, 0.0, m.bulk_modulus, m.viscosity, m.gamma))
        cols = [jnp.asarray(c, dtype) for c in zip(*rows)]
        return MPMParams(
            *cols,
            wall_mu=jnp.asarray([w.mu for w in scene.wall_list], dtype),
            obstacle_mu=jnp.asarray([o.surface.mu for o in scene.obstacles], dtype).reshape(-1),
            gravity=jnp.asarray(scene.gravity, dtype),
            damping=jnp.asarray(scene.damping, dtype),
        )

    def wave_speeds(self) -> jax.Array:
        """((B,) solid P-wave speeds sqrt((lambda + 2 mu)/rho), (B,) fluid sound speeds
        sqrt(K/rho)), m/s, for every body; the caller picks per body material."""
        mu = self.E / (2 * (1 + self.nu))
        lam = self.E * self.nu / ((1 + self.nu) * (1 - 2 * self.nu))
        solid = jnp.sqrt((lam + 2 * mu) / self.rho)
        return solid, jnp.sqrt(self.bulk_modulus / self.rho)
