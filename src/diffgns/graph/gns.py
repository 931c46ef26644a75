"""Particle graph network simulator (GNS): learned accelerations + semi-implicit Euler.

Time is in frames (dt = 1 frame): velocities are displacements per frame (m/frame),
accelerations displacements per frame^2 (m/frame^2). One GNS step advances one frame::

    a    = denormalise(network(features(history, graph)))
    v'   = (x_t - x_{t-1}) + a
    x'   = x_t + v'

Kinematic particles (type 3) are not integrated: they are set to a prescribed position when
one is given and otherwise held where they are.

The walls and obstacles the network sees are an input (:class:`~diffgns.graph.geometry
.Geometry`, traced), not configuration: ``GNSConfig.bounds`` is only the default walls and
the extent of the neighbour list's cells, so one model trains on boxes of several sizes and
runs in one it was not trained in (:meth:`GNS.for_box`).

One code path for 2D and 3D: the dimension d is ``len(GNSConfig.bounds)``
(:attr:`GNSConfig.dim`, 2 or 3; y is vertical in both), and it sets the width of the node
and edge features and of the network's output. A model is for one d: positions, walls or a
scene of the other dimension are refused with a message (:meth:`GNS.init`,
:meth:`GNS.for_box`, :meth:`GNS.features`).

The GNS is a :class:`diffgns.interface.Simulator`::

    state = gns.init(history, particle_type)          # allocates the neighbour list
    params = GNSParams(network, material)             # weights and tan(phi) per node
    frames, final = rollout(gns, params, state, n)    # diffgns.rollout

:class:`GNSConfig` is static (frozen, hashable); the network params are a pytree; the
jax-md neighbour list travels in :class:`GNSState`. Its overflow is reported per frame
(``ParticleFrame.overflow``), never hidden: :func:`diffgns.interface.rollout_safe`
re-allocates outside ``jit`` (:meth:`GNS.reallocate`) and redoes the rollout.
"""
from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.clamp import ClampCount, clamp_positions
from diffgns.graph.features import ParticleStats, edge_features, node_features
from diffgns.graph.geometry import Geometry
from diffgns.graph.neighbors import NeighborBuilder, did_overflow, edges, n_pairs
from diffgns.graph.networks import EncodeProcessDecode, init_params
from diffgns.interface import ParticleFrame
from diffgns.trajectory import KINEMATIC, Trajectory

__all__ = ["GNS", "GNSConfig", "GNSParams", "GNSState"]


@dataclasses.dataclass(frozen=True)
class GNSConfig:
    """Static configuration of a particle GNS (hashable; usable as a jit static argument).

    Attributes:
        bounds: ``((xmin, xmax), (ymin, ymax))`` (2D) or ``((xmin, xmax), (ymin, ymax),
            (zmin, zmax))`` (3D) of the domain in m: the dimension of the model
            (:attr:`dim`), the extent of the cell list and the default walls (a state's or a
            training window's :class:`~diffgns.graph.geometry.Geometry` gives the walls the
            network sees; every wall must lie inside ``bounds``).
        radius: connectivity radius R in m (pairs with distance < R are connected).
        latent: latent width (and MLP hidden width).
        mp_steps: message-passing steps.
        mlp_layers: hidden layers per MLP (>= 1).
        history: number C of input velocities (the history holds C + 1 positions).
        noise_std: random-walk training noise sigma in m (folded into the normalisers by the
            training code; kept here so a checkpoint records it).
        attention: softmax attention aggregation instead of a plain sum.
        n_types: number of particle types of the embedding.
        type_embed: width of the particle-type embedding.
        capacity_multiplier: neighbour-list head-room factor.
        use_material: feed the raw material feature (tan phi) as a node feature.
        use_obstacles: feed the distance and normal to the nearest box obstacle as node
            features (:func:`~diffgns.graph.features.obstacle_distances`; 1 + d more
            inputs).
        clamp_to_bounds: keep predicted positions inside the walls (of the state's
            geometry), so no
            particle ever leaves the domain however inaccurate the network. Never silent:
            every position moved is counted in :attr:`GNSState.clamp` and reported per frame
            (``ParticleFrame.clamp``; :mod:`diffgns.clamp`).
    """

    bounds: tuple = ((0.0, 1.0), (0.0, 1.0))
    radius: float = 0.015
    latent: int = 128
    mp_steps: int = 10
    mlp_layers: int = 2
    history: int = 5
    noise_std: float = 6.7e-4
    attention: bool = False
    n_types: int = 9
    type_embed: int = 16
    capacity_multiplier: float = 1.25
    use_material: bool = True
    clamp_to_bounds: bool = True
    use_obstacles: bool = False

    def __post_init__(self):
        bounds = tuple((float(lo), float(hi)) for lo, hi in self.bounds)
        object.__setattr__(self, "bounds", bounds)
        checks = {
            "bounds": len(bounds) in (2, 3) and all(lo < hi for lo, hi in bounds),
            "radius": self.radius > 0, "latent": self.latent > 0,
            "mp_steps": self.mp_steps >= 0, "mlp_layers": self.mlp_layers >= 1,
            "history": self.history >= 1, "noise_std": self.noise_std >= 0,
            "n_types": self.n_types > KINEMATIC, "capacity_multiplier":
            self.capacity_multiplier >= 1.0,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"invalid GNSConfig field(s) {bad}: {self}")

    @property
    def dim(self) -> int:
        """Spatial dimension d of the model, 2 or 3: the number of axes of ``bounds``."""
        return len(self.bounds)


