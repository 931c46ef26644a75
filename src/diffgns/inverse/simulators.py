"""Simulators for inverse problems: functions ``theta -> positions (T, n, 2)``.

Every simulator here observes the same thing, so objectives and targets do not care which
one produced a trajectory: a granular column collapse seen as **nodes** (cluster means of
``coarse_grain`` MPM particles, :func:`diffgns.graph.data.coarse_grain_map` of the initial
column) every ``frame_stride`` MPM frames -- exactly the representation the shipped GNS
(``models/gns_columns``: coarse-graining 4, stride 2, 5 ms frames) was trained on.

* :func:`mpm_simulator`: the differentiable MPM, observed (the physical truth);
* :class:`GNSSimulator`: the learned simulator; its first ``history + 1`` frames are given
  (the observed ones, or a short differentiable MPM start-up at ``theta``) and the rest is a
  GNS rollout with ``jax.checkpoint`` blocks; the material feature is ``tan(phi)``;
* :class:`HybridSimulator`: :class:`diffgns.hybrid.simulator.Hybrid` (MPM warm-up, then GNS segments
  with MPM refinement), observed the same way.

``theta`` is a dict of scalars: ``friction_angle`` (degrees) and, where supported,
``aspect_ratio`` (a vertical stretch of the initial column at a fixed particle count) or the
MPM parameters of :func:`diffgns.inverse.apply_theta`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.graph.data import coarse_grain_map
from diffgns.hybrid.handoff import node_means
from diffgns.inverse.solve import apply_theta
from diffgns.mpm import MPM
from diffgns.scene.builders import column_collapse
from diffgns.trajectory import SAND

DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "models" / "gns_columns"  # shipped data


@dataclass(frozen=True)
class ColumnCase:
    """A column collapse in the box the shipped GNS was trained in (lengths m, frames of
    2.5 ms): column ``width`` x ``aspect_ratio * width`` against the left wall."""

    aspect_ratio: float = 2.0
    width: float = 0.1
    cells_across: int = 8
    domain_length: float = 0.8
    domain_height: float = 0.35
    floor_mu: float = 0.5
    n_frames: int = 250
    frame_stride: int = 2
    coarse_grain: int = 4


class Column:
    """MPM scene, initial state and observation operator of a :class:`ColumnCase`.

    The scene's own friction angle (30 deg) is used only where ``theta`` omits one.
    """

    def __init__(self, case: ColumnCase | None = None, dtype=None):
        self.case = case = case or ColumnCase()
        self.scene = column_collapse(
            width=case.width, aspect_ratio=case.aspect_ratio, friction_angle=30.0,
            cells_across=case.cells_across, floor_mu=case.floor_mu,
            domain_length=case.domain_length, domain_height=case.domain_height)
        self.mpm = MPM(self.scene, dtype)
        self.state = self.mpm.init_state()
        self.cluster = coarse_grain_map(np.asarray(self.state.x.T), case.coarse_grain)
        self.n_nodes = int(self.cluster.max()) + 1
        self.counts = np.bincount(self.cluster, minlength=self.n_nodes)
        self.n_obs = case.n_frames // case.frame_stride + 1  # observed frames

    @property
    def bounds(self):
        return self.scene.domain

    def nodes(self, positions):
        """Particle positions (T, N, 2) -> node positions (cluster means) (T, n, 2)."""
        cluster = jnp.asarray(self.cluster)
        counts = jnp.asarray(self.counts, positions.dtype)
        return jax.vmap(lambda p: node_means(p.T, cluster, counts))(positions)

    def observe(self, positions):
        """MPM particle positions (T, N, 2) at MPM frames -> node positions
        (ceil(T / stride), n, 2) at GNS frames."""
        return self.nodes(positions[:: self.case.frame_stride])

    def initial_state(self, theta: dict):
        """MPM state; ``theta["aspect_ratio"]`` stretches the column (and its particle
        volumes) vertically at a fixed particle count."""
        if "aspect_ratio" not in theta:
            return self.state
        s = jnp.asarray(theta["aspect_ratio"], self.state.x.dtype) / self.case.aspect_ratio
        return self.state.replace(x=self.state.x.at[1].multiply(s), vol=self.state.vol * s)

    def mpm_positions(self, theta: dict, n_frames: int, checkpoint: bool = True,
                      block: int = 25):
        """(n_frames + 1, N, 2) MPM particle positions at ``theta`` (differentiable)."""
        params = apply_theta(self.mpm.params(), theta)
        pos, _, _, _ = self.mpm.rollout_full(params, self.initial_state(theta),
                                             n_frames=n_frames, checkpoint=checkpoint,
                                             block=block)
        return pos

    def observation(self, theta: dict) -> np.ndarray:
        """Observed node trajectory (n_obs, n, 2) of an MPM run at ``theta`` (the truth),
        with the MPM's stability check."""
        params = apply_theta(self.mpm.params(), theta)
        traj, _, _ = self.mpm.run(params, self.initial_state(theta), self.case.n_frames)
        return np.asarray(self.observe(traj.positions))


