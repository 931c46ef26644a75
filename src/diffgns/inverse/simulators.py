"""Simulators for inverse problems: ``theta -> observed node positions (T, n, 2)``.

Each adapter is built on a :class:`~diffgns.inverse.observation.SceneObservation` of any
scene and runs the one :func:`diffgns.interface.rollout`; all of them observe the same nodes
and frames, so objectives and targets do not care which one produced a trajectory:

* :class:`MPMSimulator` (:func:`mpm_simulator`): the differentiable MPM (the physical truth);
* :class:`GNSSimulator` (:func:`gns_simulator`): a trained GNS; its first ``history + 1``
  frames are given (the observed ones, or a short differentiable MPM start-up at ``theta``),
  the rest is a GNS rollout in ``jax.checkpoint`` blocks; the material feature is
  ``tan(friction_angle)`` of each node's body;
* :class:`HybridSimulator` (:func:`hybrid_simulator`): :class:`diffgns.hybrid.Hybrid` (MPM
  warm-up, then GNS segments with MPM refinement).

Every adapter has ``simulate(theta) -> (positions, overflow)`` (traceable), is callable
(``theta -> positions``) and has ``reallocate(theta)`` (outside jit) and
``parameter_warnings(theta)`` (a learned simulator's: values outside its training data,
:func:`~diffgns.graph.support.friction_warnings`). The neighbour list of
a learned simulator travels in its state: the adapter holds an allocated initial state, and
``reallocate`` replaces it by one with room for a rollout at ``theta``
(:func:`diffgns.interface.rollout_safe`); :func:`diffgns.inverse.optimize` calls it through
``on_overflow`` and recompiles. :func:`gns_simulator` and :func:`hybrid_simulator` refuse a
scene or observation the model does not support, naming why.
"""
from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.graph.gns import GNSParams
from diffgns.interface import rollout, rollout_safe
from diffgns.inverse.observation import Column, ColumnCase, SceneObservation
from diffgns.inverse.parameters import STATE_PARAMS
from diffgns.models import model_dir
from diffgns.scene.materials import friction_feature

__all__ = ["Column", "ColumnCase", "DEFAULT_MODEL", "GNSSimulator", "HybridSimulator",
           "MODELS_BY_ACCURACY", "MPMSimulator", "SceneObservation", "check_model",
           "default_model", "gns_simulator", "hybrid_simulator", "load_gns", "model_info",
           "mpm_simulator"]

#: shipped particle GNS models, most accurate first on the scenes each was trained for
#: (held-out runout error, mean / max, from their model cards: gns_cg16_pfn 1.4% / 4.4% on
#: columns against the left wall; gns_general, every granular family, 8.0% / 32.9%;
#: gns_cg16_pf 3.2% / 9.5%, gns_cg16 5.5% / 14.8%, gns_columns 5.3% / 17.3%, gns_small
#: 8.5% / 21.1% on columns); :func:`default_model` prefers the first with no warning for
#: the scene
MODELS_BY_ACCURACY = ("gns_cg16_pfn", "gns_general", "gns_cg16_pf", "gns_cg16", "gns_columns",
                      "gns_small")
DEFAULT_MODEL = MODELS_BY_ACCURACY[0]  # a shipped model (diffgns.models.model_path)


class MPMSimulator:
    """theta -> observed node positions (n_obs, n, 2) of a checkpointed MPM rollout.

    Args:
        obs: the :class:`SceneObservation`.
        block: MPM frames per ``jax.checkpoint`` block (None/0: none; substeps are always
            checkpointed).
    """

    def __init__(self, obs: SceneObservation, block: int | None = 25):
        self.obs, self.block = obs, block

    def simulate(self, theta):
        """((n_obs, n, 2) node positions, False): the MPM never overflows."""
        pos = self.obs.mpm_positions(theta, self.obs.n_frames, self.block)
        return self.obs.observe(pos), jnp.asarray(False)

    def __call__(self, theta):
        return self.simulate(theta)[0]

    def reallocate(self, theta) -> None:
        """Nothing to re-allocate."""

    def parameter_warnings(self, theta) -> list[str]:
        """None: the MPM has no training range."""
        return []


