"""Particle-to-grid (one scatter) and grid-to-particle (one gather) transfers, MLS/APIC.

All particle arrays are component-major: vectors (2, N), matrices (2, 2, N).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from diffgns.mpm.linalg import safe_div


def p2g(idx, w, dpos, mass, momentum, affine, n_nodes: int, dx: float):
    """Scatter mass and MLS momentum to the grid in one scatter-add.

    Args:
        idx, w, dpos: stencil from :func:`diffgns.mpm.shape.stencil` ((9,N), (9,N), (2,9,N) cells).
        mass: (N,) particle mass, kg.
        momentum: (2, N) particle momentum m v, kg m/s.
        affine: (2, 2, N) affine momentum matrix (m C - dt vol 4/dx^2 tau), kg/s.
        n_nodes: number of grid nodes.
        dx: cell size, m.
    Returns:
        (n_nodes, 3) grid momentum (x, y) and mass.
    """
    dx_, dy_ = dpos[0] * dx, dpos[1] * dx
    mvx = w * (momentum[0][None] + affine[0, 0][None] * dx_ + affine[0, 1][None] * dy_)
    mvy = w * (momentum[1][None] + affine[1, 0][None] * dx_ + affine[1, 1][None] * dy_)
    m = w * mass[None]
    vals = jnp.stack([mvx, mvy, m], -1).reshape(-1, 3)
    grid = jnp.zeros((n_nodes, 3), vals.dtype)
    return grid.at[idx.reshape(-1)].add(vals, mode="promise_in_bounds")


def grid_velocity(grid: jax.Array) -> jax.Array:
    """Grid velocity (2, n_nodes) from momentum and mass; 0 at empty nodes (finite gradient)."""
    inv = safe_div(1.0, grid[:, 2])
    return jnp.stack([grid[:, 0] * inv, grid[:, 1] * inv])


def g2p(idx, w, dpos, gv: jax.Array, dx: float):
    """Gather grid velocities back to particles.

    Args:
        gv: (2, n_nodes) grid velocity, m/s.
    Returns:
        v: (2, N) particle velocity, m/s; C: (2, 2, N) APIC velocity gradient, 1/s.
    """
    g = jnp.stack([gv[0], gv[1]], -1).at[idx].get(mode="promise_in_bounds")  # (9, N, 2)
    gx, gy = w * g[..., 0], w * g[..., 1]
    k = 4.0 / dx
    v = jnp.stack([gx.sum(0), gy.sum(0)])
    C = k * jnp.stack([
        jnp.stack([(gx * dpos[0]).sum(0), (gx * dpos[1]).sum(0)]),
        jnp.stack([(gy * dpos[0]).sum(0), (gy * dpos[1]).sum(0)]),
    ])
    return v, C

