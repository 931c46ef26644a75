"""What an inverse problem observes of a scene: nodes every ``frame_stride`` MPM frames.

Every simulator of :mod:`diffgns.inverse.simulators` is seen through one
:class:`SceneObservation`, so objectives and targets do not care which one produced a
trajectory: the MPM particles of any valid :class:`~diffgns.scene.Scene` (bodies, walls,
obstacles) grouped into **nodes** (cluster means of ``coarse_grain`` particles,
:func:`diffgns.graph.data.coarse_grain_map` of the initial particles) every ``frame_stride``
MPM frames. For a learned simulator the operator comes from its model folder
(:meth:`SceneObservation.for_model`, refusing a scene the model does not support); the MPM
alone may observe every particle and frame (``coarse_grain = frame_stride = 1``).

``theta`` is a dict of named scalars: any ``MPMParams`` leaf
(:mod:`diffgns.inverse.parameters`) and, for a scene of one rectangular body,
``aspect_ratio`` (a vertical stretch of the body about its base at a fixed particle count).
:class:`Column` is the column collapse of the shipped GNS (``ColumnCase``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.graph.data import cluster_means, coarse_grain_map
from diffgns.hybrid.handoff import node_means
from diffgns.interface import rollout
from diffgns.inverse.parameters import check_names, set_params
from diffgns.mpm import MPM
from diffgns.scene.builders import column_collapse
from diffgns.scene.shapes import Rectangle

__all__ = ["Column", "ColumnCase", "SceneObservation", "coarse_grain_positions"]


def coarse_grain_positions(positions: np.ndarray, factor: int) -> np.ndarray:
    """(T, n, 2) node positions (cluster means, clusters of the first frame) of particle
    positions (T, N, 2) (numpy; any particle set)."""
    positions = np.asarray(positions)
    cid = coarse_grain_map(positions[0], factor)
    return cluster_means(positions, cid).astype(positions.dtype)  # the dataset's node means


class SceneObservation:
    """The MPM of a scene, its initial state and the observation operator.

    Args:
        scene: any valid :class:`~diffgns.scene.Scene`.
        n_frames: MPM frames of a rollout (>= 1); ``n_obs = n_frames // frame_stride + 1``
            frames are observed.
        coarse_grain: MPM particles per node (1: every particle).
        frame_stride: MPM frames per observed frame.
        dtype: float dtype of the MPM (default: JAX's default float).

    Attributes:
        mpm, state: the :class:`~diffgns.mpm.MPM` and its initial state.
        cluster: (N,) node of every particle; ``n_nodes``, ``counts`` (n,).
        node_type: (n,) particle type of every node; ``n_obs``: observed frames.
        state_params: initial-state quantities ``theta`` may set (``("aspect_ratio",)`` for
            one rectangular body, else none).
        warnings: what a learned model was not trained on (see :meth:`for_model`).
    """

    def __init__(self, scene, n_frames: int, coarse_grain: int = 1, frame_stride: int = 1,
                 dtype=None):
        if int(n_frames) < 1 or int(coarse_grain) < 1 or int(frame_stride) < 1:
            raise ValueError(f"n_frames ({n_frames}), coarse_grain ({coarse_grain}) and "
                             f"frame_stride ({frame_stride}) must be >= 1")
        self.scene = scene
        self.n_frames, self.frame_stride = int(n_frames), int(frame_stride)
        self.coarse_grain = int(coarse_grain)
        self.mpm = MPM(scene, dtype, checkpoint_substeps=True)  # gradients: 1 state/frame
        self.state = self.mpm.init()
        self.cluster = coarse_grain_map(np.asarray(self.state.x.T), self.coarse_grain)
        self.n_nodes = int(self.cluster.max()) + 1
        self.counts = np.bincount(self.cluster, minlength=self.n_nodes)
        first = np.zeros(self.n_nodes, np.int64)
        first[self.cluster[::-1]] = np.arange(len(self.cluster))[::-1]
        self.first = first
        self.node_type = self.mpm.particle_type()[first]
        self.n_obs = self.n_frames // self.frame_stride + 1
        self.warnings: tuple[str, ...] = ()
        rect = [b.shape for b in scene.bodies]
        self._rect = rect[0] if len(rect) == 1 and isinstance(rect[0], Rectangle) else None
        self.state_params = ("aspect_ratio",) if self._rect is not None else ()

    @classmethod
    def for_model(cls, scene, info: dict, n_frames: int, dtype=None, resolution: str = "exact",
                  model: str = "the model") -> SceneObservation:
        """The observation a GNS model sees of ``scene`` (its ``config.json`` as ``info``):
        its particles per node and frame stride; raises
        :class:`~diffgns.graph.support.UnsupportedSceneError` naming why ``scene`` is not
        one the model supports."""
        from diffgns.graph.support import check_scene

        sup = check_scene(scene, info, resolution, model)
        obs = cls(scene, n_frames, sup.factor, sup.frame_stride, dtype)
        obs.warnings = sup.warnings
        return obs

    @property
    def bounds(self):
        return self.scene.domain

    @property
    def frame_dt(self) -> float:
        """Seconds between observed frames."""
        return float(self.scene.frame_dt) * self.frame_stride

    # ------------------------------------------------------------ parameters
    def check_names(self, names) -> None:
        """Raise ValueError naming a parameter this scene does not have."""
        for k in names:
            if k == "aspect_ratio" and not self.state_params:
                raise ValueError("aspect_ratio is defined for a scene of one rectangular body; "
                                 f"this scene has {len(self.scene.bodies)} body(ies) of shape "
                                 f"{[type(b.shape).__name__ for b in self.scene.bodies]}")
        check_names(self.scene, names, self.state_params)

    def params(self, theta: dict):
        """MPMParams of the scene with ``theta`` written in (differentiable)."""
        return set_params(self.mpm.params(), self.scene, theta)

    def _rectangle(self) -> Rectangle:
        if self._rect is None:
            self.check_names(["aspect_ratio"])  # raises, naming what the scene has
        assert self._rect is not None
        return self._rect

    @property
    def aspect_ratio(self) -> float:
        """Height / width of the scene's one rectangular body."""
        r = self._rectangle()
        return (r.y1 - r.y0) / (r.x1 - r.x0)

    def initial_state(self, theta: dict):
        """MPM state; ``theta["aspect_ratio"]`` stretches the body (and its particle volumes)
        vertically about its base at a fixed particle count."""
        if "aspect_ratio" not in theta:
            return self.state
        x = self.state.x
        s = jnp.asarray(theta["aspect_ratio"], x.dtype) / self.aspect_ratio
        y0 = jnp.asarray(self._rectangle().y0, x.dtype)
        return dataclasses.replace(self.state, x=x.at[1].set(y0 + (x[1] - y0) * s),
                                   vol=self.state.vol * s)

    def node_material(self, theta: dict) -> jax.Array:
        """(n,) GNS material feature, tan(friction angle), of every node at ``theta``."""
        return self.mpm.material_feature(self.params(theta))[self.first]

    # ----------------------------------------------------------- observation
    def nodes(self, positions):
        """Particle positions (T, N, 2) -> node positions (cluster means) (T, n, 2)."""
        cluster = jnp.asarray(self.cluster)
        counts = jnp.asarray(self.counts, positions.dtype)
        return jax.vmap(lambda p: node_means(p.T, cluster, counts))(positions)

    def observe(self, positions):
        """MPM particle positions (T, N, 2) at MPM frames -> node positions
        (ceil(T / stride), n, 2) at observed frames."""
        return self.nodes(positions[:: self.frame_stride])

    def mpm_positions(self, theta: dict, n_frames: int, block: int | None = 25):
        """(n_frames + 1, N, 2) MPM particle positions at ``theta`` (differentiable; frames in
        ``jax.checkpoint`` blocks of ``block``, substeps always checkpointed)."""
        frames, _ = rollout(self.mpm, self.params(theta), self.initial_state(theta),
                            int(n_frames), checkpoint_block=block or None)
        return frames.positions

    def observation(self, theta: dict) -> np.ndarray:
        """Observed nodes (n_obs, n, 2) of an MPM run at ``theta`` (the truth), with the
        MPM's stability check."""
        traj, _ = self.mpm.run(self.params(theta), self.initial_state(theta), self.n_frames)
        return np.asarray(self.observe(traj.positions))

    def same_particles(self, positions0) -> bool:
        """Whether ``positions0`` (N', 2) are this scene's initial particles (same order)."""
        x0 = np.asarray(self.state.x.T)
        p = np.asarray(positions0)
        return p.shape == x0.shape and bool(np.allclose(p, x0, atol=1e-6))

    def observe_trajectory(self, positions, frame_dt: float) -> np.ndarray:
        """Observed nodes (n_obs, n', 2) of a recorded trajectory (T, N', 2) sampled every
        ``frame_dt`` s: the MPM frames (``scene.frame_dt``) are strided, the observed frames
        taken as they are; particles are grouped ``coarse_grain`` per node by their own first
        frame (the same nodes as the simulator's when they are the scene's particles)."""
        positions = np.asarray(positions)
        mpm_dt = float(self.scene.frame_dt)
        if np.isclose(frame_dt, mpm_dt, rtol=1e-6):
            positions = positions[:: self.frame_stride]
        elif not np.isclose(frame_dt, self.frame_dt, rtol=1e-6):
            raise ValueError(f"the observed trajectory has frames of {frame_dt:g} s; the scene "
                             f"has MPM frames of {mpm_dt:g} s, observed every "
                             f"{self.frame_stride} ({self.frame_dt:g} s)")
        if len(positions) < self.n_obs:
            raise ValueError(f"the observed trajectory has {len(positions)} observed frames, "
                             f"{self.n_obs} are needed ({self.n_frames} MPM frames)")
        return coarse_grain_positions(positions[: self.n_obs], self.coarse_grain)


@dataclass(frozen=True)
class ColumnCase:
    """A column collapse (lengths m, frames of 2.5 ms): column ``width`` x ``aspect_ratio *
    width`` against the left wall of a ``domain_length`` x ``domain_height`` box, observed as
    nodes of ``coarse_grain`` particles every ``frame_stride`` frames. :meth:`from_model`
    reads all but the aspect ratio, floor and duration from a model folder; the defaults are
    the training columns of the shipped 8-cell models (``gns_columns``, ``gns_small``)."""

    aspect_ratio: float = 2.0
    width: float = 0.1
    cells_across: int = 8
    domain_length: float = 0.8
    domain_height: float = 0.35
    floor_mu: float = 0.5
    n_frames: int = 250
    frame_stride: int = 2
    coarse_grain: int = 4

    @classmethod
    def from_model(cls, info: dict, aspect_ratio: float = 2.0, floor_mu: float = 0.5,
                   n_frames: int = 250) -> ColumnCase:
        """The column of a model's training data (``info``: its ``config.json``): column
        width, cells across it, box, particles per node and frame stride."""
        src = info.get("source") or {}
        if src.get("kind") != "column" or not {"width", "cells_across"} <= set(src):
            raise ValueError(f"the model was not trained on column collapses (source {src})")
        (x0, x1), (y0, y1) = src.get("bounds") or info["gns"]["bounds"]

        def tidy(v: float) -> float:  # 0.35000000000000003 -> 0.35 (a whole number of cells)
            return float(f"{v:.12g}")

        return cls(aspect_ratio=aspect_ratio, width=float(src["width"]),
                   cells_across=int(src["cells_across"]), domain_length=tidy(x1 - x0),
                   domain_height=tidy(y1 - y0), floor_mu=floor_mu, n_frames=n_frames,
                   frame_stride=int(info.get("frame_stride", 1)),
                   coarse_grain=int(info.get("factor", 1)))


class Column(SceneObservation):
    """The :class:`SceneObservation` of a :class:`ColumnCase` (its scene's own friction
    angle, 30 deg, is used only where ``theta`` omits one)."""

    def __init__(self, case: ColumnCase | None = None, dtype=None):
        self.case = case = case or ColumnCase()
        scene = column_collapse(
            width=case.width, aspect_ratio=case.aspect_ratio, friction_angle=30.0,
            cells_across=case.cells_across, floor_mu=case.floor_mu,
            domain_length=case.domain_length, domain_height=case.domain_height)
        super().__init__(scene, case.n_frames, case.coarse_grain, case.frame_stride, dtype)
