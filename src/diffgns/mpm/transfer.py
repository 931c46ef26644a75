"""Particle-to-grid (one scatter) and grid-to-particle (one gather) transfers, MLS/APIC,
in 2D or 3D.

All particle arrays are component-major: vectors (d, N), matrices (d, d, N); a particle's
stencil has S = 3^d nodes (9 in 2D, 27 in 3D).

Both transfers are shaped for XLA's CPU scatter and gather, whose cost grows with the number
of indexed rows (measured in 2D, issue 22, and 3D, issue 24; `docs/performance.md`). They
address the grid by *rows*: the 3 consecutive nodes of a stencil along the grid's last
(fastest) axis, so a stencil is 3^(d-1) rows (3 in 2D, 9 in 3D) of 3 nodes each.

* :func:`p2g` computes the (S N, d + 1) contributions first, lays them out as
  (S/3 N, 3, d + 1) rows and scatters them in one windowed ``scatter-add``; an
  ``optimization_barrier`` keeps XLA from fusing the arithmetic into the scatter loop, where
  it was recomputed row by row (-23% P2G time at 8k particles in 2D).
* :func:`g2p` gathers the same rows of grid velocity in one windowed gather. An earlier
  version first laid the grid out as a (n_nodes, S d) *patch* array (S dense shifted copies)
  and gathered one row per particle: -47% G2P time in 2D, but in 3D the 27 copies of the
  whole grid cost more than the gather they saved (the mpm3d J-fluid substep took 1.8x as
  long as with the rows; 2026-12-04). Its sums over the stencil are S - 1 fused adds
  (:func:`~diffgns.mpm.linalg.sum0`), and the APIC gradient uses the constant offsets
  instead of a pass over the (d, S, N) ``dpos``.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from diffgns.mpm import linalg as la
from diffgns.mpm.linalg import tiny
from diffgns.mpm.shape import offsets

# A *row*: the 3 consecutive nodes of a stencil along the grid's last (fastest) axis; a
# particle's stencil is 3^(d-1) rows, indexed by their first node (``idx[::3]``).
_ROWS_SCATTER = jax.lax.ScatterDimensionNumbers(
    update_window_dims=(1, 2), inserted_window_dims=(), scatter_dims_to_operand_dims=(0,))
_ROWS_GATHER = jax.lax.GatherDimensionNumbers(
    offset_dims=(1, 2), collapsed_slice_dims=(), start_index_map=(0,))


def p2g(idx, w, dpos, mass, momentum, affine, n_nodes: int, dx: float, affine_free=None):
    """Scatter mass and MLS momentum to the grid in one scatter-add.

    Args:
        idx, w, dpos: stencil from :func:`diffgns.mpm.shape.stencil` ((S,N), (S,N), (d,S,N) cells).
        mass: (N,) particle mass, kg.
        momentum: (d, N) particle momentum m v, kg m/s.
        affine: (d, d, N) affine momentum matrix (m C - dt vol 4/dx^2 tau), kg/s.
        n_nodes: number of grid nodes.
        dx: cell size, m.
        affine_free: optional (d, d, N) affine matrix without the stress (m C), kg/s: the
            momentum before this substep's forces is then scattered too, in the same pass
            (the grid velocity change a FLIP update needs).
    Returns:
        (n_nodes, d + 1) grid momentum (x, y[, z]) and mass; with ``affine_free``
        (n_nodes, 2 d + 1), the momentum before the forces appended.
    """
    d = momentum.shape[0]
    dxs = [dpos[a] * dx for a in range(d)]

    def mls(aff):
        return [w * la._sum([momentum[c][None], *[aff[c, a][None] * dxs[a] for a in range(d)]])
                for c in range(d)]

    channels = [*mls(affine), w * mass[None]]
    if affine_free is not None:
        channels += mls(affine_free)
    k = len(channels)
    S = idx.shape[0]
    # (S, N, k) -> one row of 3 consecutive nodes along the last axis per (outer offset,
    # particle): (S/3 N, 3, k), scattered at the row's first node
    vals = jnp.stack(channels, -1).reshape(S // 3, 3, -1, k).transpose(0, 2, 1, 3)
    # materialise the contributions: fused into the scatter they are recomputed per row
    vals = jax.lax.optimization_barrier(vals.reshape(-1, 3, k))
    grid = jnp.zeros((n_nodes, k), vals.dtype)
    return jax.lax.scatter_add(grid, idx[::3].reshape(-1, 1), vals, _ROWS_SCATTER,
                               mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS)


def _velocity(grid: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(v (d, n_nodes), 1 / m (n_nodes,)): 1 / m where m > ``tiny`` (kg), else 0 (a node no
    particle reaches, or one only the vanishing corner of a stencil touches, weights ~1e-10
    per axis, counts as empty)."""
    d = grid.shape[1] - 1
    m = grid[:, d]
    ok = m > tiny(m.dtype)
    inv = jnp.where(ok, 1.0 / jnp.where(ok, m, 1.0), 0.0)
    return jnp.stack([grid[:, c] * inv for c in range(d)]), inv


