"""Hybrid GNS/MPM rollouts: learned frames with MPM refinement, differentiable end to end.

    hyb = Hybrid(mpm, gns, frame_stride=2, factor=4,
                 schedule=Schedule(warmup=5, gns_frames=10, mpm_frames=2))
    params = HybridParams(mpm.params(), network)                 # network: the GNS weights
    frames, final = rollout(hyb, params, hyb.init(mpm.init()), n_frames=125)
    result, _ = hyb.run(params, mpm.init(), n_frames=125)     # jitted, re-allocates on overflow

Time runs in GNS frames (``frame_stride`` MPM frames each). The first ``warmup`` frames are
MPM frames (they give the GNS its velocity history; with ``Schedule.warmup_settle`` the
warm-up lasts until the flow's kinetic energy has fallen to that fraction of its peak); then
GNS segments of up to
``gns_frames`` frames alternate with MPM segments of ``mpm_frames`` frames. With
``adaptive_tol`` set, a GNS segment also ends as soon as an energy-balance indicator
exceeds ``adaptive_tol`` J/kg: the sum over the segment's GNS frames of
``|dE_gns - dE_mpm|``, where dE is the change of mechanical energy (kinetic + gravitational,
per unit mass) over a frame and dE_mpm the change in the last MPM frame. The MPM's
dissipation rate varies slowly, so a GNS that dissipates much faster or slower (or creates
energy) is drifting from the physics.

The hybrid is a :class:`diffgns.interface.Simulator`: its ``step`` is a ``lax.cond`` between a
GNS frame and ``frame_stride`` MPM frames, and :func:`diffgns.interface.rollout` scans it;
the node history is a rolling window fed by whichever
simulator ran, and every GNS frame also moves the MPM particles (see
:mod:`diffgns.hybrid.handoff`), so either simulator can take over at any frame. Blocks of
frames are ``jax.checkpoint``-ed for reverse mode. ``jax.grad`` with respect to the MPM
parameters flows through the MPM frames and through the GNS material feature (tan phi).
"""
from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.clamp import ClampCount, clamp_summary
from diffgns.graph.data import coarse_grain_map
from diffgns.graph.geometry import obstacle_array
from diffgns.graph.gns import GNS
from diffgns.graph.neighbors import did_overflow, edges
from diffgns.hybrid.handoff import (
    BOUNDARY_SLIP_CELLS,
    HANDOFFS,
    PARTICLE_MAPS,
    lsq_gradient,
    node_means,
    particles_from_nodes,
    specific_energy,
)
from diffgns.interface import rollout_safe

GNS_MODE, MPM_MODE = 0, 1
#: MPM frames before the first GNS frame, unless a :class:`Schedule` says otherwise
DEFAULT_WARMUP = 5


