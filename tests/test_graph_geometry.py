"""Walls and obstacles as inputs of the particle GNS (diffgns.graph.geometry): one compiled
step serves every box; a window's own walls reach the loss; a padded obstacle is no
obstacle; obstacles survive the dataset round trip; a model that lists its training boxes
runs in a longer one."""
import json

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns.graph.data import WindowSampler, coarse_grain
from diffgns.graph.features import ParticleStats
from diffgns.graph.geometry import PARKED, Geometry, obstacle_array, walls_array
from diffgns.graph.gns import GNS, GNSConfig
from diffgns.graph.support import UnsupportedSceneError, check_scene
from diffgns.graph.training import window_loss
from diffgns.io.dataset import DatasetWriter, iter_dataset
from diffgns.models import model_path
from diffgns.scene import Body, BoxObstacle, Rectangle, Sand, Scene, Wall, Walls
from diffgns.trajectory import SAND, Trajectory

BOX = ((0.0, 1.0), (0.0, 0.5))
R = 0.05


def _gns(use_obstacles=False, bounds=BOX):
    cfg = GNSConfig(bounds=bounds, radius=R, latent=16, mp_steps=2, mlp_layers=1,
                    use_obstacles=use_obstacles)
    # frame-unit statistics of a slow granular flow: an untrained network's outputs stay
    # ~1e-4 m/frame^2, so nothing reaches a wall and no clamp hides a difference
    stats = dict(vel_mean=[0.0, 0.0], vel_std=[2e-3, 2e-3], acc_mean=[0.0, 0.0],
                 acc_std=[1e-4, 1e-4])
    return GNS(cfg, ParticleStats.from_metadata(stats, 0.0))


def _history(x0=0.05, n=24, seed=0):
    """(n, 6, 2) a block near the left wall and the floor, moving right and down."""
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(np.arange(6), np.arange(4), indexing="ij"), -1).reshape(-1, 2)
    x = np.array([x0, 0.02]) + 0.02 * g[:n] + rng.uniform(0, 2e-3, (n, 2))
    t = np.arange(6)[None, :, None]
    return jnp.asarray(x[:, None] + np.array([2e-3, -1e-3]) * t, jnp.float32)


def _params(gns, h):
    return gns.init_network(jax.random.PRNGKey(0), (h, jnp.full(h.shape[0], SAND, jnp.int32),
                                                    jnp.full(h.shape[0], 0.5)))


def _rollout(gns, params, h, geometry, n=6):
    from diffgns import rollout
    from diffgns.graph.gns import GNSParams

    state = gns.init(h, jnp.full(h.shape[0], SAND, jnp.int32), geometry=geometry)
    frames, _ = rollout(gns, GNSParams(params, jnp.float32(0.5)), state, n)
    return np.asarray(frames.positions)


def test_geometry_arrays_validate_and_pad():
    assert walls_array(BOX).shape == (2, 2)
    with pytest.raises(ValueError, match="min < max"):
        walls_array(((0.0, 1.0), (0.5, 0.5)))
    obs = obstacle_array([(0.2, 0.0, 0.3, 0.1)], pad_to=3)
    assert obs.shape == (3, 4) and np.array_equal(obs[1], PARKED)
    with pytest.raises(ValueError, match="x0 < x1"):
        obstacle_array([(0.3, 0.0, 0.2, 0.1)])


def test_default_geometry_is_the_config_box_to_round_off():
    """A state's geometry (traced walls) gives what the config's static box gave, to float32
    round-off (XLA folds the static walls into constants, so the rounding may differ)."""
    gns = _gns()
    h = _history()
    params = _params(gns, h)
    ptype, mat = jnp.full(h.shape[0], SAND, jnp.int32), jnp.full(h.shape[0], 0.5)
    nb = gns.allocate(h[:, -1])
    f = jax.jit(lambda g: gns.advance(params, h, ptype, mat, nb, None, g)[0])
    np.testing.assert_allclose(np.asarray(f(None)), np.asarray(f(gns.geometry())), rtol=0,
                               atol=1e-6)


