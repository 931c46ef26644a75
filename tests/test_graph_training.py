"""GNS training: noise-corrected target, learning, exact resume, 2-device data parallel."""
import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns.graph.data import WindowSampler, coarse_grain, load_trajectories
from diffgns.graph.features import ParticleStats, random_walk_noise
from diffgns.graph.gns import GNS, GNSConfig
from diffgns.graph.training import (
    NeighborLists,
    TrainConfig,
    Trainer,
    load_checkpoint,
    pushed_target,
    save_checkpoint,
    step_rng,
    step_with_reallocation,
    window_loss,
)
from diffgns.io.npz import write_gns_npz
from diffgns.trajectory import SAND, Trajectory

BOUNDS = ((0.0, 1.0), (0.0, 1.0))


def synthetic(n_traj=3, T=12, seed=0):
    """Lattice blocks drifting with constant acceleration (frame units)."""
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(np.arange(4), np.arange(4), indexing="ij"), -1).reshape(-1, 2)
    out = []
    for _ in range(n_traj):
        x0 = 0.3 + 0.02 * g + rng.uniform(0, 0.2, 2)
        v, a = rng.normal(0, 2e-3, 2), rng.normal(0, 2e-4, 2)
        t = np.arange(T)[:, None, None]
        pos = x0[None] + v * t + 0.5 * a * t**2
        out.append(Trajectory(positions=jnp.asarray(pos, jnp.float32),
                              velocities=jnp.zeros_like(jnp.asarray(pos)),
                              particle_type=jnp.full(16, SAND, jnp.int32),
                              material=jnp.full(16, 0.5), bounds=BOUNDS))
    return out


def small_gns(trajs):
    from diffgns.graph.data import frame_statistics

    cfg = GNSConfig(bounds=BOUNDS, radius=0.045, latent=16, mp_steps=1, mlp_layers=1,
                    noise_std=1e-4)
    return GNS(cfg, ParticleStats.from_metadata(frame_statistics(trajs), cfg.noise_std))


def _init(gns, trajs):
    t = trajs[0]
    return gns.init_network(jax.random.PRNGKey(0), (jnp.swapaxes(t.positions[:6], 0, 1),
                                                    t.particle_type, t.material))


def _zero_network_window():
    """(window_loss arguments of a zero network on one 7-frame window, the normalised
    noise-corrected target (N, 2): the zero network's error)."""
    trajs = synthetic(1)
    gns = small_gns(trajs)
    w, t = trajs[0].positions[:7], trajs[0]
    zero = jax.tree.map(jnp.zeros_like, _init(gns, trajs))
    nbrs = gns.allocate(w[5])
    key = jax.random.PRNGKey(3)
    clean = jnp.swapaxes(w[:6], 0, 1)
    n = random_walk_noise(key, clean, gns.config.noise_std, t.particle_type)
    target = (w[6] + n[:, -1]) - 2 * (clean[:, -1] + n[:, -1]) + (clean[:, -2] + n[:, -2])
    args = (gns, zero, w, t.particle_type, t.material, nbrs, key, 0, 0.0, None)
    return args, gns.normalizer.acceleration.normalize(target)


def test_target_is_corrected_for_input_noise_exactly_once():
    args, target = _zero_network_window()
    loss, _ = window_loss(*args)
    expect = jnp.mean(jnp.sum(target**2, -1))
    assert float(loss) == pytest.approx(float(expect), rel=1e-4)


def test_huber_loss_is_the_mse_inside_delta_and_linear_beyond():
    args, target = _zero_network_window()
    mse = float(window_loss(*args)[0])
    e = jnp.abs(target)
    assert float(window_loss(*args, huber_delta=1e3)[0]) == pytest.approx(mse, rel=1e-4)
    d = 0.5 * float(jnp.min(e))  # every component beyond delta: 2 delta |e| - delta^2
    expect = float(jnp.mean(jnp.sum(2 * d * e - d**2, -1)))
    assert float(window_loss(*args, huber_delta=d)[0]) == pytest.approx(expect, rel=1e-4)
    assert expect < mse
    with pytest.raises(ValueError, match="huber_delta"):
        TrainConfig(huber_delta=-1.0)