def mpm_simulator(obs: SceneObservation, block: int | None = 25) -> MPMSimulator:
    """The :class:`MPMSimulator` of ``obs``."""
    return MPMSimulator(obs, block)


def _tan_phi(theta):
    return friction_feature(theta["friction_angle"])


class _Learned:
    """What the learned adapters share: their model's training range."""

    info: dict | None

    def parameter_warnings(self, theta) -> list[str]:
        """Warnings for the values of ``theta`` (physical units) outside the model's training
        data (:func:`~diffgns.graph.support.friction_warnings`)."""
        from diffgns.graph.support import friction_warnings

        return friction_warnings(theta, self.info or {}, "the")


class GNSSimulator(_Learned):
    """theta -> (C + 1 + n_steps, n, 2) positions of a GNS rollout (jit/grad-friendly).

    Args:
        gns, network: a :class:`~diffgns.graph.gns.GNS` and its network weights.
        history: (C + 1, n, 2) given first frames (oldest first), or a function
            ``theta -> (C + 1, n, 2)`` (e.g. a differentiable MPM start-up).
        particle_type: (n,) int.
        n_steps: GNS frames to predict after the history.
        checkpoint_block: frames per ``jax.checkpoint`` block (None: no checkpointing).
        extra_capacity: neighbour-list head-room (edge slots per node) above what the
            initial frame needs; an overflow is reported by :meth:`simulate` and fixed by
            :meth:`reallocate`.
        material: ``theta -> (n,) or scalar`` material feature (default
            ``tan(theta["friction_angle"])``).
        geometry: the walls and obstacles the network sees
            (:class:`~diffgns.graph.geometry.Geometry`; default the GNS's box, no obstacle).
        info: the model folder's ``config.json`` (for :meth:`parameter_warnings`; None: no
            training range known).
    """

    def __init__(self, gns, network, history, particle_type, n_steps: int,
                 checkpoint_block: int | None = 10, extra_capacity: int = 4,
                 material: Callable | None = None, geometry=None, info: dict | None = None):
        self.gns, self.network, self.info = gns, network, info
        self.geometry = geometry  # walls and obstacles (None: the GNS's box, no obstacle)
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
        self.material = material or _tan_phi
        self.state = None  # GNSState with an allocated neighbour list
        if self._fixed is not None:
            self.allocate({})

    def history(self, theta) -> jax.Array:
        """(C + 1, n, 2) initial frames at ``theta``."""
        if self._history is None:
            return self._fixed[: self.C + 1]
        return self._history(theta)

    def allocate(self, theta) -> None:
        """Allocate the initial state (neighbour list at the last initial frame at ``theta``;
        outside jit)."""
        hist = jnp.swapaxes(self.history(theta), 0, 1)
        self.state = self.gns.init(hist, self.particle_type,
                                   extra_capacity=self.extra_capacity,
                                   geometry=self.geometry)

    def _inputs(self, theta):
        if self.state is None:
            if any(isinstance(v, jax.core.Tracer) for v in jax.tree.leaves(theta)):
                raise RuntimeError("GNSSimulator: call allocate(theta0) outside jit before "
                                   "tracing a rollout (its history depends on theta)")
            self.allocate(theta)
        hist = self.history(theta)
        state = self.state._replace(history=jnp.swapaxes(hist, 0, 1))
        mat = jnp.asarray(self.material(theta), hist.dtype)
        return hist, GNSParams(self.network, mat), state

    def simulate(self, theta):
        """((C + 1 + n_steps, n, 2) positions, overflow flag) at ``theta``."""
        hist, params, state = self._inputs(theta)
        frames, _ = rollout(self.gns, params, state, self.n_steps,
                            checkpoint_block=self.checkpoint_block)
        return jnp.concatenate([hist, frames.positions[1:]]), jnp.any(frames.overflow)

    def __call__(self, theta):
        return self.simulate(theta)[0]

    def reallocate(self, theta) -> None:
        """Grow the neighbour list until a forward rollout at ``theta`` does not overflow."""
        _, params, state = self._inputs(theta)
        _, _, start = rollout_safe(self.gns, params, state, self.n_steps)
        self.state = self.state._replace(nbrs=start.nbrs)


