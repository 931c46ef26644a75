"""Quadratic B-spline shape functions on a regular grid.

Positions are given in grid units relative to the grid origin (``X = (x - origin)/dx``).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

# The nine stencil offsets (i, j), i-major.
OFFSET_I = np.repeat(np.arange(3, dtype=np.int32), 3)
OFFSET_J = np.tile(np.arange(3, dtype=np.int32), 3)


def bspline_weights(fx: jax.Array) -> jax.Array:
    """Quadratic B-spline weights of the three stencil nodes along one axis.

    Args:
        fx: (N,) position relative to the base node, in cells, in [0.5, 1.5).
    Returns:
        (3, N) weights, summing to 1.
    """
    return jnp.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2])


def stencil(X: jax.Array, grid_shape: tuple[int, int]):
    """Stencil of each particle.

    Args:
        X: (2, N) positions in grid units.
        grid_shape: (nx, ny) nodes.
    Returns:
        idx: (9, N) flat node indices (i * ny + j).
        w: (9, N) weights.
        dpos: (2, 9, N) node position minus particle position, in cells.
    """
    base = jnp.floor(X - 0.5)
    fx = X - base
    base = base.astype(jnp.int32)
    wx, wy = bspline_weights(fx[0]), bspline_weights(fx[1])
    w = jnp.stack([wx[i] * wy[j] for i in range(3) for j in range(3)])
    dpos = jnp.stack([OFFSET_I[:, None] - fx[0][None], OFFSET_J[:, None] - fx[1][None]])
    idx = (base[0][None] + OFFSET_I[:, None]) * grid_shape[1] + base[1][None] + OFFSET_J[:, None]
    return idx, w, dpos.astype(X.dtype)
