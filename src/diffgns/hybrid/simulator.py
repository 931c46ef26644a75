"""Hybrid GNS/MPM rollouts: learned frames with MPM refinement, differentiable end to end.

    hyb = Hybrid(mpm, gns, gns_params, frame_stride=2, factor=4,
                 schedule=Schedule(warmup=5, gns_frames=10, mpm_frames=2))
    out = hyb.run(mpm.params(), mpm.init_state(), n_frames=125)

Time runs in GNS frames (``frame_stride`` MPM frames each). The first ``warmup`` frames are
MPM frames (they give the GNS its velocity history); then GNS segments of up to
``gns_frames`` frames alternate with MPM segments of ``mpm_frames`` frames. With
``adaptive_tol`` set, a GNS segment also ends as soon as an energy-balance indicator
exceeds ``adaptive_tol`` J/kg: the sum over the segment's GNS frames of
``|dE_gns - dE_mpm|``, where dE is the change of mechanical energy (kinetic + gravitational,
per unit mass) over a frame and dE_mpm the change in the last MPM frame. The MPM's
dissipation rate varies slowly, so a GNS that dissipates much faster or slower (or creates
energy) is drifting from the physics.

The whole loop is one ``lax.scan`` over frames whose body is a ``lax.cond`` between a GNS
frame and ``frame_stride`` MPM frames; the node history is a rolling window fed by whichever
simulator ran, and every GNS frame also moves the MPM particles (see
:mod:`diffgns.hybrid.handoff`), so either simulator can take over at any frame. Blocks of
frames are ``jax.checkpoint``-ed for reverse mode. ``jax.grad`` with respect to the MPM
parameters flows through the MPM frames and through the GNS material feature (tan phi).
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.graph.data import coarse_grain_map
from diffgns.graph.gns import GNS
from diffgns.graph.neighbors import did_overflow, edges
from diffgns.hybrid.handoff import (
    HANDOFFS,
    PARTICLE_MAPS,
    lsq_gradient,
    node_means,
    particles_from_nodes,
    specific_energy,
)

GNS_MODE, MPM_MODE = 0, 1


@dataclasses.dataclass(frozen=True)
class Schedule:
    """When each simulator runs (all counts in GNS frames).

    Attributes:
        warmup: MPM frames at the start (>= 1; the GNS needs ``history`` frames of motion to
            be accurate, so ``warmup >= history`` is the sensible choice).
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

    warmup: int = 5
    gns_frames: int = 10
    mpm_frames: int = 2
    handoff: str = "carry"
    adaptive_tol: float | None = None
    min_gns_frames: int = 1
    particle_map: str = "affine"

    def __post_init__(self):
        bad = []
        if self.warmup < 1:
            bad.append("warmup >= 1")
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
        rigid = " rigid" if self.particle_map == "rigid" else ""
        if self.gns_frames == 0:
            return "MPM"
        if self.mpm_frames == 0:
            return "GNS" + rigid
        tag = f"adaptive tol={self.adaptive_tol:g} M<={self.gns_frames}" \
            if self.adaptive_tol else f"M={self.gns_frames}"
        return f"hybrid K={self.mpm_frames} {tag} ({self.handoff}{rigid})"


@dataclasses.dataclass
class HybridResult:
    """Output of :meth:`Hybrid.run` (frames 0..T, T = n_frames, in GNS frames).

    positions: (T+1, N, 2) particle positions, m. nodes: (T+1, M, 2) node positions, m.
    mode: (T,) 0 = GNS frame, 1 = MPM frame. indicator: (T,) energy-balance deviation
    accumulated in the current GNS segment, J/kg (0 on MPM frames). final_state: MPM state
    after the last frame. frame_dt: s.
    """

    positions: jax.Array
    nodes: jax.Array
    mode: jax.Array
    indicator: jax.Array
    final_state: object
    frame_dt: float

    @property
    def mpm_fraction(self) -> float:
        return float(np.mean(np.asarray(self.mode) == MPM_MODE))