def test_walls_are_an_input_one_program_serves_every_box():
    """Moving the right wall next to the block changes the prediction (the wall is seen) and
    runs the same compiled step; a wall farther than R changes nothing."""
    gns = _gns()
    h = _history()
    params = _params(gns, h)
    ptype, mat = jnp.full(h.shape[0], SAND, jnp.int32), jnp.full(h.shape[0], 0.5)
    edges = _edges(gns, h)
    f = jax.jit(lambda g: gns.acceleration(params, h, ptype, mat, *edges, g))
    base = np.asarray(f(gns.geometry()))
    xmax = float(h[:, -1, 0].max())
    far = np.asarray(f(gns.geometry(bounds=((0.0, xmax + 2 * R), (0.0, 0.5)))))
    near = np.asarray(f(gns.geometry(bounds=((0.0, xmax + 0.3 * R), (0.0, 0.5)))))
    assert f._cache_size() == 1
    assert np.array_equal(base, far)
    assert np.abs(near - base).max() > 1e-3 * np.abs(base).max() > 0


def test_longer_box_rollout_equals_the_training_box_one():
    """for_box: the same network in a box twice as long gives the same rollout while the
    flow is farther than R from the moved wall (edges may come in another order: round-off)."""
    gns = _gns()
    h = _history()
    params = _params(gns, h)
    long = gns.for_box(((0.0, 2.0), (0.0, 0.5)))
    assert long.config.bounds == ((0.0, 2.0), (0.0, 0.5)) and gns.for_box(BOX) is gns
    a = _rollout(gns, params, h, None)
    b = _rollout(long, params, h, None)
    assert np.abs(a[-1] - a[0]).max() > 1e-3  # the block moved
    np.testing.assert_allclose(a, b, atol=1e-6)
    with pytest.raises(ValueError, match=r"gns.for_box\(bounds\)"):
        gns.init(h, jnp.full(h.shape[0], SAND, jnp.int32),
                 geometry=gns.geometry(bounds=((0.0, 2.0), (0.0, 0.5))))


def test_window_loss_uses_each_windows_own_walls():
    """In a batch of windows from two boxes, each window's loss is the loss of a GNS built
    for its box: the walls reach the loss per window."""
    big = _gns(bounds=((0.0, 1.0), (0.0, 0.5)))
    small = big.for_box(((0.0, 0.18), (0.0, 0.5)))  # right wall within R of the block
    w = jnp.swapaxes(_history(), 0, 1)  # (6, n, 2): history 5 ... use L = 7 below
    w = jnp.concatenate([w, w[-1:] + (w[-1:] - w[-2:-1])])
    ptype, mat = jnp.full(w.shape[1], SAND, jnp.int32), jnp.full(w.shape[1], 0.5)
    params = _params(big, _history())
    nb = big.allocate(w[5])
    key = jax.random.PRNGKey(1)
    loss = lambda g, geo: float(window_loss(g, params, w, ptype, mat, nb, key, 0, 0.0, geo)[0])
    assert loss(big, big.geometry(bounds=small.config.bounds)) == pytest.approx(
        loss(small, None), rel=1e-6)
    assert loss(big, None) != pytest.approx(loss(small, None), rel=1e-4)