def mpm_simulator(column: Column, block: int = 25):
    """theta -> observed node positions (n_obs, n, 2) of a checkpointed MPM rollout."""
    def simulate(theta):
        return column.observe(column.mpm_positions(theta, column.case.n_frames, True, block))
    return simulate


class GNSSimulator:
    """theta -> (C + 1 + n_steps, n, 2) positions of a GNS rollout (jit/grad-friendly).

    Args:
        gns, params: a :class:`~diffgns.graph.gns.GNS` and its network parameters.
        history: (C + 1, n, 2) given first frames (oldest first), or a function
            ``theta -> (C + 1, n, 2)`` (e.g. a differentiable MPM start-up).
        particle_type: (n,) int.
        n_steps: GNS frames to predict after the history.
        checkpoint_block: frames per ``jax.checkpoint`` block (None: no checkpointing).
        extra_capacity: neighbour-list head-room (edge slots per node) above what the
            initial frame needs; an overflow is reported through :meth:`rollout` and fixed
            by :meth:`reallocate`.
    """

    def __init__(self, gns, params, history, particle_type, n_steps: int,
                 checkpoint_block: int | None = 10, extra_capacity: int = 4):
        self.gns, self.params = gns, params
        self.C = gns.config.history
        self._history = history if callable(history) else None
        self._fixed = None if callable(history) else jnp.asarray(history)
        if self._fixed is not None and self._fixed.shape[0] < self.C + 1:
            raise ValueError(f"the GNS needs {self.C + 1} initial frames, got "
                             f"{self._fixed.shape[0]}")
        self.particle_type = jnp.asarray(particle_type, jnp.int32)
        if n_steps < 1:
            raise ValueError(f"n_steps must be >= 1, got {n_steps}")
        self.n_steps, self.checkpoint_block = int(n_steps), checkpoint_block
        self.extra_capacity = int(extra_capacity)
        self.nbrs = None
        if self._fixed is not None:
            self.allocate({})

    def history(self, theta) -> jax.Array:
        """(C + 1, n, 2) initial frames at ``theta``."""
        if self._history is None:
            return self._fixed[: self.C + 1]
        return self._history(theta)

    def allocate(self, theta, extra: int = 0) -> None:
        """(Re)allocate the neighbour list at the last initial frame (outside jit)."""
        x = self.history(theta)[-1]
        self.nbrs = self.gns.allocate(x, extra_capacity=self.extra_capacity + extra)

    def rollout(self, theta):
        """((C + 1 + n_steps, n, 2) positions, overflow flag) at ``theta``."""
        if self.nbrs is None:
            if any(isinstance(v, jax.core.Tracer) for v in jax.tree.leaves(theta)):
                raise RuntimeError("GNSSimulator: call allocate(theta0) outside jit before "
                                   "tracing a rollout (its history depends on theta)")
            self.allocate(theta)
        hist = self.history(theta)
        mat = jnp.tan(jnp.deg2rad(theta["friction_angle"])) * jnp.ones(hist.shape[1])
        xs, overflow = self.gns.rollout(self.params, jnp.swapaxes(hist, 0, 1),
                                        self.particle_type, mat.astype(hist.dtype),
                                        self.n_steps, self.nbrs, self.checkpoint_block)
        return jnp.concatenate([hist, xs]), overflow

    def __call__(self, theta):
        return self.rollout(theta)[0]

    def reallocate(self, theta) -> None:
        """Grow the neighbour list until a forward rollout at ``theta`` does not overflow."""
        hist = jnp.swapaxes(self.history(theta), 0, 1)
        mat = jnp.full(hist.shape[0], math.tan(math.radians(float(theta["friction_angle"]))))
        _, self.nbrs = self.gns.rollout_safe(self.params, hist, self.particle_type,
                                             mat.astype(hist.dtype), self.n_steps, self.nbrs)


def load_gns(model: str | Path = DEFAULT_MODEL):
    """(GNS, params, info) of a model folder, with a clear error if it is missing."""
    from diffgns.graph.train_loop import load_model
    model = Path(model)
    if not (model / "config.json").exists():
        raise FileNotFoundError(f"no GNS model in {model} (config.json missing); pass "
                                "--model models/gns_columns or train one with `diffgns train`")
    return load_model(model)


