"""Node and edge features, the normaliser and training noise for the particle GNS.

Units: positions in m (the dataset's position unit); time in **frames**, so a velocity is a
displacement per frame (m/frame) and an acceleration a displacement per frame^2 (m/frame^2),
as in the dataset metadata (``vel_mean``/``vel_std``, ``acc_mean``/``acc_std``).

Every function here is dimension-generic: positions are ``(..., d)`` with d = 2 (x, y) or
3 (x, y, z; y vertical in both), and the width of every feature follows from d (one code
path; :func:`n_node_features`).

A *history* is the array of the last ``C + 1`` positions of every particle, shape
``(N, C + 1, d)``, oldest first; ``history[:, -1]`` is the current position. Its ``C``
finite differences are the input velocities.

Node features (:func:`node_features`), in this order along the last axis:

1. the ``C`` velocities, normalised with the velocity :class:`Normalizer`, flattened
   (``d C`` columns, time-major: ``v_0x, v_0y, (v_0z,) v_1x, ...``);
2. the distances of the current position to the ``2 d`` walls ``(x - xmin, y - ymin,
   (z - zmin,) xmax - x, ymax - y (, zmax - z))`` divided by the radius ``R`` and clipped
   to ``[-1, 1]`` (``2 d`` columns);
3. optionally (``obstacles`` given) the nearest box obstacle, :func:`obstacle_distances`
   (``1 + d`` columns);
4. optionally the raw material feature ``tan(phi)`` (1 column, not normalised).

The particle type is not a feature here: the network embeds it. Absolute position never
enters except through the clipped wall and obstacle distances, so the features (and the
network's output) are invariant to translating the particles, the box and the obstacles
together, and a particle farther than ``R`` from every wall and obstacle sees the same
features in a box of any size (a box 1.5-2x longer than the training box is not new input).

Obstacles are node features from the signed distance, not boundary particles as in the
reference GNS: a static axis-aligned box is described exactly by its distance field, the
feature costs O(N K) per step for K obstacles (boundary particles would add ~4 nodes per
0.05 m of surface at the node spacing of coarse-graining 16, each with its edges, to a step
whose cost is ~65% edge MLPs), needs no kinematic type to mask from the loss, and a
particle sees the same ``1 + d`` numbers in front of a wall and of an obstacle face.
Models trained without obstacles (every shipped model) pass ``obstacles=None`` and get
exactly their old features.

Edge features (:func:`edge_features`): ``(x_sender - x_receiver) / R`` and its norm,
``(E, d + 1)``, zero on masked edges; the norm uses a safe square root (finite gradient at 0,
needed for self-edges).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from diffgns.trajectory import KINEMATIC

__all__ = [
    "Normalizer", "ParticleStats", "combine_std", "edge_features",
    "node_features", "n_node_features", "obstacle_distances", "random_walk_noise",
    "target_acceleration", "velocities", "wall_distances",
]


def combine_std(std_data, sigma: float) -> jax.Array:
    """``sqrt(std_data^2 + sigma^2)``: a data std widened by the training noise ``sigma``."""
    std_data = jnp.asarray(std_data, dtype=jnp.result_type(float))
    return jnp.sqrt(std_data**2 + sigma**2)


@struct.dataclass
class Normalizer:
    """Affine normaliser ``(x - mean) / std``: the one normaliser of diffgns (particle GNS,
    MeshGraphNet, message networks); ``mean``, ``std`` broadcast against ``x``.

    Attributes:
        mean: (D,) or () array, in the units of the quantity (e.g. m/frame).
        std: same shape and units, > 0.
    """

    mean: jax.Array
    std: jax.Array

    def normalize(self, x: jax.Array) -> jax.Array:
        return (x - self.mean) / self.std

    def denormalize(self, y: jax.Array) -> jax.Array:
        return y * self.std + self.mean

    @classmethod
    def identity(cls, dim: int = 2) -> Normalizer:
        return cls(jnp.zeros((dim,)), jnp.ones((dim,)))

    @classmethod
    def fit(cls, x, min_std: float = 0.0, center: bool = True) -> Normalizer:
        """Per-feature statistics of samples ``x`` (..., D) over every leading axis (or of
        all of ``x`` when it is 1-D), computed in float64; the std is floored at ``min_std``.
        ``center=False`` keeps ``mean = 0`` (a pure scale)."""
        a = np.asarray(x, np.float64)
        a = a.reshape(-1, a.shape[-1]) if a.ndim > 1 else a.reshape(-1)
        f = jnp.result_type(float)
        mean = a.mean(0) if center else np.zeros(a.shape[1:])
        return cls(jnp.asarray(mean, f), jnp.asarray(np.maximum(a.std(0), min_std), f))


@struct.dataclass
class ParticleStats:
    """Normalisation statistics of a particle GNS: velocity (m/frame) and acceleration
    (m/frame^2) :class:`Normalizer`."""

    velocity: Normalizer
    acceleration: Normalizer

    @classmethod
    def from_metadata(cls, meta: dict, noise_std: float = 0.0) -> ParticleStats:
        """Build from a metadata dict with ``vel_mean``, ``vel_std``, ``acc_mean``, ``acc_std``.

        The random-walk noise ``noise_std`` (m) is folded into both stds,
        ``std = sqrt(std_data^2 + noise_std^2)``, as in the reference GNS.
        """
        missing = [k for k in ("vel_mean", "vel_std", "acc_mean", "acc_std") if k not in meta]
        if missing:
            raise KeyError(f"metadata lacks {missing}; compute the dataset statistics first")
        f = jnp.result_type(float)
        return cls(
            velocity=Normalizer(jnp.asarray(meta["vel_mean"], f),
                                combine_std(meta["vel_std"], noise_std)),
            acceleration=Normalizer(jnp.asarray(meta["acc_mean"], f),
                                    combine_std(meta["acc_std"], noise_std)),
        )

    @classmethod
    def identity(cls, dim: int = 2) -> ParticleStats:
        return cls(Normalizer.identity(dim), Normalizer.identity(dim))




def velocities(history: jax.Array) -> jax.Array:
    """(N, C+1, d) positions -> (N, C, d) velocities in m/frame (finite differences)."""
    return history[:, 1:] - history[:, :-1]


def wall_distances(x: jax.Array, walls, radius: float) -> jax.Array:
    """(N, d) positions -> (N, 2d) ``(x - lower, upper - x) / R`` in [-1, 1]: in 2D
    ``(x - xmin, y - ymin, xmax - x, ymax - y) / R``, in 3D ``(x - xmin, y - ymin, z - zmin,
    xmax - x, ymax - y, zmax - z) / R``.

    ``walls``: ``((xmin, xmax), (ymin, ymax)(, (zmin, zmax)))`` m, as a tuple (static) or a
    (d, 2) array (traced, e.g. :attr:`diffgns.graph.geometry.Geometry.walls`); ValueError
    when d differs from the positions'."""
    walls = jnp.asarray(walls, dtype=x.dtype)
    if walls.shape != (x.shape[-1], 2):
        raise ValueError(f"walls {walls.shape} do not match {x.shape[-1]}D positions: give "
                         f"({x.shape[-1]}, 2) [lo, hi] per axis")
    lower, upper = walls[:, 0], walls[:, 1]
    d = jnp.concatenate([x - lower, upper - x], axis=-1) / radius
    return jnp.clip(d, -1.0, 1.0)