class GNSParams(NamedTuple):
    """What a GNS rollout may vary or fit.

    Attributes:
        network: the network weights (from :meth:`GNS.init_network` or a model folder).
        material: (N,) or scalar raw material feature, tan(friction angle) (differentiable).
    """

    network: Any
    material: jax.Array


class GNSState(NamedTuple):
    """State of a GNS rollout.

    Attributes:
        history: (N, C+1, d) positions in m, oldest first; ``history[:, -1]`` is the current
            frame.
        nbrs: jax-md neighbour list (capacity fixed at :meth:`GNS.init`, overflow flag sticky).
        particle_type: (N,) int32.
        kinematic: (K, N, d) prescribed positions of the kinematic particles for the next
            K frames (frame ``t + 1`` uses ``kinematic[t]``), or None: they are held.
        t: int32 scalar, frames advanced since :meth:`GNS.init`.
        clamp: :class:`~diffgns.clamp.ClampCount` of the last frame (positions the domain
            clamp moved, largest move in m).
        geometry: :class:`~diffgns.graph.geometry.Geometry` the network sees (walls,
            obstacles; traced); None: the config's box, no obstacle.
    """

    history: jax.Array
    nbrs: Any
    particle_type: jax.Array
    kinematic: jax.Array | None
    t: jax.Array
    clamp: ClampCount
    geometry: Geometry | None = None