@dataclasses.dataclass(frozen=True)
class Schedule:
    """When each simulator runs (all counts in GNS frames).

    ``Schedule()`` is a fixed schedule: 5 MPM warm-up frames, then 2 GNS frames after every
    8 MPM frames, carrying F, with the affine particle map (``diffgns hybrid``'s default
    until 2026-12-07). ``diffgns hybrid``'s default is :data:`DEFAULT_SCHEDULE`.

    Attributes:
        warmup: MPM frames at the start (>= 1; the GNS needs ``history`` frames of motion to
            be accurate, so ``warmup >= history`` is the sensible choice). With
            ``warmup_settle`` the shortest warm-up.
        warmup_settle: None, or a fraction in (0, 1): the warm-up then lasts until the
            nodes' kinetic energy per unit mass has fallen below this fraction of its peak
            so far (and at least ``warmup`` frames): the MPM runs the flow's fast phase,
            however long it lasts, and the GNS takes over once the flow is settling. A flow
            that never settles stays in the MPM.
        gns_frames: M, GNS frames per segment (the maximum when adaptive). 0: MPM only.
        mpm_frames: K, MPM frames per refinement segment. 0: GNS only after the warm-up.
        handoff: GNS -> MPM deformation state: "reset" (F = I), "carry" (last MPM F) or
            "reconstruct" (F updated with the GNS displacement gradient).
        adaptive_tol: J/kg of accumulated energy-balance deviation that ends a GNS segment
            early (None: fixed schedule).
        particle_map: how particles follow their node in GNS frames: "affine" (with the
            node field's displacement gradient) or "rigid" (the node's displacement).
        min_gns_frames: shortest GNS segment when adaptive.
    """

    warmup: int = DEFAULT_WARMUP
    warmup_settle: float | None = None
    gns_frames: int = 2
    mpm_frames: int = 8
    handoff: str = "carry"
    adaptive_tol: float | None = None
    min_gns_frames: int = 1
    particle_map: str = "affine"

    def __post_init__(self):
        bad = []
        if self.warmup < 1:
            bad.append("warmup >= 1")
        if self.warmup_settle is not None and not 0 < self.warmup_settle < 1:
            bad.append("0 < warmup_settle < 1")
        if self.gns_frames < 0 or self.mpm_frames < 0:
            bad.append("gns_frames, mpm_frames >= 0")
        if self.gns_frames == 0 and self.mpm_frames == 0:
            bad.append("gns_frames + mpm_frames > 0")
        if self.handoff not in HANDOFFS:
            bad.append(f"handoff in {HANDOFFS}")
        if self.adaptive_tol is not None and not self.adaptive_tol > 0:
            bad.append("adaptive_tol > 0")
        if self.min_gns_frames < 1:
            bad.append("min_gns_frames >= 1")
        if self.particle_map not in PARTICLE_MAPS:
            bad.append(f"particle_map in {PARTICLE_MAPS}")
        if bad:
            raise ValueError(f"invalid Schedule ({', '.join(bad)} required): {self}")

    @property
    def label(self) -> str:
        """A name for tables, unique per schedule: ``MPM``, ``GNS``, ``hybrid K=8 M=2
        (carry)``, ..., with the warm-up when it is not :data:`DEFAULT_WARMUP` (``GNS after
        100 MPM frames``)."""
        rigid = " rigid" if self.particle_map == "rigid" else ""
        if self.gns_frames == 0:
            return "MPM"
        warm = "" if self.warmup == DEFAULT_WARMUP else f" after {self.warmup} MPM frames"
        if self.warmup_settle is not None:
            warm = (f" after MPM frames to kinetic energy < {self.warmup_settle:g} of its peak"
                    f" (>= {self.warmup} frames)")
        if self.mpm_frames == 0:
            return "GNS" + rigid + warm
        tag = f"adaptive tol={self.adaptive_tol:g} M<={self.gns_frames}" \
            if self.adaptive_tol else f"M={self.gns_frames}"
        return f"hybrid K={self.mpm_frames} {tag} ({self.handoff}{rigid}){warm}"


#: The hybrid's schedule (``diffgns hybrid``, ``diffgns invert --simulator hybrid`` and
#: :class:`~diffgns.inverse.simulators.HybridSimulator`): the MPM until the flow's kinetic
#: energy per unit mass is below 0.05 of its peak so far (at least 5 frames), then 2 MPM
#: frames after every 8 GNS frames. Chosen on a held-out draw made after the settling
#: warm-up existed (``make granular-fresh3-data``, 48 cases, 2026-12-07): with ``gns_general``
#: it was within 5% / 5% on 47 cases against 44 for a tenth (the default one session before),
#: at a mean position error of 0.007-0.010 against 0.016-0.038 and 70-73% MPM frames against
#: 61-68%, and never worse than the GNS alone (hybrid guide, "A twentieth, on a fresh draw").
DEFAULT_SCHEDULE = Schedule(warmup_settle=0.05, gns_frames=8, mpm_frames=2)


class HybridParams(NamedTuple):
    """Parameters of a hybrid rollout: the MPM's (friction angle, ...) and the GNS weights."""

    mpm: Any
    network: Any


