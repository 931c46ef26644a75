"""Features, normalisation, training noise and the encode-process-decode network."""
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns.graph.features import (
    Normalizer,
    ParticleStats,
    edge_features,
    n_node_features,
    node_features,
    random_walk_noise,
    target_acceleration,
    wall_distances,
)
from diffgns.graph.networks import (
    EncodeProcessDecode,
    SplitEdgeDense,
    concat_dense_params,
    init_params,
    segment_softmax,
)

BOUNDS = ((0.0, 1.0), (0.0, 2.0))
R = 0.1
# Test-owned jits compile without LLVM optimisation: several times faster for tiny inputs.
FAST = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


def jit(f, **kw):
    return jax.jit(f, compiler_options=FAST, **kw)


def _graph(n=10, n_edges=30, n_pad=6, seed=0):
    """Random graph with self-edges and padded (masked, index N) slots at the end."""
    rng = np.random.default_rng(seed)
    s = np.concatenate([rng.integers(0, n, n_edges), np.arange(n), np.full(n_pad, n)])
    r = np.concatenate([rng.integers(0, n, n_edges), np.arange(n), np.full(n_pad, n)])
    mask = s < n
    return jnp.asarray(s, jnp.int32), jnp.asarray(r, jnp.int32), jnp.asarray(mask)


def _history(n=10, c=5, seed=0):
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(0.2, 0.8, (n, 1, 2))
    steps = rng.normal(0, 1e-3, (n, c, 2))
    return jnp.asarray(np.concatenate([x0, x0 + np.cumsum(steps, 1)], 1), jnp.float32)


def test_feature_shapes_and_wall_clipping():
    h = _history(n=4)
    h = h.at[:, -1].set(jnp.array([[0.05, 1.0], [0.5, 1.97], [-0.2, 1.0], [0.5, 1.0]]))
    nf = node_features(h, BOUNDS, R, Normalizer.identity(), material=jnp.full(4, 0.7))
    assert nf.shape == (4, n_node_features(5, True)) == (4, 15)
    walls = np.asarray(nf[:, 10:14])
    np.testing.assert_allclose(walls[0], [0.5, 1.0, 1.0, 1.0], atol=1e-5)
    np.testing.assert_allclose(walls[1], [1.0, 1.0, 1.0, 0.3], atol=1e-4)
    np.testing.assert_allclose(walls[2], [-1.0, 1.0, 1.0, 1.0])  # outside: clipped at -1
    np.testing.assert_allclose(walls[3], 1.0)
    np.testing.assert_allclose(nf[:, 14], 0.7)  # material raw
    np.testing.assert_allclose(nf[:, :2], h[:, 1] - h[:, 0], atol=1e-7)  # oldest velocity
    assert node_features(h, BOUNDS, R, Normalizer.identity()).shape == (4, 14)
    assert float(jnp.abs(wall_distances(h[:, -1], BOUNDS, R)).max()) <= 1.0


def test_edge_features_and_masking():
    x = jnp.array([[0.0, 0.0], [0.03, 0.04], [0.5, 0.5]])
    s, r, m = jnp.array([1, 0, 2, 3]), jnp.array([0, 0, 2, 3]), jnp.array([1, 1, 1, 0], bool)
    f = lambda x: edge_features(x, s, r, m, R)
    ef, vjp = jit(lambda x: jax.vjp(f, x))(x)
    assert ef.shape == (4, 3)
    np.testing.assert_allclose(ef[0], [0.3, 0.4, 0.5], rtol=1e-5)
    np.testing.assert_allclose(ef[1:], 0.0)  # self-edges and the padded slot
    (g,) = vjp(jnp.ones_like(ef))
    assert np.isfinite(np.asarray(g)).all()  # safe norm at zero length


def test_normalizer_round_trip_and_noise_folding():
    meta = {"vel_mean": [1e-4, -2e-4], "vel_std": [3e-3, 4e-3],
            "acc_mean": [0.0, -1e-4], "acc_std": [2e-4, 5e-4]}
    sigma = 6.7e-4
    norm = ParticleStats.from_metadata(meta, noise_std=sigma)
    np.testing.assert_allclose(norm.velocity.std, np.sqrt(np.square([3e-3, 4e-3]) + sigma**2))
    np.testing.assert_allclose(norm.acceleration.std,
                               np.sqrt(np.square([2e-4, 5e-4]) + sigma**2), rtol=1e-6)
    x = jnp.asarray(np.random.default_rng(0).normal(0, 1e-3, (7, 2)), jnp.float32)
    for n in (norm.velocity, norm.acceleration):
        np.testing.assert_allclose(n.denormalize(n.normalize(x)), x, rtol=1e-5, atol=1e-9)
    leaves = jax.tree.leaves(norm)
    assert len(leaves) == 4  # a pytree of arrays: can be passed through jit
    with pytest.raises(KeyError, match="acc_std"):
        ParticleStats.from_metadata({k: v for k, v in meta.items() if k != "acc_std"})


