"""Particle GNS: invariances, semi-implicit Euler, jitted/checkpointed/differentiated rollouts,
kinematic particles and neighbour-list overflow handling inside rollouts."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns.graph.features import ParticleStats
from diffgns.graph.gns import GNS, CompactionWarning, GNSConfig, GNSParams, warn_if_compacted
from diffgns.graph.neighbors import did_overflow, edges
from diffgns.interface import NeighborOverflowError, rollout, rollout_safe

N, C, STEPS = 30, 5, 7
# Test-owned jits compile without LLVM optimisation: several times faster for tiny inputs.
FAST = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
META = {"vel_mean": [0.0, -1e-4], "vel_std": [1e-3, 1e-3],
        "acc_mean": [0.0, -2e-5], "acc_std": [5e-5, 5e-5]}


def _history(seed=0):
    """(N, C+1, 2) history in [0.3, 0.7]^2, further than R = 0.1 from every wall."""
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(0.3, 0.7, (N, 1, 2))
    steps = rng.normal(0, 1e-3, (N, C, 2))
    return np.concatenate([x0, x0 + np.cumsum(steps, 1)], 1).astype(np.float32)


@pytest.fixture(scope="module")
def sim():
    # One message-passing step and one hidden layer: the network itself is tested in
    # test_graph_networks; compile time dominates here.
    cfg = GNSConfig(bounds=((0.0, 1.0), (0.0, 1.0)), radius=0.1, latent=16, mp_steps=1,
                    mlp_layers=1, history=C)
    gns = GNS(cfg, ParticleStats.from_metadata(META, cfg.noise_std))
    # Inputs stay numpy: jitted calls take them as they are, test-side maths is numpy, and
    # no eager JAX op (each compiled on first use) is needed.
    hist = _history()
    ptype = np.where(np.arange(N) < 3, 3, 6).astype(np.int32)  # 3 kinematic
    material = np.full((N,), 0.6, np.float32)
    params = gns.init_network(jax.random.key(0), (hist, ptype, material))
    nbrs = gns.allocate(hist[:, -1])
    jitted = jax.jit(gns.acceleration, compiler_options=FAST)
    acc = lambda *a: np.asarray(jitted(*a))
    return gns, params, hist, ptype, material, nbrs, acc


def _roll(gns, network, hist, ptype, material, n, nbrs=None, kinematic_path=None, **kw):
    """(positions of the n predicted frames (n, N, 2), the list the valid rollout used)."""
    state = gns.init(hist, ptype, kinematic_path)
    if nbrs is not None:
        state = state._replace(nbrs=nbrs)
    frames, _, start = rollout_safe(gns, GNSParams(network, material), state, n, **kw)
    return np.asarray(frames.positions[1:]), start.nbrs


def test_acceleration_is_translation_invariant(sim):
    gns, params, hist, ptype, material, nbrs, acc = sim
    s, r, m = edges(nbrs, N)
    a0 = acc(params, hist, ptype, material, s, r, m)
    assert a0.shape == (N, 2) and np.isfinite(a0).all()
    scale = np.abs(a0).max()
    shift = np.array([0.12, -0.15], np.float32)  # walls stay beyond R: features clip at 1
    a1 = acc(params, hist + shift, ptype, material, s, r, m)
    np.testing.assert_allclose(a1, a0, rtol=0, atol=1e-4 * scale)  # float32 rounding only
    # Closer than R to the bottom wall, the wall feature changes the prediction.
    a_wall = acc(params, hist + np.float32([0.0, -0.27]), ptype, material, s, r, m)
    assert np.abs(a_wall - a0).max() > 1e-2 * scale
    # The material feature does enter.
    a2 = acc(params, hist, ptype, material + np.float32(0.5), s, r, m)
    assert np.abs(a2 - a0).max() > 1e-3 * scale


def test_rollout_scan_euler_and_kinematic_hold(sim):
    gns, params, hist, ptype, material, nbrs, acc = sim
    # rollout_safe jits rollout (lax.scan inside) and returns the list it used: the same
    # object means no overflow and no re-allocation.
    xs, used = _roll(gns, params, hist, ptype, material, STEPS, nbrs)
    assert used is nbrs
    xs = np.asarray(xs)
    assert xs.shape == (STEPS, N, 2) and np.isfinite(xs).all()
    # First frame: semi-implicit Euler in frame units with the predicted acceleration (the
    # initial list is exact for the initial positions).
    a = acc(params, hist, ptype, material, *edges(nbrs, N))
    euler = 2 * hist[:, -1] - hist[:, -2] + a
    np.testing.assert_allclose(xs[0, 3:], euler[3:], atol=1e-6)
    # Kinematic particles without a prescribed path are held in place.
    np.testing.assert_array_equal(xs[:, :3], np.broadcast_to(hist[:3, -1], (STEPS, 3, 2)))
    assert np.abs(xs[-1, 3:] - hist[3:, -1]).max() > 1e-4  # the others move
    state = gns.init(hist, ptype)
    frames, _ = rollout(gns, GNSParams(params, 0.6), state, STEPS)
    traj = gns.trajectory(GNSParams(params, 0.6), frames, ptype)
    assert traj.positions.shape == (STEPS + 1, N, 2) and traj.material.shape == (N,)
    np.testing.assert_allclose(traj.velocities[0], (hist[:, -1] - hist[:, -2]) / 2.5e-3,
                               rtol=1e-5)


def test_checkpointed_rollout_values_and_gradient(sim):
    gns, params, hist, ptype, material, nbrs, _ = sim
    xs, _ = _roll(gns, params, hist, ptype, material, STEPS, nbrs)
    state = gns.init(hist, ptype)

    def loss(p, mat):
        # 4 steps in checkpointed blocks of 3: one scanned block plus a remainder of 1.
        frames, _ = rollout(gns, GNSParams(p, mat), state, 4, checkpoint_block=3)
        xs = frames.positions[1:]
        return jnp.sum(xs[-1, :, 0]), (xs, jnp.any(frames.overflow))  # runout-like scalar

    grad = jax.jit(jax.grad(loss, argnums=(0, 1), has_aux=True), compiler_options=FAST)
    (g_params, g_mat), (xs_ck, overflow) = grad(params, material)
    assert not bool(overflow)
    np.testing.assert_allclose(xs_ck, np.asarray(xs)[:4], rtol=0, atol=1e-6)  # same values
    leaves = [np.asarray(x) for x in jax.tree.leaves(g_params)]
    assert all(np.isfinite(x).all() for x in leaves)
    assert sum(np.abs(x).sum() for x in leaves) > 0
    g_mat = np.asarray(g_mat)
    assert np.isfinite(g_mat).all() and np.abs(g_mat).sum() > 0


def test_kinematic_path_and_overflow_reallocation(sim):
    gns, params, hist, ptype, material, nbrs, _ = sim
    # Half the particles are kinematic; their path first takes them into a tight cluster
    # around particle 20, so the list allocated on the initial (sparse) frame overflows.
    half = N // 2
    ptype = np.where(np.arange(N) < half, 3, 6).astype(np.int32)
    end = hist[20, -1] + np.random.default_rng(1).normal(0, 0.01, (half, 2))
    drift = np.arange(1, STEPS + 1)[:, None, None] * 1e-3
    path = np.zeros((STEPS, N, 2), np.float32)
    path[:, :half] = end + drift

    with pytest.raises(NeighborOverflowError, match="overflowing"):  # reported, not hidden
        _roll(gns, params, hist, ptype, material, STEPS, nbrs, kinematic_path=path,
              max_retries=0)
    with pytest.warns(CompactionWarning, match="compacted to .*x the neighbour pairs"):
        xs, big = _roll(gns, params, hist, ptype, material, STEPS, nbrs, kinematic_path=path)
    assert big.idx.shape[1] > nbrs.idx.shape[1] and not bool(did_overflow(big))
    np.testing.assert_array_equal(np.asarray(xs)[:, :half], path[:, :half])  # follow path
    # Same result as a rollout with a list that holds every pair from the start.
    everything = gns.allocate(np.broadcast_to(end[0], (N, 2)).astype(np.float32))
    assert everything.idx.shape[1] == N * (N - 1)
    ref, _ = _roll(gns, params, hist, ptype, material, STEPS, everything,
                   kinematic_path=path)
    np.testing.assert_allclose(xs, ref, atol=1e-6)


def test_config_validation():
    with pytest.raises(ValueError, match="radius"):
        GNSConfig(radius=-1.0)
    cfg = GNSConfig(bounds=[[0, 1], [0, 2]])
    assert cfg.bounds == ((0.0, 1.0), (0.0, 2.0))
    hash(cfg)  # usable as a static argument


def test_rollout_stays_inside_the_domain(sim):
    """Particles thrown at the walls (huge initial velocity) never leave the box."""
    gns, params, hist, ptype, material, nbrs, _ = sim
    fast = hist.copy()
    fast[:, -1] = fast[:, -2] + np.float32([0.2, -0.3])  # 0.2-0.3 domain widths per frame
    with pytest.warns(CompactionWarning):  # every particle piled on the floor: reported
        xs, _ = _roll(gns, params, fast, ptype, material, 5)
    assert np.isfinite(xs).all()
    assert (xs >= 0.0).all() and (xs <= 1.0).all()
    assert np.isclose(xs[..., 1].min(), 0.0)  # pressed against the floor, not through it


def test_compaction_warning_fires_on_packing_not_on_a_moved_or_spread_flow(sim, recwarn):
    """The pair count of a list against that of the first frame: a lattice squeezed to a
    third of its spacing warns; the same lattice moved, or spread out, does not."""
    gns = sim[0]
    g = np.arange(6, dtype=np.float32) * 0.06
    x0 = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2) + 0.3  # spacing 0.06 < R = 0.1
    nb = gns.neighbors
    assert warn_if_compacted(nb, x0, nb.allocate(x0 + 0.05), 5) == pytest.approx(1.0)
    assert warn_if_compacted(nb, x0, nb.allocate(0.3 + 1.5 * (x0 - 0.3)), 5) < 1.0
    assert not [w for w in recwarn if w.category is CompactionWarning]
    with pytest.warns(CompactionWarning, match="by frame 9"):
        ratio = warn_if_compacted(nb, x0, nb.allocate(0.4 + (x0 - 0.3) / 3), 9)
    assert ratio > 5
    # through GNS.reallocate, on a later retry too (a rerun rollout overflows further on)
    from diffgns.interface import ParticleFrame

    squeezed = 0.4 + (x0 - 0.3) / 3
    state = gns.init(np.repeat(x0[:, None], C + 1, 1), np.full(len(x0), 6, np.int32))
    frames = ParticleFrame(np.stack([x0, x0, squeezed]), None, None, None)
    for attempt in (0, 2):
        with pytest.warns(CompactionWarning, match="by frame 2"):
            gns.reallocate(state, frames, 3, attempt)