def obstacle_distances(x: jax.Array, obstacles, radius: float) -> jax.Array:
    """(N, d) positions -> (N, 1 + d) ``[s, w n]`` of the nearest box obstacle (2D ``[s, w n_x,
    w n_y]``, 3D ``[s, w n_x, w n_y, w n_z]``).

    ``s = clip(d / R, -1, 1)`` with ``d`` the signed distance (m) to the nearest obstacle
    (> 0 outside, < 0 inside), ``n`` the unit outward normal of that obstacle at the particle
    (outside: from the nearest surface point to the particle; inside: of the nearest face),
    ``w = 1 - clip(d / R, 0, 1)``: the normal fades out linearly over ``R``. Farther than
    ``R`` from every obstacle, and with no obstacle at all (K = 0), the features are exactly
    ``(1, 0, ..., 0)``, like a clipped wall distance. Continuous outside the obstacles; gradients
    are finite everywhere (safe norm).

    Args:
        x: (N, d) positions, m.
        obstacles: (K, 2d) ``[lo..., hi...]`` boxes (2D ``[x0, y0, x1, y1]``, 3D ``[x0, y0,
            z0, x1, y1, z1]``), m (K >= 0).
        radius: connectivity radius R, m.
    """
    dim = x.shape[-1]
    obs = jnp.asarray(obstacles, x.dtype)
    if obs.size and obs.shape[-1] != 2 * dim:
        raise ValueError(f"obstacles {obs.shape} do not match {dim}D positions: give "
                         f"(K, {2 * dim}) boxes [lo..., hi...]")
    obs = obs.reshape(-1, 2 * dim)
    if obs.shape[0] == 0:
        none = jnp.asarray([1.0] + [0.0] * dim, x.dtype)
        return jnp.broadcast_to(none, (x.shape[0], 1 + dim))
    lo, hi = obs[None, :, :dim], obs[None, :, dim:]  # (1, K, d)
    p = x[:, None, :]  # (N, 1, d)
    out = p - jnp.clip(p, lo, hi)  # (N, K, d) nearest surface point -> p; 0 inside
    dist_out = _safe_norm(out)[..., 0]
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    q = jnp.abs(p - centre) - half  # (N, K, d) < 0 on every axis inside
    depth = jnp.max(q, axis=-1)  # inside: -(distance to the nearest face)
    inside = depth < 0
    signed = jnp.where(inside, depth, dist_out)
    k = jnp.argmin(signed, axis=1)  # nearest obstacle
    take = jax.vmap(lambda a, i: a[i])
    d, ins = take(signed, k), take(inside, k)
    face = jnp.argmax(take(q, k), axis=-1)  # (N,) axis of the nearest face when inside
    sign = jnp.sign(take(p - centre, k))  # (N, d)
    n_in = jnp.where(jnp.arange(dim)[None] == face[:, None], sign, 0.0)
    safe = jnp.where(dist_out > 0, dist_out, 1.0)
    n_out = take(out / safe[..., None], k)
    n = jnp.where(ins[:, None], n_in, n_out)
    s = jnp.clip(d / radius, -1.0, 1.0)
    w = 1.0 - jnp.clip(d / radius, 0.0, 1.0)
    return jnp.concatenate([s[:, None], w[:, None] * n], axis=-1)