def test_target_scaled_loss_is_the_relative_error_with_a_floor():
    """Each window's loss over (its mean squared normalised target + floor); the scale is a
    constant of the window (no gradient through it), so the gradient is the plain one
    divided by it."""
    args, target = _zero_network_window()
    gns, params = args[0], args[1]
    ms = float(jnp.mean(jnp.sum(target**2, -1)))
    for floor in (1.0, 0.25):
        scaled = float(window_loss(*args, target_scale_floor=floor)[0])
        assert scaled == pytest.approx(ms / (ms + floor), rel=1e-4)
    g0 = jax.grad(lambda p: window_loss(gns, p, *args[2:])[0])(params)
    g1 = jax.grad(lambda p: window_loss(gns, p, *args[2:], target_scale_floor=1.0)[0])(params)
    for a, b in zip(jax.tree.leaves(g0), jax.tree.leaves(g1)):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a) / (ms + 1.0), rtol=2e-4,
                                   atol=1e-9)
    with pytest.raises(ValueError, match="target_scale_floor"):
        TrainConfig(target_scale_floor=-1.0)


def test_push_forward_target_corrects_velocity_not_position():
    trajs = synthetic(1)
    w = trajs[0].positions[:9]  # history 5, 2 pushed frames, 1 target frame
    truth = jnp.swapaxes(w[2:8], 0, 1)
    clean_acc = w[8] - 2 * w[7] + w[6]
    # a pushed history that is off the data by a constant offset keeps that offset
    shifted = truth + jnp.array([3e-3, -2e-3])
    assert jnp.allclose(pushed_target(w, shifted, 2), clean_acc, atol=1e-7)
    # a velocity error on the last pushed frame is undone in one step, not its position error
    bent = truth.at[:, -1].add(1e-3)
    assert jnp.allclose(pushed_target(w, bent, 2), clean_acc - 1e-3, atol=1e-7)


def test_push_forward_loss_is_of_the_order_of_the_unpushed_one():
    trajs = synthetic(1)
    gns = small_gns(trajs)
    t = trajs[0]
    w = t.positions[:9]
    zero = jax.tree.map(jnp.zeros_like, _init(gns, trajs))
    nbrs = gns.allocate(w[5])
    key = jax.random.PRNGKey(3)
    l0, _ = window_loss(gns, zero, w[:7], t.particle_type, t.material, nbrs, key, 0, 0.0)
    l2, _ = window_loss(gns, zero, w, t.particle_type, t.material, nbrs, key, 2, 0.0)
    # zero network = zero acceleration: pushing drifts the history by the missed
    # acceleration; the velocity-correcting target keeps the loss the same size (a target
    # that also undid the position drift gave 20x the unpushed loss here)
    assert np.isfinite(float(l2)) and float(l2) < 2 * float(l0)


def test_push_forward_is_one_scanned_frame_equal_to_the_models_rollout_without_gradient():
    """The push-forward frames are one scanned frame: the traced program of 2 and 5 frames
    has the same number of equations (a Python loop traced the model once per frame and
    compiled for half a minute per step at 16), and the loss and gradient (3 frames) equal those of
    an explicit rollout with :meth:`GNS.advance` from the noisy history, whose parameters
    are held constant (no gradient through the pushed frames)."""
    from diffgns.graph.neighbors import edges

    trajs = synthetic(1)
    gns = small_gns(trajs)
    t = trajs[0]
    params = _init(gns, trajs)
    nbrs = gns.allocate(t.positions[5])
    key = jax.random.PRNGKey(11)
    rest = (t.particle_type, t.material, nbrs, key)

    def loss(p, u):
        return window_loss(gns, p, t.positions[: 7 + u], *rest, u, 0.0)[0]

    def n_eqns(u):
        return len(jax.make_jaxpr(lambda p: loss(p, u))(params).eqns)

    assert abs(n_eqns(2) - n_eqns(5)) <= 2  # a Python loop adds dozens per frame

    def explicit(p, u):  # pushed with the fixed ``params``: only the last step sees ``p``
        w = t.positions[: 7 + u]
        clean = jnp.swapaxes(w[:6], 0, 1)
        hist = clean + random_walk_noise(key, clean, gns.config.noise_std, t.particle_type)
        for k in range(u):
            x, _, _ = gns.advance(params, hist, t.particle_type, t.material, nbrs, w[6 + k])
            hist = jnp.concatenate([hist[:, 1:], x[:, None]], axis=1)
        s, r, m = edges(gns.neighbors.update(hist[:, -1], nbrs), hist.shape[0])
        pred = gns.normalized_acceleration(p, hist, t.particle_type, t.material, s, r, m)
        tgt = gns.normalizer.acceleration.normalize(pushed_target(w, hist, u))
        return jnp.mean(jnp.sum((pred - tgt) ** 2, -1))

    flat = lambda tree: np.concatenate([np.ravel(x) for x in jax.tree.leaves(tree)])
    value_grad = lambda f: jax.jit(jax.value_and_grad(lambda p: f(p, 3)))
    (v, g), (v_ref, g_ref) = value_grad(loss)(params), value_grad(explicit)(params)
    assert float(v) == pytest.approx(float(v_ref), rel=1e-5)
    g, g_ref = flat(g), flat(g_ref)
    assert np.linalg.norm(g - g_ref) <= 1e-4 * np.linalg.norm(g_ref)


