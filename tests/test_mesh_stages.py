"""Staged MeshGraphNet training (issue 23): unrolled loss through the model's own rollout,
noise stages, exact resume across a stage boundary; the Re-sweep recipe."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns.errors import InputError
from diffgns.mesh.meshnet import pad_mesh
from diffgns.mesh.stages import Stage, parse_stages, stage_at, unrolled_loss
from test_meshnet import NU, WALL, _grid_mesh, _model, _synthetic_dataset


def _setup(k=3, seed=0):
    pos, cells, types = _grid_mesh()
    g = pad_mesh(pos, cells, types, 32, 128, NU)
    model = _model()
    params = model.init_network(jax.random.PRNGKey(seed), g)
    rng = np.random.default_rng(seed)
    v = jnp.asarray(rng.normal(size=(k + 1, 32, 2)), jnp.float32)
    p = jnp.asarray(rng.normal(size=(k, 32)), jnp.float32)
    return model, params, g, v, p


def test_one_frame_unroll_is_the_one_step_loss():
    from diffgns.mesh.train import _loss

    model, params, g, v, p = _setup(k=1)
    key = jax.random.PRNGKey(3)
    model = type(model)(type(model.config)(**{**model.config.__dict__, "noise_std": 0.05}),
                        model.stats)
    a = unrolled_loss(model, params, g, v, p, key, 0.05)
    b = _loss(model, params, g, v[0], v[1], p[0], key)
    np.testing.assert_allclose(float(a), float(b), rtol=2e-6)


@pytest.mark.slow  # 47 s in the full suite beside a 2-process CFD job (2026-12-03)
def test_unrolled_loss_backpropagates_through_the_rollout():
    """K = 2: the value is the mean of two one-step errors, the second from the model's own
    first prediction; its gradient differs from the one with the rollout's carry stopped."""
    model, params, g, v, p = _setup(k=2)
    key = jax.random.PRNGKey(0)
    val = unrolled_loss(model, params, g, v, p, key, 0.0)
    v1, _ = model.advance(params, g, v[0], v[0])
    l0 = unrolled_loss(model, params, g, v[:2], p[:1], key, 0.0)
    l1 = unrolled_loss(model, params, g, jnp.stack([v1, v[2]]), p[1:], key, 0.0)
    np.testing.assert_allclose(float(val), 0.5 * float(l0 + l1), rtol=1e-5)
    full = jax.grad(lambda q: unrolled_loss(model, q, g, v, p, key, 0.0))(params)

    def detached(q):
        v1s = jax.lax.stop_gradient(model.advance(q, g, v[0], v[0])[0])
        return 0.5 * (unrolled_loss(model, q, g, v[:2], p[:1], key, 0.0)
                      + unrolled_loss(model, q, g, jnp.stack([v1s, v[2]]), p[1:], key, 0.0))

    stopped = jax.grad(detached)(params)
    np.testing.assert_allclose(float(detached(params)), float(val), rtol=1e-5)
    diff = sum(float(jnp.abs(a - b).sum()) for a, b in zip(jax.tree_util.tree_leaves(full),
                                                           jax.tree_util.tree_leaves(stopped)))
    assert diff > 1e-3


@pytest.mark.slow  # 68 s in the full suite (2026-12-03, loaded machine)
def test_checkpointed_unroll_equals_plain_and_matches_finite_differences():
    with jax.enable_x64(True):
        model, params, g, v, p = _setup(k=3)
        params = jax.tree_util.tree_map(lambda a: a.astype(jnp.float64), params)
        v, p = v.astype(jnp.float64), p.astype(jnp.float64)
        key = jax.random.PRNGKey(1)
        f = lambda q, c: unrolled_loss(model, q, g, v, p, key, 0.01, checkpoint=c)
        ga, gb = jax.grad(f)(params, True), jax.grad(f)(params, False)
        for a, b in zip(jax.tree_util.tree_leaves(ga), jax.tree_util.tree_leaves(gb)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-12)
        d = jax.tree_util.tree_map(lambda a: jnp.asarray(
            np.random.default_rng(2).normal(size=a.shape)), params)
        eps = 1e-7  # small: the ReLU kinks make a larger step's difference inexact
        shift = lambda s: jax.tree_util.tree_map(lambda a, b: a + s * b, params, d)
        fd = (f(shift(eps), True) - f(shift(-eps), True)) / (2 * eps)
        ad = sum(jnp.vdot(a, b) for a, b in zip(jax.tree_util.tree_leaves(ga),
                                                jax.tree_util.tree_leaves(d)))
        np.testing.assert_allclose(float(ad), float(fd), rtol=1e-5)