@jax.custom_jvp
def grid_velocity(grid: jax.Array) -> jax.Array:
    """Grid velocity (d, n_nodes) m/s from ``grid`` (n_nodes, d + 1) = [momentum (kg m/s),
    mass (kg)]; 0 at empty nodes.

    The derivative is written as dv = (dp - v dm) / m, never with 1 / m^2: a node reached
    only by the far corner of one particle's stencil has a mass of ~1e-20 kg, and the
    chain rule of p / m then forms 1 / m^2 ~ 1e40, which overflows float32 (and inf * 0 gives
    NaN) although the derivative itself is bounded (v of such a node is the particle's own
    affine velocity). Found as a NaN gradient of an inverse sweep (column a = 2.5, phi = 45,
    frame 92 of gns_cg16_pfn's MPM, only under jit).
    """
    return _velocity(grid)[0]


@grid_velocity.defjvp
def _grid_velocity_jvp(primals, tangents):
    (grid,), (dgrid,) = primals, tangents
    d = grid.shape[1] - 1
    v, inv = _velocity(grid)
    dv = jnp.stack([(dgrid[:, c] - v[c] * dgrid[:, d]) * inv for c in range(d)])
    return v, dv


def g2p(idx, w, dpos, gv: jax.Array, dx: float, extra: jax.Array | None = None):
    """Gather grid velocities back to particles.

    Args:
        idx, w, dpos: stencil from :func:`diffgns.mpm.shape.stencil`.
        gv: (d, nx, ny[, nz]) grid velocity, m/s.
        dx: cell size, m.
        extra: optional (d, nx, ny[, nz]) grid field (e.g. the velocity change of a FLIP
            update, m/s) interpolated to the particles in the same gather.
    Returns:
        v: (d, N) particle velocity, m/s; C: (d, d, N) APIC velocity gradient, 1/s; with
        ``extra`` also its (d, N) interpolation.
    """
    d = gv.shape[0]
    if gv.ndim != d + 1 or d not in (2, 3):
        raise ValueError(f"g2p: gv must be (d, nx, ny[, nz]) with d = 2 or 3, got shape "
                         f"{gv.shape}")
    S = 3 ** d
    field = gv if extra is None else jnp.concatenate([gv, extra])
    k = field.shape[0]
    flat = field.reshape(k, -1).T  # (n_nodes, k)
    rows = jax.lax.gather(flat, idx[::3].reshape(-1, 1), _ROWS_GATHER, (3, k),
                          mode=jax.lax.GatherScatterMode.PROMISE_IN_BOUNDS)  # (S/3 N, 3, k)
    g = rows.reshape(S // 3, -1, 3, k).transpose(0, 2, 1, 3).reshape(S, -1, k)  # (S, N, k)
    gw = [w * g[..., c] for c in range(d)]
    k4 = 4.0 / dx
    vs = [la.sum0(gw[c]) for c in range(d)]
    # sum_s gw_s dpos_as = sum_s gw_s off_as - fx_a v, with off_as in {0, 1, 2} constants
    # and -fx_a = dpos[a, 0] (offset 0 is the first column of ``offsets``): no pass over
    # the (S, N) offsets
    off = offsets(d)
    C = k4 * jnp.stack([jnp.stack([la.sum0(gw[c], off[a]) + dpos[a, 0] * vs[c]
                                   for a in range(d)]) for c in range(d)])
    if extra is None:
        return jnp.stack(vs), C
    return jnp.stack(vs), C, jnp.stack([la.sum0(w * g[..., c]) for c in range(d, k)])

