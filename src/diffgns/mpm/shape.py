"""Quadratic B-spline shape functions on a regular grid, in 2D or 3D.

Positions are given in grid units relative to the grid origin (``X = (x - origin)/dx``).
A particle's stencil is the 3^d nodes around it: 9 in 2D, 27 in 3D.
"""
from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np


def offsets(d: int) -> np.ndarray:
    """(d, 3^d) int32 stencil offsets, first axis slowest (i-major): column k of
    ``offsets(2)`` is (i, j) = (k // 3, k % 3)."""
    return np.array(list(itertools.product(range(3), repeat=d)), np.int32).T


# The nine 2D stencil offsets (i, j), i-major.
OFFSET_I, OFFSET_J = offsets(2)


def bspline_weights(fx: jax.Array) -> jax.Array:
    """Quadratic B-spline weights of the three stencil nodes along one axis.

    Args:
        fx: (N,) position relative to the base node, in cells, in [0.5, 1.5).
    Returns:
        (3, N) weights, summing to 1.
    """
    return jnp.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2])


def flat_strides(grid_shape: tuple[int, ...]) -> tuple[int, ...]:
    """Row-major strides of a grid of node counts ``grid_shape`` (flat index = sum i_a s_a)."""
    return tuple(int(np.prod(grid_shape[a + 1:], dtype=np.int64)) for a in range(len(grid_shape)))


def stencil(X: jax.Array, grid_shape: tuple[int, ...]):
    """Stencil of each particle.

    Args:
        X: (d, N) positions in grid units (d = 2 or 3).
        grid_shape: (nx, ny[, nz]) nodes.
    Returns:
        idx: (3^d, N) flat node indices (row-major: i * ny + j in 2D).
        w: (3^d, N) weights (products of the per-axis weights).
        dpos: (d, 3^d, N) node position minus particle position, in cells.
    """
    d = X.shape[0]
    off = offsets(d)
    base = jnp.floor(X - 0.5)
    fx = X - base
    base = base.astype(jnp.int32)
    ws = [bspline_weights(fx[a]) for a in range(d)]
    terms = []
    for k in range(off.shape[1]):
        t = ws[0][off[0, k]]
        for a in range(1, d):
            t = t * ws[a][off[a, k]]
        terms.append(t)
    w = jnp.stack(terms)
    dpos = jnp.stack([off[a][:, None] - fx[a][None] for a in range(d)])
    # flat index of the base node (N,), plus each offset's constant flat shift (S,): the
    # same integers as sum_a (base_a + off_a) stride_a, with 3^d times fewer multiplies
    strides = flat_strides(grid_shape)
    shifts = np.array([sum(int(off[a, k]) * strides[a] for a in range(d))
                       for k in range(off.shape[1])], np.int32)
    flat = base[0] * strides[0]
    for a in range(1, d):
        flat = flat + base[a] * strides[a]
    idx = flat[None] + jnp.asarray(shifts)[:, None]
    return idx, w, dpos.astype(X.dtype)