def test_unrolled_loss_is_the_mean_of_one_step_losses_along_the_models_rollout():
    """loss_frames = 2: the value is the mean of the one-step loss and the loss after one
    model frame (which equals the 1-frame push-forward loss: same noise, same frame); unlike
    that push-forward, the gradient flows through the first frame (it differs from the mean
    of the two one-step gradients) and matches central finite differences. A window of the
    wrong length and a loss of no frame are refused."""
    trajs = synthetic(1)
    gns = small_gns(trajs)
    t = trajs[0]
    w = t.positions[:8]
    params = _init(gns, trajs)
    nbrs = gns.allocate(w[5])
    key = jax.random.PRNGKey(5)
    rest = (t.particle_type, t.material, nbrs, key)

    @jax.jit
    def two(p):
        return window_loss(gns, p, w, *rest, 0, 0.0, loss_frames=2)[0]

    @jax.jit
    def pieces(p):
        return (window_loss(gns, p, w[:7], *rest, 0, 0.0)[0]
                + window_loss(gns, p, w, *rest, 1, 0.0)[0]) / 2

    assert float(two(params)) == pytest.approx(float(pieces(params)), rel=1e-5)
    g, g_pieces = jax.grad(two)(params), jax.grad(pieces)(params)
    flat = lambda tree: np.concatenate([np.ravel(x) for x in jax.tree.leaves(tree)])
    assert np.linalg.norm(flat(g) - flat(g_pieces)) > 1e-2 * np.linalg.norm(flat(g))
    # along the decoder's output bias (a uniform acceleration: the graph's edges do not
    # change, so the loss is smooth there) the gradient is the finite difference
    d = jax.tree_util.tree_map_with_path(
        lambda path, a: jnp.ones_like(a) if "decoder" in jax.tree_util.keystr(path)
        and jax.tree_util.keystr(path).endswith("['out']['bias']") else jnp.zeros_like(a),
        params)
    assert np.count_nonzero(flat(d)) == 2
    shift = lambda s: jax.tree.map(lambda a, b: a + s * b, params, d)
    fd = (float(two(shift(1e-2))) - float(two(shift(-1e-2)))) / 2e-2
    assert float(np.dot(flat(g), flat(d))) == pytest.approx(fd, rel=5e-3)
    assert abs(float(np.dot(flat(g_pieces), flat(d))) - fd) > 0.05 * abs(fd)
    with pytest.raises(ValueError, match="need 9"):
        window_loss(gns, params, w, *rest, 1, 0.0, loss_frames=2)
    with pytest.raises(ValueError, match="unroll"):
        TrainConfig(unroll=0)


def test_unrolled_loss_traces_one_frame_for_any_k_and_keeps_its_value():
    """The K loss frames are one scanned (rematerialised) frame: the traced program of
    K = 3 and K = 6 has the same number of equations (a Python loop grows with K, and
    compiled for minutes at K = 8), and K = 3's value is the mean of the one-step losses
    after 0, 1 and 2 frames of the model's own rollout (the push-forward losses)."""
    trajs = synthetic(1)
    gns = small_gns(trajs)
    t = trajs[0]
    params = _init(gns, trajs)
    nbrs = gns.allocate(t.positions[5])
    rest = (t.particle_type, t.material, nbrs, jax.random.PRNGKey(7))

    def loss(p, K, w):
        return window_loss(gns, p, w, *rest, 0, 0.0, loss_frames=K)[0]

    def n_eqns(K):
        return len(jax.make_jaxpr(lambda p: loss(p, K, t.positions[: 6 + K]))(params).eqns)

    assert abs(n_eqns(3) - n_eqns(6)) <= 2  # a Python loop adds dozens per frame

    def primitives(jaxpr) -> set:  # every primitive, nested jaxprs (scan, remat) included
        out = set()
        for e in jaxpr.eqns:
            out.add(e.primitive.name)
            for v in e.params.values():
                for sub in v if isinstance(v, (list, tuple)) else [v]:
                    inner = getattr(sub, "jaxpr", sub)
                    if hasattr(inner, "eqns"):
                        out |= primitives(inner)
        return out

    def remat(K):  # is the scanned frame rematerialised (memory independent of K)?
        jx = jax.make_jaxpr(jax.grad(lambda p: loss(p, K, t.positions[: 6 + K])))(params)
        return any("remat" in n or "checkpoint" in n for n in primitives(jx.jaxpr))

    assert remat(3) and not remat(1)  # K = 1, every default training, traces as before
    three = float(jax.jit(lambda p: loss(p, 3, t.positions[:9]))(params))
    pieces = [float(window_loss(gns, params, t.positions[: 7 + u], *rest, u, 0.0)[0])
              for u in range(3)]
    assert three == pytest.approx(np.mean(pieces), rel=1e-5)