def test_random_walk_noise_statistics():
    sigma, c, n = 6.7e-4, 5, 20000
    seq = np.zeros((n, c + 1, 2), np.float32)
    ptype = np.where(np.arange(n) % 2 == 0, 3, 6)  # every other particle kinematic
    noise = np.asarray(jit(random_walk_noise)(jax.random.key(1), seq, sigma, ptype))
    assert noise.shape == seq.shape
    np.testing.assert_array_equal(noise[::2], 0.0)  # kinematic particles: no noise
    noise = noise[1::2]
    np.testing.assert_array_equal(noise[:, 0], 0.0)  # the oldest position is not perturbed
    vel_noise = noise[:, 1:] - noise[:, :-1]
    assert abs(vel_noise.std() / (sigma / np.sqrt(c)) - 1) < 0.02  # per step sigma/sqrt(C)
    assert abs(np.corrcoef(vel_noise[:, 0, 0], vel_noise[:, 1, 0])[0, 1]) < 0.05  # i.i.d.
    assert abs(noise[:, -1].std() / sigma - 1) < 0.03  # cumulated: sigma on the last input


def test_target_acceleration_corrects_last_input_noise():
    h = _history(n=8)
    nxt = 2 * h[:, -1] - h[:, -2] + 1e-4
    np.testing.assert_allclose(target_acceleration(nxt, h), 1e-4, rtol=1e-2)
    noise = jnp.asarray(np.random.default_rng(2).normal(0, 1e-3, h.shape), jnp.float32)
    a = target_acceleration(nxt, h, noise)
    hn = h + noise
    # Semi-implicit Euler from the noisy inputs with this target keeps the clean velocity.
    x_next = hn[:, -1] + (hn[:, -1] - hn[:, -2]) + a
    np.testing.assert_allclose(x_next - hn[:, -1], nxt - h[:, -1], atol=1e-6)


def test_split_first_layer_equals_concat_dense():
    rng = np.random.default_rng(3)
    s, r, _ = _graph()
    e = jnp.asarray(rng.normal(size=(s.shape[0], 8)), jnp.float32)
    v = jnp.asarray(rng.normal(size=(10, 6)), jnp.float32)
    mod = SplitEdgeDense(16)
    params = init_params(mod, jax.random.key(3), e, v, s, r)["params"]
    params["edge"]["bias"] = jnp.asarray(rng.normal(size=16), jnp.float32)  # not just 0
    split = jit(mod.apply)({"params": params}, e, v, s, r)
    # A plain Dense on the concatenation [e, v_s, v_r] with the stacked kernels.
    sc, rc = jnp.clip(s, 0, 9), jnp.clip(r, 0, 9)
    cat = jnp.concatenate([e, v[sc], v[rc]], axis=-1)
    dense = concat_dense_params(params)
    assert dense["kernel"].shape == (8 + 6 + 6, 16)
    full = nn.Dense(16).apply({"params": dense}, cat)
    np.testing.assert_allclose(split, full, rtol=1e-5, atol=1e-5)


@pytest.fixture(scope="module")
def net_setup():
    s, r, m = _graph()
    n = 10
    rng = np.random.default_rng(4)
    nf = jnp.asarray(rng.normal(size=(n, 15)), jnp.float32)
    ef = jnp.where(m[:, None], jnp.asarray(rng.normal(size=(s.shape[0], 3)), jnp.float32), 0.0)
    ptype = jnp.asarray(np.arange(n) % 9, jnp.int32)
    args = (nf, ptype, ef, s, r, m)
    nets = {att: EncodeProcessDecode(latent=16, mp_steps=2, mlp_layers=2, attention=att)
            for att in (False, True)}
    # One (slow to compile) init: the plain network's params are the attention network's
    # without the score layers.
    p_att = init_params(nets[True], jax.random.key(4), *args)
    p_plain = jax.tree.map(lambda x: x, p_att)
    for k in range(2):
        del p_plain["params"][f"processor_{k}"]["score"]
    params = {True: p_att, False: p_plain}
    applies = {att: jit(nets[att].apply) for att in (False, True)}
    return nets, params, applies, args


