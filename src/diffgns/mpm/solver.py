"""The explicit MLS-MPM solver assembled from a scene's declared effects.

    sim = MPM(scene)
    params, state = sim.params(), sim.init()
    frames, final = rollout(sim, params, state, n_frames=200)   # diffgns.rollout
    traj, final = sim.run(params, state, 200)                    # Trajectory + stability check

The MPM is a :class:`diffgns.interface.Simulator`: ``step(params, state)`` advances one frame
(``scene.substeps`` substeps of ``substep``; with ``checkpoint_substeps`` each is
``jax.checkpoint``-ed so reverse mode stores one state per frame), ``observe(state)`` gives
a :class:`~diffgns.interface.ParticleFrame`.

On a CPU with two host devices (diffgns asks for them, :mod:`diffgns.hostdevices`) a frame of
a scene with enough particles runs *sharded*: the particles are split over the devices
(``jax.shard_map``; each material group padded to a multiple of the device count with
massless copies), each device scatters its share into a full grid, one ``psum`` adds the
grids, and every device runs the grid update and the G2P of its share. The same
:meth:`MPM._substep` serves both layouts; the state a user sees is the same either way.

On the CPU a 2D frame also runs its particles in a *shuffled order* (``particle_order``):
XLA's CPU scatter-add is a serial loop over rows, and a scene built cell by cell hands it
runs of rows that add into the same grid nodes one after the other. Inside blocks of
:data:`ORDER_BLOCK` consecutive particles the frame permutes them once (fixed seed, a
per-frame gather in and out, as the sharded frame does anyway): 1.2-1.3x faster frames of
the 2D sand column at 8,100 particles and ~1.1-1.2x at 32,400, no gain in 3D
(``benchmarks/mpm_levers.py``, docs/performance.md).
"""
from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from diffgns import hostdevices
from diffgns.clamp import ClampCount, clamp_positions
from diffgns.errors import InputError, UnstableError
from diffgns.interface import ParticleFrame, rollout_jit
from diffgns.mpm import boundaries, constitutive
from diffgns.mpm import linalg as la
from diffgns.mpm.shape import stencil
from diffgns.mpm.state import MPMParams, MPMState
from diffgns.mpm.transfer import g2p, grid_velocity, p2g
from diffgns.scene.materials import Fluid, Sand, friction_feature
from diffgns.trajectory import ELASTIC, FLUID, SAND, Trajectory

AXIS = "particles"  # the shard_map axis of the sharded substep
#: particles permuted within blocks of this many (``particle_order="auto"`` on the CPU, 2D)
ORDER_BLOCK = 1024
#: seed of that permutation (fixed: the same scene always runs in the same order)
ORDER_SEED = 0


