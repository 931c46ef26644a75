"""Message network training (loss falls, exact resume, save/load) and message read-out."""
import jax
import numpy as np
import pytest

from diffgns.graph.training import TrainConfig
from diffgns.interpret import message_net, messages, nbody_data
from diffgns.interpret.nbody import NBodyConfig

SMALL = message_net.MessageNetConfig(msg_dim=8, hidden=32, layers=2)


@pytest.fixture(scope="module")
def samples(tmp_path_factory):
    path = tmp_path_factory.mktemp("nb") / "spring.h5"
    nbody_data.generate(path, NBodyConfig(), 3, 60, progress=False)
    return nbody_data.edge_samples(*nbody_data.load(path))


def _tcfg(steps):
    return TrainConfig(steps=steps, batch_size=8, lr=3e-3, lr_final=1e-4, lr_decay_steps=400,
                       log_every=50, checkpoint_every=50)


def _leaves(p):
    return jax.tree_util.tree_leaves(p)


def test_training_reduces_loss_and_resumes_exactly(samples, tmp_path):
    _, _, p_full = message_net.train(samples, tmp_path / "a", SMALL, _tcfg(400), progress=False)
    message_net.train(samples, tmp_path / "b", SMALL, _tcfg(200), progress=False)
    _, _, p_res = message_net.train(samples, tmp_path / "b", SMALL, _tcfg(400), progress=False)
    for a, b in zip(_leaves(p_full), _leaves(p_res)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    log = np.genfromtxt(tmp_path / "a" / "train_log.csv", delimiter=",", names=True)
    assert log["fit"][-2:].mean() < 0.5 * log["fit"][0]  # 1.0 = the all-zero prediction
    net, norm, params, info = message_net.load(tmp_path / "a" / "model")
    assert info["steps"] == 400
    acc1, msg1 = message_net.forward(net, norm, params, samples["edges"][:4],
                                     samples["node"][:4], samples["receivers"])
    acc2, _ = message_net.forward(net, norm, p_full, samples["edges"][:4],
                                  samples["node"][:4], samples["receivers"])
    assert acc1.shape == (4, 10, 2) and msg1.shape == (4, 90, 8)
    np.testing.assert_allclose(np.asarray(acc1), np.asarray(acc2), rtol=1e-6)


def test_invalid_loss_rejected():
    with pytest.raises(ValueError, match="loss"):
        message_net.MessageNetConfig(loss="huber")


def test_premise_metrics_on_synthetic_messages():
    rng = np.random.default_rng(0)
    F = rng.normal(size=(5000, 2))
    A = np.array([[2.0, -1.0], [0.5, 3.0]])
    msgs = np.concatenate([F @ A.T + 0.3, 1e-3 * rng.normal(size=(5000, 4))], axis=1)
    order, std = messages.rank_components(msgs)
    assert set(order[:2]) == {0, 1} and std[1] > 100 * std[2]
    assert messages.linear_r2(msgs[:, 0], F) > 0.9999
    assert messages.linear_r2(msgs[:, 3], F) < 0.01
    W = messages.force_calibration(msgs[:, :2], F)
    # radial projection of the recovered force: features (dx, dy, d)
    dx = rng.normal(size=(5000, 2))
    feats = np.concatenate([dx, np.linalg.norm(dx, axis=1, keepdims=True)], axis=1)
    expect = np.sum(F * dx, axis=1) / feats[:, 2]
    np.testing.assert_allclose(messages.radial_force(msgs[:, :2], W, feats), expect, atol=1e-6)


def test_message_stats_fit_the_samples_and_round_trip(samples):
    st = message_net.MessageStats.fit(samples)
    e = samples["edges"].reshape(-1, samples["edges"].shape[-1]).astype(np.float64)
    np.testing.assert_allclose(st.edge.mean, e.mean(0), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(st.edge.std, np.maximum(e.std(0), 1e-8), rtol=1e-5)
    assert float(st.acceleration.mean) == 0.0  # a pure scale
    assert float(st.acceleration.std) == pytest.approx(float(np.std(samples["acc"])), rel=1e-5)
    back = message_net.MessageStats.from_dict(st.to_dict())
    for a, b in zip(jax.tree_util.tree_leaves(st), jax.tree_util.tree_leaves(back)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("name", ["message_net_spring", "message_net_spring_l1",
                                  "message_net_inverse_square",
                                  "message_net_inverse_square_l1"])
def test_shipped_message_nets_load_with_their_normaliser(name):
    import json

    from diffgns.models import model_dir

    folder = model_dir(name)
    net, norm, params, _ = message_net.load(folder)
    saved = json.loads((folder / "model.json").read_text())["normaliser"]
    for k, v in norm.to_dict().items():
        np.testing.assert_allclose(v, saved[k], rtol=1e-6)
    # the loaded network runs on its own feature widths
    E, N = len(saved["edge_mean"]), len(saved["node_mean"])
    acc, msg = message_net.forward(net, norm, params, np.ones((1, 3, E), np.float32),
                                   np.ones((1, 2, N), np.float32), np.array([0, 1, 1]))
    assert acc.shape == (1, 2, 2) and msg.shape == (1, 3, net.cfg.msg_dim)
    assert np.isfinite(np.asarray(acc)).all()
