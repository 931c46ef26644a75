"""Scalar and profile measures of particle configurations (pure, differentiable).

Positions are (N, d) or (T, N, d) in m (d = 2, or 3 where said; y vertical); masses (N,)
in kg; velocities in m/s.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def runout(x: jax.Array, origin: float = 0.0, method: str = "max", q: float = 99.0,
           temperature: float = 2e-3, center=None) -> jax.Array:
    """Front position along x relative to ``origin``, or the radius of the front about a
    vertical axis (3D), m.

    Args:
        x: (..., N, d) positions, d = 2 or 3 (y vertical).
        origin: x from which the front is measured (without ``center``), m.
        method: "max" (farthest particle: the gradient flows through one particle),
            "percentile" (q-th percentile: robust to stray particles, gradient spread over
            two particles), or "softmax" (temperature-weighted soft maximum: smooth,
            gradient spread over the front; tends to "max" as temperature -> 0).
        temperature: length scale of the soft maximum, m.
        center: (cx, cz) of a vertical axis, m (3D only): the front is then the horizontal
            distance ``sqrt((x - cx)^2 + (z - cz)^2)`` (an axisymmetric collapse's runout
            radius; its gradient is finite on the axis).
    """
    xs = x[..., 0] - origin if center is None else radial_distance(x, center)
    if method == "max":
        return xs.max(-1)
    if method == "percentile":
        return jnp.percentile(xs, q, axis=-1)
    if method == "softmax":
        return temperature * jax.nn.logsumexp(xs / temperature, axis=-1) - temperature * jnp.log(
            xs.shape[-1])
    raise ValueError(f"runout method {method!r} is unknown; use 'max', 'percentile' or 'softmax'")


def radial_distance(x: jax.Array, center) -> jax.Array:
    """Horizontal distance (..., N), m, of 3D positions ``x`` (..., N, 3) from the vertical
    axis x = cx, z = cz (``center``, m); its gradient is finite (0) on the axis."""
    if x.shape[-1] != 3:
        raise ValueError(f"a radial distance (a runout about a centre) needs 3D positions "
                         f"(..., N, 3), got {tuple(x.shape)}")
    x = jnp.asarray(x)
    c = jnp.asarray(center, x.dtype)
    h = jnp.stack([x[..., 0] - c[0], x[..., 2] - c[1]])
    return jnp.sqrt(jnp.sum(h * h, axis=0) + jnp.finfo(x.dtype).tiny)


def deposit_profile(x: jax.Array, edges: jax.Array, sharpness: float | None = None) -> jax.Array:
    """Deposit height in bins along x: the highest particle in each bin, m.

    Args:
        x: (N, 2) positions.
        edges: (B + 1,) bin edges along x, m.
        sharpness: if given, membership of a bin is a sigmoid of width 1/sharpness (m), which
            makes the profile differentiable with respect to horizontal positions too.
    Returns:
        (B,) heights (0 for an empty bin).
    """
    lo, hi = edges[:-1, None], edges[1:, None]
    px, py = x[None, :, 0], x[None, :, 1]
    if sharpness is None:
        inside = (px >= lo) & (px < hi)
        return jnp.max(jnp.where(inside, py, 0.0), axis=1)
    w = jax.nn.sigmoid(sharpness * (px - lo)) * jax.nn.sigmoid(sharpness * (hi - px))
    return jnp.max(w * py, axis=1)


def deposit_front(x: jax.Array, bin_width: float, min_height: float, origin: float = 0.0,
                  length: float | None = None) -> jax.Array:
    """Front of the continuous deposit: the far edge of the farthest bin (width ``bin_width``)
    whose deposit height reaches ``min_height``; ignores a sheet of stray particles thinner
    than ``min_height`` ahead of the front. m, relative to ``origin``."""
    xs = x[:, 0] - origin
    length = float(jnp.max(xs)) + bin_width if length is None else length
    n = int(jnp.ceil(length / bin_width)) + 1
    edges = origin + bin_width * jnp.arange(n + 1, dtype=x.dtype)
    h = deposit_profile(x, edges)
    idx = jnp.where(h >= min_height, jnp.arange(n), -1).max()
    return (idx + 1) * bin_width


def flow_runout(x0: np.ndarray, x_final: np.ndarray, direction: int | None = None
                ) -> tuple[float, int]:
    """Runout of any granular flow along x, measured from the back of the initial mass.

    Args:
        x0, x_final: (N, d) initial and final positions, m.
        direction: +1 (flow to +x), -1 (to -x), or None: the side whose front advanced
            farther (give the reference's direction when scoring a prediction).
    Returns:
        (runout m, direction): ``max x_final - min x0`` to +x, ``max x0 - min x_final`` to
        -x. For a column collapsing away from a wall it is the usual runout from the wall
        (up to the particles' half-spacing at the wall); for a mass in the open, mirrored
        or against an obstacle it is the same definition, whichever way it flows.
    """
    x0, xf = np.asarray(x0)[:, 0], np.asarray(x_final)[:, 0]
    if direction is None:
        direction = 1 if xf.max() - x0.max() >= x0.min() - xf.min() else -1
    if direction not in (1, -1):
        raise ValueError(f"direction must be +1, -1 or None, got {direction!r}")
    run = xf.max() - x0.min() if direction == 1 else x0.max() - xf.min()
    return float(run), int(direction)


#: largest point count :func:`matched_position_error` accepts (an O(N^3) assignment, N^2 memory)
MATCHED_MAX_POINTS = 2048


def matched_position_error(x_pred: np.ndarray, x_ref: np.ndarray) -> float:
    """Mean distance between two point sets under their best one-to-one matching, m.

    A correspondence-free position error: the mean of ``|x_pred[s(i)] - x_ref[i]|`` over
    the permutation ``s`` that minimises it (an optimal assignment, the 1-Wasserstein
    distance between equal-weight point clouds). It scores the mass distribution (where
    the material is), not which labelled point went where, so it is at most the per-point
    error and is zero for any relabelling of the same set. Use it beside the per-point
    error where a point's identity is not physical (e.g. a coarse-grained node, the mean of
    particles that scatter).

    Args:
        x_pred, x_ref: (N, d) positions, m; same N and d, at most
            :data:`MATCHED_MAX_POINTS` points.
    Raises:
        ValueError: shapes differ, or N exceeds :data:`MATCHED_MAX_POINTS`.
    """
    from scipy.optimize import linear_sum_assignment

    xp, xr = np.asarray(x_pred, np.float64), np.asarray(x_ref, np.float64)
    if xp.shape != xr.shape or xp.ndim != 2:
        raise ValueError(f"matched_position_error: need two (N, d) arrays of one shape, got "
                         f"{xp.shape} and {xr.shape}")
    if len(xp) > MATCHED_MAX_POINTS:
        raise ValueError(f"matched_position_error: {len(xp)} points, at most "
                         f"{MATCHED_MAX_POINTS} (the assignment is O(N^3)); score nodes, not "
                         "particles")
    cost = np.sqrt(((xr[:, None, :] - xp[None, :, :]) ** 2).sum(-1))
    rows, cols = linear_sum_assignment(cost)
    return float(cost[rows, cols].mean())


def kinetic_energy(v: jax.Array, mass: jax.Array) -> jax.Array:
    """Kinetic energy 0.5 sum m |v|^2; v (..., N, d). J (J per m of depth in 2D)."""
    return 0.5 * jnp.sum(mass * jnp.sum(v * v, -1), -1)


def momentum(v: jax.Array, mass: jax.Array) -> jax.Array:
    """Total momentum (..., d), kg m/s (per m of depth in 2D)."""
    return jnp.sum(mass[:, None] * v, -2)


def lube_runout(aspect_ratio):
    """Normalised runout (L_inf - L0)/L0 of Lube et al. (2005) quasi-2D collapses:
    1.2 a for a < 1.8, 1.9 a^(2/3) for a > 2.8 (the larger of the two in between)."""
    a = jnp.asarray(aspect_ratio)
    return jnp.where(a < 1.8, 1.2 * a, jnp.where(a > 2.8, 1.9 * a ** (2 / 3),
                                                  jnp.maximum(1.2 * a, 1.9 * a ** (2 / 3))))