def _check_model(column: Column, loaded, model) -> None:
    gns, _, info = loaded
    case = column.case
    want = dict(factor=case.coarse_grain, frame_stride=case.frame_stride)
    got = {k: info.get(k) for k in want}
    if got != want:
        raise ValueError(f"GNS model {model} was trained with {got}, the column case uses "
                         f"{want}; build the ColumnCase to match the model")
    box = tuple(tuple(b) for b in column.bounds)
    if not np.allclose(np.asarray(gns.config.bounds), np.asarray(box)):
        raise ValueError(f"GNS bounds {gns.config.bounds} differ from the column box {box}")


def gns_simulator(column: Column, model=DEFAULT_MODEL, history="observed", observed=None,
                  checkpoint_block: int | None = 10, n_steps: int | None = None,
                  loaded=None) -> GNSSimulator:
    """A :class:`GNSSimulator` for ``column`` with a trained model.

    Args:
        history: "observed" (the first C + 1 frames of ``observed``, (T, n, 2): fixed,
            theta-independent) or "mpm" (C * stride MPM frames at theta, observed:
            differentiable in every MPM parameter and in ``aspect_ratio``).
        loaded: an already loaded ``(gns, params, info)``.
    """
    loaded = loaded or load_gns(model)
    _check_model(column, loaded, model)
    gns, params, _ = loaded
    case = column.case
    C = gns.config.history
    if history == "observed":
        if observed is None:
            raise ValueError("history='observed' needs the observed trajectory (T, n, 2)")
        hist = jnp.asarray(observed[: C + 1], jnp.float32)
    elif history == "mpm":
        def hist(theta):
            pos = column.mpm_positions(theta, C * case.frame_stride, checkpoint=True, block=5)
            return column.observe(pos).astype(jnp.float32)
    else:
        raise ValueError(f"history must be 'observed' or 'mpm', got {history!r}")
    n_steps = column.n_obs - (C + 1) if n_steps is None else n_steps
    return GNSSimulator(gns, params, hist, np.full(column.n_nodes, SAND), n_steps,
                        checkpoint_block)


class HybridSimulator:
    """theta -> (n_obs, n, 2) node positions of a :class:`diffgns.hybrid.simulator.Hybrid` rollout
    (MPM warm-up, then GNS segments with MPM refinement), differentiable end to end.

    Args:
        column: the :class:`Column` (its MPM scene is shared).
        loaded: ``(gns, params, info)`` of the trained model.
        schedule: :class:`diffgns.hybrid.simulator.Schedule` (default: 5 MPM warm-up frames, then 10
            GNS frames and 2 MPM frames alternately, deformation carried over).
        checkpoint_block: GNS frames per ``jax.checkpoint`` block (also checkpoints MPM
            substeps).
    """

    def __init__(self, column: Column, loaded, schedule=None, checkpoint_block: int = 10,
                 extra_capacity: int = 4):
        from diffgns.hybrid.simulator import Hybrid, Schedule
        gns, params, _ = loaded
        self.column = column
        self.schedule = schedule or Schedule(warmup=5, gns_frames=10, mpm_frames=2)
        case = column.case
        self.hybrid = Hybrid(column.mpm, gns, params, case.frame_stride, case.coarse_grain,
                             self.schedule, checkpoint_block)
        self.n_frames = column.n_obs - 1
        self.nbrs = self.hybrid.allocate(column.state, extra_capacity)

    def rollout(self, theta):
        """((n_obs, n, 2) node positions, overflow flag) at ``theta``."""
        params = apply_theta(self.column.mpm.params(), theta)
        _, nodes, overflow = self.hybrid.rollout(params, self.column.initial_state(theta),
                                                 self.n_frames, self.nbrs)
        return nodes, overflow  # the hybrid's nodes are the column's (same clusters)

    def __call__(self, theta):
        return self.rollout(theta)[0]

    def reallocate(self, theta) -> None:
        """Grow the neighbour list until a forward rollout at ``theta`` does not overflow."""
        params = apply_theta(self.column.mpm.params(), theta)
        _, self.nbrs = self.hybrid.run(params, self.column.initial_state(theta),
                                       self.n_frames, self.nbrs)


def hybrid_simulator(column: Column, model=DEFAULT_MODEL, loaded=None, **kw) -> HybridSimulator:
    """A :class:`HybridSimulator` for ``column`` with a trained GNS (see its arguments)."""
    loaded = loaded or load_gns(model)
    _check_model(column, loaded, model)
    return HybridSimulator(column, loaded, **kw)
