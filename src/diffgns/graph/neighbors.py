"""Radius-graph neighbour lists on top of :mod:`jax_md.partition`.

A :class:`NeighborBuilder` wraps ``jax_md.partition.neighbor_list`` with

* free (non-periodic) space, ``space.free()``;
* the ``Sparse`` format: ``nbrs.idx`` is ``(2, capacity)`` int32, padded with ``N``;
* for more than ``all_pairs_max`` particles, a cell list sized from the domain bounds
  (used by jax-md whenever the cell side, the radius, is below a third of the domain in
  every dimension); for up to ``all_pairs_max`` particles (default 1024), an all-pairs
  candidate list. The all-pairs list costs O(N^2) distances per update (176 nodes: 120
  updates take 0.077 s, as with the cell list, against 0.83 s for the network), and it has
  only one capacity (the edge buffer), so a particle pile-up that outgrows a cell's slots
  cannot force a re-allocation (which, with the cell list, also enlarged the edge buffer);
* positions shifted so that the domain's lower corner is the origin.

Radius convention (checked in jax-md 0.2.x, ``partition.py``): a pair ``(i, j)`` with
``i != j`` is kept when ``|x_i - x_j|^2 < R^2`` -- **strict**: two particles exactly ``R``
apart are *not* neighbours. ``dr_threshold`` is 0, so the list is rebuilt from scratch at
every update (no skin / Verlet buffer). jax-md's sparse list never contains ``i == j``;
:func:`edges` appends the ``N`` self-edges explicitly.

Capacity: :meth:`NeighborBuilder.allocate` (outside ``jit``) sizes the edge buffer and the
cell list to ``capacity_multiplier`` times what the given positions need. :meth:`update`
(jit-safe) cannot resize; if a configuration needs more, jax-md sets an overflow bit in
``nbrs.error`` (sticky across updates), read by :func:`did_overflow`. Edges beyond the
capacity are then missing, so the caller must re-allocate outside ``jit`` and redo the
step (:meth:`NeighborBuilder.reallocate` under
:func:`diffgns.interface.retry_on_overflow`). Overflow is never silent as long as the flag
is checked.

Particles somewhat outside the domain are still handled correctly (cell indices wrap around,
which only makes the cell list less efficient), but many particles far outside will overflow
the cell list, which is again reported by the flag.
"""
from __future__ import annotations

import contextlib
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from jax_md import partition, space

__all__ = [
    "NeighborBuilder", "brute_force_edges", "capacity", "did_overflow", "edge_set", "edges",
    "n_pairs",
]


def _as_bounds(bounds) -> tuple[tuple[float, float], ...]:
    """Normalise ``((xmin, xmax), (ymin, ymax)(, (zmin, zmax)))`` to a hashable tuple of
    float pairs (2 or 3 of them)."""
    out = tuple((float(lo), float(hi)) for lo, hi in bounds)
    if len(out) not in (2, 3) or any(hi <= lo for lo, hi in out):
        raise ValueError(f"bounds must be ((xmin, xmax), (ymin, ymax)[, (zmin, zmax)]) with "
                         f"min < max, got {bounds!r}")
    return out


class NeighborBuilder:
    """Allocates and updates jax-md sparse neighbour lists for a fixed domain and radius.

    Args:
        bounds: ``((xmin, xmax), (ymin, ymax))`` of the domain, in position units (m), or
            ``((xmin, xmax), (ymin, ymax), (zmin, zmax))`` in 3D (one code path: jax-md's
            cell list and all-pairs list are dimension-generic).
        radius: connectivity radius ``R`` (same units); pairs with ``d < R`` are neighbours.
        capacity_multiplier: head-room factor for the edge buffer and cell list (>= 1).
        all_pairs_max: largest particle count that uses the all-pairs candidate list
            instead of a cell list (chosen at :meth:`allocate`, where N is known).
    """

    def __init__(self, bounds, radius: float, capacity_multiplier: float = 1.25,
                 all_pairs_max: int = 1024):
        self.bounds = _as_bounds(bounds)
        self.radius = float(radius)
        if self.radius <= 0:
            raise ValueError(f"radius must be > 0, got {radius}")
        if capacity_multiplier < 1.0:
            raise ValueError(f"capacity_multiplier must be >= 1, got {capacity_multiplier}")
        self.capacity_multiplier = float(capacity_multiplier)
        self.lower = np.array([lo for lo, _ in self.bounds], dtype=np.float32)
        self.box = np.array([hi - lo for lo, hi in self.bounds], dtype=np.float32)
        self.all_pairs_max = int(all_pairs_max)
        displacement, _ = space.free()
        self._fns, self._fns_all_pairs = (partition.neighbor_list(
            displacement, jnp.asarray(self.box), self.radius, dr_threshold=0.0,
            capacity_multiplier=self.capacity_multiplier, format=partition.Sparse,
            disable_cell_list=off) for off in (False, True))

    def _shift(self, x: jax.Array) -> jax.Array:
        x = jax.lax.stop_gradient(jnp.asarray(x))
        return x - jnp.asarray(self.lower, dtype=x.dtype)

    def allocate(self, x: jax.Array, extra_capacity: int = 0) -> partition.NeighborList:
        """Allocate a list for positions ``x`` (N, d). Not jittable (shapes depend on values).

        ``extra_capacity`` adds ``N * extra_capacity`` edge slots and ``extra_capacity`` slots
        per cell on top of ``capacity_multiplier`` times the current need.
        """
        x = self._shift(x)
        fns = self._fns_all_pairs if x.shape[0] <= self.all_pairs_max else self._fns
        with _jax_md_x64_scatter_warning_ignored():
            return fns.allocate(x, extra_capacity=int(extra_capacity))

    def reallocate(self, x: jax.Array, nbrs: partition.NeighborList, attempt: int = 0
                   ) -> partition.NeighborList:
        """A new list for positions ``x`` after ``nbrs`` overflowed (outside jit).

        The one growth rule of the package: the first re-allocation (``attempt = 0``) sizes
        the list for ``x`` with the usual head-room; every further attempt adds
        ``ceil(K / 4N)`` edge slots per particle (and cell slots) more, K being the old
        capacity, so repeated overflows grow the list geometrically enough to end.
        """
        n = int(x.shape[0])
        extra = int(attempt) * max(1, math.ceil(capacity(nbrs) / (4 * n)))
        return self.allocate(x, extra_capacity=extra)

    def update(self, x: jax.Array, nbrs: partition.NeighborList) -> partition.NeighborList:
        """Rebuild the list for positions ``x`` (N, d) with the same capacity (jit-safe)."""
        with _jax_md_x64_scatter_warning_ignored():
            return nbrs.update(self._shift(x))


