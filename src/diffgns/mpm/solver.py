"""The explicit MLS-MPM solver assembled from a scene's declared effects.

    sim = MPM(scene)
    params, state = sim.params(), sim.init()
    frames, final = rollout(sim, params, state, n_frames=200)   # diffgns.rollout
    traj, final = sim.run(params, state, 200)                    # Trajectory + stability check

The MPM is a :class:`diffgns.interface.Simulator`: ``step(params, state)`` advances one frame
(``scene.substeps`` substeps of ``substep``; with ``checkpoint_substeps`` each is
``jax.checkpoint``-ed so reverse mode stores one state per frame), ``observe(state)`` gives
a :class:`~diffgns.interface.ParticleFrame`.
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.clamp import ClampCount, clamp_positions
from diffgns.errors import UnstableError
from diffgns.interface import ParticleFrame, rollout_jit
from diffgns.mpm import boundaries, constitutive
from diffgns.mpm import linalg as la
from diffgns.mpm.shape import stencil
from diffgns.mpm.state import MPMParams, MPMState
from diffgns.mpm.transfer import g2p, grid_velocity, p2g
from diffgns.scene.materials import Fluid, Sand, friction_feature
from diffgns.trajectory import ELASTIC, FLUID, SAND, Trajectory


class MPM:
    """Explicit MLS-MPM for one scene (static); parameters and state are pytrees.

    The spatial dimension d (2 or 3) is the scene's (``scene.dim``); one code path serves
    both: 3^d-node quadratic B-spline stencils, d x d constitutive laws, 2d box walls.

    Args:
        scene: the :class:`~diffgns.scene.Scene` (its declared effects are all that is traced).
        dtype: float dtype of parameters and state (default: JAX's default float).
        checkpoint_substeps: ``jax.checkpoint`` every substep, so reverse mode stores one
            state per frame instead of one per substep. Use it for gradients through long
            rollouts; it costs ~4% in forward runs (measured against the plain step,
            ``runs/ab_old_new.py``), so it is off by default.
    """

    def __init__(self, scene, dtype=None, checkpoint_substeps: bool = False):
        self.scene = scene
        self.frame_dt = float(scene.frame_dt)
        self.checkpoint_substeps = bool(checkpoint_substeps)
        self.dtype = jnp.dtype(dtype) if dtype is not None else jnp.asarray(0.0).dtype
        self.dx = float(scene.dx)
        self.dt = float(scene.substep_dt)
        self.n_sub = int(scene.substeps)
        self.grid_shape = scene.grid_shape
        self.dim = int(scene.dim)
        self.n_nodes = int(np.prod(self.grid_shape))
        self.origin = np.asarray(scene.grid_origin)
        self.lo = np.array([lo for lo, _ in scene.domain])
        self.hi = np.array([hi for _, hi in scene.domain])
        self.effects = scene.effects
        parts = scene.particles()
        self.body = parts["body"]
        self.groups = scene.material_groups()
        self.obstacle_nodes = boundaries.obstacle_nodes(
            scene.obstacles, self.grid_shape, self.origin, self.dx) if scene.obstacles else {}

    # ------------------------------------------------------------ construction
    def params(self) -> MPMParams:
        """Parameters of the scene as differentiable leaves."""
        return MPMParams.from_scene(self.scene, self.dtype)

    def init(self) -> MPMState:
        """Initial state of the scene's particles (positions, velocities, volumes)."""
        p = self.scene.particles()
        return MPMState.from_particles(p["x"], p["v"], p["vol"], self.dtype)

    def particle_type(self) -> np.ndarray:
        kinds = {"sand": SAND, "fluid": FLUID}
        return np.array([kinds.get(b.material.kind, ELASTIC) for b in self.scene.bodies],
                        np.int32)[self.body]

    def material_feature(self, params: MPMParams) -> jax.Array:
        """(N,) tan(friction angle) for sand particles, 0 otherwise."""
        is_sand = np.array([isinstance(b.material, Sand) for b in self.scene.bodies])[self.body]
        tan = friction_feature(params.friction_angle)[self.body]
        return jnp.where(is_sand, tan, 0.0)

    # ------------------------------------------------------------------ physics
    def _per_particle(self, arr, sl):
        ids = self.body[sl]
        if np.all(ids == ids[0]):
            return arr[int(ids[0])]  # one body in the group: a broadcast scalar
        return arr[ids]

    def stress(self, params: MPMParams, state: MPMState, F=None):
        """Kirchhoff stress tau (d,d,N) Pa and projected F of every particle."""
        F = state.F if F is None else F
        taus, Fs = [], []
        for eff, sl in self.groups.items():
            Fg = F[:, :, sl]
            pp = partial(self._per_particle, sl=sl)
            if eff == "elastic_linear":
                t, f = constitutive.elastic_linear(Fg, pp(params.E), pp(params.nu))
            elif eff == "elastic_corotated":
                t, f = constitutive.elastic_corotated(Fg, pp(params.E), pp(params.nu))
            elif eff == "sand":
                t, f = constitutive.drucker_prager(Fg, pp(params.E), pp(params.nu),
                                                   pp(params.friction_angle), pp(params.cohesion))
            else:
                t, f = constitutive.fluid(Fg, state.C[:, :, sl], pp(params.bulk_modulus),
                                          pp(params.viscosity), pp(params.gamma))
            taus.append(t)
            Fs.append(f)
        if len(taus) == 1:
            return taus[0], Fs[0]
        return jnp.concatenate(taus, -1), jnp.concatenate(Fs, -1)

    def cauchy_stress(self, params: MPMParams, state: MPMState) -> jax.Array:
        """(N, d, d) Cauchy stress sigma = tau / J, Pa (tension positive)."""
        tau, F = self.stress(params, state)
        return jnp.moveaxis(tau / la.det(F), -1, 0)

    def mass(self, params: MPMParams, state: MPMState) -> jax.Array:
        """(N,) particle masses, kg."""
        return params.rho[self.body] * state.vol

    def substep(self, params: MPMParams, state: MPMState) -> MPMState:
        """One explicit MLS-MPM substep of ``self.dt`` seconds."""
        dt, dx, n_nodes, d = self.dt, self.dx, self.n_nodes, self.dim
        F_trial = state.F + dt * la.matmul(state.C, state.F)
        tau, F = self.stress(params, state, F_trial)
        mass = self.mass(params, state)
        X = (state.x - jnp.asarray(self.origin, state.x.dtype)[:, None]) / dx
        idx, w, dpos = stencil(X, self.grid_shape)
        affine = mass * state.C - (dt * 4.0 / dx**2) * state.vol * tau
        grid = p2g(idx, w, dpos, mass, mass * state.v, affine, n_nodes, dx)
        gv = grid_velocity(grid)
        if "gravity" in self.effects:
            gv = gv + dt * params.gravity[:, None]
        if "damping" in self.effects:
            gv = gv * jnp.exp(-dt * params.damping)
        gv = boundaries.apply_walls(gv.reshape(d, *self.grid_shape), self.scene.wall_list,
                                    params.wall_mu, self.scene.padding, self.scene.n_cells)
        gv = gv.reshape(d, n_nodes)
        if self.obstacle_nodes:
            gv = boundaries.apply_obstacles(gv, self.obstacle_nodes, params.obstacle_mu)
        v, C = g2p(idx, w, dpos, gv.reshape(d, *self.grid_shape), dx)
        x = state.x + dt * v
        lo, hi = jnp.asarray(self.lo, x.dtype), jnp.asarray(self.hi, x.dtype)
        # never leave the domain (and the grid), and count it (diffgns.clamp)
        x, clamp = clamp_positions(x, lo[:, None], hi[:, None], axis=0)
        return state.replace(x=x, v=v, C=C, F=F, clamp=state.clamp.merge(clamp))

    def step(self, params: MPMParams, state: MPMState) -> MPMState:
        """Advance one frame (``scene.substeps`` substeps of ``scene.substep_dt`` s)."""
        sub = self.substep
        if self.checkpoint_substeps:
            sub = jax.checkpoint(sub, prevent_cse=False)
        state = state.replace(clamp=ClampCount.zero(state.x.dtype))  # counts of this frame
        state, _ = jax.lax.scan(lambda s, _: (sub(params, s), None), state, None,
                                length=self.n_sub)
        return state

    def observe(self, state: MPMState) -> ParticleFrame:
        """Positions (N, 2) m, velocities (N, 2) m/s, no overflow (the MPM never overflows)
        and the frame's domain clamps."""
        return ParticleFrame(state.x.T, state.v.T, jnp.zeros((), bool), state.clamp)

    def trajectory(self, params: MPMParams, frames: ParticleFrame) -> Trajectory:
        """The :class:`Trajectory` of stacked frames (with particle types and tan phi)."""
        return Trajectory(positions=frames.positions, velocities=frames.velocities,
                          particle_type=jnp.asarray(self.particle_type()),
                          material=self.material_feature(params),
                          frame_dt=self.frame_dt, bounds=self.scene.domain,
                          clamped=frames.clamp.moved, clamp_shift=frames.clamp.shift)

    def run(self, params: MPMParams, state: MPMState, n_frames: int,
            checkpoint_block: int | None = None, check: bool = True
            ) -> tuple[Trajectory, MPMState]:
        """Jitted :func:`diffgns.interface.rollout` returning ``(Trajectory (T = n_frames + 1),
        final state)``; with ``check`` (outside jit) raises UnstableError on a CFL breach or a
        non-finite state."""
        frames, final = rollout_jit(self, params, state, n_frames=int(n_frames),
                                    checkpoint_block=checkpoint_block)
        if check and not isinstance(frames.velocities, jax.core.Tracer):
            self.check_stability(params, max_speed(frames.velocities), frames.positions)
        return self.trajectory(params, frames), final

    def courant(self, params: MPMParams, max_speed) -> float:
        """Largest Courant number dt (c + |v|) / dx for the given max particle speed."""
        solid, fluid_c = params.wave_speeds()
        is_fluid = np.array([isinstance(b.material, Fluid) for b in self.scene.bodies])
        c = jnp.max(jnp.where(is_fluid, fluid_c, solid))
        return float(self.dt * (c + jnp.max(max_speed)) / self.dx)

    def check_stability(self, params, speed, pos) -> None:
        """Raise UnstableError if ``pos`` is non-finite or the Courant number for the
        per-frame max speeds ``speed`` (m/s) exceeds 1."""
        if not bool(jnp.all(jnp.isfinite(pos))):
            raise UnstableError("MPM state became non-finite; reduce dt (Scene.cfl) or check "
                                "material parameters")
        cr = self.courant(params, speed)
        if cr > 1.0:
            raise UnstableError(
                f"MPM Courant number reached {cr:.2f} > 1 (max speed {float(jnp.max(speed)):.2f} "
                f"m/s, dt = {self.dt:.2e} s): results are unreliable; set Scene.max_speed higher "
                "or lower Scene.cfl")


def max_speed(velocities: jax.Array) -> jax.Array:
    """(T,) largest particle speed of each frame (m/s) of velocities (T, N, d)."""
    return jnp.sqrt(jnp.max(jnp.sum(velocities * velocities, -1), -1))
