"""The explicit MLS-MPM solver assembled from a scene's declared effects.

    sim = MPM(scene)
    params, state = sim.params(), sim.init_state()
    traj = sim.rollout(params, state, n_frames=200)      # Trajectory, T = n_frames + 1

``substep(params, state) -> state`` is pure; ``rollout`` scans frames (``lax.scan``),
each frame scanning ``scene.substeps`` substeps, with optional ``jax.checkpoint`` on
substeps and on blocks of frames for gradients through long rollouts.
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.errors import UnstableError
from diffgns.mpm import boundaries, constitutive
from diffgns.mpm import linalg as la
from diffgns.mpm.shape import stencil
from diffgns.mpm.state import MPMParams, MPMState
from diffgns.mpm.transfer import g2p, grid_velocity, p2g
from diffgns.scene.materials import Fluid, Sand
from diffgns.trajectory import ELASTIC, FLUID, SAND, Trajectory


class MPM:
    """Explicit 2D MLS-MPM for one scene (static); parameters and state are pytrees."""

    def __init__(self, scene, dtype=None):
        self.scene = scene
        self.dtype = jnp.dtype(dtype) if dtype is not None else jnp.asarray(0.0).dtype
        self.dx = float(scene.dx)
        self.dt = float(scene.substep_dt)
        self.n_sub = int(scene.substeps)
        self.grid_shape = scene.grid_shape
        self.origin = np.asarray(scene.grid_origin)
        self.lo = np.array([lo for lo, _ in scene.domain])
        self.hi = np.array([hi for _, hi in scene.domain])
        self.effects = scene.effects
        parts = scene.particles()
        self.body = parts["body"]
        self.groups = scene.material_groups()
        self.obstacle_nodes = boundaries.obstacle_nodes(
            scene.obstacles, self.grid_shape, self.origin, self.dx) if scene.obstacles else {}
        self.rollout_full = jax.jit(self._rollout, static_argnames=("n_frames", "checkpoint",
                                                                     "block"))

    # ------------------------------------------------------------ construction
    def params(self) -> MPMParams:
        """Parameters of the scene as differentiable leaves."""
        return MPMParams.from_scene(self.scene, self.dtype)

    def init_state(self) -> MPMState:
        p = self.scene.particles()
        return MPMState.from_particles(p["x"], p["v"], p["vol"], self.dtype)

    def particle_type(self) -> np.ndarray:
        kinds = {"sand": SAND, "fluid": FLUID}
        return np.array([kinds.get(b.material.kind, ELASTIC) for b in self.scene.bodies],
                        np.int32)[self.body]

    def material_feature(self, params: MPMParams) -> jax.Array:
        """(N,) tan(friction angle) for sand particles, 0 otherwise."""
        is_sand = np.array([isinstance(b.material, Sand) for b in self.scene.bodies])[self.body]
        tan = jnp.tan(jnp.deg2rad(params.friction_angle))[self.body]
        return jnp.where(is_sand, tan, 0.0)

    # ------------------------------------------------------------------ physics
    def _per_particle(self, arr, sl):
        ids = self.body[sl]
        if np.all(ids == ids[0]):
            return arr[int(ids[0])]  # one body in the group: a broadcast scalar
        return arr[ids]

    def stress(self, params: MPMParams, state: MPMState, F=None):
        """Kirchhoff stress tau (2,2,N) Pa and projected F of every particle."""
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
        """(N, 2, 2) Cauchy stress sigma = tau / J, Pa (tension positive)."""
        tau, F = self.stress(params, state)
        return jnp.moveaxis(tau / la.det(F), -1, 0)

    def mass(self, params: MPMParams, state: MPMState) -> jax.Array:
        """(N,) particle masses, kg."""
        return params.rho[self.body] * state.vol

    def substep(self, params: MPMParams, state: MPMState) -> MPMState:
        """One explicit MLS-MPM substep of ``self.dt`` seconds."""
        dt, dx, n_nodes = self.dt, self.dx, self.grid_shape[0] * self.grid_shape[1]
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
        gv = boundaries.apply_walls(gv.reshape(2, *self.grid_shape), self.scene.walls,
                                    params.wall_mu, self.scene.padding, self.scene.n_cells)
        gv = gv.reshape(2, n_nodes)
        if self.obstacle_nodes:
            gv = boundaries.apply_obstacles(gv, self.obstacle_nodes, params.obstacle_mu)
        v, C = g2p(idx, w, dpos, gv, dx)
        x = state.x + dt * v
        lo, hi = jnp.asarray(self.lo, x.dtype), jnp.asarray(self.hi, x.dtype)
        x = jnp.clip(x, lo[:, None], hi[:, None])  # never leave the domain (and the grid)
        return state.replace(x=x, v=v, C=C, F=F)

    def frame(self, params: MPMParams, state: MPMState, checkpoint: bool = False) -> MPMState:
        """Advance one frame (``scene.substeps`` substeps)."""
        sub = self.substep
        if checkpoint:
            sub = jax.checkpoint(sub)
        state, _ = jax.lax.scan(lambda s, _: (sub(params, s), None), state, None,
                                length=self.n_sub)
        return state

    # ------------------------------------------------------------------ rollout
    def _rollout(self, params, state, n_frames: int, checkpoint: bool = False,
                 block: int | None = None):
        init = state

        def one(s, _):
            s = self.frame(params, s, checkpoint)
            speed = jnp.sqrt(jnp.max(jnp.sum(s.v * s.v, 0)))
            return s, (s.x.T, s.v.T, speed)

        def frames(s, n):
            return jax.lax.scan(one, s, None, length=n)

        if checkpoint and block and n_frames > block:
            nb, rem = divmod(n_frames, block)
            blk = jax.checkpoint(lambda s, _: frames(s, block))
            state, out = jax.lax.scan(blk, state, None, length=nb)
            out = jax.tree.map(lambda a: a.reshape(nb * block, *a.shape[2:]), out)
            if rem:
                state, out2 = frames(state, rem)
                out = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), out, out2)
        else:
            state, out = frames(state, n_frames)
        pos = jnp.concatenate([init.x.T[None], out[0]])
        vel = jnp.concatenate([init.v.T[None], out[1]])
        return pos, vel, out[2], state

    def rollout(self, params: MPMParams, state: MPMState, n_frames: int,
                checkpoint: bool = False, block: int | None = None) -> Trajectory:
        """Roll out ``n_frames`` frames; the Trajectory has T = n_frames + 1 frames
        (frame 0 is ``state``). ``checkpoint``/``block`` trade compute for memory in
        reverse-mode gradients."""
        traj, _, _ = self.run(params, state, n_frames, checkpoint=checkpoint, block=block,
                              check=False)
        return traj

    def run(self, params, state, n_frames, checkpoint=False, block=None, check=True):
        """Like :meth:`rollout` but also returns the final state and per-frame max speed
        (m/s); with ``check`` (outside jit/grad) raises UnstableError on a CFL breach or a
        non-finite state."""
        pos, vel, speed, final = self.rollout_full(params, state, n_frames=n_frames,
                                                   checkpoint=checkpoint, block=block)
        traj = Trajectory(positions=pos, velocities=vel,
                          particle_type=jnp.asarray(self.particle_type()),
                          material=self.material_feature(params),
                          frame_dt=self.scene.frame_dt, bounds=self.scene.domain)
        if check and not isinstance(speed, jax.core.Tracer):
            self.check_stability(params, speed, pos)
        return traj, final, speed

    def courant(self, params: MPMParams, max_speed) -> float:
        """Largest Courant number dt (c + |v|) / dx for the given max particle speed."""
        solid, fluid_c = params.wave_speeds()
        is_fluid = np.array([isinstance(b.material, Fluid) for b in self.scene.bodies])
        c = jnp.max(jnp.where(is_fluid, fluid_c, solid))
        return float(self.dt * (c + jnp.max(max_speed)) / self.dx)

    def check_stability(self, params, speed, pos) -> None:
        if not bool(jnp.all(jnp.isfinite(pos))):
            raise UnstableError("MPM state became non-finite; reduce dt (Scene.cfl) or check "
                                "material parameters")
        cr = self.courant(params, speed)
        if cr > 1.0:
            raise UnstableError(
                f"MPM Courant number reached {cr:.2f} > 1 (max speed {float(jnp.max(speed)):.2f} "
                f"m/s, dt = {self.dt:.2e} s): results are unreliable; set Scene.max_speed higher "
                "or lower Scene.cfl")