@dataclasses.dataclass(frozen=True)
class Share:
    """The particles one substep sees (static): all of them, or one device's share.

    Attributes:
        groups: particle slices per material effect, e.g. {"sand": slice(0, 1200)}.
        single: per group, its one body id, or None when it holds several bodies (then
            per-particle parameters are gathered with the body ids passed to the substep).
        axis: the ``shard_map`` axis to sum the grid and the clamp counts over (None: the
            substep sees every particle).
    """

    groups: dict[str, slice]
    single: dict[str, int | None]
    axis: str | None = None


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
        devices: host devices a frame is sharded over: ``"auto"`` (default: every local CPU
            device when the backend is the CPU and the scene has at least
            :data:`diffgns.hostdevices.AUTO_MIN_PARTICLES` particles, 3D
            :data:`~diffgns.hostdevices.AUTO_MIN_PARTICLES_3D`), ``1`` or None (one
            device), an integer, or a list of jax devices
            (:func:`diffgns.hostdevices.mpm_devices`). Results agree with one device to
            float round-off (the grid is summed in another order).
        particle_order: the order a frame runs its particles in: ``"auto"`` (default:
            shuffled within blocks of :data:`ORDER_BLOCK` for 2D scenes on the CPU backend,
            as given otherwise), ``"shuffled"`` or ``"given"``. States and trajectories are
            always in the scene's order; results agree to float round-off (the grid sums in
            another order).
    """

    def __init__(self, scene, dtype=None, checkpoint_substeps: bool = False,
                 devices: Any = "auto", particle_order: str = "auto"):
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
        self.share = Share(self.groups, self._single_bodies(self.groups, self.body))
        self.devices = hostdevices.mpm_devices(devices, len(self.body), self.dim)
        self.shuffled = _shuffled(particle_order, self.dim)
        self._layout = (self._frame_layout(len(self.devices or [None]))
                        if self.devices is not None or self.shuffled else None)

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
    @staticmethod
    def _single_bodies(groups: dict[str, slice], body: np.ndarray) -> dict[str, int | None]:
        out: dict[str, int | None] = {}
        for eff, sl in groups.items():
            ids = body[sl]
            out[eff] = int(ids[0]) if np.all(ids == ids[0]) else None
        return out

    @staticmethod
    def _per_particle(arr, body, share: Share, eff: str, sl: slice):
        one = share.single[eff]
        if one is not None:
            return arr[one]  # one body in the group: a broadcast scalar
        return arr[body[sl]]

    def stress(self, params: MPMParams, state: MPMState, F=None, *, body=None,
               share: Share | None = None):
        """Kirchhoff stress tau (d,d,N) Pa and projected F of every particle (``body``,
        ``share``: the particles' body ids and :class:`Share`, default the scene's)."""
        F = state.F if F is None else F
        body = self.body if body is None else body
        share = self.share if share is None else share
        taus, Fs = [], []
        for eff, sl in share.groups.items():
            Fg = F[:, :, sl]
            pp = partial(self._per_particle, body=body, share=share, eff=eff, sl=sl)
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

    def mass(self, params: MPMParams, state: MPMState, body=None) -> jax.Array:
        """(N,) particle masses, kg (``body``: the particles' body ids, default the
        scene's)."""
        return params.rho[self.body if body is None else body] * state.vol

    def substep(self, params: MPMParams, state: MPMState) -> MPMState:
        """One explicit MLS-MPM substep of ``self.dt`` seconds (on one device; :meth:`step`
        shards its substeps when the MPM has several devices)."""
        return self._substep(params, state, self.body, self.share)

    def _substep(self, params: MPMParams, state: MPMState, body, share: Share,
                 real=None) -> MPMState:
        """The substep on the particles of ``share``: every particle (``share.axis`` None),
        or one device's share inside ``shard_map`` (grid and clamp counts summed over
        ``share.axis``). ``body``: (n,) body ids of these particles; ``real``: (n,) bool,
        False for padding (counted in no clamp), None when all are real."""
        dt, dx, n_nodes, d = self.dt, self.dx, self.n_nodes, self.dim
        F_trial = state.F + dt * la.matmul(state.C, state.F)
        tau, F = self.stress(params, state, F_trial, body=body, share=share)
        mass = self.mass(params, state, body)
        X = (state.x - jnp.asarray(self.origin, state.x.dtype)[:, None]) / dx
        idx, w, dpos = stencil(X, self.grid_shape)
        affine = mass * state.C - (dt * 4.0 / dx**2) * state.vol * tau
        flip = "flip" in self.effects  # also scatter the momentum before the forces
        grid = p2g(idx, w, dpos, mass, mass * state.v, affine, n_nodes, dx,
                   affine_free=mass * state.C if flip else None)
        if share.axis is not None:
            grid = jax.lax.psum(grid, share.axis)
        gv = grid_velocity(grid[:, : d + 1])
        if "gravity" in self.effects:
            gv = gv + dt * params.gravity[:, None]
        if "damping" in self.effects:
            gv = gv * jnp.exp(-dt * params.damping)
        gv = boundaries.apply_walls(gv.reshape(d, *self.grid_shape), self.scene.wall_list,
                                    params.wall_mu, self.scene.padding, self.scene.n_cells)
        gv = gv.reshape(d, n_nodes)
        if self.obstacle_nodes:
            gv = boundaries.apply_obstacles(gv, self.obstacle_nodes, params.obstacle_mu)
        if flip:  # the particle's own velocity plus the grid's change, blended with APIC
            gv_free = grid_velocity(jnp.concatenate([grid[:, d + 1:], grid[:, d:d + 1]], 1))
            v_grid, C, dv = g2p(idx, w, dpos, gv.reshape(d, *self.grid_shape), dx,
                                extra=(gv - gv_free).reshape(d, *self.grid_shape))
            v = self.scene.flip * (state.v + dv) + (1.0 - self.scene.flip) * v_grid
        else:
            v_grid, C = g2p(idx, w, dpos, gv.reshape(d, *self.grid_shape), dx)
            v = v_grid
        x = state.x + dt * v_grid  # positions move with the grid velocity
        lo, hi = jnp.asarray(self.lo, x.dtype), jnp.asarray(self.hi, x.dtype)
        # never leave the domain (and the grid), and count it (diffgns.clamp)
        x, clamp = clamp_positions(x, lo[:, None], hi[:, None], axis=0, valid=real)
        if share.axis is not None:
            clamp = ClampCount(jax.lax.psum(clamp.moved, share.axis),
                               jax.lax.pmax(clamp.shift, share.axis))
        return state.replace(x=x, v=v, C=C, F=F, clamp=state.clamp.merge(clamp))

    def step(self, params: MPMParams, state: MPMState) -> MPMState:
        """Advance one frame (``scene.substeps`` substeps of ``scene.substep_dt`` s), on one
        device or sharded over ``self.devices`` (not under ``jax.disable_jit``)."""
        state = state.replace(clamp=ClampCount.zero(state.x.dtype))  # counts of this frame
        # eagerly (jax.disable_jit) a shard_map runs op by op per device, far slower than the
        # one-device substeps in the given order, which give the same frame up to round-off
        if self._layout is not None and not jax.config.jax_disable_jit:
            return self._step_laid_out(params, state)
        return self._substeps(params, state, self.body, self.share)

    def _substeps(self, params: MPMParams, state: MPMState, body, share: Share,
                  real=None) -> MPMState:
        """``scene.substeps`` substeps in one ``lax.scan`` (each ``jax.checkpoint``-ed with
        :attr:`checkpoint_substeps`) on the particles of ``share``."""
        sub = partial(self._substep, body=body, share=share, real=real)
        if self.checkpoint_substeps:
            sub = jax.checkpoint(sub, prevent_cse=False)
        return jax.lax.scan(lambda c, _: (sub(params, c), None), state, None,
                            length=self.n_sub)[0]

    # --------------------------------------------------- particle order and sharding
    def _frame_layout(self, n_dev: int) -> dict[str, Any]:
        """Static layout of a frame over ``n_dev`` devices (1: one device, shuffled order):
        every material group split into ``n_dev`` equal parts (padded with copies of its
        first particle), device ``k``'s block holding part ``k`` of each group in group
        order; with :attr:`shuffled`, each part permuted within blocks of
        :data:`ORDER_BLOCK` (:func:`block_permutation`).

        Returns ``src`` (n_dev M,) the particle of each slot, ``real`` (n_dev M,) bool,
        ``slot`` (N,) the slot of each particle, ``body`` (n_dev M,) body ids, the
        per-device :class:`Share` and the device ``mesh`` (None for one device)."""
        parts = [(eff, sl, -(-(sl.stop - sl.start) // n_dev)) for eff, sl in
                 self.groups.items()]
        M = sum(m for _, _, m in parts)
        src = np.zeros(n_dev * M, np.int64)
        real = np.zeros(n_dev * M, bool)
        local: dict[str, slice] = {}
        rng = np.random.default_rng(ORDER_SEED)
        start = 0
        for eff, sl, m in parts:
            local[eff] = slice(start, start + m)
            for k in range(n_dev):
                ids = np.arange(sl.start + k * m, min(sl.start + (k + 1) * m, sl.stop))
                if self.shuffled:
                    ids = ids[block_permutation(len(ids), ORDER_BLOCK, rng)]
                at = k * M + start
                src[at:at + m] = sl.start  # padding: a massless copy of the group's first
                src[at:at + len(ids)] = ids
                real[at:at + len(ids)] = True
            start += m
        slot = np.empty(len(self.body), np.int64)
        slot[src[real]] = np.flatnonzero(real)
        sharded = n_dev > 1
        mesh = jax.sharding.Mesh(np.array(self.devices), (AXIS,)) if sharded else None
        return dict(src=src, real=real, slot=slot, body=self.body[src].astype(np.int32),
                    share=Share(local, self.share.single, AXIS if sharded else None),
                    mesh=mesh)

    def _step_laid_out(self, params: MPMParams, state: MPMState) -> MPMState:
        """One frame in the static layout: the state gathered into it, the substeps (in
        ``shard_map`` over the devices when there are several), gathered back."""
        from jax.sharding import PartitionSpec as Spec

        lay = self._layout
        assert lay is not None
        src, slot, share = lay["src"], lay["slot"], lay["share"]
        padded = state.replace(x=state.x[:, src], v=state.v[:, src], C=state.C[..., src],
                               F=state.F[..., src],
                               vol=jnp.where(lay["real"], state.vol[src], 0.0))
        if lay["mesh"] is None:  # one device: no padding, every slot real
            out = self._substeps(params, padded, lay["body"], share)
        else:
            vec, mat = Spec(None, AXIS), Spec(None, None, AXIS)
            spec = state.replace(x=vec, v=vec, C=mat, F=mat, vol=Spec(AXIS),
                                 clamp=ClampCount(Spec(), Spec()))
            out = jax.shard_map(lambda p, s, b, r: self._substeps(p, s, b, share, r),
                                mesh=lay["mesh"],
                                in_specs=(Spec(), spec, Spec(AXIS), Spec(AXIS)),
                                out_specs=spec)(params, padded, lay["body"], lay["real"])
        return out.replace(x=out.x[:, slot], v=out.v[:, slot], C=out.C[..., slot],
                           F=out.F[..., slot], vol=state.vol)

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


def _shuffled(particle_order: str, dim: int) -> bool:
    """Whether a frame runs its particles shuffled (see :class:`MPM`'s ``particle_order``)."""
    if particle_order == "auto":
        return jax.default_backend() == "cpu" and dim == 2
    if particle_order in ("shuffled", "given"):
        return particle_order == "shuffled"
    raise InputError("particle_order", f"{particle_order!r} is not an order",
                     "give 'auto', 'shuffled' or 'given'")


def block_permutation(n: int, block: int, rng: np.random.Generator) -> np.ndarray:
    """(n,) permutation of ``range(n)`` that shuffles each run of ``block`` consecutive
    indices (the last run may be shorter) and keeps the runs in place: particles stay near
    their neighbours in memory, but consecutive scatter rows rarely share a grid node."""
    perm = np.arange(n)
    for s in range(0, n, block):
        perm[s:s + block] = perm[s:s + block][rng.permutation(min(block, n - s))]
    return perm