def test_sampler_batches_carry_walls_and_padded_obstacles():
    x = np.zeros((8, 4, 2), np.float32) + 0.1
    def traj(bounds, obstacles):
        return Trajectory(positions=x, velocities=x, particle_type=np.full(4, SAND),
                          material=np.zeros(4), bounds=bounds, obstacles=obstacles)
    trajs = [traj(BOX, ()), traj(((0.0, 0.6), (0.0, 0.5)),
                                 ((0.3, 0.0, 0.35, 0.1), (0.4, 0.0, 0.45, 0.05)))]
    s = WindowSampler(trajs, history=5)
    b = s.sample(np.random.default_rng(0), 16)
    assert b["walls"].shape == (16, 2, 2) and b["obstacles"].shape == (16, 2, 4)
    assert b["walls"].dtype == np.float32
    right = b["walls"][:, 0, 1].astype(float)
    assert set(np.round(right, 6).tolist()) == {1.0, 0.6}  # both boxes drawn
    none, two = b["obstacles"][right == 1.0], b["obstacles"][right == 0.6]
    np.testing.assert_allclose(none, np.broadcast_to(np.asarray(PARKED, np.float32),
                                                     none.shape))  # no obstacle: both parked
    np.testing.assert_allclose(two, np.broadcast_to(np.asarray(  # its two, in order
        [[0.3, 0.0, 0.35, 0.1], [0.4, 0.0, 0.45, 0.05]], np.float32), two.shape), rtol=1e-6)


def test_padding_obstacle_is_no_obstacle_and_a_near_one_is_seen():
    gns = _gns(use_obstacles=True)
    h = _history()
    params = _params(gns, h)
    ptype, mat = jnp.full(h.shape[0], SAND, jnp.int32), jnp.full(h.shape[0], 0.5)
    edges = _edges(gns, h)
    f = jax.jit(lambda g: gns.acceleration(params, h, ptype, mat, *edges, g))
    none = np.asarray(gns.acceleration(params, h, ptype, mat, *edges))
    padded = np.asarray(f(gns.geometry([], pad_to=2)))
    xmax = float(h[:, -1, 0].max())
    near = np.asarray(f(gns.geometry([(xmax + 0.2 * R, 0.0, xmax + R, 0.1)], pad_to=2)))
    np.testing.assert_allclose(none, padded, rtol=1e-5)  # static vs traced: round-off
    assert np.abs(near - padded).max() > 1e-3 * np.abs(padded).max() > 0
    nf, _ = gns.features(h, mat, *edges)
    nf_padded, _ = gns.features(h, mat, *edges, gns.geometry([], pad_to=2))
    assert nf.shape[1] == 2 * 5 + 4 + 3 + 1
    np.testing.assert_array_equal(nf, nf_padded)  # the obstacle columns exactly (1, 0, 0)


def _edges(gns, h):
    from diffgns.graph.neighbors import edges

    return edges(gns.allocate(h[:, -1]), h.shape[0])


def test_obstacles_survive_the_dataset_round_trip_and_coarse_graining(tmp_path):
    x = np.random.default_rng(0).uniform(0.1, 0.2, (3, 16, 2)).astype(np.float32)
    obs = ((0.3, 0.0, 0.35, 0.1),)
    t = Trajectory(positions=x, velocities=x, particle_type=np.full(16, SAND),
                   material=np.full(16, 0.5), bounds=BOX, obstacles=obs)
    w = DatasetWriter(tmp_path / "d.h5")
    w.append(t)
    w.finalize(connectivity_radius=R)
    back = list(iter_dataset(tmp_path / "d.h5"))[0]
    assert back.obstacles == obs and back.bounds == BOX
    assert coarse_grain(back, 4).obstacles == obs


def _scene(domain):
    body = Body(Rectangle(0.05, 0.0, 0.15, 0.1), Sand(friction_angle=30.0),
                particles_per_cell=4, name="mass")
    return Scene(domain=domain, dx=0.1 / 16, bodies=(body,),
                 walls=Walls(bottom=Wall("friction", 0.5)), frame_dt=2.5e-3,
                 obstacles=(BoxObstacle(0.5, 0.0, 0.55, 0.05),))