def n_node_features(history: int = 5, use_material: bool = True,
                    use_obstacles: bool = False, dim: int = 2) -> int:
    """Width F of :func:`node_features` in ``dim`` dimensions: ``d C + 2 d (+ 1 + d) (+ 1)``
    (2D: ``2 C + 4 (+ 3) (+ 1)``)."""
    return dim * history + 2 * dim + (1 + dim) * int(use_obstacles) + int(use_material)


def node_features(history: jax.Array, bounds, radius: float, vel_normalizer: Normalizer,
                  material: jax.Array | None = None, obstacles=None) -> jax.Array:
    """Node features of a position history.

    Args:
        history: (N, C+1, d) positions in m, oldest first (d = 2 or 3).
        bounds: the walls ``((xmin, xmax), (ymin, ymax)(, (zmin, zmax)))`` in m (tuple or
            (d, 2) array).
        radius: connectivity radius R in m.
        vel_normalizer: velocity normaliser (m/frame).
        material: optional (N,) or scalar raw material feature (tan of the friction angle);
            a scalar is broadcast to all particles (as in the inverse problems).
        obstacles: optional (K, 2d) box obstacles ``[lo..., hi...]`` in m (K >= 0): adds
            :func:`obstacle_distances`; None (every shipped model) adds nothing.

    Returns:
        (N, d C + 2 d (+ 1 + d) (+ 1)) features (see the module docstring for the order).
    """
    n = history.shape[0]
    vel = vel_normalizer.normalize(velocities(history)).reshape(n, -1)
    parts = [vel, wall_distances(history[:, -1], bounds, radius)]
    if obstacles is not None:
        parts.append(obstacle_distances(history[:, -1], obstacles, radius))
    if material is not None:
        parts.append(jnp.broadcast_to(jnp.asarray(material, history.dtype), (n,))[:, None])
    return jnp.concatenate(parts, axis=-1)