class GNS:
    """Particle GNS bound to a config and a normaliser; methods are pure and jit-friendly.

    Args:
        config: :class:`GNSConfig`.
        normalizer: :class:`~diffgns.graph.features.ParticleStats` (velocity m/frame,
            acceleration m/frame^2), usually ``ParticleStats.from_metadata(meta, noise_std)``.
        frame_dt: seconds per GNS frame (for the velocities it observes, m/s).
    """

    def __init__(self, config: GNSConfig, normalizer: ParticleStats, frame_dt: float = 2.5e-3):
        self.config = config
        self.frame_dt = float(frame_dt)
        self.normalizer = normalizer
        self.network = EncodeProcessDecode(
            latent=config.latent, mp_steps=config.mp_steps, mlp_layers=config.mlp_layers,
            n_types=config.n_types, type_embed=config.type_embed, attention=config.attention,
            out=config.dim)
        self.neighbors = NeighborBuilder(config.bounds, config.radius,
                                         config.capacity_multiplier)

    def for_box(self, bounds) -> GNS:
        """This GNS (same network, normaliser and frame) with the neighbour-list extent and
        default walls of another box ``((xmin, xmax), (ymin, ymax)(, (zmin, zmax)))`` m, e.g.
        a longer one than training's; ``self`` if it is the same box. ValueError for a box
        of another dimension than the model's."""
        bounds = tuple((float(lo), float(hi)) for lo, hi in bounds)
        if bounds == self.config.bounds:
            return self
        self.check_dim(len(bounds), f"the box {list(bounds)} m")
        return GNS(dataclasses.replace(self.config, bounds=bounds), self.normalizer,
                   self.frame_dt)

    def geometry(self, obstacles=(), pad_to: int = 0, bounds=None) -> Geometry:
        """:class:`Geometry` of the walls ``bounds`` (default the config's box) and box
        ``obstacles`` ``[lo..., hi...]`` m (2D ``[x0, y0, x1, y1]``; padded to ``pad_to``
        rows)."""
        bounds = self.config.bounds if bounds is None else bounds
        self.check_dim(len(bounds), f"the walls {[list(b) for b in bounds]} m")
        return Geometry.of(bounds, obstacles, pad_to)

    def check_dim(self, dim: int, what: str) -> None:
        """ValueError naming ``what`` unless ``dim`` is the model's dimension."""
        if dim != self.config.dim:
            raise ValueError(
                f"{what} is {dim}D but this GNS is a {self.config.dim}D model (bounds "
                f"{[list(b) for b in self.config.bounds]} m); a model runs only in the "
                f"dimension it was trained in: use a model trained on {dim}D data "
                f"(diffgns train --data <{dim}D dataset>)")

    def for_scene(self, scene) -> tuple[GNS, Geometry]:
        """(this GNS for ``scene``'s box (:meth:`for_box`), the scene's :class:`Geometry`:
        its walls and box obstacles) -- what every scene-driven rollout (inverse, hybrid,
        command line) hands the network."""
        self.check_dim(len(scene.domain), "the scene")
        g = self.for_box(scene.domain)
        obs = [tuple(o.lower) + tuple(o.upper) for o in getattr(scene, "obstacles", ())]
        return g, g.geometry(obs)

    # ----------------------------------------------------------------- network
    def init_network(self, key: jax.Array, example_inputs) -> dict:
        """Network params for ``example_inputs = (history (N, C+1, d), particle_type (N,)
        [, material (N,)])``; a self-edge graph is used (param shapes do not depend on E).

        Flax's default initial distributions, drawn by :func:`~.networks.init_params` (fast
        to compile; call outside ``jit``).
        """
        history, particle_type, *rest = example_inputs
        n = history.shape[0]
        material = rest[0] if rest else np.zeros(n, np.float32)
        idx = jax.ShapeDtypeStruct((n,), jnp.int32)
        mask = jax.ShapeDtypeStruct((n,), jnp.bool_)
        # Only shapes matter: nothing is computed (or compiled) until the host-side draw.
        nf, ef = jax.eval_shape(self.features, history, material, idx, idx, mask)
        ptype = jax.ShapeDtypeStruct(np.shape(particle_type), jnp.int32)
        return init_params(self.network, key, nf, ptype, ef, idx, idx, mask)

    def features(self, history, material, senders, receivers, mask,
                 geometry: Geometry | None = None):
        """(node_features (N, F), edge_features (E, d + 1)) of a history and a graph;
        ``geometry``: the walls and obstacles (default: the config's box, no obstacle)."""
        cfg = self.config
        if history.ndim != 3 or history.shape[1] != cfg.history + 1:
            raise ValueError(f"history must be (N, {cfg.history + 1}, {cfg.dim}), got "
                             f"{history.shape}")
        self.check_dim(history.shape[-1], f"the history {tuple(history.shape)}")
        walls = cfg.bounds if geometry is None else geometry.walls
        obstacles = None
        if cfg.use_obstacles:
            obstacles = (jnp.zeros((0, 2 * cfg.dim), history.dtype) if geometry is None
                         else geometry.obstacles)
        nf = node_features(history, walls, cfg.radius, self.normalizer.velocity,
                           material if cfg.use_material else None, obstacles)
        ef = edge_features(history[:, -1], senders, receivers, mask, cfg.radius)
        return nf, ef

    def normalized_acceleration(self, params, history, particle_type, material, senders,
                                receivers, mask, geometry: Geometry | None = None
                                ) -> jax.Array:
        """(N, d) network output: the normalised acceleration (what the loss compares)."""
        nf, ef = self.features(history, material, senders, receivers, mask, geometry)
        return self.network.apply(params, nf, particle_type, ef, senders, receivers, mask)

    def acceleration(self, params, history, particle_type, material, senders, receivers,
                     mask, geometry: Geometry | None = None) -> jax.Array:
        """(N, d) predicted acceleration in m/frame^2 (denormalised).

        Args:
            params: network params from :meth:`init`.
            history: (N, C+1, d) positions in m, oldest first.
            particle_type: (N,) int.
            material: (N,) raw material feature (tan phi); ignored if not ``use_material``.
            senders, receivers, mask: (E,) graph from :func:`~diffgns.graph.neighbors.edges`.
            geometry: walls and obstacles (:class:`Geometry`; default the config's box).
        """
        out = self.normalized_acceleration(params, history, particle_type, material,
                                           senders, receivers, mask, geometry)
        return self.normalizer.acceleration.denormalize(out)

    # -------------------------------------------------------------- simulation
    def allocate(self, x: jax.Array, extra_capacity: int = 0):
        """Neighbour list for positions ``x`` (N, d) (outside jit)."""
        return self.neighbors.allocate(x, extra_capacity)

    def init(self, history, particle_type, kinematic_path=None, extra_capacity: int = 0,
             geometry: Geometry | None = None) -> GNSState:
        """Initial state (outside jit: allocates the neighbour list at the current frame).

        Args:
            history: (N, C+1, d) positions in m, oldest first.
            particle_type: (N,) int.
            kinematic_path: optional (K, N, d) prescribed positions of the kinematic particles
                for the next K frames (a rollout may then run at most K frames).
            extra_capacity: edge slots per particle above the list's head-room.
            geometry: walls and obstacles the network sees (default :meth:`geometry`: the
                config's box, no obstacle); walls outside the config's box are refused (the
                neighbour list covers only that box: use :meth:`for_box`). Positions or
                walls of another dimension than the model's are refused.
        """
        history = jnp.asarray(history)
        C = self.config.history
        if history.ndim != 3 or history.shape[1] != C + 1:
            raise ValueError(f"history must be (N, {C + 1}, d), got {history.shape}")
        self.check_dim(history.shape[-1], f"the history {tuple(history.shape)}")
        geometry = self.geometry() if geometry is None else geometry
        walls = np.asarray(geometry.walls)
        self.check_dim(walls.shape[0], f"the geometry's walls {walls.tolist()} m")
        box = np.asarray(self.config.bounds)
        if np.any(walls[:, 0] < box[:, 0] - 1e-6) or np.any(walls[:, 1] > box[:, 1] + 1e-6):
            raise ValueError(f"GNS.init: walls {walls.tolist()} m reach outside the GNS's box "
                             f"{box.tolist()} m (its neighbour list's extent); build the GNS "
                             "for the scene's box with gns.for_box(bounds)")
        nbrs = self.allocate(history[:, -1], extra_capacity)
        kin = None if kinematic_path is None else jnp.asarray(kinematic_path, history.dtype)
        geometry = Geometry(jnp.asarray(geometry.walls, history.dtype),
                            jnp.asarray(geometry.obstacles, history.dtype))
        return GNSState(history, nbrs, jnp.asarray(particle_type, jnp.int32), kin,
                        jnp.zeros((), jnp.int32), ClampCount.zero(history.dtype), geometry)

    def advance(self, network, history, particle_type, material, nbrs, kinematic_next=None,
                geometry: Geometry | None = None):
        """Next positions (N, d) of one semi-implicit Euler step, the updated list, and the
        :class:`~diffgns.clamp.ClampCount` of the step.

        ``nbrs`` is updated to the current positions here; ``did_overflow(nbrs)`` tells
        whether edges were dropped (sticky). Kinematic particles go to ``kinematic_next``
        (N, d) when given, else stay where they are. With ``clamp_to_bounds`` the predicted
        positions (and any prescribed kinematic position outside the box) are clipped to the
        walls (of ``geometry``, default the config's box) and every clipped position is
        counted.
        """
        n = history.shape[0]
        x = history[:, -1]
        nbrs = self.neighbors.update(x, nbrs)
        senders, receivers, mask = edges(nbrs, n)
        acc = self.acceleration(network, history, particle_type, material, senders,
                                receivers, mask, geometry)
        x_next, clamp = self.integrate(history, acc, particle_type, kinematic_next, geometry)
        return x_next, nbrs, clamp

    def integrate(self, history, acc, particle_type, kinematic_next=None,
                  geometry: Geometry | None = None):
        """Next positions (N, d) m of the semi-implicit Euler step ``x + (x - x_prev) +
        acc`` from ``history`` (N, C+1, d) and the acceleration ``acc`` (N, d) m/frame^2, with
        the kinematic and wall rules of :meth:`advance`, and the step's
        :class:`~diffgns.clamp.ClampCount`."""
        x = history[:, -1]
        x_next = x + (x - history[:, -2]) + acc
        target = x if kinematic_next is None else kinematic_next
        x_next = jnp.where((particle_type == KINEMATIC)[:, None], target, x_next)
        clamp = ClampCount.zero(history.dtype)
        if self.config.clamp_to_bounds:
            walls = jnp.asarray(self.config.bounds if geometry is None else geometry.walls,
                                x_next.dtype)
            lo, hi = walls[:, 0], walls[:, 1]
            x_next, clamp = clamp_positions(x_next, lo, hi, axis=-1)
        return x_next.astype(history.dtype), clamp

    def step(self, params: GNSParams, state: GNSState) -> GNSState:
        """Advance one frame (pure)."""
        kin = None
        if state.kinematic is not None:
            kin = jax.lax.dynamic_index_in_dim(state.kinematic, state.t, keepdims=False)
        material = jnp.broadcast_to(jnp.asarray(params.material, state.history.dtype),
                                    state.particle_type.shape)
        x_next, nbrs, clamp = self.advance(params.network, state.history,
                                           state.particle_type, material, state.nbrs, kin,
                                           state.geometry)
        hist = jnp.concatenate([state.history[:, 1:], x_next[:, None]], axis=1)
        return state._replace(history=hist, nbrs=nbrs, t=state.t + 1, clamp=clamp)

    def observe(self, state: GNSState) -> ParticleFrame:
        """Positions (N, d) m, velocities (backward difference, m/s), overflow flag, clamps."""
        x = state.history[:, -1]
        v = (x - state.history[:, -2]) / self.frame_dt
        return ParticleFrame(x, v, did_overflow(state.nbrs), state.clamp)

    def reallocate(self, state: GNSState, frames: ParticleFrame, first_bad: int,
                   attempt: int) -> GNSState:
        """``state`` with a larger neighbour list (outside jit), sized at the last valid
        frame before the overflow at frame ``first_bad`` of ``frames``."""
        return state._replace(nbrs=self.grown_neighbors(state.nbrs, frames.positions,
                                                        first_bad, attempt))

    def grown_neighbors(self, nbrs, positions, first_bad: int, attempt: int):
        """A larger list than ``nbrs`` (outside jit), sized at the last valid frame of
        ``positions`` ((T, N, d) m: a rollout's nodes) before the overflow at ``first_bad``,
        with the compaction check (:func:`warn_if_compacted`) against frame 0. Every
        attempt is checked: a retry reruns the rollout, which may overflow again further
        on. The one re-allocation of the GNS's nodes, in GNS and hybrid rollouts alike."""
        k = max(int(first_bad) - 1, 0)
        grown = self.neighbors.reallocate(positions[k], nbrs, attempt)
        warn_if_compacted(self.neighbors, positions[0], grown, k)
        return grown

    def trajectory(self, params: GNSParams, frames: ParticleFrame, particle_type
                   ) -> Trajectory:
        """:class:`Trajectory` of stacked frames (material broadcast per particle)."""
        particle_type = jnp.asarray(particle_type)
        return Trajectory(positions=frames.positions, velocities=frames.velocities,
                          particle_type=particle_type,
                          material=jnp.broadcast_to(jnp.asarray(params.material),
                                                    particle_type.shape),
                          frame_dt=self.frame_dt, bounds=self.config.bounds,
                          clamped=frames.clamp.moved, clamp_shift=frames.clamp.shift)