def test_unrolled_training_draws_windows_long_enough_and_records_the_option(tmp_path, capsys):
    """diffgns.graph.train_loop.train with unroll 3 and push-forward 1: the sampler's
    windows fit the loss (a wrong length raises), the run trains to a finite loss and
    records the option; --unroll is refused for a MeshGraphNet."""
    from diffgns.cli import main as cli_main
    from diffgns.graph.train_loop import train

    path = tmp_path / "d.npz"
    write_gns_npz(path, synthetic(2, T=14))
    tcfg = TrainConfig(steps=2, batch_size=1, lr=1e-3, push_forward=1, unroll=3,
                       log_every=1, checkpoint_every=2, validate_every=100)
    train([path], tmp_path / "run", dict(bounds=BOUNDS, radius=0.045, latent=8, mp_steps=1,
                                         mlp_layers=1, noise_std=1e-4), tcfg, progress=False)
    info = json.loads((tmp_path / "run" / "train_config.json").read_text())
    assert info["train"]["unroll"] == 3 and info["train"]["push_forward"] == 1
    log = (tmp_path / "run" / "train_log.csv").read_text().splitlines()
    assert np.isfinite(float(log[-1].split(",")[1]))
    assert cli_main(["train", "--kind", "mesh", "--data", str(path), "--out",
                     str(tmp_path / "m"), "--unroll", "2"]) != 0
    assert "--unroll: is a particle-GNS option" in capsys.readouterr().err


