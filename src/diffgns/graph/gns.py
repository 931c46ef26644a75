"""Particle graph network simulator (GNS): learned accelerations + semi-implicit Euler.

Time is in frames (dt = 1 frame): velocities are displacements per frame (m/frame),
accelerations displacements per frame^2 (m/frame^2). One GNS step advances one frame::

    a    = denormalise(network(features(history, graph)))
    v'   = (x_t - x_{t-1}) + a
    x'   = x_t + v'

Kinematic particles (type 3) are not integrated: they are set to a prescribed position when
one is given and otherwise held where they are.

Everything is functional: :class:`GNSConfig` is static (frozen, hashable), the network
params are a pytree, the neighbour list is a jax-md pytree carried through ``lax.scan``.
Overflow of the neighbour list inside a rollout is reported, never hidden; the caller
re-allocates outside ``jit`` and redoes the rollout (:meth:`GNS.rollout_safe` does that).
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.graph.features import Normalizers, edge_features, node_features
from diffgns.graph.neighbors import NeighborBuilder, did_overflow, edges
from diffgns.graph.networks import EncodeProcessDecode, init_params
from diffgns.trajectory import KINEMATIC, Trajectory

__all__ = ["GNS", "GNSConfig"]


@dataclasses.dataclass(frozen=True)
class GNSConfig:
    """Static configuration of a particle GNS (hashable; usable as a jit static argument).

    Attributes:
        bounds: ``((xmin, xmax), (ymin, ymax))`` of the domain in m (walls for the features,
            extent of the cell list).
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
        clamp_to_bounds: keep predicted positions inside ``bounds`` (the box walls), so no
            particle ever leaves the domain however inaccurate the network.
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

    def __post_init__(self):
        bounds = tuple((float(lo), float(hi)) for lo, hi in self.bounds)
        object.__setattr__(self, "bounds", bounds)
        checks = {
            "bounds": len(bounds) == 2 and all(lo < hi for lo, hi in bounds),
            "radius": self.radius > 0, "latent": self.latent > 0,
            "mp_steps": self.mp_steps >= 0, "mlp_layers": self.mlp_layers >= 1,
            "history": self.history >= 1, "noise_std": self.noise_std >= 0,
            "n_types": self.n_types > KINEMATIC, "capacity_multiplier":
            self.capacity_multiplier >= 1.0,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise ValueError(f"invalid GNSConfig field(s) {bad}: {self}")


class GNS:
    """Particle GNS bound to a config and a normaliser; methods are pure and jit-friendly.

    Args:
        config: :class:`GNSConfig`.
        normalizer: :class:`~diffgns.graph.features.Normalizers` (velocity m/frame,
            acceleration m/frame^2), usually ``Normalizers.from_metadata(meta, noise_std)``.
        compiler_options: optional XLA options for the internal ``jit`` of
            :meth:`rollout_safe`, e.g. ``{"xla_backend_optimization_level": 0}`` to compile
            several times faster for short runs (tests, debugging).
    """

    def __init__(self, config: GNSConfig, normalizer: Normalizers,
                 compiler_options: dict | None = None):
        self.config = config
        self.normalizer = normalizer
        self.network = EncodeProcessDecode(
            latent=config.latent, mp_steps=config.mp_steps, mlp_layers=config.mlp_layers,
            n_types=config.n_types, type_embed=config.type_embed, attention=config.attention)
        self.neighbors = NeighborBuilder(config.bounds, config.radius,
                                         config.capacity_multiplier)
        self._rollout_flags_jit = jax.jit(self._rollout_flags,
                                          static_argnames=("n_steps", "checkpoint_block"),
                                          compiler_options=compiler_options)

    # ----------------------------------------------------------------- network
    def init(self, key: jax.Array, example_inputs) -> dict:
        """Network params for ``example_inputs = (history (N, C+1, 2), particle_type (N,)
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

    def features(self, history, material, senders, receivers, mask):
        """(node_features (N, F), edge_features (E, 3)) of a history and a graph."""
        cfg = self.config
        if history.shape[1] != cfg.history + 1:
            raise ValueError(f"history must be (N, {cfg.history + 1}, 2), got {history.shape}")
        nf = node_features(history, cfg.bounds, cfg.radius, self.normalizer.velocity,
                           material if cfg.use_material else None)
        ef = edge_features(history[:, -1], senders, receivers, mask, cfg.radius)
        return nf, ef

    def normalized_acceleration(self, params, history, particle_type, material, senders,
                                receivers, mask) -> jax.Array:
        """(N, 2) network output: the normalised acceleration (what the loss compares)."""
        nf, ef = self.features(history, material, senders, receivers, mask)
        return self.network.apply(params, nf, particle_type, ef, senders, receivers, mask)

    def acceleration(self, params, history, particle_type, material, senders, receivers,
                     mask) -> jax.Array:
        """(N, 2) predicted acceleration in m/frame^2 (denormalised).

        Args:
            params: network params from :meth:`init`.
            history: (N, C+1, 2) positions in m, oldest first.
            particle_type: (N,) int.
            material: (N,) raw material feature (tan phi); ignored if not ``use_material``.
            senders, receivers, mask: (E,) graph from :func:`~diffgns.graph.neighbors.edges`.
        """
        out = self.normalized_acceleration(params, history, particle_type, material,
                                           senders, receivers, mask)
        return self.normalizer.acceleration.denormalize(out)

    # -------------------------------------------------------------- simulation
    def allocate(self, x: jax.Array, extra_capacity: int = 0):
        """Neighbour list for positions ``x`` (N, 2) (outside jit)."""
        return self.neighbors.allocate(x, extra_capacity)

    def step(self, params, history, particle_type, material, nbrs, kinematic_position=None):
        """Advance one frame.

        Args:
            history: (N, C+1, 2) positions in m; ``history[:, -1]`` is the current frame.
            nbrs: jax-md neighbour list; it is updated to the current positions here.
            kinematic_position: optional (N, 2) prescribed next positions; used for the
                kinematic particles only. Without it they keep their current position.

        Returns:
            ``(next_positions (N, 2), nbrs)`` with ``nbrs`` the list used for this step;
            ``did_overflow(nbrs)`` tells whether edges were dropped (sticky).
        """
        n = history.shape[0]
        x = history[:, -1]
        nbrs = self.neighbors.update(x, nbrs)
        senders, receivers, mask = edges(nbrs, n)
        acc = self.acceleration(params, history, particle_type, material, senders,
                                receivers, mask)
        x_next = x + (x - history[:, -2]) + acc
        if self.config.clamp_to_bounds:
            lo = jnp.asarray([b[0] for b in self.config.bounds], x_next.dtype)
            hi = jnp.asarray([b[1] for b in self.config.bounds], x_next.dtype)
            x_next = jnp.clip(x_next, lo, hi)
        target = x if kinematic_position is None else kinematic_position
        x_next = jnp.where((particle_type == KINEMATIC)[:, None], target, x_next)
        return x_next, nbrs

    def _scan(self, params, particle_type, material, carry, kin, length):
        def body(c, k):
            hist, nbrs = c
            x_next, nbrs = self.step(params, hist, particle_type, material, nbrs, k)
            hist = jnp.concatenate([hist[:, 1:], x_next[:, None]], axis=1)
            return (hist, nbrs), (x_next, did_overflow(nbrs))
        return jax.lax.scan(body, carry, kin, length=length)

    @staticmethod
    def _kinematic_path(initial_history, n_steps, kinematic_path):
        """Held kinematic particles == a constant prescribed path (one code path to trace)."""
        if kinematic_path is not None:
            return kinematic_path
        x0 = initial_history[:, -1]
        return jnp.broadcast_to(x0, (n_steps,) + x0.shape)

    def _rollout_flags(self, params, initial_history, particle_type, material, n_steps, nbrs,
                       checkpoint_block=None, kinematic_path=None):
        """Rollout returning ``(positions (T, N, 2), overflowed (T,) bool per step)``."""
        kinematic_path = self._kinematic_path(initial_history, n_steps, kinematic_path)
        carry = (initial_history, nbrs)
        if not checkpoint_block or checkpoint_block >= n_steps:
            scan = self._scan
            if checkpoint_block:
                scan = jax.checkpoint(scan, static_argnums=(5,))
            _, (xs, flags) = scan(params, particle_type, material, carry, kinematic_path,
                                  n_steps)
            return xs, flags
        block = int(checkpoint_block)
        n_blocks, rem = divmod(n_steps, block)
        scan_ckpt = jax.checkpoint(self._scan, static_argnums=(5,))
        kin_main = kinematic_path[: n_blocks * block].reshape(
            (n_blocks, block) + kinematic_path.shape[1:])
        kin_tail = kinematic_path[n_blocks * block:]

        def outer(c, k):
            return scan_ckpt(params, particle_type, material, c, k, block)

        carry, (xs, flags) = jax.lax.scan(outer, carry, kin_main, length=n_blocks)
        xs = xs.reshape((n_blocks * block,) + xs.shape[2:])
        flags = flags.reshape(-1)
        if rem:
            _, (xt, ft) = scan_ckpt(params, particle_type, material, carry, kin_tail, rem)
            xs, flags = jnp.concatenate([xs, xt]), jnp.concatenate([flags, ft])
        return xs, flags

    def rollout(self, params, initial_history, particle_type, material, n_steps: int, nbrs,
                checkpoint_block: int | None = None, kinematic_path=None):
        """Roll out ``n_steps`` frames with ``lax.scan`` (jit with ``n_steps`` and
        ``checkpoint_block`` static).

        Args:
            initial_history: (N, C+1, 2) positions in m.
            particle_type: (N,) int; material: (N,) or scalar tan phi (differentiable).
            n_steps: number of frames to predict.
            nbrs: allocated neighbour list (capacity is fixed for the whole rollout).
            checkpoint_block: if set, ``jax.checkpoint`` blocks of this many steps, so
                reverse mode stores only the block boundaries (memory ~ n_steps / block).
            kinematic_path: optional (n_steps, N, 2) prescribed positions of the kinematic
                particles for each predicted frame.

        Returns:
            ``(positions (n_steps, N, 2), overflow)``: ``overflow`` is a bool scalar, True if
            the neighbour list overflowed at any step (results then invalid: re-allocate
            outside jit with more capacity and redo, see :meth:`rollout_safe`).
        """
        xs, flags = self._rollout_flags(params, initial_history, particle_type, material,
                                        n_steps, nbrs, checkpoint_block, kinematic_path)
        return xs, jnp.any(flags)

    def rollout_safe(self, params, initial_history, particle_type, material, n_steps: int,
                     nbrs=None, checkpoint_block: int | None = None, kinematic_path=None,
                     max_retries: int = 5):
        """Jitted :meth:`rollout` that re-allocates on overflow and redoes (outside jit).

        On overflow the list is re-allocated at the positions of the first overflowing frame
        (computed correctly, before the overflow), with growing extra capacity on repeated
        failures. Returns ``(positions (n_steps, N, 2), nbrs)``; the returned list is large
        enough for this rollout, so a following ``jax.grad`` of :meth:`rollout` can reuse it.
        """
        x0 = initial_history[:, -1]
        n = x0.shape[0]
        if nbrs is None:
            nbrs = self.allocate(x0)
        kinematic_path = self._kinematic_path(initial_history, n_steps, kinematic_path)
        for attempt in range(max_retries + 1):
            xs, flags = self._rollout_flags_jit(params, initial_history, particle_type,
                                                material, n_steps, nbrs, checkpoint_block,
                                                kinematic_path)
            flags = np.asarray(flags)
            if not flags.any():
                return xs, nbrs
            k = int(np.argmax(flags))
            x_k = x0 if k == 0 else xs[k - 1]
            extra = attempt * max(1, math.ceil(nbrs.idx.shape[1] / (4 * n)))
            nbrs = self.allocate(x_k, extra_capacity=extra)
        raise RuntimeError(f"neighbour list still overflowing after {max_retries} "
                           "re-allocations; raise capacity_multiplier")

    def to_trajectory(self, initial_history, positions, particle_type, material,
                      frame_dt: float = 2.5e-3) -> Trajectory:
        """Trajectory of the current frame of ``initial_history`` followed by ``positions``.

        Velocities (m/s) are backward differences divided by ``frame_dt`` (s).
        """
        pos = jnp.concatenate([initial_history[:, -2:].swapaxes(0, 1), positions])
        return Trajectory(positions=pos[1:], velocities=jnp.diff(pos, axis=0) / frame_dt,
                          particle_type=particle_type,
                          material=jnp.broadcast_to(jnp.asarray(material), particle_type.shape),
                          frame_dt=frame_dt, bounds=self.config.bounds)

