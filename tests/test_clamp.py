"""Counted clamps (diffgns.clamp): exact counts and shifts, traceable under jit/grad/scan."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.clamp import ClampCount, clamp_positions, clamp_summary, clamp_warning

LO, HI = jnp.array([0.0, 0.0]), jnp.array([0.8, 0.35])
X = jnp.array([[0.1, 0.1], [-0.003, 0.2], [0.81, -0.004], [0.8, 0.0]])  # (N, 2)


def test_counts_the_moved_positions_and_the_largest_move():
    y, c = clamp_positions(X, LO, HI, axis=-1)
    np.testing.assert_array_equal(y, np.array([[0.1, 0.1], [0.0, 0.2], [0.8, 0.0], [0.8, 0.0]],
                                              np.asarray(X).dtype))
    assert int(c.moved) == 2  # a particle exactly on a wall is not moved
    np.testing.assert_allclose(float(c.shift), np.hypot(0.01, 0.004), rtol=1e-6)
    yt, ct = clamp_positions(X.T, LO[:, None], HI[:, None], axis=0)  # (d, N) layout
    np.testing.assert_array_equal(yt, y.T)
    assert int(ct.moved) == 2 and float(ct.shift) == float(c.shift)
    merged = c.merge(ClampCount(jnp.asarray(3, jnp.int32), jnp.asarray(0.5)))
    assert int(merged.moved) == 5 and float(merged.shift) == 0.5


def test_traceable_jit_grad_and_scan_equal_eager():
    def run(x):
        def body(c, k):
            y, cc = clamp_positions(x + 0.01 * k, LO, HI)
            return c.merge(cc), jnp.sum(y)
        return jax.lax.scan(body, ClampCount.zero(x.dtype), jnp.arange(3.0))

    eager, jitted = run(X), jax.jit(run)(X)
    for a, b in zip(jax.tree.leaves(eager), jax.tree.leaves(jitted)):
        np.testing.assert_array_equal(a, b)
    assert int(eager[0].moved) == 2 + 2 + 2  # k = 1, 2: the left escapee is back inside,
    # the one on the right wall has crossed it
    g = jax.grad(lambda x: jnp.sum(clamp_positions(x, LO, HI)[0]))(X)
    np.testing.assert_array_equal(g[:3], [[1, 1], [0, 1], [0, 0]])  # clipped: no gradient


def test_summary_and_warning_name_the_first_frame_and_the_move():
    s = clamp_summary([0, 0, 3, 1], [0.0, 0.0, 0.002, 0.001])
    assert s == dict(clamped_positions=4, clamped_frames=2, first_clamped_frame=2,
                     max_clamp_shift_m=0.002)
    w = clamp_warning(s, "the GNS rollout")
    assert w is not None and w.startswith("warning: the GNS rollout clamped 4 particle")
    assert "first at frame 2" in w and "2 mm" in w
    assert clamp_warning(clamp_summary([0, 0], [0.0, 0.0])) is None