def test_training_reduces_loss_and_resumes_exactly(tmp_path):
    trajs = synthetic()
    gns = small_gns(trajs)
    tr = Trainer(gns, TrainConfig(lr=3e-3, lr_final=3e-3, batch_size=2))
    sampler = WindowSampler(trajs, 5)
    p0 = _init(gns, trajs)
    nbrs = NeighborLists()

    def run(params, opt, start, stop):
        losses = []
        for step in range(start, stop):
            rng, key = step_rng(0, step)
            params, opt, loss = step_with_reallocation(tr, params, opt, sampler.sample(rng, 2),
                                                       nbrs, key)
            losses.append(float(loss))
        return params, opt, losses

    straight, _, losses = run(p0, tr.opt.init(p0), 0, 60)
    assert np.mean(losses[-10:]) < 0.5 * np.mean(losses[:5])
    nbrs.clear()
    half, opt, _ = run(p0, tr.opt.init(p0), 0, 30)
    save_checkpoint(tmp_path / "ckpt", half, opt, 30, {})
    at_30 = nbrs.state_dict()
    nbrs.load_state_dict(at_30)  # a resumed process: no lists, the saved capacities
    assert len(nbrs) == 0 and set(at_30) == {"16"}
    p, o, step = load_checkpoint(tmp_path / "ckpt", p0, tr.opt.init(p0))
    assert step == 30
    for a, b in zip(jax.tree.leaves((half, opt)), jax.tree.leaves((p, o))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))  # state restored exactly
    resumed, _, _ = run(p, o, step, 60)
    # same batches and noise (a function of seed and step), same list capacities
    for a, b in zip(jax.tree.leaves(straight), jax.tree.leaves(resumed)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_coarse_graining_and_frame_stride():
    t = synthetic(1, T=13)[0]
    c = coarse_grain(t, 4, frame_stride=3)
    assert c.n_particles == 4 and c.n_frames == 5 and c.frame_dt == pytest.approx(3 * t.frame_dt)
    np.testing.assert_allclose(np.asarray(c.positions).mean(1),
                               np.asarray(t.positions)[::3].mean(1), rtol=1e-6)


def test_gns_npz_datasets_load_for_training(tmp_path):
    trajs = synthetic(2)
    write_gns_npz(tmp_path / "train.npz", trajs)
    loaded, _ = load_trajectories(tmp_path / "train.npz")
    assert len(loaded) == 2
    np.testing.assert_allclose(np.asarray(loaded[1].positions), np.asarray(trajs[1].positions))


SCRIPT = r"""
import os, sys, json
os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
import jax, jax.numpy as jnp, numpy as np
sys.path.insert(0, os.path.dirname(sys.argv[1]))
from test_graph_training import synthetic, small_gns, _init
from diffgns.graph.data import WindowSampler
from diffgns.graph.training import Trainer, TrainConfig, step_rng
assert len(jax.devices()) == 2
trajs = synthetic(); gns = small_gns(trajs); p0 = _init(gns, trajs)
batch = WindowSampler(trajs, 5).sample(np.random.default_rng(0), 4)
nbrs = gns.allocate(trajs[0].positions[5])
key = jax.random.PRNGKey(1)
out = []
for devs in (jax.devices()[:1], jax.devices()):
    tr = Trainer(gns, TrainConfig(lr=1e-3, batch_size=4), devices=devs)
    p, _, loss, _ = tr.step(p0, tr.opt.init(p0), batch, nbrs, key)
    out.append((float(loss), [np.asarray(x) for x in jax.tree.leaves(p)]))
    if len(devs) == 2:
        shard = tr.shard(batch)["positions"]
        assert len(shard.sharding.device_set) == 2
diff = max(float(np.abs(a - b).max()) for a, b in zip(out[0][1], out[1][1]))
print(json.dumps(dict(loss1=out[0][0], loss2=out[1][0], max_param_diff=diff)))
"""


@pytest.mark.slow  # 48 s in the full suite (2026-12-03, loaded machine)
def test_two_device_step_equals_one_device_step(tmp_path):
    script = tmp_path / "dp.py"
    script.write_text(SCRIPT)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    r = subprocess.run([sys.executable, str(script), str(Path(__file__))], capture_output=True,
                       text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["loss2"] == pytest.approx(res["loss1"], rel=1e-5)
    assert res["max_param_diff"] < 1e-6


def test_fine_tuning_keeps_the_normaliser_and_may_change_only_noise_and_head_room(tmp_path):
    import dataclasses

    from diffgns.graph.train_loop import _initial_model, save_model

    trajs = synthetic()
    gns = small_gns(trajs)
    params = _init(gns, trajs)
    save_model(tmp_path / "m", gns, params, {})
    quieter = GNS(dataclasses.replace(gns.config, noise_std=3e-5, capacity_multiplier=1.1),
                  ParticleStats.from_metadata({"vel_mean": [0, 0], "vel_std": [1, 1],
                                             "acc_mean": [0, 0], "acc_std": [1, 1]}))
    tuned, p = _initial_model(tmp_path / "m", quieter)
    assert tuned.config.noise_std == 3e-5
    assert tuned.config.capacity_multiplier == 1.1  # neighbour-list head-room: not the network
    np.testing.assert_allclose(tuned.normalizer.velocity.std, gns.normalizer.velocity.std,
                               rtol=1e-6)  # the base model's scale, not the new one's
    for a, b in zip(jax.tree.leaves(p), jax.tree.leaves(params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    wider = GNS(dataclasses.replace(gns.config, latent=32), gns.normalizer)
    with pytest.raises(ValueError, match="latent"):
        _initial_model(tmp_path / "m", wider)


def test_average_models_is_the_elementwise_mean_of_compatible_models(tmp_path):
    import dataclasses

    from diffgns.cli import main
    from diffgns.graph.train_loop import average_models, load_model, save_model

    trajs = synthetic()
    gns = small_gns(trajs)
    pa = _init(gns, trajs)
    pb = jax.tree.map(lambda x: x * 3.0 + 1.0, pa)
    save_model(tmp_path / "a", gns, pa, {})
    save_model(tmp_path / "b", GNS(dataclasses.replace(gns.config, noise_std=1e-6),
                                   gns.normalizer), pb, {})
    assert main(["average", str(tmp_path / "a"), str(tmp_path / "b"),
                 "--out", str(tmp_path / "ab")]) == 0
    g, p, info = load_model(tmp_path / "ab")
    assert g.config == gns.config and info["averaged_from"][1].endswith("b")
    for m, a, b in zip(jax.tree.leaves(p), jax.tree.leaves(pa), jax.tree.leaves(pb)):
        np.testing.assert_allclose(np.asarray(m), (np.asarray(a) + np.asarray(b)) / 2,
                                   rtol=1e-6, atol=1e-7)
    wider = GNS(dataclasses.replace(gns.config, latent=32), gns.normalizer)
    save_model(tmp_path / "w", wider, _init(wider, trajs), {})
    with pytest.raises(ValueError, match="different configuration"):
        average_models([tmp_path / "a", tmp_path / "w"], tmp_path / "x")
    with pytest.raises(ValueError, match="at least two"):
        average_models([tmp_path / "a"], tmp_path / "x")
    assert main(["average", str(tmp_path / "a"), str(tmp_path / "w"),
                 "--out", str(tmp_path / "x")]) == 2  # a clear error, no traceback
    (tmp_path / "mesh").mkdir()
    (tmp_path / "mesh" / "config.json").write_text('{"meshnet": {}}')
    with pytest.raises(ValueError, match="not a particle GNS"):
        average_models([tmp_path / "a", tmp_path / "mesh"], tmp_path / "x")


def _small_run(tmp_path, **cfg):
    """``run(out, steps)``: train() of a tiny GNS on synthetic data (validated on one
    trajectory) into ``tmp_path / out``; ``cfg`` adds TrainConfig fields."""
    from diffgns.graph import train_loop

    write_gns_npz(tmp_path / "train.npz", synthetic())
    write_gns_npz(tmp_path / "valid.npz", synthetic(1, seed=5))
    kw = dict(bounds=BOUNDS, radius=0.045, latent=16, mp_steps=1, mlp_layers=1,
              noise_std=1e-4)
    tcfg = lambda steps: TrainConfig(steps=steps, batch_size=2, lr=3e-3, lr_final=3e-4,
                                     lr_decay_steps=8, log_every=2, checkpoint_every=4,
                                     validate_every=4, **cfg)
    return lambda out, steps: train_loop.train(
        [tmp_path / "train.npz"], tmp_path / out, kw, tcfg(steps),
        valid_path=tmp_path / "valid.npz", n_valid=1, progress=False)


def test_train_run_resumes_validates_and_writes_a_loadable_model(tmp_path):
    """train(): the GNS run on the shared loop; stopped at a checkpoint and resumed it ends
    where an uninterrupted run does, with the validation log and a model folder."""
    from diffgns.graph.train_loop import load_model

    run = _small_run(tmp_path)
    _, straight = run("a", 8)
    run("b", 4)
    gns, resumed = run("b", 8)
    for a, b in zip(jax.tree.leaves(straight), jax.tree.leaves(resumed)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    log = (tmp_path / "b" / "train_log.csv").read_text().splitlines()
    assert log[0] == "step,loss,lr,seconds" and [r.split(",")[0] for r in log[1:]] == \
        ["2", "4", "6", "8"]
    valid = [json.loads(s) for s in (tmp_path / "b" / "valid_log.jsonl").read_text()
             .splitlines()]
    assert [v["step"] for v in valid] == [4, 8] and "runout_rel_error" in valid[0]
    g, p, info = load_model(tmp_path / "b" / "model")
    assert g.config == gns.config and info["steps"] == 8
    for a, b in zip(jax.tree.leaves(p), jax.tree.leaves(resumed)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_a_resumed_fine_tune_ends_where_a_straight_one_does_in_the_start_models_units(
        tmp_path):
    """A fine-tune (``init_from``) with another noise, stopped at a checkpoint and resumed,
    ends bit for bit where an uninterrupted one does and keeps the start model's normaliser
    (its params are trained in those units). Before the fix the resumed run rebuilt the
    normaliser from the data with the new noise folded in (the 3D stage 3 resumed at a loss
    500x its last, 0.004 -> 2.1)."""
    from diffgns.graph.train_loop import load_model, train

    write_gns_npz(tmp_path / "train.npz", synthetic())
    kw = dict(bounds=BOUNDS, radius=0.045, latent=16, mp_steps=1, mlp_layers=1)
    cfg = lambda steps: TrainConfig(steps=steps, batch_size=2, lr=3e-3, lr_final=3e-4,
                                    lr_decay_steps=8, log_every=2, checkpoint_every=4)
    run = lambda out, steps, noise, init=None: train(
        [tmp_path / "train.npz"], tmp_path / out, dict(kw, noise_std=noise), cfg(steps),
        init_from=init, progress=False)
    run("base", 4, 3e-4)
    base = tmp_path / "base" / "model"
    _, straight = run("a", 8, 5e-5, base)
    run("b", 4, 5e-5, base)
    _, resumed = run("b", 8, 5e-5, base)
    for a, b in zip(jax.tree.leaves(straight), jax.tree.leaves(resumed)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    g0, _, _ = load_model(base)
    g, _, _ = load_model(tmp_path / "b" / "model")
    assert g.config.noise_std == 5e-5
    for a, b in ((g.normalizer.velocity, g0.normalizer.velocity),
                 (g.normalizer.acceleration, g0.normalizer.acceleration)):
        np.testing.assert_array_equal(np.asarray(a.std), np.asarray(b.std))
        np.testing.assert_array_equal(np.asarray(a.mean), np.asarray(b.mean))


def test_several_steps_in_one_call_equal_single_steps_and_redo_on_overflow():
    """Trainer.steps (k optimiser steps looped inside one device call, the default training
    path) computes what k single steps compute, to float32 round-off; one compiled program
    serves every count k <= steps_per_call; an overflow in any step of the call re-allocates
    for that step's positions and redoes the call, so no edge is dropped."""
    from diffgns.graph.training import steps_with_reallocation

    trajs = synthetic()
    gns = small_gns(trajs)
    tr = Trainer(gns, TrainConfig(lr=3e-3, lr_final=3e-3, batch_size=2, steps_per_call=4))
    sampler = WindowSampler(trajs, 5)
    p0 = _init(gns, trajs)
    draws = [step_rng(0, s) for s in range(7)]
    batches = [sampler.sample(rng, 2) for rng, _ in draws]
    keys = [k for _, k in draws]
    p, o, single = p0, tr.opt.init(p0), []
    nb1 = NeighborLists()
    for b, k in zip(batches, keys):
        p, o, loss = step_with_reallocation(tr, p, o, b, nb1, k)
        single.append(float(loss))
    # a list allocated too small for the later batches: the call must be redone
    nb = NeighborLists()
    spread = 0.1 + 0.2 * np.stack(np.meshgrid(np.arange(4), np.arange(4)), -1).reshape(-1, 2)
    nb[16] = gns.allocate(jnp.asarray(spread, jnp.float32))  # no neighbours within 0.045
    tiny = int(nb[16].idx.shape[1])
    q, s, losses = p0, tr.opt.init(p0), []
    programs = []
    for lo, hi in ((0, 4), (4, 7)):  # a full call and a short one
        q, s, ls = steps_with_reallocation(tr, q, s, batches[lo:hi], nb, keys[lo:hi])
        assert ls.shape == (hi - lo,)
        losses += [float(x) for x in ls]
        programs.append(tr._steps._cache_size())
    assert int(nb[16].idx.shape[1]) > tiny  # re-allocated
    np.testing.assert_allclose(losses, single, rtol=2e-5)
    for a, b in zip(jax.tree.leaves(p), jax.tree.leaves(q)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)
    assert programs[1] == programs[0]  # counts 4 and 3: one program (same capacity)
    with pytest.raises(ValueError, match="one node count"):
        small = {k: (v[..., :9, :] if k == "positions" else v[..., :9])
                 for k, v in batches[1].items()}
        steps_with_reallocation(tr, q, s, [batches[0], small], nb, keys[:2])


def test_early_windows_are_drawn_weight_times_as_often():
    """Starts in the first K frames are W times as likely as each later one: the early share
    is K W / (K W + n - K); the default draws exactly the uniform starts of before."""
    trajs = synthetic(1, T=107)  # 107 frames, windows of 7: 101 starts
    n = 101
    plain, early = WindowSampler(trajs, 5), WindowSampler(trajs, 5, early_frames=5,
                                                          early_weight=10.0)
    a, b = np.random.default_rng(3), np.random.default_rng(3)
    assert [plain.draw_start(a, 0) for _ in range(50)] == \
        [int(b.integers(0, n)) for _ in range(50)]
    rng = np.random.default_rng(0)
    starts = np.array([early.draw_start(rng, 0) for _ in range(40000)])
    assert starts.min() == 0 and starts.max() == n - 1
    want = 5 * 10 / (5 * 10 + n - 5)
    assert abs(np.mean(starts < 5) - want) < 0.01
    counts = np.bincount(starts, minlength=n)
    assert abs(counts[:5].mean() / counts[5:].mean() - 10.0) < 1.0  # each early start 10x
    # K beyond the trajectory: every start early, so uniform again
    short = WindowSampler(trajs, 5, early_frames=500, early_weight=3.0)
    s = np.array([short.draw_start(rng, 0) for _ in range(20000)])
    assert abs(np.bincount(s, minlength=n).std() / (20000 / n) - 0.1) < 0.05
    for bad in (dict(early_frames=-1), dict(early_weight=0.0), dict(early_weight=np.inf),
                dict(early_frames=2.5)):
        with pytest.raises(ValueError, match="early windows"):
            WindowSampler(trajs, 5, **bad)


def kicked(T=60, frame=30, kick=1e-3, n_kin=2):
    """A 16-node block in free fall (frame units) whose node 0 gets an extra velocity
    ``kick`` at ``frame`` (its acceleration deviates at that frame alone), and ``n_kin``
    kinematic nodes that jump about (to be ignored)."""
    from diffgns.trajectory import KINEMATIC

    t = np.arange(T)[:, None, None]
    g = np.stack(np.meshgrid(np.arange(4), np.arange(4), indexing="ij"), -1).reshape(-1, 2)
    pos = 0.3 + 0.02 * g[None] + np.array([1e-3, 0.0]) * t + 0.5 * np.array([0, -2e-4]) * t**2
    pos[frame + 1:, 0, 0] += kick * (np.arange(T - frame - 1) + 1)
    junk = np.random.default_rng(0).uniform(0, 0.8, (T, n_kin, 2))
    pos = np.concatenate([pos, junk], 1)
    ptype = np.array([SAND] * 16 + [KINEMATIC] * n_kin, np.int32)
    return Trajectory(positions=jnp.asarray(pos), velocities=jnp.zeros_like(jnp.asarray(pos)),
                      particle_type=jnp.asarray(ptype), material=jnp.full(16 + n_kin, 0.5),
                      bounds=BOUNDS)


def test_window_activity_is_zero_in_free_flight_and_measures_a_kick_at_its_target_frames():
    """One node of 16 kicked at frame f: its acceleration deviates by k there, so the frame's
    RMS deviation from the mean is k sqrt(15)/16 (analytic); a window is active exactly when
    one of its target frames s + C .. s + C + unroll is f; kinematic nodes never count."""
    from diffgns.graph.data import window_activity

    T, f, k, C = 60, 30, 1e-3, 5
    t = kicked(T, f, k)
    for unroll in (0, 2):
        L = C + 2 + unroll
        act = window_activity(t.positions, t.particle_type, C, L)
        assert act.shape == (T - L + 1,)
        active = {s for s in range(T - L + 1) if s + C <= f <= s + C + unroll}
        want = np.array([k * np.sqrt(15) / 16 if s in active else 0.0
                         for s in range(T - L + 1)])
        np.testing.assert_allclose(act, want, atol=1e-3 * k)  # float32 positions
    # only kinematic nodes: no activity, and no warning from an empty mean
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        still = window_activity(t.positions, np.full(18, 3), C, C + 2)
    assert still.shape == (T - C - 1,) and not still.any()


def test_active_windows_draw_starts_in_proportion_to_one_plus_weight_times_activity():
    """With weight W the kicked window (activity A, mean activity A / n over n starts) is
    drawn with probability (1 + W n) / (n + W n) of all starts; W = 0 draws the starts
    exactly as before; negative or infinite weights are refused."""
    T, f, C = 60, 30, 5
    trajs = [kicked(T, f)]
    n = T - (C + 2) + 1
    plain, active = WindowSampler(trajs, C), WindowSampler(trajs, C, active_weight=4.0)
    a, b = np.random.default_rng(5), np.random.default_rng(5)
    assert [WindowSampler(trajs, C, active_weight=0.0).draw_start(a, 0)
            for _ in range(50)] == [plain.draw_start(b, 0) for _ in range(50)]
    rng = np.random.default_rng(1)
    starts = np.array([active.draw_start(rng, 0) for _ in range(40000)])
    want = (1 + 4.0 * n) / (n + 4.0 * n)
    assert abs(np.mean(starts == f - C) - want) < 0.01
    assert starts.min() >= 0 and starts.max() == n - 1
    for bad in (-1.0, np.inf, np.nan):
        with pytest.raises(ValueError, match="active windows"):
            WindowSampler(trajs, C, active_weight=bad)


def test_early_windows_option_is_parsed_and_rejected_with_a_message():
    from diffgns.cli.train import _early_windows
    from diffgns.errors import InputError

    assert _early_windows("5:4") == (5, 4.0) and _early_windows(None) is None
    for bad in ("5", "0:2", "5:0", "a:b", "5:inf"):
        with pytest.raises(InputError, match="--early-windows"):
            _early_windows(bad)


def test_an_interrupted_run_writes_the_model_of_its_checkpoint_beside_it(tmp_path,
                                                                         monkeypatch):
    """SIGTERM part-way: the checkpoint and, to evaluate the run part-way, its model as
    ``model_partial`` (never ``model``: a staged script takes ``model`` for a finished
    stage); the same command then resumes to the end and writes ``model``."""
    import os
    import signal

    import diffgns.graph.train_loop as tl
    from diffgns.graph.fit import TrainingInterrupted

    run = _small_run(tmp_path, steps_per_call=1)
    real = tl.evaluate

    def stop_at_first_validation(*a, **k):  # the signal arrives during step 4's validation
        os.kill(os.getpid(), signal.SIGTERM)
        return real(*a, **k)

    monkeypatch.setattr(tl, "evaluate", stop_at_first_validation)
    with pytest.raises(TrainingInterrupted):
        run("b", 8)
    monkeypatch.setattr(tl, "evaluate", real)
    assert not (tmp_path / "b" / "model").exists()
    g, p, info = tl.load_model(tmp_path / "b" / "model_partial")
    assert info["partial"] is True and info["steps"] == 5  # stopped after the next step
    _, at5 = run("a", 5)
    for a, b in zip(jax.tree.leaves(at5), jax.tree.leaves(p)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    run("b", 8)
    assert tl.load_model(tmp_path / "b" / "model")[2]["steps"] == 8
