"""Particle-to-grid (one scatter) and grid-to-particle (one gather) transfers, MLS/APIC,
in 2D or 3D.

All particle arrays are component-major: vectors (d, N), matrices (d, d, N); a particle's
stencil has S = 3^d nodes (9 in 2D, 27 in 3D).

Both transfers are shaped for XLA's CPU scatter and gather, whose cost grows with the number
of indexed rows (measured in 2D, issue 22; `docs/performance.md`):

* :func:`p2g` computes the (S N, d + 1) contributions first and scatters them in one
  ``scatter-add``; an ``optimization_barrier`` keeps XLA from fusing the arithmetic into the
  scatter loop, where it was recomputed row by row (-23% P2G time at 8k particles).
* :func:`g2p` first lays the grid velocities out as a (n_nodes, S d) *patch* array (node ->
  the velocities of its stencil, S dense shifted copies), then gathers one row of S d
  values per particle at its base node instead of S rows of d (-47% G2P time in 2D). Same
  values, same order of summation.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from diffgns.mpm.linalg import safe_div
from diffgns.mpm.shape import flat_strides, offsets


def _axpy_sum(first, terms):
    out = first
    for t in terms:
        out = out + t
    return out


def p2g(idx, w, dpos, mass, momentum, affine, n_nodes: int, dx: float):
    """Scatter mass and MLS momentum to the grid in one scatter-add.

    Args:
        idx, w, dpos: stencil from :func:`diffgns.mpm.shape.stencil` ((S,N), (S,N), (d,S,N) cells).
        mass: (N,) particle mass, kg.
        momentum: (d, N) particle momentum m v, kg m/s.
        affine: (d, d, N) affine momentum matrix (m C - dt vol 4/dx^2 tau), kg/s.
        n_nodes: number of grid nodes.
        dx: cell size, m.
    Returns:
        (n_nodes, d + 1) grid momentum (x, y[, z]) and mass.
    """
    d = momentum.shape[0]
    dxs = [dpos[a] * dx for a in range(d)]
    mv = [w * _axpy_sum(momentum[c][None], [affine[c, a][None] * dxs[a] for a in range(d)])
          for c in range(d)]
    m = w * mass[None]
    # materialise the contributions: fused into the scatter they are recomputed per row
    vals = jax.lax.optimization_barrier(jnp.stack([*mv, m], -1).reshape(-1, d + 1))
    grid = jnp.zeros((n_nodes, d + 1), vals.dtype)
    return grid.at[idx.reshape(-1)].add(vals, mode="promise_in_bounds")


def grid_velocity(grid: jax.Array) -> jax.Array:
    """Grid velocity (d, n_nodes) from momentum and mass; 0 at empty nodes (finite gradient)."""
    d = grid.shape[1] - 1
    inv = safe_div(1.0, grid[:, d])
    return jnp.stack([grid[:, c] * inv for c in range(d)])


def stencil_patches(gv: jax.Array) -> jax.Array:
    """(n_nodes, S d) velocities of each node's stencil, offsets i-major as in
    :func:`~diffgns.mpm.shape.offsets`, components last: row ``b`` holds
    ``gv[:, b + shift(o)]`` for the S offsets ``o`` (nodes past the grid's end read 0;
    a particle's stencil never reaches them).

    Args:
        gv: (d, nx, ny[, nz]) grid velocity, m/s.
    """
    d, grid_shape = gv.shape[0], gv.shape[1:]
    n_nodes = int(gv[0].size)
    strides = flat_strides(grid_shape)
    off = offsets(d)
    shifts = [sum(int(off[a, k]) * strides[a] for a in range(d)) for k in range(off.shape[1])]
    flat = jnp.pad(gv.reshape(d, n_nodes).T, ((0, max(shifts)), (0, 0)))  # (n + s, d)
    return jnp.concatenate([flat[s:s + n_nodes] for s in shifts], axis=1)


def g2p(idx, w, dpos, gv: jax.Array, dx: float):
    """Gather grid velocities back to particles.

    Args:
        idx, w, dpos: stencil from :func:`diffgns.mpm.shape.stencil`.
        gv: (d, nx, ny[, nz]) grid velocity, m/s.
        dx: cell size, m.
    Returns:
        v: (d, N) particle velocity, m/s; C: (d, d, N) APIC velocity gradient, 1/s.
    """
    d = gv.shape[0]
    if gv.ndim != d + 1 or d not in (2, 3):
        raise ValueError(f"g2p: gv must be (d, nx, ny[, nz]) with d = 2 or 3, got shape "
                         f"{gv.shape}")
    S = 3 ** d
    rows = stencil_patches(gv).at[idx[0]].get(mode="promise_in_bounds")  # (N, S d)
    g = rows.reshape(-1, S, d).transpose(1, 0, 2)  # (S, N, d)
    gw = [w * g[..., c] for c in range(d)]
    k = 4.0 / dx
    v = jnp.stack([gw[c].sum(0) for c in range(d)])
    C = k * jnp.stack([jnp.stack([(gw[c] * dpos[a]).sum(0) for a in range(d)])
                       for c in range(d)])
    return v, C