def test_network_jit_matches_eager(net_setup):
    nets, params, applies, args = net_setup
    out_jit = applies[False](params[False], *args)
    assert out_jit.shape == (10, 2)
    with jax.disable_jit():
        out_eager = nets[False].apply(params[False], *args)
    np.testing.assert_allclose(out_jit, out_eager, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("attention", [False, True])
def test_network_ignores_masked_edges(net_setup, attention):
    nets, params, applies, args = net_setup
    out = applies[attention](params[attention], *args)
    assert np.isfinite(np.asarray(out)).all()
    # Garbage in padded slots (features and indices pointing anywhere) changes nothing.
    nf, ptype, ef, s, r, m = args
    s2, r2 = jnp.where(m, s, 3), jnp.where(m, r, 4)
    ef2 = jnp.where(m[:, None], ef, 7.0)
    out2 = applies[attention](params[attention], nf, ptype, ef2, s2, r2, m)
    np.testing.assert_allclose(out2, out, rtol=1e-5, atol=1e-6)
    # ... whereas the valid edges matter.
    ef3 = ef + jnp.where(m[:, None], 0.5, 0.0)  # (not a rescale: LayerNorm undoes those)
    out3 = applies[attention](params[attention], nf, ptype, ef3, s, r, m)
    assert np.abs(np.asarray(out3 - out)).max() > 1e-4


def test_edge_latents_change_through_processor(net_setup):
    nets, params, _, args = net_setup
    apply = jit(nets[False].apply, static_argnames="return_edge_latents")
    out, lat = apply(params[False], *args, return_edge_latents=True)
    assert lat.shape == (3, args[3].shape[0], 16)  # encoder + 2 steps
    m = np.asarray(args[5])
    lat = np.asarray(lat)
    for k in range(2):  # every step updates every valid edge latent
        assert np.abs(lat[k + 1][m] - lat[k][m]).max(axis=-1).min() > 0
        assert np.abs(lat[k + 1][m] - lat[k][m]).mean() > 1e-2
    np.testing.assert_allclose(lat[:, ~m], 0.0)
    p = params[False]["params"]
    assert {"processor_0", "processor_1"} <= set(p)  # separate weights per step
    assert "norm" not in p["decoder"] and "norm" in p["node_encoder"]


def test_init_params_follow_flax_defaults(net_setup):
    nets, params, _, args = net_setup
    ref = jax.eval_shape(nets[True].init, jax.random.key(0), *args)
    assert jax.tree.structure(ref) == jax.tree.structure(params[True])
    p = params[True]["params"]
    k = np.asarray(p["processor_0"]["node_mlp"]["hidden_0"]["kernel"])  # fan_in 32
    assert abs(k.std() * np.sqrt(32) - 1) < 0.15 and np.abs(k).max() <= 2 / np.sqrt(32) / 0.879
    np.testing.assert_array_equal(p["processor_0"]["node_mlp"]["norm"]["scale"], 1.0)
    np.testing.assert_array_equal(p["decoder"]["out"]["bias"], 0.0)
    again = init_params(nets[True], jax.random.key(4), *args)
    other = init_params(nets[True], jax.random.key(5), *args)
    k2 = p["processor_1"]["edge_in"]["sender"]["kernel"]
    np.testing.assert_array_equal(again["params"]["processor_1"]["edge_in"]["sender"]["kernel"], k2)
    assert not np.allclose(other["params"]["processor_1"]["edge_in"]["sender"]["kernel"], k2)


def test_segment_softmax_normalised_and_differentiable():
    s, r, m = _graph(seed=5)
    m_np, r_np = np.asarray(m), np.asarray(r)
    scores = np.random.default_rng(6).normal(0, 30.0, s.shape).astype(np.float32)
    scores[~m_np] = 1e30  # garbage in padded slots must not leak (nor give NaN gradients)
    w = np.asarray(jit(segment_softmax, static_argnums=3)(scores, r, m, 10))
    for node in range(10):  # reference softmax per receiver over its valid edges
        sel = m_np & (r_np == node)
        ref = np.exp(scores[sel] - scores[sel].max())
        np.testing.assert_allclose(w[sel], ref / ref.sum(), rtol=1e-4, atol=1e-7)
    np.testing.assert_array_equal(w[~m_np], 0.0)
    g = jit(jax.grad(lambda x: (segment_softmax(x, r, m, 10) ** 2).sum()))(scores)
    assert np.isfinite(np.asarray(g)).all()