def test_stage_parsing_and_lookup():
    st = parse_stages("10:0.01:1, 30:0.005:4,40:0")
    assert st == (Stage(10, 0.01, 1), Stage(30, 0.005, 4), Stage(40, 0.0, 1))
    assert [stage_at(st, s).until for s in (0, 9, 10, 29, 30, 39, 99)] == [10, 10, 30, 30,
                                                                           40, 40, 40]
    for bad, msg in [("10:0.01,5:0", "increase"), ("10", "UNTIL:NOISE"),
                     ("10:-1", "noise"), ("10:0.1:0", "unroll"), ("x:0.1", "integers")]:
        with pytest.raises(InputError, match=msg):
            parse_stages(bad)


@pytest.mark.slow  # 614 s under a load average of ~25 on 2 cores (quiet: not measured)
def test_staged_training_learns_and_resumes_exactly_across_a_stage_boundary(tmp_path):
    from diffgns.graph.fit import TrainConfig
    from diffgns.mesh.meshnet import MeshNetConfig
    from diffgns.mesh.stages import train_staged
    from diffgns.mesh.train import load_model

    _synthetic_dataset(tmp_path / "d.h5")
    cfg = MeshNetConfig(latent=16, mp_steps=2)
    tc = lambda n: TrainConfig(steps=n, batch_size=2, lr=3e-3, lr_final=1e-4,
                               lr_decay_steps=80, log_every=10, checkpoint_every=10)
    full = parse_stages("40:0.002:1,80:0.001:3")
    _, p_full = train_staged(tmp_path / "d.h5", tmp_path / "a", cfg, tc(80), full,
                             progress=False)
    train_staged(tmp_path / "d.h5", tmp_path / "b", cfg, tc(30), parse_stages("30:0.002:1"),
                 progress=False)
    _, p_res = train_staged(tmp_path / "d.h5", tmp_path / "b", cfg, tc(80), full,
                            progress=False)
    for a, b in zip(jax.tree_util.tree_leaves(p_full), jax.tree_util.tree_leaves(p_res)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    log = np.genfromtxt(tmp_path / "a" / "train_log.csv", delimiter=",", names=True)
    assert list(log["unroll"][[0, -1]]) == [1, 3]
    assert log["noise_std"][-1] == pytest.approx(0.001)
    assert log["loss"][3] < 0.7 * log["loss"][0]  # learns (1.02 -> 0.56 measured)
    model, params, info = load_model(tmp_path / "a" / "model")
    assert info["steps"] == 80 and info["stages"][1]["unroll"] == 3
    with pytest.raises(InputError, match="last stage"):
        train_staged(tmp_path / "d.h5", tmp_path / "c", cfg, tc(50), full, progress=False)


def test_sweep_one_mesh_one_trajectory_per_reynolds_number_resumes_and_refuses(tmp_path):
    from diffgns.mesh.datagen import CylinderRun
    from diffgns.mesh.sweep import COARSE_MESH, Sweep, generate_sweep
    from diffgns.mesh.train import load_cylinder

    run = CylinderRun(n_frames=3, frame_dt=0.02, spinup=0.0, kick=1.0, kick_time=0.3,
                      **COARSE_MESH)
    res = generate_sweep(tmp_path / "s.h5", Sweep((100.0, 200.0), run=run), workers=2,
                         progress=False)
    assert [c[1] for c in res["cases"]] == [100.0, 200.0]
    a, b = load_cylinder(tmp_path / "s.h5")
    np.testing.assert_array_equal(a["mesh_pos"], b["mesh_pos"])  # one mesh
    assert 1200 < len(a["mesh_pos"]) < 1400
    for t, re in ((a, 100.0), (b, 200.0)):
        assert t["attrs"]["reynolds"] == re and t["attrs"]["u_max"] == 1.5
        assert t["attrs"]["nu"] == pytest.approx(1.0 * 0.1 / re, rel=1e-12)  # Ubar D / Re
        assert t["velocity"].shape == (3, len(t["mesh_pos"]), 2)
    assert not np.array_equal(a["velocity"][-1], b["velocity"][-1])
    again = generate_sweep(tmp_path / "s.h5", Sweep((100.0, 200.0), run=run), progress=False)
    assert again["cases"] == []  # resumed: nothing left to run
    with pytest.raises(InputError, match="different recipe"):
        generate_sweep(tmp_path / "s.h5", Sweep((100.0, 150.0), run=run), progress=False)
    with pytest.raises(InputError, match="--re"):
        Sweep((100.0, -5.0))
    # a sweep with one Re in common reuses that trajectory bit for bit and runs the other
    both = generate_sweep(tmp_path / "r.h5", Sweep((200.0, 150.0), run=run), workers=1,
                          progress=False, reuse=tmp_path / "s.h5")
    assert both["reused"] == 1 and [c[1] for c in both["cases"]] == [150.0]
    r200, r150 = load_cylinder(tmp_path / "r.h5")
    assert r200["attrs"]["reynolds"] == 200.0 and r200["attrs"]["index"] == 0
    np.testing.assert_array_equal(r200["velocity"], b["velocity"])
    np.testing.assert_array_equal(r200["pressure"], b["pressure"])
    assert not np.array_equal(r150["velocity"], r200["velocity"])
    other = CylinderRun(n_frames=4, frame_dt=0.02, spinup=0.0, kick=1.0, kick_time=0.3,
                        **COARSE_MESH)  # another frame count: not the same data
    with pytest.raises(InputError, match=r"another sweep recipe \(differs in \['run'\]\)"):
        generate_sweep(tmp_path / "o.h5", Sweep((100.0,), run=other), progress=False,
                       reuse=tmp_path / "s.h5")
    with pytest.raises(InputError, match="not a finished sweep file"):
        generate_sweep(tmp_path / "o.h5", Sweep((100.0,), run=run), progress=False,
                       reuse=tmp_path / "missing.h5")


@pytest.mark.slow  # ~20 s: 0.36 s of CFD at the sweep's time step
def test_sweep_time_step_survives_the_spin_pulse_at_the_highest_reynolds_number():
    """At CFL 0.15 the Re >= 200 sweep runs blew up during the spin pulse (make meshnet-data
    failed); the sweep's own time step must carry Re 275 (the top held-out value) through
    it."""
    from diffgns.mesh.cfd import run_case
    from diffgns.mesh.datagen import case_setup
    from diffgns.mesh.sweep import Sweep

    sw = Sweep((275.0,))
    mesh, prm = case_setup(sw.case(0), sw.run)
    # past the pulse to a whole number of frames (run_case needs a multiple of its dt, which
    # divides the frame interval; kick_time + 0.05 s = 0.35 s is not one)
    t_end = (np.ceil((sw.run.kick_time + 0.05) / sw.run.frame_dt - 1e-9)) * sw.run.frame_dt
    res = run_case(mesh, prm, float(t_end), sw.run.frame_dt)
    assert np.isfinite(res.velocity).all() and np.abs(res.velocity).max() < 3 * sw.u_max


def test_near_wall_ring_and_its_loss_weight():
    """The ring is the predicted nodes one mesh edge from a wall node; the weighted loss is
    the weighted node mean of the one-step errors: velocity on the advanced nodes, pressure
    on every mesh vertex, walls included (weight 1 = the unweighted loss)."""
    from diffgns.mesh.meshnet import PAD, loss_weights, near_wall

    pos, cells, types = _grid_mesh(6, 6)  # walls at rows j = 0 and 5
    g = pad_mesh(pos, cells, types, 48, 192, NU)
    nbrs = {n: set() for n in range(36)}
    for c in cells:
        for a in c:
            nbrs[a].update(c)
    ring = np.zeros(48, bool)
    ring[:36] = [bool(g.predicted[n]) and any(types[m] == WALL for m in nbrs[n])
                 for n in range(36)]
    np.testing.assert_array_equal(np.asarray(near_wall(g)), ring)
    j = np.arange(36) % 6  # rows 2 and 3 are two edges from the walls
    assert not ring[:36][np.isin(j, (2, 3))].any() and ring.sum() >= 8
    w_v, w_p = (np.asarray(w) for w in loss_weights(g, 4.0))
    np.testing.assert_array_equal(w_v, np.where(ring, 4.0, np.asarray(g.predicted, float)))
    real = np.asarray(g.node_type) != PAD
    np.testing.assert_array_equal(w_p, np.where(ring, 4.0, real.astype(float)))
    assert (w_p[np.asarray(g.node_type) == WALL] == 1.0).all() and (w_p[~real] == 0).all()

    model = _model()
    params = model.init_network(jax.random.PRNGKey(0), g)
    rng = np.random.default_rng(1)
    v = jnp.asarray(rng.normal(size=(2, 48, 2)), jnp.float32)
    p = jnp.asarray(rng.normal(size=(1, 48)), jnp.float32)
    key = jax.random.PRNGKey(0)
    new_v, new_p = model.advance(params, g, v[0], v[0])
    s = model.stats.target.std
    e_v = np.asarray(((new_v - v[1]) / s[:2]) ** 2).sum(1)
    e_p = np.asarray(((new_p - p[0]) / s[2]) ** 2)
    for weight in (1.0, 4.0):
        wv, wp = (np.asarray(w) for w in loss_weights(g, weight))
        want = ((wv * e_v).sum() + (wp * e_p).sum()) / (2 * wv.sum() + wp.sum())
        got = unrolled_loss(model, params, g, v, p, key, 0.0, near_wall_weight=weight)
        np.testing.assert_allclose(float(got), want, rtol=1e-5)
    # the weight changes the loss: the ring's errors differ from the others' on this data
    assert abs(float(unrolled_loss(model, params, g, v, p, key, 0.0, near_wall_weight=4.0))
               - float(unrolled_loss(model, params, g, v, p, key, 0.0))) > 1e-4
    # a wall vertex's pressure counts (the lift is read there); its velocity, held, does not
    wall = int(np.flatnonzero(np.asarray(g.node_type) == WALL)[0])
    base = float(unrolled_loss(model, params, g, v, p, key, 0.0))
    assert float(unrolled_loss(model, params, g, v, p.at[0, wall].add(1.0), key, 0.0)) > base
    moved = v.at[1, wall].add(1.0)
    assert float(unrolled_loss(model, params, g, moved, p, key, 0.0)) == pytest.approx(base)
    pad = 47  # and padding counts for neither
    assert float(unrolled_loss(model, params, g, v.at[1, pad].add(1.0), p.at[0, pad].add(1.0),
                               key, 0.0)) == pytest.approx(base)


def test_staged_training_starts_from_a_model_and_refuses_bad_options(tmp_path):
    """--init-from: the run starts at the model's params and keeps its normalisers (a step at
    a vanishing learning rate leaves them); another configuration or a weight <= 0 is refused.
    The start model is trained by diffgns.mesh.train, whose normalisers fold its noise in, so
    they differ from the ones the staged trainer would build from the data."""
    from diffgns.graph.fit import TrainConfig
    from diffgns.mesh.meshnet import MeshNetConfig
    from diffgns.mesh.stages import main, train_staged
    from diffgns.mesh.train import load_model, train

    _synthetic_dataset(tmp_path / "d.h5")
    cfg = MeshNetConfig(latent=8, mp_steps=1, noise_std=0.05)
    tc = lambda lr: TrainConfig(steps=2, batch_size=1, lr=lr, lr_final=lr, log_every=1,
                                checkpoint_every=1)
    train(tmp_path / "d.h5", tmp_path / "a", cfg, tc(1e-2), progress=False)
    start, p_start, _ = load_model(tmp_path / "a" / "model")
    fresh, _ = train_staged(tmp_path / "d.h5", tmp_path / "f", cfg, tc(1e-12),
                            parse_stages("2:0.0:1"), progress=False)
    assert not np.allclose(np.asarray(fresh.stats.velocity.std),
                           np.asarray(start.stats.velocity.std))
    _, p_b = train_staged(tmp_path / "d.h5", tmp_path / "b", cfg, tc(1e-12),
                          parse_stages("2:0.0:2"), progress=False, near_wall_weight=3.0,
                          init_from=tmp_path / "a" / "model")
    model_b, _, info = load_model(tmp_path / "b" / "model")
    for a, b in zip(jax.tree_util.tree_leaves(p_start), jax.tree_util.tree_leaves(p_b)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-8)
    leaves = jax.tree_util.tree_leaves
    for a, b in zip(leaves(start.stats), leaves(model_b.stats)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert info["near_wall_weight"] == 3.0 and info["init_from"].endswith("model")
    with pytest.raises(ValueError, match="configuration"):
        train_staged(tmp_path / "d.h5", tmp_path / "c", MeshNetConfig(latent=4, mp_steps=1),
                     tc(1e-3), parse_stages("2:0.0:1"), progress=False,
                     init_from=tmp_path / "a" / "model")
    with pytest.raises(InputError, match="near-wall-weight"):
        main(["--data", str(tmp_path / "d.h5"), "--out", str(tmp_path / "e"),
              "--stages", "2:0.0:1", "--near-wall-weight", "0"])


def test_oversampling_draws_the_high_reynolds_trajectories_by_their_factor(tmp_path):
    """--oversample-re RE:FACTOR: trajectory frequencies follow the weights (4 trajectories,
    factor 3 on the top two: 1/8, 1/8, 3/8, 3/8); no option keeps the uniform draws of the
    earlier runs bit for bit (their exact resume); a run records its weights and trains on
    them (an overwhelming factor gives other parameters than uniform draws)."""
    from diffgns.graph.fit import TrainConfig
    from diffgns.mesh.meshnet import MeshNetConfig
    from diffgns.mesh.stages import (
        draw_windows,
        main,
        parse_oversample,
        train_staged,
        trajectory_weights,
    )
    from diffgns.mesh.train import load_model

    assert parse_oversample(" 200:3") == (200.0, np.inf, 3.0)
    assert parse_oversample("75-100:2.5") == (75.0, 100.0, 2.5)
    for bad in ("200", "200:3:1", "x:3", "200:0.5", "-1:2", "200:nan", "100-75:2",
                "75-100-200:2", "75-:2"):
        with pytest.raises(InputError, match="oversample-re"):
            parse_oversample(bad)
    w = trajectory_weights([75, 150, 200, 300], 200, np.inf, 3)
    np.testing.assert_allclose(w, [1 / 8, 1 / 8, 3 / 8, 3 / 8])
    np.testing.assert_allclose(trajectory_weights([75, 150, 200, 300], 75, 150, 2),
                               [1 / 3, 1 / 3, 1 / 6, 1 / 6])
    with pytest.raises(InputError, match=r"no trajectory has Re in \[400, inf\]"):
        trajectory_weights([75, 300], 400, np.inf, 2)
    ti, win = draw_windows(np.random.default_rng(1), 4, 20, 3, 40000, w)
    np.testing.assert_allclose(np.bincount(ti, minlength=4) / 40000, w, atol=0.01)
    assert win.shape == (40000, 4) and win.min() == 0 and win.max() == 19
    np.testing.assert_array_equal(win[:, 1:] - win[:, :-1], 1)
    rng_a, rng_b = np.random.default_rng([0, 7]), np.random.default_rng([0, 7])
    ti, win = draw_windows(rng_a, 4, 20, 3, 5)
    np.testing.assert_array_equal(ti, rng_b.integers(0, 4, 5))
    np.testing.assert_array_equal(win[:, 0], rng_b.integers(0, 17, 5))

    _synthetic_dataset(tmp_path / "d.h5")  # Re 100 and 200
    cfg = MeshNetConfig(latent=8, mp_steps=1)
    tc = TrainConfig(steps=3, batch_size=1, lr=1e-2, lr_final=1e-2, log_every=1,
                     checkpoint_every=3)
    runs = {}
    for name, over in [("u", None), ("o", (150.0, np.inf, 1e9))]:
        train_staged(tmp_path / "d.h5", tmp_path / name, cfg, tc, parse_stages("3:0.0:1"),
                     progress=False, oversample_re=over)
        runs[name] = load_model(tmp_path / name / "model")
    assert runs["u"][2]["trajectory_weights"] is None
    np.testing.assert_allclose(runs["o"][2]["trajectory_weights"], [0, 1], atol=1e-8)
    leaves = lambda r: jax.tree_util.tree_leaves(r[1])
    assert any(not np.array_equal(a, b) for a, b in zip(leaves(runs["u"]), leaves(runs["o"])))
    with pytest.raises(InputError, match="no trajectory has Re in"):
        main(["--data", str(tmp_path / "d.h5"), "--out", str(tmp_path / "e"),
              "--stages", "2:0.0:1", "--oversample-re", "500:2"])


def test_push_forward_starts_the_loss_from_the_models_own_rollout_without_its_gradient():
    """push = P: the loss equals the P = 0 loss on a window whose first frame is the model's
    own P-frame rollout (computed here by hand), its gradient equals that loss's gradient
    with the rolled frame held constant, and the push changes the loss (it is not the loss of
    the data window from frame P)."""
    from diffgns.mesh.stages import unrolled_loss

    K, P = 2, 3
    model, params, g, v, p = _setup(k=K + P, seed=4)
    key = jax.random.PRNGKey(0)

    def by_hand(params):
        frozen = jax.lax.stop_gradient(params)
        vp = v[0]
        for _ in range(P):
            vp = model.advance(frozen, g, vp, v[0])[0]
        return unrolled_loss(model, params, g, jnp.concatenate([vp[None], v[P + 1:]]), p[P:],
                             key, 0.0)

    pushed = lambda params: unrolled_loss(model, params, g, v, p, key, 0.0, push=P)
    assert float(pushed(params)) == pytest.approx(float(by_hand(params)), rel=1e-5)
    data_only = unrolled_loss(model, params, g, v[P:], p[P:], key, 0.0)
    assert abs(float(pushed(params)) - float(data_only)) > 1e-3 * float(data_only)
    ga, gb = jax.grad(pushed)(params), jax.grad(by_hand)(params)
    for a, b in zip(jax.tree_util.tree_leaves(ga), jax.tree_util.tree_leaves(gb)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4,
                                   atol=1e-5 * float(np.abs(np.asarray(b)).max()))
    assert parse_stages("10:0.01:4:16") == (Stage(10, 0.01, 4, 16),)
    with pytest.raises(InputError, match="push"):
        parse_stages("10:0.01:4:-1")



def test_push_mask_false_starts_the_window_from_the_noisy_data_frame_and_the_trainer_sets_it(
        tmp_path):
    """push_mask False: the loss is the unpushed loss of the data window from frame P with the
    same noise draw (by hand); True is the pushed loss. In training, --push-min-re leaves the
    windows of higher-Re trajectories pushed as before and changes only the lower ones; a
    threshold above every trajectory is refused."""
    from diffgns.graph.fit import TrainConfig
    from diffgns.mesh.meshnet import FLUID, MeshNetConfig
    from diffgns.mesh.stages import main, train_staged, unrolled_loss
    from diffgns.mesh.train import load_model

    K, P, sigma = 2, 3, 0.05
    model, params, g, v, p = _setup(k=K + P, seed=6)
    key = jax.random.PRNGKey(2)
    noise = sigma * jax.random.normal(key, v[0].shape, v.dtype) * (g.node_type == FLUID)[:, None]
    by_hand = unrolled_loss(model, params, g, v[P:].at[0].add(noise), p[P:], key, 0.0)
    off = unrolled_loss(model, params, g, v, p, key, sigma, push=P, push_mask=jnp.asarray(False))
    on = unrolled_loss(model, params, g, v, p, key, sigma, push=P, push_mask=jnp.asarray(True))
    assert float(off) == pytest.approx(float(by_hand), rel=1e-5)
    assert float(on) == pytest.approx(float(unrolled_loss(model, params, g, v, p, key, sigma,
                                                          push=P)), rel=1e-6)
    assert abs(float(on) - float(off)) > 1e-3 * float(off)

    _synthetic_dataset(tmp_path / "d.h5")  # Re 100 and 200
    cfg = MeshNetConfig(latent=8, mp_steps=1)
    tc = TrainConfig(steps=2, batch_size=1, lr=1e-2, lr_final=1e-2, log_every=1,
                     checkpoint_every=2)
    leaves = {}
    for only, lo_hi in (("low", (50.0, 150.0, 1e9)), ("high", (150.0, np.inf, 1e9))):
        for thr in (None, 150.0):
            out = tmp_path / f"{only}{thr}"
            train_staged(tmp_path / "d.h5", out, cfg, tc, parse_stages("2:0.01:1:2"),
                         progress=False, oversample_re=lo_hi, push_min_re=thr)
            m = load_model(out / "model")
            assert m[2]["push_min_re"] == thr
            leaves[only, thr] = jax.tree_util.tree_leaves(m[1])
    same = lambda a, b: all(np.array_equal(x, y) for x, y in zip(leaves[a], leaves[b]))
    assert same(("high", None), ("high", 150.0))  # Re 200 windows: pushed either way
    assert not same(("low", None), ("low", 150.0))  # Re 100 windows: no longer pushed
    with pytest.raises(InputError, match="no trajectory has Re >= 500"):
        main(["--data", str(tmp_path / "d.h5"), "--out", str(tmp_path / "e"),
              "--stages", "2:0.0:1:2", "--push-min-re", "500"])

def test_divergence_weight_adds_the_continuity_term_of_each_frame_and_bad_weights_are_refused(
        tmp_path):
    """divergence_weight = L: the loss of a one-frame window grows by exactly L times the
    continuity loss of the model's error (model minus data velocity over the rms
    velocity-change scale, times the edge scale); 0 leaves it unchanged; a negative weight is
    refused before any training."""
    from diffgns.graph.features import Normalizer
    from diffgns.mesh.meshnet import MeshNet, MeshStats, divergence_loss
    from diffgns.mesh.stages import main

    model, params, g, v, p = _setup(k=1, seed=4)
    st = model.stats  # unequal velocity-change scales, so one scale must serve both
    model = MeshNet(model.config, MeshStats(st.velocity, Normalizer(
        st.target.mean, jnp.asarray([0.1, 0.03, 0.1])), st.edge_scale, st.viscosity))
    key = jax.random.PRNGKey(1)
    base = float(unrolled_loss(model, params, g, v, p, key, 0.0))
    assert float(unrolled_loss(model, params, g, v, p, key, 0.0, divergence_weight=0.0)) == base
    new_v, _ = model.advance(params, g, v[0], v[0])
    term = float(divergence_loss(g, (new_v - v[1]) / np.sqrt((0.1**2 + 0.03**2) / 2),
                                 model.stats.edge_scale))
    assert term > 1e-3 * base
    with_term = float(unrolled_loss(model, params, g, v, p, key, 0.0, divergence_weight=2.5))
    assert with_term == pytest.approx(base + 2.5 * term, rel=1e-5)
    _synthetic_dataset(tmp_path / "d.h5")
    with pytest.raises(InputError, match="divergence-weight"):
        main(["--data", str(tmp_path / "d.h5"), "--out", str(tmp_path / "e"),
              "--stages", "2:0.0:1", "--divergence-weight", "-1"])


def test_near_wall_noise_scales_the_input_noise_on_the_first_ring_only():
    """near_wall_noise = F: the loss equals the noise-free loss from a frame perturbed by hand
    with the same draws, F times larger on the first fluid ring off the walls, none on the
    held nodes; the option is refused below 0."""
    from diffgns.mesh.meshnet import FLUID, near_wall
    from diffgns.mesh.stages import train_staged, unrolled_loss

    pos, cells, types = _grid_mesh(6, 6)  # interior rows 2-3 are off the walls
    g = pad_mesh(pos, cells, types, 48, 256, NU)
    model = _model()
    params = model.init_network(jax.random.PRNGKey(5), g)
    rng = np.random.default_rng(5)
    v = jnp.asarray(rng.normal(size=(3, 48, 2)), jnp.float32)
    p = jnp.asarray(rng.normal(size=(2, 48)), jnp.float32)
    key, sigma, F = jax.random.PRNGKey(9), 0.05, 7.0
    ring, fluid = near_wall(g), g.node_type == FLUID
    assert 0 < int((ring & fluid).sum()) < int(fluid.sum())
    draw = sigma * jax.random.normal(key, v[0].shape, v.dtype)
    noise = draw * jnp.where(ring, F, 1.0)[:, None] * fluid[:, None]
    by_hand = unrolled_loss(model, params, g, v.at[0].add(noise), p, key, 0.0)
    scaled = unrolled_loss(model, params, g, v, p, key, sigma, near_wall_noise=F)
    plain = unrolled_loss(model, params, g, v, p, key, sigma)
    assert float(scaled) == pytest.approx(float(by_hand), rel=1e-5)
    assert abs(float(scaled) - float(plain)) > 1e-4 * float(plain)
    with pytest.raises(InputError, match="near-wall-noise"):
        train_staged("missing.h5", "x", None, None, (), near_wall_noise=-1.0)


def test_drawn_reynolds_numbers_depend_on_the_seed_alone_and_bad_draws_are_refused(capsys):
    from diffgns.mesh.sweep import draw_reynolds, main

    a = draw_reynolds(75.0, 300.0, 4, 20261206)
    assert a == draw_reynolds(75.0, 300.0, 4, 20261206)  # named by its command
    assert a != draw_reynolds(75.0, 300.0, 4, 20261207)
    assert len(a) == 4 and all(75.0 <= r <= 300.0 for r in a)
    assert all(r == round(r, 1) for r in a)
    # the draw is spread over the range, not a constant or an endpoint
    many = [r for seed in range(50) for r in draw_reynolds(75.0, 300.0, 4, seed)]
    assert 165 < np.mean(many) < 210 and min(many) < 80 and max(many) > 295
    with pytest.raises(ValueError, match="repeats"):  # two trajectories at one Re
        draw_reynolds(100.0, 100.05, 5, 0)
    for lo, hi, n in ((300.0, 75.0, 4), (0.0, 10.0, 2), (75.0, 300.0, 0), (75.0, 300.0, 2.5)):
        with pytest.raises(ValueError, match="LO < HI"):
            draw_reynolds(lo, hi, n, 0)
    with pytest.raises(InputError, match="--draw"):
        main(["--out", "x.h5", "--draw", "300", "75", "4"])
    with pytest.raises(SystemExit):  # --re and --draw exclude each other
        main(["--out", "x.h5", "--re", "100", "--draw", "75", "300", "4"])
