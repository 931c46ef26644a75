"""Particle-to-grid (one scatter) and grid-to-particle (one gather) transfers, MLS/APIC.

All particle arrays are component-major: vectors (2, N), matrices (2, 2, N).

Both transfers are shaped for XLA's CPU scatter and gather, whose cost grows with the number
of indexed rows (measured, issue 22; `docs/performance.md`):

* :func:`p2g` computes the (9N, 3) contributions first and scatters them in one
  ``scatter-add``; an ``optimization_barrier`` keeps XLA from fusing the arithmetic into the
  scatter loop, where it was recomputed row by row (-23% P2G time at 8k particles).
* :func:`g2p` first lays the grid velocities out as a (n_nodes, 9, 2) *patch* array (node ->
  the velocities of its 3 x 3 stencil, nine dense shifted copies), then gathers one row of 18
  values per particle at its base node instead of nine rows of 2 (-47% G2P time). Same
  values, same order of summation.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from diffgns.mpm.linalg import safe_div
from diffgns.mpm.shape import OFFSET_I, OFFSET_J


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
    # materialise the contributions: fused into the scatter they are recomputed per row
    vals = jax.lax.optimization_barrier(jnp.stack([mvx, mvy, m], -1).reshape(-1, 3))
    grid = jnp.zeros((n_nodes, 3), vals.dtype)
    return grid.at[idx.reshape(-1)].add(vals, mode="promise_in_bounds")


def grid_velocity(grid: jax.Array) -> jax.Array:
    """Grid velocity (2, n_nodes) from momentum and mass; 0 at empty nodes (finite gradient)."""
    inv = safe_div(1.0, grid[:, 2])
    return jnp.stack([grid[:, 0] * inv, grid[:, 1] * inv])


def stencil_patches(gv: jax.Array) -> jax.Array:
    """(n_nodes, 18) velocities of each node's 3 x 3 stencil, offsets i-major as in
    :data:`~diffgns.mpm.shape.OFFSET_I`, components last: row ``b`` holds
    ``gv[:, b + shift(o)]`` for the nine offsets ``o`` (nodes past the grid's end read 0;
    a particle's stencil never reaches them).

    Args:
        gv: (2, nx, ny) grid velocity, m/s.
    """
    _, nx, ny = gv.shape
    n_nodes = nx * ny
    shifts = [int(i) * ny + int(j) for i, j in zip(OFFSET_I, OFFSET_J)]
    flat = jnp.pad(gv.reshape(2, n_nodes).T, ((0, max(shifts)), (0, 0)))  # (n + s, 2)
    return jnp.concatenate([flat[s:s + n_nodes] for s in shifts], axis=1)


def g2p(idx, w, dpos, gv: jax.Array, dx: float):
    """Gather grid velocities back to particles.

    Args:
        idx, w, dpos: stencil from :func:`diffgns.mpm.shape.stencil`.
        gv: (2, nx, ny) grid velocity, m/s.
        dx: cell size, m.
    Returns:
        v: (2, N) particle velocity, m/s; C: (2, 2, N) APIC velocity gradient, 1/s.
    """
    if gv.ndim != 3:
        raise ValueError(f"g2p: gv must be (2, nx, ny), got shape {gv.shape}")
    rows = stencil_patches(gv).at[idx[0]].get(mode="promise_in_bounds")  # (N, 18)
    g = rows.reshape(-1, 9, 2).transpose(1, 0, 2)  # (9, N, 2)
    gx, gy = w * g[..., 0], w * g[..., 1]
    k = 4.0 / dx
    v = jnp.stack([gx.sum(0), gy.sum(0)])
    C = k * jnp.stack([
        jnp.stack([(gx * dpos[0]).sum(0), (gx * dpos[1]).sum(0)]),
        jnp.stack([(gy * dpos[0]).sum(0), (gy * dpos[1]).sum(0)]),
    ])
    return v, C
