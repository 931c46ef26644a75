"""MeshGraphNet: edges from cells, padding, boundary handling, rollout, training and resume."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns.graph.features import Normalizer
from diffgns.interface import rollout, rollout_jit
from diffgns.mesh.meshnet import (
    FLUID,
    INFLOW,
    OUTFLOW,
    PAD,
    WALL,
    MeshNet,
    MeshNetConfig,
    MeshStats,
    mesh_edges,
    pad_mesh,
)


def _grid_mesh(nx=6, ny=4):
    """Structured triangulation of [0, 1] x [0, 0.5]: (pos, cells, node_type)."""
    xs, ys = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 0.5, ny), indexing="ij")
    pos = np.stack([xs.ravel(), ys.ravel()], 1)
    idx = np.arange(nx * ny).reshape(nx, ny)
    cells = []
    for i in range(nx - 1):
        for j in range(ny - 1):
            a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
            cells += [[a, b, c], [a, c, d]]
    types = np.full(nx * ny, FLUID)
    types[idx[:, 0]] = types[idx[:, -1]] = WALL
    types[idx[0]] = INFLOW
    types[idx[-1]] = OUTFLOW
    return pos, np.array(cells), types


def test_mesh_edges_both_directions_no_duplicates():
    cells = np.array([[0, 1, 2], [1, 3, 2]])
    s, r = mesh_edges(cells)
    pairs = set(zip(s.tolist(), r.tolist()))
    assert len(pairs) == len(s) == 10  # 5 distinct sides, both ways
    assert all((b, a) in pairs for a, b in pairs)
    with pytest.raises(ValueError, match="cells"):
        mesh_edges(np.zeros((3, 4), int))


def test_padding_masks_and_rejects_overflow():
    pos, cells, types = _grid_mesh()
    g = pad_mesh(pos, cells, types, 32, 128, NU)
    n_edges = len(mesh_edges(cells)[0])
    assert int(g.edge_mask.sum()) == n_edges
    assert np.all(np.asarray(g.node_type)[len(pos):] == PAD)
    assert not np.any(np.asarray(g.predicted)[len(pos):])
    with pytest.raises(ValueError, match="exceeds"):
        pad_mesh(pos, cells, types, 10, 128)


NU = 1e-3  # kinematic viscosity of the test flows, m^2/s


def _model(latent=16, steps=2, viscosity_feature=True):
    stats = MeshStats(Normalizer(jnp.zeros(2), jnp.ones(2)),
                      Normalizer(jnp.zeros(3), jnp.full(3, 0.1)), 0.2,
                      Normalizer(jnp.asarray(np.log(NU)), jnp.asarray(0.5)))
    cfg = MeshNetConfig(latent=latent, mp_steps=steps, viscosity_feature=viscosity_feature)
    return MeshNet(cfg, stats)


def test_rollout_holds_boundary_nodes_and_jit_matches_eager():
    pos, cells, types = _grid_mesh()
    g = pad_mesh(pos, cells, types, 32, 128, NU)
    model = _model()
    params = model.init_network(jax.random.PRNGKey(0), g)
    v0 = jnp.asarray(np.random.default_rng(0).normal(size=(32, 2)), jnp.float32)
    frames, _ = rollout_jit(model, params, model.init(g, v0), n_frames=5)
    vs, ps = frames.velocity, frames.pressure
    with jax.disable_jit():
        vs_e = rollout(model, params, model.init(g, v0), 5)[0].velocity
    assert vs.shape == (6, 32, 2) and ps.shape == (6, 32)
    np.testing.assert_allclose(np.asarray(vs), np.asarray(vs_e), rtol=1e-4, atol=1e-5)
    held = ~np.asarray(g.predicted)
    np.testing.assert_array_equal(np.asarray(vs)[:, held], np.broadcast_to(
        np.asarray(v0)[held], (6, held.sum(), 2)))
    assert np.any(np.asarray(vs)[-1, ~held] != np.asarray(v0)[~held])


def test_padding_does_not_change_predictions():
    pos, cells, types = _grid_mesh()
    model = _model()
    g1, g2 = pad_mesh(pos, cells, types, 32, 128, NU), pad_mesh(pos, cells, types, 48, 200, NU)
    params = model.init_network(jax.random.PRNGKey(1), g1)
    v = np.random.default_rng(1).normal(size=(len(pos), 2)).astype(np.float32)
    pad = lambda n: jnp.asarray(np.concatenate([v, np.zeros((n - len(pos), 2), np.float32)]))
    a, pa = model.predict(params, g1, pad(32))
    b, pb = model.predict(params, g2, pad(48))
    np.testing.assert_allclose(np.asarray(a)[: len(pos)], np.asarray(b)[: len(pos)], atol=1e-5)
    np.testing.assert_allclose(np.asarray(pa)[: len(pos)], np.asarray(pb)[: len(pos)],
                               atol=1e-5)


def test_invalid_config_rejected():
    with pytest.raises(ValueError, match="MeshNetConfig"):
        MeshNetConfig(latent=0)


def _synthetic_dataset(path, n_traj=2, frames=12):
    """A travelling wave on the grid mesh, written with the CFD dataset writer."""
    from diffgns.mesh.dataset import CylinderDatasetWriter

    pos, cells, types = _grid_mesh()
    with CylinderDatasetWriter(path) as w:
        for k in range(n_traj):
            t = np.arange(frames)[:, None] * 0.01
            phase = 2 * np.pi * (pos[None, :, 0] - (1 + 0.2 * k) * t)
            vel = np.stack([1 + 0.1 * np.sin(phase), 0.1 * np.cos(phase)], -1)
            vel[:, types == WALL] = 0.0
            arrays = dict(mesh_pos=pos, cells=cells.astype(np.int32),
                          node_type=types.astype(np.int32),
                          on_cylinder=np.zeros(len(pos), bool), velocity=vel.astype(np.float32),
                          pressure=np.sin(phase).astype(np.float32), time=t[:, 0],
                          cd=np.zeros(frames), cl=np.zeros(frames))
            w.write(f"{k:05d}", arrays, dict(frame_dt=0.01, reynolds=100.0 * (1 + k), u_max=1.5,
                                              nu=NU * (1 + k), radius=0.05,
                                              center=[0.2, 0.2]))
        w.finalize()


@pytest.mark.slow  # 44 s in the full suite beside a 2-process CFD job (2026-12-03)
def test_training_on_a_dataset_learns_and_resumes_exactly(tmp_path):
    from diffgns.graph.training import TrainConfig
    from diffgns.mesh import train as mesh_train

    _synthetic_dataset(tmp_path / "d.h5")
    cfg = MeshNetConfig(latent=16, mp_steps=2, noise_std=0.002)
    tc = lambda n: TrainConfig(steps=n, batch_size=2, lr=3e-3, lr_final=1e-4,
                               lr_decay_steps=120, log_every=20, checkpoint_every=20)
    _, p_full = mesh_train.train(tmp_path / "d.h5", tmp_path / "a", cfg, tc(120),
                                 progress=False)
    mesh_train.train(tmp_path / "d.h5", tmp_path / "b", cfg, tc(60), progress=False)
    _, p_res = mesh_train.train(tmp_path / "d.h5", tmp_path / "b", cfg, tc(120),
                                progress=False)
    for a, b in zip(jax.tree_util.tree_leaves(p_full), jax.tree_util.tree_leaves(p_res)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    log = np.genfromtxt(tmp_path / "a" / "train_log.csv", delimiter=",", names=True)
    assert log["loss"][-1] < 0.5 * log["loss"][0]
    model, params, info = mesh_train.load_model(tmp_path / "a" / "model")
    assert info["kind"] == "meshgraphnet" and info["steps"] == 120
    g = pad_mesh(*_grid_mesh(), *info["padding"], viscosity=NU)
    v = jnp.zeros((info["padding"][0], 2))
    np.testing.assert_allclose(np.asarray(model.predict(params, g, v)[0]),
                               np.asarray(model.predict(p_full, g, v)[0]), rtol=1e-6)


def test_vorticity_of_solid_rotation_and_shear():
    from diffgns.mesh.figures import vorticity

    pos, cells, _ = _grid_mesh()
    omega = 3.0
    rot = np.stack([-omega * pos[:, 1], omega * pos[:, 0]], -1)  # solid rotation: 2 omega
    np.testing.assert_allclose(vorticity(pos, cells, rot), 2 * omega, rtol=1e-10)
    shear = np.stack([5.0 * pos[:, 1], 0 * pos[:, 0]], -1)      # u = 5 y: -5
    np.testing.assert_allclose(vorticity(pos, cells, shear[None]), -5.0, rtol=1e-10)


def test_push_forward_unrolls_the_model_without_gradient(tmp_path):
    from diffgns.graph.training import TrainConfig
    from diffgns.mesh import train as mesh_train

    pos, cells, types = _grid_mesh()
    g = pad_mesh(pos, cells, types, 32, 128, NU)
    model = _model()
    params = model.init_network(jax.random.PRNGKey(0), g)
    v = jnp.asarray(np.random.default_rng(2).normal(size=(32, 2)), jnp.float32)
    np.testing.assert_array_equal(np.asarray(mesh_train.pushed(model, params, g, v, 0)),
                                  np.asarray(v))
    two = model.advance(params, g, model.advance(params, g, v, v)[0], v)[0]
    np.testing.assert_allclose(np.asarray(mesh_train.pushed(model, params, g, v, 2)),
                               np.asarray(two), rtol=1e-5, atol=1e-6)
    # the unrolled frames carry no gradient: d/dparams of the pushed state is zero
    grads = jax.grad(lambda p: mesh_train.pushed(model, p, g, v, 2).sum())(params)
    assert all(np.all(np.asarray(x) == 0) for x in jax.tree_util.tree_leaves(grads))

    _synthetic_dataset(tmp_path / "d.h5")
    cfg = MeshNetConfig(latent=16, mp_steps=2, noise_std=0.002)
    tc = TrainConfig(steps=40, batch_size=2, lr=3e-3, lr_final=1e-4, push_forward=3,
                     log_every=20, checkpoint_every=20)
    mesh_train.train(tmp_path / "d.h5", tmp_path / "a", cfg, tc, progress=False)
    log = np.genfromtxt(tmp_path / "a" / "train_log.csv", delimiter=",", names=True)
    assert np.all(np.isfinite(log["loss"]))
    with pytest.raises(ValueError, match="push_forward"):
        mesh_train.train(tmp_path / "d.h5", tmp_path / "b", cfg,
                         dataclasses.replace(tc, push_forward=11), progress=False)


def test_viscosity_is_an_input_and_a_graph_without_it_is_rejected():
    pos, cells, types = _grid_mesh()
    model = _model()
    g = pad_mesh(pos, cells, types, 32, 128, NU)
    params = model.init_network(jax.random.PRNGKey(3), g)
    v = jnp.asarray(np.random.default_rng(3).normal(size=(32, 2)), jnp.float32)
    thicker = pad_mesh(pos, cells, types, 32, 128, 3 * NU)
    a, b = model.predict(params, g, v)[0], model.predict(params, thicker, v)[0]
    assert np.max(np.abs(np.asarray(a) - np.asarray(b))) > 1e-4
    model.check_graph(g)
    with pytest.raises(ValueError, match="viscosity"):
        model.check_graph(pad_mesh(pos, cells, types, 32, 128))
    with pytest.raises(ValueError, match="positive kinematic viscosity"):
        pad_mesh(pos, cells, types, 32, 128, -1e-3)
    with pytest.raises(ValueError, match="MeshStats.viscosity"):
        MeshNet(MeshNetConfig(latent=8, mp_steps=1), dataclasses.replace(model.stats,
                                                                         viscosity=None))


@pytest.mark.slow  # 35 s in the full suite (2026-12-03, loaded machine)
def test_fine_tuning_adds_the_viscosity_input_without_changing_the_start(tmp_path):
    """A model trained without the viscosity input, grown to read it: the new input's
    weights start at zero, so the grown network predicts exactly what the old one did; a
    configuration that differs otherwise is rejected; old model.json files load."""
    import json

    from diffgns.graph.training import TrainConfig
    from diffgns.mesh import train as mesh_train

    _synthetic_dataset(tmp_path / "d.h5")
    old_cfg = MeshNetConfig(latent=16, mp_steps=2, noise_std=0.002, viscosity_feature=False)
    tc = TrainConfig(steps=20, batch_size=2, lr=3e-3, lr_final=1e-4, log_every=10,
                     checkpoint_every=10)
    mesh_train.train(tmp_path / "d.h5", tmp_path / "old", old_cfg, tc, progress=False)
    # a model.json written before the option existed has no viscosity_feature key
    meta = tmp_path / "old" / "model" / "model.json"
    info = json.loads(meta.read_text())
    del info["config"]["viscosity_feature"]
    meta.write_text(json.dumps(info))
    old, old_params, info = mesh_train.load_model(tmp_path / "old" / "model")
    assert old.config.viscosity_feature is False

    new_cfg = dataclasses.replace(old_cfg, viscosity_feature=True, noise_std=0.001)
    trajs = mesh_train.load_cylinder(tmp_path / "d.h5")
    new = MeshNet(new_cfg, dataclasses.replace(old.stats, viscosity=mesh_train.viscosity_stats(
        trajs)))
    graph = mesh_train.graph_of(trajs[1], tuple(info["padding"]))
    template = new.init_network(jax.random.PRNGKey(0), graph)
    params, stats = mesh_train.fine_tune_start(tmp_path / "old" / "model", new_cfg, template,
                                               new.stats)
    grown = MeshNet(new_cfg, stats)
    n = len(trajs[1]["mesh_pos"])
    v = jnp.asarray(np.pad(trajs[1]["velocity"][3], ((0, info["padding"][0] - n), (0, 0))))
    np.testing.assert_allclose(np.asarray(grown.normalized_output(params, graph, v)),
                               np.asarray(old.normalized_output(old_params, graph, v)),
                               rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="differs"):
        mesh_train.fine_tune_start(tmp_path / "old" / "model",
                                   dataclasses.replace(new_cfg, latent=8), template, new.stats)
    # and training from it runs and learns the new input
    tc2 = dataclasses.replace(tc, steps=20)
    _, p = mesh_train.train(tmp_path / "d.h5", tmp_path / "new", new_cfg, tc2, progress=False,
                            init_from=tmp_path / "old" / "model")
    assert np.any(np.asarray(p["params"]["node_encoder"]["hidden_0"]["kernel"])[2] != 0)


def test_teacher_forced_pressure_is_the_model_pressure_of_each_given_frame():
    """The evaluation's pressure-head check: one compiled map over frames equals predicting
    each frame's pressure from that frame's given velocity (not from the model's rollout),
    and a second call on the same mesh compiles nothing new."""
    from diffgns.mesh.evaluate import teacher_forced_pressure

    pos, cells, types = _grid_mesh()
    g = pad_mesh(pos, cells, types, 32, 128, NU)
    model = _model()
    params = model.init_network(jax.random.PRNGKey(2), g)
    v = np.random.default_rng(0).normal(size=(4, 32, 2)).astype(np.float32)
    got = teacher_forced_pressure(model, params, g, v)
    want = np.stack([np.asarray(model.predict(params, g, jnp.asarray(f))[1]) for f in v])
    assert got.shape == (4, 32)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    # frame 2's pressure comes from frame 2's velocity alone
    v2 = v.copy()
    v2[1] += 1.0
    again = teacher_forced_pressure(model, params, g, v2)
    np.testing.assert_array_equal(again[[0, 2, 3]], got[[0, 2, 3]])
    assert np.abs(again[1] - got[1]).max() > 1e-4
    from diffgns.mesh.evaluate import _pressures

    assert _pressures._cache_size() == 1  # one program for every call on this mesh


def test_average_of_meshgraphnets_is_the_elementwise_mean_and_refuses_other_normalisers(
        tmp_path):
    import dataclasses

    from diffgns.cli import main
    from diffgns.mesh.train import average_models, load_model, save_model

    model, pa, info = load_model("meshnet_sweep")
    pb = jax.tree.map(lambda x: x * 3.0 + 1.0, pa)
    save_model(tmp_path / "a", model, pa, info["padding"], {"frame_dt": info["frame_dt"]})
    noisier = MeshNet(dataclasses.replace(model.config, noise_std=0.005), model.stats,
                      model.frame_dt)
    save_model(tmp_path / "b", noisier, pb, info["padding"], {"frame_dt": info["frame_dt"]})
    assert main(["average", str(tmp_path / "a"), str(tmp_path / "b"),
                 "--out", str(tmp_path / "ab")]) == 0
    m, p, got = load_model(tmp_path / "ab")
    assert m.config == model.config and got["averaged_from"][1].endswith("b")
    assert got["frame_dt"] == info["frame_dt"]
    for x, a, b in zip(jax.tree.leaves(p), jax.tree.leaves(pa), jax.tree.leaves(pb)):
        np.testing.assert_allclose(np.asarray(x), (np.asarray(a) + np.asarray(b)) / 2,
                                   rtol=1e-6, atol=1e-6)
    other = MeshNet(model.config, model.stats.replace(edge_scale=1.0), model.frame_dt)
    save_model(tmp_path / "c", other, pa, info["padding"], {})
    with pytest.raises(ValueError, match="different normaliser"):
        average_models([tmp_path / "a", tmp_path / "c"], tmp_path / "x")
    assert main(["average", str(tmp_path / "a"), str(tmp_path / "c"),
                 "--out", str(tmp_path / "x")]) == 2  # a clear error, no traceback


def test_divergence_is_exact_for_linear_fields_and_its_loss_ignores_solenoidal_errors():
    """The least-squares divergence is exact for a linear field on every mesh node (boundary
    nodes included) and 0 on padding; it converges on a smooth field; the continuity loss is
    0 for a rotation (divergence-free) error and (2 h)^2 for a radial one, on the predicted
    nodes."""
    from diffgns.mesh.meshnet import divergence, divergence_loss

    pos, cells, types = _grid_mesh(nx=9, ny=7)
    g = pad_mesh(pos, cells, types, 80, 320, NU)
    x, y = g.mesh_pos[:, 0], g.mesh_pos[:, 1]
    real = np.asarray(g.node_type) != PAD
    lin = jnp.stack([2.0 * x - 0.7 * y + 0.3, 1.1 * x - 0.5 * y], -1)
    d = np.asarray(divergence(g, lin))
    np.testing.assert_allclose(d[real], 1.5, rtol=1e-5)
    assert np.all(d[~real] == 0.0)
    smooth = jnp.stack([jnp.sin(3 * x) * jnp.cos(2 * y), x * y**2], -1)
    exact = 3 * np.cos(3 * x) * np.cos(2 * y) + 2 * x * y
    inner = np.asarray(g.node_type) == FLUID
    d_s = np.asarray(divergence(g, smooth))[inner]
    assert np.isfinite(d_s).all() and np.max(np.abs(d_s - exact[inner])) < 0.1
    h = 0.05
    assert float(divergence_loss(g, jnp.stack([-y, x], -1), h)) == pytest.approx(0, abs=1e-9)
    assert float(divergence_loss(g, jnp.stack([x, y], -1), h)) == pytest.approx((2 * h) ** 2,
                                                                                  rel=1e-5)
    only_walls = jnp.where((g.node_type == WALL)[:, None], jnp.stack([x, y], -1), 0.0)
    assert float(divergence_loss(g, only_walls, h)) > 0  # felt by the fluid nodes next to them