#: largest growth of the neighbour-pair count over a rollout, relative to its first frame,
#: that a GNS rollout passes without a warning. The MPM flows of the granular training and
#: validation sets (224 trajectories, 16 particles per node) never exceed 1.08.
COMPACTION_WARN = 2.0


class CompactionWarning(UserWarning):
    """A GNS rollout packed its nodes far closer than granular matter packs."""


def warn_if_compacted(neighbors: NeighborBuilder, x0, nbrs, frame: int,
                      limit: float = COMPACTION_WARN) -> float:
    """Warn (:class:`CompactionWarning`) when the list ``nbrs``, allocated at rollout frame
    ``frame``, holds more than ``limit`` times the neighbour pairs of the first frame's
    positions ``x0`` (N, d) m. Called on a re-allocation (outside jit), the only time a
    rollout's pair count can have grown past its head-room. Returns the ratio."""
    first = max(n_pairs(neighbors.allocate(x0)), 1)
    now = n_pairs(nbrs)
    ratio = now / first
    if ratio > limit:
        import warnings

        warnings.warn(
            f"GNS rollout: the nodes compacted to {ratio:.1f}x the neighbour pairs of the "
            f"first frame by frame {frame} ({now} against {first}); granular "
            f"matter does not compress like that (the MPM training flows stay below "
            f"1.1x), so the model is outside what it learnt and this prediction is not "
            "trustworthy", CompactionWarning, stacklevel=2)
    return ratio