def test_a_model_listing_its_training_boxes_runs_in_a_longer_box():
    info = json.loads((model_path("gns_cg16_pfn") / "config.json").read_text())
    longer = _scene(((0.0, 1.4), (0.0, 0.35)))
    with pytest.raises(UnsupportedSceneError, match="is not the training box"):
        check_scene(longer, info)  # shipped models predate per-trajectory walls
    info["source"]["boxes"] = [[[0.0, 0.8], [0.0, 0.35]], [[0.0, 0.6], [0.0, 0.5]]]
    sup = check_scene(longer, info)
    assert any("outside the range of the training boxes" in w for w in sup.warnings)
    assert any("obstacle" in w for w in sup.warnings)
    inside = check_scene(_scene(((0.0, 0.7), (0.0, 0.4))), dict(info, gns=dict(
        info["gns"], use_obstacles=True), source=dict(info["source"], kind="granular")))
    assert inside.warnings == ()


def test_for_scene_gives_the_scene_box_and_obstacles():
    gns = _gns(bounds=((0.0, 0.8), (0.0, 0.35)))
    g, geo = gns.for_scene(_scene(((0.0, 1.4), (0.0, 0.35))))
    assert g.config.bounds == ((0.0, 1.4), (0.0, 0.35))
    np.testing.assert_allclose(np.asarray(geo.walls), [[0.0, 1.4], [0.0, 0.35]])
    np.testing.assert_allclose(np.asarray(geo.obstacles), [[0.5, 0.0, 0.55, 0.05]])
    assert isinstance(geo, Geometry)


@pytest.mark.slow  # 61 s in the full suite (2026-12-03, loaded machine)
def test_training_on_two_boxes_with_families_obstacles_and_padding(tmp_path, monkeypatch):
    """One run over trajectories of two box sizes, two families and obstacles: every window
    reaches the loss with its own walls and obstacles, node counts are padded to the
    multiple asked, the steps of a call share one node count, and the model folder records
    its training boxes (so it then supports both, graph.support)."""
    import diffgns.graph.train_loop as train_loop
    from diffgns.graph.fit import TrainConfig

    rng = np.random.default_rng(0)
    w = DatasetWriter(tmp_path / "g.h5")
    for i, (n, box, fam, obs) in enumerate([
            (10, ((0.0, 0.8), (0.0, 0.35)), "squares", ()),
            (12, ((0.0, 0.6), (0.0, 0.5)), "squares", ()),  # with the 10: one padded group
            (13, ((0.0, 0.6), (0.0, 0.5)), "obstacles", ((0.4, 0.0, 0.45, 0.05),)),
            (7, ((0.0, 0.8), (0.0, 0.35)), "squares", ())]):
        x0 = rng.uniform(0.1, 0.3, (n, 2))
        t = np.arange(12)[:, None, None]
        pos = (x0 + np.array([2e-3, -1e-3]) * t).astype(np.float32)
        w.write(f"{i:05d}", Trajectory(positions=pos, velocities=np.zeros_like(pos),
                                       particle_type=np.full(n, SAND), material=np.full(n, 0.5),
                                       bounds=box, obstacles=obs), attrs=dict(family=fam))
    w.finalize(connectivity_radius=R)
    seen = []
    real = train_loop.steps_with_reallocation

    def record(trainer, params, opt, batches, *a):
        seen.append([(b["positions"].shape[2],
                      tuple(np.round(b["walls"][:, 0, 1].astype(float), 3).tolist()),
                      b["obstacles"].shape) for b in batches])
        return real(trainer, params, opt, batches, *a)

    monkeypatch.setattr(train_loop, "steps_with_reallocation", record)
    tcfg = TrainConfig(steps=24, batch_size=2, lr=1e-3, lr_final=1e-4, lr_decay_steps=24,
                       log_every=12, checkpoint_every=12, steps_per_call=4)
    kw = dict(radius=R, latent=8, mp_steps=1, mlp_layers=1, noise_std=1e-4,
              use_obstacles=True)
    gns, params = train_loop.train([tmp_path / "g.h5"], tmp_path / "run", kw, tcfg,
                                   progress=False, pad_to=8)
    assert all(len({c[0] for c in call}) == 1 for call in seen)  # one node count per call
    assert {c[0] for call in seen for c in call} <= {8, 16}  # 7 -> 8; 10, 12, 13 -> 16
    assert all(c[2] == (2, 1, 4) for call in seen for c in call)  # obstacles padded to K = 1
    walls = {x for call in seen for c in call for x in c[1]}
    assert walls == {0.8, 0.6}  # both boxes reached the loss
    info = json.loads((tmp_path / "run" / "model" / "config.json").read_text())
    assert sorted(map(tuple, [tuple(map(tuple, b)) for b in info["source"]["boxes"]])) == [
        ((0.0, 0.6), (0.0, 0.5)), ((0.0, 0.8), (0.0, 0.35))]
    assert info["families"] == ["obstacles", "squares"] and info["gns"]["use_obstacles"]
    with h5py.File(tmp_path / "g.h5", "r") as f:  # the recorded range is the data's
        tan = np.concatenate([f[k]["material_property"][()] for k in f])
    assert info["source"]["friction_angle"] == pytest.approx(
        np.degrees(np.arctan([tan.min(), tan.max()])), abs=1e-5)
    assert gns.config.bounds == ((0.0, 0.8), (0.0, 0.5))  # the union: the cell list's extent
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(params))
    # the per-family held-out table of the benchmark script, on the same files: each case
    # rolled out in its own box with its obstacles
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import granular_heldout

    granular_heldout.main(["--model", str(tmp_path / "run" / "model"), "--data",
                           str(tmp_path / "g.h5"), "--out", str(tmp_path / "h.json")])
    out = json.loads((tmp_path / "h.json").read_text())
    assert set(out["table"]) == {"squares", "obstacles", "all"}
    assert out["table"]["squares"]["cases"] == 3 and out["table"]["all"]["cases"] == 4
    assert [r["family"] for r in out["rows"]] == ["squares", "squares", "obstacles", "squares"]
    assert all(r["finite"] and r["inside_domain"] for r in out["rows"])
    # one family only: the rows keep their case numbers in the file, the table its family
    granular_heldout.main(["--model", str(tmp_path / "run" / "model"), "--data",
                           str(tmp_path / "g.h5"), "--families", "obstacles", "--out",
                           str(tmp_path / "o.json")])
    one = json.loads((tmp_path / "o.json").read_text())
    assert [r["case"] for r in one["rows"]] == [2] and set(one["table"]) == {"obstacles", "all"}
    assert one["rows"][0]["final_position_error_rel_displacement"] == pytest.approx(
        out["rows"][2]["final_position_error_rel_displacement"], rel=1e-5)


