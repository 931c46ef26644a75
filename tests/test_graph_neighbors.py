"""Neighbour lists: agreement with brute force, the strict-radius convention, overflow."""
import jax
import numpy as np
import pytest

from diffgns.graph.neighbors import (
    NeighborBuilder,
    brute_force_edges,
    capacity,
    did_overflow,
    edge_set,
    edges,
)
from diffgns.interface import retry_on_overflow

# Dyadic numbers so that distances of exactly R are exact in float32 (also after the shift
# of the domain's lower corner (-1, 0) to the origin).
R = 5.0 / 32.0
BOUNDS = ((-1.0, 1.0), (0.0, 2.0))


def _points(n=150, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform((-1.0, 0.0), (1.0, 2.0), (n, 2)).astype(np.float32)
    # Exactly R apart: axis-aligned pair and a 3-4-5 pair; a pair just inside R.
    x[0], x[1] = (0.25, 1.0), (0.25 + R, 1.0)
    x[2], x[3] = (-0.5, 0.5), (-0.5 + 3 / 32, 0.5 + 4 / 32)
    x[4], x[5] = (0.75, 1.5), (0.75 + R - 1 / 1024, 1.5)
    return x


@pytest.fixture(scope="module", params=["cell_list", "all_pairs"])
def builder(request):
    """Both candidate paths: a cell list (forced) and all-pairs (the default up to 1024)."""
    return NeighborBuilder(BOUNDS, R, all_pairs_max=0 if request.param == "cell_list" else 1024)


def test_matches_brute_force_with_strict_radius(builder):
    x = _points()
    nbrs = builder.allocate(x)
    assert not did_overflow(nbrs)
    # the path the fixture asks for is the one tested
    assert (nbrs.cell_list_capacity is not None) == (builder.all_pairs_max < len(x))
    got = edge_set(*edges(nbrs, len(x), self_edges=False))
    want = brute_force_edges(x, R)
    assert got == want
    # jax-md keeps d^2 < R^2 (strict): pairs exactly R apart are not neighbours ...
    for a, b in [(0, 1), (1, 0), (2, 3), (3, 2)]:
        assert (a, b) not in got
    # ... while a pair just inside is, in both directions (symmetric graph).
    assert (4, 5) in got and (5, 4) in got
    assert len(want) > 100


def test_self_edges_appended_and_padding_masked(builder):
    x = _points()
    n = len(x)
    nbrs = builder.allocate(x)
    s, r, m = edges(nbrs, n, self_edges=True)
    k = capacity(nbrs)
    assert s.shape == r.shape == m.shape == (k + n,)
    assert edge_set(s, r, m) == brute_force_edges(x, R) | {(i, i) for i in range(n)}
    s, r, m = map(np.asarray, (s, r, m))
    assert (s[~m] == n).all() and (r[~m] == n).all()  # jax-md padding index N
    assert (~m).sum() > 0  # capacity_multiplier leaves head-room


def test_update_is_jit_safe(builder):
    x = _points()
    nbrs = builder.allocate(x)
    x2 = _points(seed=1)
    upd = jax.jit(builder.update)(x2, nbrs)
    assert not did_overflow(upd)
    assert edge_set(*edges(upd, len(x2), False)) == edge_set(
        *edges(builder.update(x2, nbrs), len(x2), False))


def test_no_reallocation_when_capacity_suffices(builder):
    x = _points()
    nbrs = builder.allocate(x)
    x2 = x + np.float32(1e-3)
    new, used = retry_on_overflow(lambda nb: builder.update(x2, nb), nbrs,
                                  lambda nb: bool(did_overflow(nb)),
                                  lambda nb, _, k: builder.reallocate(x2, nb, k))
    assert used is nbrs  # no re-allocation
    assert capacity(new) == capacity(nbrs)
    assert edge_set(*edges(new, len(x2), False)) == brute_force_edges(x2, R)


def test_overflow_is_detected_and_fixed(builder):
    x_sparse = _points(n=120, seed=3)
    nbrs = builder.allocate(x_sparse)
    rng = np.random.default_rng(4)
    x_dense = rng.uniform((0.0, 1.0), (0.3, 1.3), (120, 2)).astype(np.float32)
    want = brute_force_edges(x_dense, R)

    stale = builder.update(x_dense, nbrs)
    assert bool(did_overflow(stale))
    dropped = edge_set(*edges(stale, 120, False))
    assert len(dropped) < len(want)  # what would be silently lost without the flag

    fixed, used = retry_on_overflow(lambda nb: builder.update(x_dense, nb), nbrs,
                                    lambda nb: bool(did_overflow(nb)),
                                    lambda nb, _, k: builder.reallocate(x_dense, nb, k))
    assert used is not nbrs and not bool(did_overflow(fixed))
    assert capacity(fixed) > capacity(nbrs)
    assert edge_set(*edges(fixed, 120, False)) == want
    # The overflow bit is sticky until re-allocation.
    assert bool(did_overflow(builder.update(x_sparse, stale)))


def test_all_pairs_list_survives_a_pile_up_that_overflows_the_cell_list():
    """Particles crowding into one cell overflow a cell list's slots (a re-allocation);
    the all-pairs list has only the edge buffer, which a pile-up of few particles fits."""
    rng = np.random.default_rng(5)
    x = rng.uniform((-1.0, 0.0), (1.0, 2.0), (100, 2)).astype(np.float32)
    piled = x.copy()
    piled[:6] = np.float32((0.01, 1.01)) + rng.uniform(0, 0.1, (6, 2)).astype(np.float32)
    cells = NeighborBuilder(BOUNDS, R, all_pairs_max=0)
    assert bool(did_overflow(cells.update(piled, cells.allocate(x))))
    pairs = NeighborBuilder(BOUNDS, R, capacity_multiplier=2.0)
    upd = pairs.update(piled, pairs.allocate(x))
    assert not bool(did_overflow(upd))
    assert edge_set(*edges(upd, 100, False)) == brute_force_edges(piled, R)


def test_rejects_bad_arguments():
    with pytest.raises(ValueError, match="bounds"):
        NeighborBuilder(((0.0, 0.0), (0.0, 1.0)), 0.1)
    with pytest.raises(ValueError, match="radius"):
        NeighborBuilder(BOUNDS, 0.0)
    with pytest.raises(ValueError, match="capacity_multiplier"):
        NeighborBuilder(BOUNDS, 0.1, capacity_multiplier=0.5)