class HybridSimulator(_Learned):
    """theta -> (n_obs, n, 2) node positions of a :class:`diffgns.hybrid.Hybrid` rollout
    (MPM warm-up, then GNS segments with MPM refinement), differentiable end to end.

    Args:
        obs: the :class:`SceneObservation` (its MPM and nodes are shared).
        gns, network: the trained GNS and its weights.
        schedule: :class:`diffgns.hybrid.Schedule` (default
            :data:`~diffgns.hybrid.simulator.DEFAULT_SCHEDULE`, the schedule of ``diffgns
            hybrid``; until 2026-12-07 the inversion had its own, 5 MPM warm-up frames then
            10 GNS frames and 2 MPM frames alternately: ``Schedule(gns_frames=10,
            mpm_frames=2)``).
        checkpoint_block: GNS frames per ``jax.checkpoint`` block.
        info: the model folder's ``config.json`` (for :meth:`parameter_warnings`).
    """

    def __init__(self, obs: SceneObservation, gns, network, schedule=None,
                 checkpoint_block: int | None = 10, extra_capacity: int = 4,
                 info: dict | None = None):
        from diffgns.hybrid.simulator import DEFAULT_SCHEDULE, Hybrid

        self.obs, self.network, self.info = obs, network, info
        self.schedule = schedule or DEFAULT_SCHEDULE
        gns, geometry = gns.for_scene(obs.scene)  # the scene's walls and obstacles
        self.hybrid = Hybrid(obs.mpm, gns, obs.frame_stride, obs.coarse_grain, self.schedule,
                             geometry=geometry)
        self.checkpoint_block = checkpoint_block
        self.n_frames = obs.n_obs - 1
        self.state = self.hybrid.init(obs.state, extra_capacity)

    def _inputs(self, theta):
        from diffgns.hybrid.simulator import HybridParams

        params = HybridParams(self.obs.params(theta), self.network)
        mpm_state = self.obs.initial_state(theta)
        state = self.state
        if mpm_state is not self.obs.state:  # theta moves the particles: new node history
            x = self.hybrid.nodes(mpm_state)
            hist = jnp.repeat(x[:, None], self.state.history.shape[1], axis=1)
            state = state._replace(mpm=mpm_state, history=hist)
        return params, state

    def simulate(self, theta):
        """((n_obs, n, 2) node positions, overflow flag) at ``theta``."""
        params, state = self._inputs(theta)
        frames, _ = rollout(self.hybrid, params, state, self.n_frames,
                            checkpoint_block=self.checkpoint_block)
        return frames.nodes, jnp.any(frames.overflow)  # the hybrid's nodes are obs's nodes

    def __call__(self, theta):
        return self.simulate(theta)[0]

    def reallocate(self, theta) -> None:
        """Grow the neighbour list until a forward rollout at ``theta`` does not overflow."""
        params, state = self._inputs(theta)
        _, _, start = rollout_safe(self.hybrid, params, state, self.n_frames)
        self.state = self.state._replace(nbrs=start.nbrs)


def model_info(model: str | Path = DEFAULT_MODEL) -> dict:
    """The ``config.json`` of a GNS model folder or shipped model name (no weights loaded)."""
    return json.loads((model_dir(model, "config.json") / "config.json").read_text())


def default_model(scene) -> str:
    """The most accurate shipped GNS (:data:`MODELS_BY_ACCURACY`) that supports ``scene`` at
    its own MPM resolution (:func:`~diffgns.graph.support.check_scene`) with no warning (the
    scene inside what it was trained on), else the most accurate that supports it at all,
    else :data:`DEFAULT_MODEL` (its refusal then names the mismatch). So a column against
    the left wall of the training box gets ``gns_cg16_pfn``, and a scene with obstacles,
    moving bodies or a column against the right wall gets ``gns_general``."""
    from diffgns.graph.support import UnsupportedSceneError, check_scene

    supported = []
    for name in MODELS_BY_ACCURACY:
        try:
            sup = check_scene(scene, model_info(name), "exact", name)
        except UnsupportedSceneError:
            continue
        if not sup.warnings:
            return name
        supported.append(name)
    return supported[0] if supported else DEFAULT_MODEL