def test_a_model_without_obstacle_inputs_starts_one_with_them(tmp_path):
    """Fine-tuning a model without obstacle inputs into one with them (the general GNS from
    a column model): the widened network's rollout next to an obstacle equals the original
    model's rollout, which ignores obstacles; its box may differ (walls are inputs)."""
    from diffgns.graph.train_loop import _initial_model, save_model, with_obstacle_inputs

    plain = _gns()
    h = _history()
    params = _params(plain, h)
    save_model(tmp_path / "plain", plain, params, {})
    wide_gns = _gns(use_obstacles=True, bounds=((0.0, 1.5), (0.0, 0.5)))
    gns2, wide = _initial_model(tmp_path / "plain", wide_gns)
    assert gns2.config.use_obstacles
    for u, v in zip(jax.tree.leaves(gns2.normalizer), jax.tree.leaves(plain.normalizer)):
        np.testing.assert_allclose(np.asarray(u), np.asarray(v))  # the model's normaliser
    obstacle = gns2.geometry([[0.12, 0.0, 0.2, 0.08]], bounds=BOX)
    assert obstacle.obstacles.shape == (1, 4)
    a = _rollout(plain, params, h, None)
    b = _rollout(gns2.for_box(BOX), wide, h, obstacle)
    np.testing.assert_allclose(b, a, atol=1e-6)
    assert np.abs(a[-1] - a[0]).max() > 1e-4  # it moved
    with pytest.raises(ValueError, match="already has obstacle inputs"):
        with_obstacle_inputs(wide, gns2.config)