class HybridState(NamedTuple):
    """State of a hybrid rollout.

    Attributes:
        mpm: the MPM state (particles); GNS frames move it too.
        history: (M, C+1, 2) node positions, m, oldest first.
        nbrs: the GNS neighbour list of the nodes.
        indicator: energy-balance deviation accumulated in the current GNS segment, J/kg.
        rate: change of specific mechanical energy in the last MPM frame, J/kg.
        mode: int32, the simulator of the next frame (GNS_MODE or MPM_MODE).
        count: int32, frames run in the current segment.
        used_mpm: bool, the last frame was an MPM frame.
        t: int32, frames advanced since :meth:`Hybrid.init`.
        warming: bool, the next frame is a warm-up frame (the warm-up has not ended).
        peak_ke: the largest kinetic energy per unit mass of the nodes so far, J/kg (kept
            only with ``Schedule.warmup_settle``; 0 otherwise).
        clamp: :class:`~diffgns.clamp.ClampCount` of the last frame: positions moved into the
            domain by the MPM's substeps, the GNS's node prediction or the particle map.
        f_kept: int32, particles of the last frame whose F the "reconstruct" hand-off kept
            (node field's area change outside ``handoff.RECONSTRUCT_JACOBIAN``).
    """

    mpm: Any
    history: jax.Array
    nbrs: Any
    indicator: jax.Array
    rate: jax.Array
    mode: jax.Array
    count: jax.Array
    used_mpm: jax.Array
    t: jax.Array
    warming: jax.Array
    peak_ke: jax.Array
    clamp: ClampCount
    f_kept: jax.Array


class HybridFrame(NamedTuple):
    """What the hybrid observes at a frame: particles (N, 2) m and m/s, nodes (M, 2) m, the
    simulator of the frame just run (1 = MPM), the indicator (J/kg), the overflow flag and
    the frame's position clamps (:class:`~diffgns.clamp.ClampCount`) and the particles whose
    F the "reconstruct" hand-off kept (int32)."""

    positions: jax.Array
    velocities: jax.Array
    nodes: jax.Array
    mode: jax.Array
    indicator: jax.Array
    overflow: jax.Array
    clamp: ClampCount
    f_kept: jax.Array


@dataclasses.dataclass
class HybridResult:
    """Output of :meth:`Hybrid.run` (frames 0..T, T = n_frames, in GNS frames).

    positions: (T+1, N, 2) particle positions, m. nodes: (T+1, M, 2) node positions, m.
    mode: (T,) 0 = GNS frame, 1 = MPM frame. indicator: (T,) energy-balance deviation
    accumulated in the current GNS segment, J/kg (0 on MPM frames). final_state: MPM state
    after the last frame. frame_dt: s. clamped: (T+1,) positions moved into the domain in
    each frame (MPM substeps, GNS nodes, particle map); clamp_shift: (T+1,) largest move, m.
    f_kept: (T+1,) particles whose F the "reconstruct" hand-off kept in each frame (their
    node field's area change was not credible:
    :data:`~diffgns.hybrid.handoff.RECONSTRUCT_JACOBIAN`).
    """

    positions: jax.Array
    nodes: jax.Array
    mode: jax.Array
    indicator: jax.Array
    final_state: object
    frame_dt: float
    clamped: jax.Array
    clamp_shift: jax.Array
    f_kept: jax.Array

    @property
    def mpm_fraction(self) -> float:
        return float(np.mean(np.asarray(self.mode) == MPM_MODE))

    @property
    def warmup_frames(self) -> int:
        """Frames before the first GNS frame (all of them if the GNS never ran)."""
        gns = np.flatnonzero(np.asarray(self.mode) != MPM_MODE)
        return int(gns[0]) if len(gns) else int(np.shape(self.mode)[0])

    def clamp_summary(self) -> dict:
        """:func:`diffgns.clamp.clamp_summary` of the run's clamps, the same split by the
        simulator that made each frame (:meth:`clamps_by_mode`), and ``f_kept_particles``:
        the hand-off's kept deformation gradients, summed over frames."""
        return dict(clamp_summary(self.clamped, self.clamp_shift), **self.clamps_by_mode(),
                    f_kept_particles=int(np.sum(np.asarray(self.f_kept))))

    def clamps_by_mode(self) -> dict:
        """Clamped positions and the largest clamp shift (m), split by the simulator that
        made each frame (``mode``): ``clamped_positions_mpm_frames``,
        ``max_clamp_shift_mpm_frames_m`` and the same for ``gns``. An MPM frame's clamps of
        a few micrometres are the MPM's particles resting on a wall; a GNS frame's are the
        GNS's nodes and the particle map's."""
        count, shift = np.asarray(self.clamped)[1:], np.asarray(self.clamp_shift)[1:]
        mpm = np.asarray(self.mode) == MPM_MODE
        out = {}
        for name, sel in (("mpm", mpm), ("gns", ~mpm)):
            out[f"clamped_positions_{name}_frames"] = int(count[sel].sum())
            out[f"max_clamp_shift_{name}_frames_m"] = float(shift[sel].max(initial=0.0))
        return out


