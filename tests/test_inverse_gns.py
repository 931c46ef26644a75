"""Inverse problems through the GNS: gradients of the runout objective w.r.t. the friction
angle (against finite differences, with and without checkpointing), simulator plumbing,
neighbour-list re-allocation held in the adapter's state."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns.graph.features import ParticleStats
from diffgns.graph.gns import GNS, GNSConfig
from diffgns.inverse import objectives
from diffgns.inverse.simulators import (
    Column,
    ColumnCase,
    GNSSimulator,
    gns_simulator,
    hybrid_simulator,
    load_gns,
)

FAST = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
META = {"vel_mean": [0.0, -5e-4], "vel_std": [1e-3, 1e-3],
        "acc_mean": [0.0, -1e-5], "acc_std": [1e-4, 1e-4]}
C, STEPS = 5, 6


def _column_history(dtype):
    """(C + 1, 24, 2): a 4 x 6 lattice column (spacing 1.25 cm) falling a little."""
    i, j = np.meshgrid(np.arange(4), np.arange(6), indexing="ij")
    x0 = 0.00625 + 0.0125 * np.stack([i.ravel(), j.ravel()], -1)
    t = np.arange(C + 1)[:, None, None]
    fall = np.array([2e-5, -1e-4]) * t**2 * (x0[None, :, 1:] / 0.07)
    return (x0[None] + fall).astype(dtype)


def _sim(checkpoint_block, dtype, **kw):
    cfg = GNSConfig(bounds=((0.0, 0.3), (0.0, 0.2)), radius=0.032, latent=16, mp_steps=2,
                    mlp_layers=1, history=C)
    gns = GNS(cfg, ParticleStats.from_metadata(META, 0.0))
    hist = _column_history(dtype)
    ptype = np.full(hist.shape[1], 6, np.int32)
    params = gns.init_network(jax.random.key(1), (np.swapaxes(hist, 0, 1), ptype,
                                                  np.ones(hist.shape[1], dtype)))
    params = jax.tree.map(lambda p: jnp.asarray(p, dtype), params)
    return GNSSimulator(gns, params, hist, ptype, STEPS, checkpoint_block, **kw)


def _loss_fn(sim):
    """Squared misfit of the soft runout to a column 4 cm wider than the initial one."""
    x0 = np.asarray(sim.history({})[0], np.float64)
    target = np.broadcast_to(x0 * np.array([1.0 + 0.04 / x0[:, 0].max(), 1.0]),
                             (C + 1 + STEPS,) + x0.shape)
    L = objectives.runout_loss(target, method="softmax")
    return lambda phi: L(sim({"friction_angle": phi}))


def test_gns_runout_gradient_matches_finite_differences(x64):
    sim = _sim(checkpoint_block=None, dtype=np.float64)
    f = _loss_fn(sim)
    vg = jax.jit(jax.value_and_grad(f), compiler_options=FAST)
    fwd = jax.jit(f, compiler_options=FAST)
    phi, h = 40.0, 1e-4
    val, g = vg(jnp.float64(phi))
    fd = (fwd(jnp.float64(phi + h)) - fwd(jnp.float64(phi - h))) / (2 * h)
    assert float(val) > 0 and abs(float(fd)) > 0
    assert float(g) == pytest.approx(float(fd), rel=1e-5)
    overflow = jax.jit(lambda p: sim.simulate({"friction_angle": p})[1],
                       compiler_options=FAST)(jnp.float64(phi))
    assert not bool(overflow)


def test_checkpointed_and_plain_gradients_agree():
    grads = []
    for block in (None, 3):
        sim = _sim(checkpoint_block=block, dtype=np.float32)
        grads.append(float(jax.jit(jax.grad(_loss_fn(sim)),
                                   compiler_options=FAST)(jnp.float32(40.0))))
    assert grads[0] != 0 and grads[1] == pytest.approx(grads[0], rel=1e-4)


def test_simulator_shapes_and_history_validation():
    sim = _sim(checkpoint_block=4, dtype=np.float32)
    pos = jax.jit(lambda phi: sim({"friction_angle": phi}),
                  compiler_options=FAST)(jnp.float32(35.0))
    assert pos.shape == (C + 1 + STEPS, 24, 2)
    np.testing.assert_array_equal(np.asarray(pos[: C + 1]), _column_history(np.float32))
    with pytest.raises(ValueError, match="needs 6 initial frames"):
        GNSSimulator(sim.gns, sim.network, _column_history(np.float32)[:3], np.full(24, 6), 4)


def test_overflow_is_reported_and_reallocation_grows_the_state_list():
    """A list allocated with no head-room overflows as the column spreads; reallocate()
    replaces the adapter's initial state by one whose list fits, and the redo matches a
    rollout that never overflowed."""
    tight = _sim(checkpoint_block=None, dtype=np.float32, extra_capacity=0)
    tight.state = tight.state._replace(
        nbrs=tight.gns.neighbors.allocate(tight.state.history[:, -1] * 2.7))  # no pairs
    run = jax.jit(lambda phi: tight.simulate({"friction_angle": phi}))
    _, overflow = run(jnp.float32(35.0))
    assert bool(overflow)
    cap = tight.state.nbrs.idx.shape
    tight.reallocate({"friction_angle": 35.0})
    assert tight.state.nbrs.idx.shape[1] > cap[1]
    pos, overflow = jax.jit(lambda phi: tight.simulate({"friction_angle": phi}))(
        jnp.float32(35.0))
    ref = _sim(checkpoint_block=None, dtype=np.float32, extra_capacity=8)
    ref_pos, ref_overflow = jax.jit(lambda phi: ref.simulate({"friction_angle": phi}))(
        jnp.float32(35.0))
    assert not bool(overflow) and not bool(ref_overflow)
    np.testing.assert_allclose(np.asarray(pos), np.asarray(ref_pos), atol=1e-6)


def test_column_observation_operator_and_model_checks(tmp_path):
    col = Column(ColumnCase(aspect_ratio=1.0))
    x = jnp.asarray(col.state.x.T)
    traj = jnp.stack([x, x + 0.01, x + 0.02])  # (3, N, 2)
    nodes = np.asarray(col.observe(traj))
    assert nodes.shape == (2, col.n_nodes, 2) and col.n_nodes == 64  # 256 / 4, frames 0, 2
    np.testing.assert_allclose(nodes[1] - nodes[0], 0.02, atol=1e-6)
    np.testing.assert_allclose(nodes[0].mean(0), np.asarray(x).mean(0), rtol=1e-6)
    st = col.initial_state({"aspect_ratio": 1.5})
    assert float(st.x[1].max()) == pytest.approx(1.5 * float(col.state.x[1].max()), rel=1e-6)
    loaded = load_gns("gns_columns")  # the 8-cell ColumnCase default is its resolution
    with pytest.raises(ValueError, match="frame_stride"):
        gns_simulator(Column(ColumnCase(aspect_ratio=1.0, frame_stride=1)),
                      observed=np.zeros((10, 64, 2)), loaded=loaded)
    with pytest.raises(ValueError, match="observed trajectory"):
        gns_simulator(col, loaded=loaded)
    with pytest.raises(FileNotFoundError, match="nor a shipped model"):
        load_gns("/nonexistent/model")
    with pytest.raises(FileNotFoundError, match="not a model folder.*lacks"):
        load_gns(tmp_path)  # a folder without config.json
    hyb = hybrid_simulator(col, loaded=loaded)  # the hybrid hook: same observation operator
    assert hyb.n_frames == col.n_obs - 1 and callable(hyb.simulate)
    with pytest.raises(ValueError, match="frame_stride"):
        hybrid_simulator(Column(ColumnCase(aspect_ratio=1.0, frame_stride=1)), loaded=loaded)