def load_gns(model: str | Path = DEFAULT_MODEL):
    """(GNS, params, info) of a model folder or shipped model name, with a clear error."""
    from diffgns.graph.train_loop import load_model

    return load_model(model_dir(model, "config.json"))


def check_model(obs: SceneObservation, loaded, model="the model") -> None:
    """Refuse a model that does not support ``obs``'s scene or observation operator."""
    from diffgns.graph.support import check_scene

    sup = check_scene(obs.scene, loaded[2], "exact", str(model))
    want = dict(factor=sup.factor, frame_stride=sup.frame_stride)
    got = dict(factor=obs.coarse_grain, frame_stride=obs.frame_stride)
    if got != want:
        raise ValueError(f"GNS model {model} observes {want} (particles per node, MPM frames "
                         f"per frame), the observation uses {got}; build it with "
                         "SceneObservation.for_model")


def check_fit(names, simulator: str, history: str = "observed") -> None:
    """Refuse fitting, with a learned simulator, a parameter it has no input for."""
    if simulator != "gns":
        return
    allowed = {"friction_angle"} | (set(STATE_PARAMS) if history == "mpm" else set())
    bad = [k for k in names if k.split("[")[0] not in allowed]
    if bad:
        raise ValueError(f"the GNS cannot fit {bad}: its only material input is "
                         "tan(friction_angle)" + ("" if history == "mpm" else
                                                  " and its history is observed")
                         + "; fit them with --simulator mpm or hybrid")


def gns_simulator(obs: SceneObservation, model=DEFAULT_MODEL, history="observed",
                  observed=None, checkpoint_block: int | None = 10,
                  n_steps: int | None = None, loaded=None) -> GNSSimulator:
    """A :class:`GNSSimulator` for ``obs`` with a trained model (refused, naming why, if the
    model does not support the scene or the observation).

    Args:
        history: "observed" (the first C + 1 frames of ``observed``, (T, n, 2): fixed,
            theta-independent) or "mpm" (C * stride MPM frames at theta, observed:
            differentiable in every MPM parameter and in ``aspect_ratio``; call
            ``allocate(theta0)`` before tracing).
        loaded: an already loaded ``(gns, params, info)``.
    """
    loaded = loaded or load_gns(model)
    check_model(obs, loaded, model)
    gns, network, _ = loaded
    gns, geometry = gns.for_scene(obs.scene)  # the scene's walls and obstacles
    C = gns.config.history
    if history == "observed":
        if observed is None:
            raise ValueError("history='observed' needs the observed trajectory (T, n, 2)")
        hist = jnp.asarray(np.asarray(observed)[: C + 1], jnp.float32)
    elif history == "mpm":
        def hist(theta):
            pos = obs.mpm_positions(theta, C * obs.frame_stride, block=5)
            return obs.observe(pos).astype(jnp.float32)
    else:
        raise ValueError(f"history must be 'observed' or 'mpm', got {history!r}")
    n_steps = obs.n_obs - (C + 1) if n_steps is None else n_steps
    return GNSSimulator(gns, network, hist, obs.node_type, n_steps, checkpoint_block,
                        material=obs.node_material, geometry=geometry, info=loaded[2])


def hybrid_simulator(obs: SceneObservation, model=DEFAULT_MODEL, loaded=None,
                     **kw) -> HybridSimulator:
    """A :class:`HybridSimulator` for ``obs`` with a trained GNS (see its arguments; refused,
    naming why, if the model does not support the scene or the observation)."""
    loaded = loaded or load_gns(model)
    check_model(obs, loaded, model)
    gns, network, info = loaded
    return HybridSimulator(obs, gns, network, info=info, **kw)