def _safe_norm(d: jax.Array) -> jax.Array:
    """Euclidean norm over the last axis with a finite (zero) gradient at 0."""
    r2 = jnp.sum(d * d, axis=-1, keepdims=True)
    pos = r2 > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, r2, 1.0)), 0.0)


def edge_features(x: jax.Array, senders: jax.Array, receivers: jax.Array, mask: jax.Array,
                  radius: float) -> jax.Array:
    """(E, d + 1) edge features ``[(x_s - x_r)/R, |x_s - x_r|/R]``, zero where ``mask`` is
    False.

    ``x`` is (N, d) in m; ``senders``/``receivers`` (E,) int may hold the padding index N.
    """
    xs = jnp.take(x, senders, axis=0, mode="clip")
    xr = jnp.take(x, receivers, axis=0, mode="clip")
    d = (xs - xr) / radius
    feats = jnp.concatenate([d, _safe_norm(d)], axis=-1)
    return jnp.where(mask[:, None], feats, 0.0)


def random_walk_noise(key: jax.Array, position_sequence: jax.Array, sigma: float,
                      particle_type: jax.Array | None = None) -> jax.Array:
    """Random-walk noise for an input position sequence (reference GNS training noise).

    Each of the ``C`` input velocities gets i.i.d. Gaussian noise of std ``sigma / sqrt(C)``;
    the velocity noise is cumulated in time to a position noise, with zero noise on the
    oldest position, so the noise on the last (current) position has std ``sigma``.
    Kinematic particles (type 3) get no noise when ``particle_type`` is given.

    Args:
        key: PRNG key.
        position_sequence: (N, C+1, d) input positions (only shape and dtype are used).
        sigma: noise scale in m.
        particle_type: optional (N,) int types.

    Returns:
        (N, C+1, d) position noise to *add* to the inputs. Use :func:`target_acceleration`
        to correct the training target for the noise on the last position.
    """
    n, cp1, dim = position_sequence.shape
    c = cp1 - 1
    vel_noise = jax.random.normal(key, (n, c, dim), position_sequence.dtype) * (sigma / c**0.5)
    pos_noise = jnp.concatenate(
        [jnp.zeros((n, 1, dim), vel_noise.dtype), jnp.cumsum(vel_noise, axis=1)], axis=1)
    if particle_type is not None:
        pos_noise = jnp.where((particle_type == KINEMATIC)[:, None, None], 0.0, pos_noise)
    return pos_noise


def target_acceleration(next_position: jax.Array, history: jax.Array,
                        noise: jax.Array | None = None) -> jax.Array:
    """Training target acceleration (m/frame^2), corrected for input noise.

    With noisy inputs ``h~ = history + noise``, the target next position is moved by the
    same noise as the last input, ``x~_{t+1} = x_{t+1} + noise[:, -1]``, so the target
    velocity ``x~_{t+1} - x~_t`` is the clean one and the target acceleration is
    ``a = x~_{t+1} - 2 x~_t + x~_{t-1}``: the model learns to undo the noise on the last
    input velocity, and a rollout with this acceleration (semi-implicit Euler) lands on the
    clean next position.

    Args:
        next_position: (N, d) clean position at t+1, in m.
        history: (N, C+1, d) clean input positions, in m.
        noise: optional (N, C+1, d) noise added to the inputs (:func:`random_walk_noise`).

    Returns:
        (N, d) target acceleration in m/frame^2 (not normalised).
    """
    if noise is not None:
        history = history + noise
        next_position = next_position + noise[:, -1]
    return next_position - 2.0 * history[:, -1] + history[:, -2]