class Hybrid:
    """A hybrid simulator for one MPM scene and one trained GNS (static parts)."""

    def __init__(self, mpm, gns: GNS, gns_params, frame_stride: int, factor: int,
                 schedule: Schedule = Schedule(), checkpoint_block: int | None = None):
        if gns.config.history > schedule.warmup and schedule.gns_frames > 0:
            raise ValueError(f"Schedule.warmup = {schedule.warmup} frames is shorter than the "
                             f"GNS history ({gns.config.history}): the first GNS frame would "
                             "see a made-up velocity history")
        self.mpm, self.gns, self.gns_params = mpm, gns, gns_params
        self.stride, self.schedule = int(frame_stride), schedule
        self.checkpoint_block = checkpoint_block
        x0 = np.asarray(mpm.init_state().x).T
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
        self._run = jax.jit(self._rollout, static_argnames=("n_frames",))

    @property
    def n_nodes(self) -> int:
        return int(self.counts.shape[0])

    def nodes(self, state) -> jax.Array:
        """(M, 2) node positions of an MPM state."""
        return node_means(state.x, self.cluster, self.counts)

    def node_material(self, mpm_params) -> jax.Array:
        """(M,) GNS material feature (tan phi) of every node."""
        return self.mpm.material_feature(mpm_params)[self.first]

    # ---------------------------------------------------------------- frames
    def _energy_change(self, params, hist, x_next):
        """Change of mechanical energy per unit mass (J/kg) over the frame to ``x_next``."""
        g = params.gravity.astype(hist.dtype)
        return jax.lax.stop_gradient(
            specific_energy(hist[:, -1], x_next, self.counts, g, self.frame_dt)
            - specific_energy(hist[:, -2], hist[:, -1], self.counts, g, self.frame_dt))

    def _mpm_frame(self, params, carry):
        state, hist, nbrs, indicator, rate = carry
        ckpt = self.checkpoint_block is not None
        for _ in range(self.stride):
            state = self.mpm.frame(params, state, checkpoint=ckpt)
        x_next = self.nodes(state)
        rate = self._energy_change(params, hist, x_next)
        hist = jnp.concatenate([hist[:, 1:], x_next[:, None]], axis=1)
        return (state, hist, nbrs, jnp.zeros_like(indicator), rate), jnp.zeros((), bool)

    def _gns_frame(self, params, gns_params, material, carry):
        state, hist, nbrs, indicator, rate = carry
        x = hist[:, -1]
        x_next, nbrs = self.gns.step(gns_params, hist, self.node_type, material, nbrs)
        x_next = x_next.astype(hist.dtype)
        s, r, m = edges(nbrs, x.shape[0])
        disp = x_next - x
        vel = disp / self.frame_dt
        grad_v = lsq_gradient(vel, x_next, s, r, m)
        sched = self.schedule
        needs_grad_u = sched.particle_map == "affine" or sched.handoff == "reconstruct"
        grad_u = lsq_gradient(disp, x, s, r, m) if needs_grad_u else jnp.zeros_like(grad_v)
        state = particles_from_nodes(state, self.cluster, x, disp, vel, grad_v, grad_u,
                                     sched.handoff, self.lo, self.hi, sched.particle_map)
        if sched.handoff == "reconstruct":  # plastic return mapping of the new F
            state = state.replace(F=self.mpm.stress(params, state)[1])
        # Energy-balance indicator: deviation of the GNS's energy change per frame from the
        # rate the MPM showed in its last frame (J/kg, accumulated over the segment).
        indicator = indicator + jnp.abs(self._energy_change(params, hist, x_next) - rate)
        hist = jnp.concatenate([hist[:, 1:], x_next[:, None]], axis=1)
        return (state, hist, nbrs, indicator, rate), did_overflow(nbrs)

    def _frame(self, params, gns_params, material, carry, t):
        sched = self.schedule
        sim, mode, count = carry[:5], carry[5], carry[6]
        use_mpm = (t < sched.warmup) | (mode == MPM_MODE)
        sim, over = jax.lax.cond(use_mpm, lambda c: self._mpm_frame(params, c),
                                 lambda c: self._gns_frame(params, gns_params, material, c),
                                 sim)
        count = count + 1
        indicator = sim[3]
        warm = t + 1 < sched.warmup
        if sched.gns_frames == 0:
            next_mode = jnp.asarray(MPM_MODE)
        elif sched.mpm_frames == 0:
            next_mode = jnp.where(warm, MPM_MODE, GNS_MODE)
        else:
            mpm_done = ~warm & ((t + 1 == sched.warmup) | (count >= sched.mpm_frames))
            gns_done = count >= sched.gns_frames
            if sched.adaptive_tol is not None:
                gns_done |= (count >= sched.min_gns_frames) & (indicator > sched.adaptive_tol)
            next_mode = jnp.where(use_mpm, jnp.where(mpm_done, GNS_MODE, MPM_MODE),
                                  jnp.where(gns_done, MPM_MODE, GNS_MODE))
        next_mode = next_mode.astype(jnp.int32)
        switched = next_mode != jnp.where(use_mpm, MPM_MODE, GNS_MODE)
        count = jnp.where(switched, 0, count).astype(jnp.int32)
        out = (sim[1][:, -1], sim[0].x.T, use_mpm.astype(jnp.int32), indicator, over)
        return (*sim, next_mode, count), out

    def _rollout(self, params, gns_params, state, nbrs, n_frames: int):
        x = self.nodes(state)
        hist = jnp.repeat(x[:, None], self.gns.config.history + 1, axis=1)
        zero = jnp.zeros((), state.x.dtype)
        carry = (state, hist, nbrs, zero, zero,
                 jnp.asarray(MPM_MODE, jnp.int32), jnp.asarray(0, jnp.int32))
        ts = jnp.arange(n_frames)
        material = self.node_material(params)  # once per rollout, not per frame
        body = lambda c, t: self._frame(params, gns_params, material, c, t)  # noqa: E731
        B = self.checkpoint_block
        if B and n_frames > B:
            nb, rem = divmod(n_frames, B)
            blk = jax.checkpoint(lambda c, tb: jax.lax.scan(body, c, tb))
            carry, out = jax.lax.scan(blk, carry, ts[: nb * B].reshape(nb, B))
            out = jax.tree.map(lambda a: a.reshape(nb * B, *a.shape[2:]), out)
            if rem:
                carry, o2 = jax.lax.scan(body, carry, ts[nb * B:])
                out = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), out, o2)
        else:
            carry, out = jax.lax.scan(body, carry, ts)
        nodes = jnp.concatenate([x[None], out[0]])
        parts = jnp.concatenate([state.x.T[None], out[1]])
        return nodes, parts, out[2], out[3], out[4], carry[0]

    # ------------------------------------------------------------------ public
    def allocate(self, state, extra_capacity: int = 0):
        """GNS neighbour list for the nodes of ``state`` (outside jit)."""
        return self.gns.allocate(self.nodes(state), extra_capacity)

    def rollout(self, params, state, n_frames: int, nbrs, gns_params=None):
        """Traceable rollout (use under ``jax.grad``); returns ``(positions (T+1, N, 2),
        nodes (T+1, M, 2), overflowed)``; an overflow means the result is invalid
        (re-allocate ``nbrs``)."""
        gp = self.gns_params if gns_params is None else gns_params
        nodes, parts, _, _, over, _ = self._rollout(params, gp, state, nbrs, n_frames)
        return parts, nodes, jnp.any(over)

    def run(self, params, state, n_frames: int, nbrs=None, max_retries: int = 4):
        """Jitted rollout of ``n_frames`` GNS frames with neighbour re-allocation on overflow
        (outside jit). Returns ``(HybridResult, nbrs)``; the list fits this rollout."""
        nbrs = self.allocate(state) if nbrs is None else nbrs
        n = self.n_nodes
        for attempt in range(max_retries + 1):
            nodes, parts, mode, energy, over, final = self._run(params, self.gns_params, state,
                                                                nbrs, n_frames=n_frames)
            over = np.asarray(over)
            if not over.any():
                return HybridResult(parts, nodes, mode, energy, final, self.frame_dt), nbrs
            k = int(np.argmax(over))
            extra = (attempt + 1) * max(1, math.ceil(nbrs.idx.shape[1] / (4 * n)))
            nbrs = self.gns.allocate(nodes[k], extra_capacity=extra)
        raise RuntimeError(f"neighbour list still overflowing after {max_retries} "
                           "re-allocations")