@contextlib.contextmanager
def _jax_md_x64_scatter_warning_ignored():
    """jax-md's all-pairs pruning scatters ``arange(N)`` (int64 under ``jax_enable_x64``) into
    an int32 buffer; jax warns about the cast. The indices are < N, so the cast is exact."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="scatter inputs have incompatible types",
                                category=FutureWarning)
        yield


def did_overflow(nbrs: partition.NeighborList) -> jax.Array:
    """Bool scalar array: the edge buffer or the cell list overflowed (jit-safe, sticky)."""
    return nbrs.did_buffer_overflow != 0


def edges(nbrs: partition.NeighborList, n_particles: int, self_edges: bool = True
          ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Fixed-size edge arrays of a sparse neighbour list (jit-safe).

    Args:
        nbrs: a ``Sparse`` jax-md list with capacity ``K`` (``nbrs.idx`` is ``(2, K)``).
        n_particles: ``N``.
        self_edges: append the ``N`` edges ``i -> i`` (always valid) after the ``K`` slots.

    Returns:
        ``(senders, receivers, mask)``, each of shape ``(E,)`` with ``E = K (+ N)``:
        int32 particle indices and a bool validity mask. Padded slots carry the index ``N``
        (out of range, as in jax-md) and ``mask == False``: gather with clipping and use
        ``segment_sum(..., num_segments=N)`` (which drops index ``N``) or multiply by the mask.
        The radius graph is symmetric, so every valid ``(s, r)`` has its ``(r, s)`` too.
    """
    receivers, senders = nbrs.idx[0], nbrs.idx[1]
    mask = (senders < n_particles) & (receivers < n_particles)
    if self_edges:
        self_idx = jnp.arange(n_particles, dtype=senders.dtype)
        senders = jnp.concatenate([senders, self_idx])
        receivers = jnp.concatenate([receivers, self_idx])
        mask = jnp.concatenate([mask, jnp.ones((n_particles,), bool)])
    return senders, receivers, mask


def brute_force_edges(x, radius: float, self_edges: bool = False) -> set[tuple[int, int]]:
    """Reference all-pairs edge set ``{(s, r)}`` with ``|x_s - x_r|^2 < R^2`` (numpy, O(N^2)).

    Uses the same strict convention and the positions' own float precision as jax-md.
    Meant for tests and debugging only.
    """
    x = np.asarray(x)
    d = x[:, None, :] - x[None, :, :]
    d2 = (d * d).sum(-1)
    keep = d2 < np.asarray(radius, dtype=x.dtype) ** 2
    if not self_edges:
        np.fill_diagonal(keep, False)
    s, r = np.nonzero(keep)
    return set(zip(s.tolist(), r.tolist()))


def edge_set(senders, receivers, mask) -> set[tuple[int, int]]:
    """The valid ``(sender, receiver)`` pairs of :func:`edges` output as a Python set."""
    s, r, m = (np.asarray(a) for a in (senders, receivers, mask))
    return set(zip(s[m].tolist(), r[m].tolist()))


def capacity(nbrs: partition.NeighborList) -> int:
    """Number of edge slots ``K`` of the list (static)."""
    return int(nbrs.idx.shape[1])


def n_pairs(nbrs: partition.NeighborList) -> int:
    """Number of valid (ordered) neighbour pairs the list holds, <= :func:`capacity`
    (host value: outside jit)."""
    n = nbrs.reference_position.shape[0]
    return int((np.asarray(nbrs.idx[0]) < n).sum())