class Hybrid:
    """A hybrid simulator for one MPM scene and one trained GNS (static parts).

    Args:
        mpm: the :class:`~diffgns.mpm.MPM` of the scene.
        gns: the trained :class:`~diffgns.graph.gns.GNS` (its weights go in
            :class:`HybridParams`).
        frame_stride: MPM frames per GNS frame.
        factor: particles per node (coarse-graining of the initial particles).
        schedule: :class:`Schedule`.
        geometry: the walls and obstacles the network sees
            (:class:`~diffgns.graph.geometry.Geometry`; default ``gns``'s box, no obstacle;
            :meth:`GNS.for_scene <diffgns.graph.gns.GNS.for_scene>` gives both for a scene).
    """

    def __init__(self, mpm, gns: GNS, frame_stride: int, factor: int,
                 schedule: Schedule = DEFAULT_SCHEDULE, geometry=None):
        if gns.config.history > schedule.warmup and schedule.gns_frames > 0:
            raise ValueError(f"Schedule.warmup = {schedule.warmup} frames is shorter than the "
                             f"GNS history ({gns.config.history}): the first GNS frame would "
                             "see a made-up velocity history")
        self.mpm, self.gns = mpm, gns
        self.geometry = gns.geometry() if geometry is None else geometry
        self.stride, self.schedule = int(frame_stride), schedule
        x0 = np.asarray(mpm.init().x).T
        cid = coarse_grain_map(x0, factor)
        self.cluster = jnp.asarray(cid, jnp.int32)
        self.counts = jnp.asarray(np.bincount(cid), mpm.dtype)
        first = np.zeros(cid.max() + 1, np.int64)
        first[cid[::-1]] = np.arange(len(cid))[::-1]
        self.first = first
        self.node_type = jnp.asarray(mpm.particle_type()[first])
        self.frame_dt = float(mpm.scene.frame_dt) * self.stride
        self.lo = jnp.asarray(mpm.lo, mpm.dtype)
        self.hi = jnp.asarray(mpm.hi, mpm.dtype)
        # the particle map keeps particles out of the scene's box obstacles (K, 4) m
        self.obstacles = jnp.asarray(obstacle_array(
            [tuple(o.lower) + tuple(o.upper) for o in mpm.scene.obstacles]), mpm.dtype)
        # the particle map keeps particles half a particle spacing from the walls (m)
        self.margin = 0.5 * min(mpm.scene.dx / np.sqrt(b.particles_per_cell)
                                for b in mpm.scene.bodies)
        # mapped particles this close to a wall or obstacle face move along it, not into it
        self.slip_band = BOUNDARY_SLIP_CELLS * float(mpm.scene.dx)

    @property
    def n_nodes(self) -> int:
        return int(self.counts.shape[0])

    def nodes(self, state) -> jax.Array:
        """(M, 2) node positions of an MPM state."""
        return node_means(state.x, self.cluster, self.counts)

    def node_material(self, mpm_params) -> jax.Array:
        """(M,) GNS material feature (tan phi) of every node."""
        return self.mpm.material_feature(mpm_params)[self.first]

    # ------------------------------------------------------------- interface
    def init(self, mpm_state, extra_capacity: int = 0) -> HybridState:
        """Initial state from an MPM state (outside jit: allocates the node neighbour list).

        The node history starts as the initial nodes repeated; the warm-up MPM frames
        replace it before the first GNS frame.
        """
        x = self.nodes(mpm_state)
        hist = jnp.repeat(x[:, None], self.gns.config.history + 1, axis=1)
        zero = jnp.zeros((), mpm_state.x.dtype)
        i0 = jnp.asarray(0, jnp.int32)
        return HybridState(mpm_state, hist, self.gns.allocate(x, extra_capacity), zero, zero,
                           jnp.asarray(MPM_MODE, jnp.int32), i0, jnp.asarray(True), i0,
                           jnp.asarray(True), zero, ClampCount.zero(mpm_state.x.dtype), i0)

    def step(self, params: HybridParams, state: HybridState) -> HybridState:
        """One GNS frame or ``frame_stride`` MPM frames, as the schedule says (pure)."""
        sched = self.schedule
        t = state.t
        use_mpm = state.warming | (state.mode == MPM_MODE)
        material = self.node_material(params.mpm)
        state = jax.lax.cond(use_mpm, lambda s: self._mpm_frame(params.mpm, s),
                             lambda s: self._gns_frame(params, material, s), state)
        warm = state.warming & (t + 1 < sched.warmup)
        peak = state.peak_ke
        if sched.warmup_settle is not None:  # and until the flow settles
            ke = self._kinetic_energy(state.history)
            peak = jnp.maximum(peak, ke)
            warm |= state.warming & ~(ke < sched.warmup_settle * peak)
        count = state.count + 1
        if sched.gns_frames == 0:
            next_mode = jnp.asarray(MPM_MODE)
        elif sched.mpm_frames == 0:
            next_mode = jnp.where(warm, MPM_MODE, GNS_MODE)
        else:
            mpm_done = ~warm & (state.warming | (count >= sched.mpm_frames))
            gns_done = count >= sched.gns_frames
            if sched.adaptive_tol is not None:
                gns_done |= (count >= sched.min_gns_frames) & (
                    state.indicator > sched.adaptive_tol)
            next_mode = jnp.where(use_mpm, jnp.where(mpm_done, GNS_MODE, MPM_MODE),
                                  jnp.where(gns_done, MPM_MODE, GNS_MODE))
        next_mode = next_mode.astype(jnp.int32)
        switched = next_mode != jnp.where(use_mpm, MPM_MODE, GNS_MODE)
        count = jnp.where(switched, 0, count).astype(jnp.int32)
        return state._replace(mode=next_mode, count=count, used_mpm=use_mpm, t=t + 1,
                              warming=warm, peak_ke=peak)

    def observe(self, state: HybridState) -> HybridFrame:
        """Particles, nodes, mode of the last frame, indicator and overflow flag."""
        return HybridFrame(state.mpm.x.T, state.mpm.v.T, state.history[:, -1],
                           state.used_mpm.astype(jnp.int32), state.indicator,
                           did_overflow(state.nbrs), state.clamp, state.f_kept)

    def reallocate(self, state: HybridState, frames: HybridFrame, first_bad: int,
                   attempt: int) -> HybridState:
        """``state`` with a larger node neighbour list (outside jit), sized at the nodes of
        the last valid frame before the overflow at frame ``first_bad``, with the GNS's
        compaction check (:meth:`~diffgns.graph.gns.GNS.grown_neighbors`)."""
        return state._replace(nbrs=self.gns.grown_neighbors(state.nbrs, frames.nodes,
                                                            first_bad, attempt))

    # ---------------------------------------------------------------- frames
    def _kinetic_energy(self, hist):
        """Kinetic energy per unit mass (J/kg) of the nodes' last frame (no gradient: it
        only decides the schedule)."""
        zero = jnp.zeros(hist.shape[-1], hist.dtype)
        return jax.lax.stop_gradient(
            specific_energy(hist[:, -2], hist[:, -1], self.counts, zero, self.frame_dt))

    def _energy_change(self, params, hist, x_next):
        """Change of mechanical energy per unit mass (J/kg) over the frame to ``x_next``."""
        g = params.gravity.astype(hist.dtype)
        return jax.lax.stop_gradient(
            specific_energy(hist[:, -1], x_next, self.counts, g, self.frame_dt)
            - specific_energy(hist[:, -2], hist[:, -1], self.counts, g, self.frame_dt))

    def _mpm_frame(self, mpm_params, s: HybridState) -> HybridState:
        mpm_state = s.mpm
        clamp = ClampCount.zero(s.mpm.x.dtype)
        for _ in range(self.stride):
            mpm_state = self.mpm.step(mpm_params, mpm_state)
            clamp = clamp.merge(mpm_state.clamp)
        x_next = self.nodes(mpm_state)
        rate = self._energy_change(mpm_params, s.history, x_next)
        hist = jnp.concatenate([s.history[:, 1:], x_next[:, None]], axis=1)
        return s._replace(mpm=mpm_state, history=hist, indicator=jnp.zeros_like(s.indicator),
                          rate=rate, clamp=clamp, f_kept=jnp.zeros_like(s.f_kept))

    def _gns_frame(self, params: HybridParams, material, s: HybridState) -> HybridState:
        hist = s.history
        x = hist[:, -1]
        x_next, nbrs, node_clamp = self.gns.advance(params.network, hist, self.node_type,
                                                    material, s.nbrs, None, self.geometry)
        x_next = x_next.astype(hist.dtype)
        snd, rcv, msk = edges(nbrs, x.shape[0])
        disp = x_next - x
        # velocity at the end of the frame, where the MPM takes over: the backward difference
        # disp / dt is the frame's mean (half a frame late, a dt / 2 off in a collapse), so
        # add half the frame's change of it (second-order backward difference)
        vel = (1.5 * disp - 0.5 * (x - hist[:, -2])) / self.frame_dt
        grad_v = lsq_gradient(vel, x_next, snd, rcv, msk)
        sched = self.schedule
        needs_grad_u = sched.particle_map == "affine" or sched.handoff == "reconstruct"
        grad_u = lsq_gradient(disp, x, snd, rcv, msk) if needs_grad_u else jnp.zeros_like(grad_v)
        mpm_state, map_clamp, f_kept = particles_from_nodes(
            s.mpm, self.cluster, x, disp, vel, grad_v, grad_u, sched.handoff, self.lo,
            self.hi, sched.particle_map, self.margin, self.obstacles,
            reach=self.gns.config.radius,  # no further than the gradients' fit reaches
            slip_band=self.slip_band)
        if sched.handoff == "reconstruct":  # plastic return mapping of the new F
            mpm_state = mpm_state.replace(F=self.mpm.stress(params.mpm, mpm_state)[1])
        # Energy-balance indicator: deviation of the GNS's energy change per frame from the
        # rate the MPM showed in its last frame (J/kg, accumulated over the segment).
        indicator = s.indicator + jnp.abs(
            self._energy_change(params.mpm, hist, x_next) - s.rate)
        hist = jnp.concatenate([hist[:, 1:], x_next[:, None]], axis=1)
        return s._replace(mpm=mpm_state, history=hist, nbrs=nbrs, indicator=indicator,
                          clamp=node_clamp.merge(map_clamp), f_kept=f_kept)

    # ------------------------------------------------------------------ public
    def run(self, params: HybridParams, mpm_state, n_frames: int,
            checkpoint_block: int | None = None, state: HybridState | None = None,
            max_retries: int = 4) -> tuple[HybridResult, HybridState]:
        """Jitted rollout of ``n_frames`` frames with neighbour re-allocation on overflow
        (outside jit). Returns ``(HybridResult, initial state)``; the initial state's list
        fits this rollout (pass it as ``state`` to reuse it)."""
        state = self.init(mpm_state) if state is None else state
        frames, final, state = rollout_safe(self, params, state, n_frames,
                                            checkpoint_block=checkpoint_block,
                                            max_retries=max_retries)
        return HybridResult(frames.positions, frames.nodes, frames.mode[1:],
                            frames.indicator[1:], final.mpm, self.frame_dt,
                            frames.clamp.moved, frames.clamp.shift, frames.f_kept), state
