"""The particle GNS in 3D (issue 24): one dimension-generic code path, d = len(bounds).

3D neighbour lists against brute force, 3D features (wall and obstacle distances of known
points), translation invariance along the horizontal axes x and z, jit == eager and
checkpointed == plain rollouts, coarse-graining into 2 x 2 x 2 nodes, a small ``diffgns
train`` / ``diffgns rollout`` run on a 3D dataset, and the refusals (mixed dimensions, a 2D
model on 3D data and vice versa). The shipped 2D models give bit-identical outputs to those
recorded before the change (``tests/fixtures/gns_2d_golden.npz``, made with the 2D-only
code on this machine's CPU XLA; another XLA version or CPU may round differently).

The architecture is not rotation-equivariant (MLPs on Cartesian components), so no rotation
test: a rotated input gives a rotated output only after training on rotated data.
"""
from __future__ import annotations

import csv
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns.cli import main
from diffgns.graph.data import WindowSampler, coarse_grain, coarse_grain_map
from diffgns.graph.features import (
    Normalizer,
    ParticleStats,
    edge_features,
    n_node_features,
    node_features,
    obstacle_distances,
    wall_distances,
)
from diffgns.graph.geometry import Geometry, obstacle_array, parked
from diffgns.graph.gns import GNS, GNSConfig, GNSParams
from diffgns.graph.neighbors import (
    NeighborBuilder,
    brute_force_edges,
    did_overflow,
    edge_set,
    edges,
)
from diffgns.graph.sampling import pad_nodes
from diffgns.interface import rollout, rollout_jit, rollout_safe
from diffgns.io.dataset import DatasetWriter
from diffgns.trajectory import Trajectory

# Made once with the 2D-only graph code (before issue 24): the MPM of column_collapse(width
# 0.1, aspect ratio 1.25, 32.5 deg, 8 or 16 cells across, 0.8 x 0.35 m box), 12 frames; each
# model's coarse_grain(factor, frame_stride) of it, the first C + 1 node frames as history,
# rollout_safe over 20 frames, node_features with the two obstacles below; and the particles
# of frame 0 with their coarse_grain_map clusters for factors 4 and 16.
GOLDEN = Path(__file__).parent / "fixtures" / "gns_2d_golden.npz"
FAST = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
BOX3 = ((0.0, 0.2), (0.0, 0.1), (0.0, 0.2))
BOX2 = BOX3[:2]
C = 3
META3 = {"vel_mean": [0.0, -1e-4, 0.0], "vel_std": [1e-3, 1e-3, 1e-3],
         "acc_mean": [0.0, -2e-5, 0.0], "acc_std": [5e-5, 5e-5, 5e-5]}


# ------------------------------------------------------------------------------ helpers
def _synthetic(dim: int = 3, n_traj: int = 3, frames: int = 25, seed: int = 0
               ) -> list[Trajectory]:
    """Small lattices (4 x 3 (x 4) nodes, 1 cm apart) in :data:`BOX3` (or its x-y face)
    drifting with ``v' = 0.8 v + g`` per frame (g = 2e-4 m/frame^2 down): a learnable
    acceleration ``-0.2 v + g`` that keeps every node inside the box."""
    rng = np.random.default_rng(seed)
    axes = [np.arange(4), np.arange(3), np.arange(4)][:dim]
    lattice = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, dim) * 0.01
    centre = np.array([0.1, 0.06, 0.1])[:dim]
    g = np.zeros(dim)
    g[1] = -2e-4
    out = []
    for _ in range(n_traj):
        x = lattice - lattice.mean(0) + centre
        v = rng.normal(0, 1e-3, dim) + rng.normal(0, 2e-4, x.shape)
        xs = [x]
        for _ in range(frames - 1):
            v = 0.8 * v + g
            x = x + v
            xs.append(x)
        pos = np.asarray(xs, np.float32)
        vel = np.concatenate([np.zeros_like(pos[:1]), np.diff(pos, axis=0)]) / 2.5e-3
        n = pos.shape[1]
        out.append(Trajectory(positions=pos, velocities=vel.astype(np.float32),
                              particle_type=np.full(n, 6, np.int32),
                              material=np.full(n, 0.6, np.float32), frame_dt=2.5e-3,
                              bounds=BOX3[:dim]))
    return out


def _write(path: Path, trajs) -> Path:
    with DatasetWriter(path) as w:
        for t in trajs:
            w.append(t)
        w.finalize(0.025)
    return path


def _small_gns(bounds=BOX3, use_obstacles=False, radius=0.025) -> GNS:
    cfg = GNSConfig(bounds=bounds, radius=radius, latent=16, mp_steps=1, mlp_layers=1,
                    history=C, use_obstacles=use_obstacles)
    return GNS(cfg, ParticleStats.from_metadata(META3, cfg.noise_std))


def _history(n=40, seed=0, centre=(0.1, 0.05, 0.1), spread=(0.02, 0.015, 0.02)):
    """(n, C+1, 3) history of random nodes around ``centre``, steps of ~1 mm per frame."""
    rng = np.random.default_rng(seed)
    x0 = np.asarray(centre) + rng.uniform(-np.asarray(spread), spread, (n, 1, 3))
    steps = rng.normal(0, 1e-3, (n, C, 3))
    return np.concatenate([x0, x0 + np.cumsum(steps, 1)], 1).astype(np.float32)


@pytest.fixture(scope="module")
def small3d():
    """An untrained 3D GNS (one message-passing step), its params and a history."""
    gns = _small_gns()
    hist = _history()
    ptype = np.full(len(hist), 6, np.int32)
    material = np.full(len(hist), 0.6, np.float32)
    net = gns.init_network(jax.random.key(0), (hist, ptype, material))
    return gns, net, hist, ptype, material


# ------------------------------------------------------------- 2D results are unchanged
MODELS_2D = [("gns_small", 8), ("gns_columns", 8), ("gns_cg16", 16), ("gns_cg16_pf", 16),
             ("gns_cg16_pfn", 16)]


@pytest.mark.parametrize("name, cells", [
    pytest.param(n, c, marks=() if n == "gns_cg16_pfn" else pytest.mark.slow)
    for n, c in MODELS_2D])
def test_shipped_2d_models_equal_the_2d_only_code(name, cells):
    """A 20-frame rollout (jitted) and the node features with two obstacles of each shipped
    model on a column collapse's nodes equal those of the 2D-only code (recorded before
    issue 24): bit for bit on the machine that recorded them, to float32 round-off on
    others (an AMD EPYC VM, 2026-12-03: 3.7e-8 m after 20 frames, a CPU whose vector code
    rounds differently; a 3D-generalisation slip moves positions by far more). The
    coarse-graining clusters are integers: equal."""
    from diffgns.graph.train_loop import load_model
    from diffgns.models import model_path

    g = np.load(GOLDEN)
    for factor in (4, 16):
        np.testing.assert_array_equal(coarse_grain_map(g[f"mpm{cells}_x0"], factor),
                                      g[f"mpm{cells}_cluster{factor}"])
    gns, params, _ = load_model(model_path(name))
    assert gns.config.dim == 2
    hist = jnp.asarray(g[f"{name}_history"])
    n = hist.shape[0]
    ptype = jnp.full(n, 6, jnp.int32)
    material = jnp.full(n, g["material"][0], jnp.float32)
    state = gns.init(hist, ptype)
    frames, _, _ = rollout_safe(gns, GNSParams(params, material), state, 20)
    np.testing.assert_allclose(np.asarray(frames.positions), g[f"{name}_rollout"], rtol=0,
                               atol=1e-6)
    obstacles = jnp.asarray([[0.1, 0.0, 0.16, 0.05], [0.3, 0.0, 0.4, 0.02]], jnp.float32)
    nf = node_features(hist, gns.config.bounds, gns.config.radius, gns.normalizer.velocity,
                       material, obstacles)
    np.testing.assert_allclose(np.asarray(nf), g[f"{name}_features_obstacles"], rtol=1e-6,
                               atol=1e-6)


# ------------------------------------------------------------------- neighbours, features
def test_3d_neighbour_list_equals_brute_force():
    """The cell list (jax-md's 3D cells; forced with all_pairs_max = 0) and the all-pairs list
    give exactly the pairs closer than R, also after an update inside jit."""
    rng = np.random.default_rng(1)
    x = rng.uniform([0.0, 0.0, 0.0], [0.2, 0.1, 0.2], (300, 3)).astype(np.float32)
    want = brute_force_edges(x, 0.03)
    assert len(want) > 1000
    cells = NeighborBuilder(BOX3, 0.03, all_pairs_max=0)
    nbrs = cells.allocate(x)
    assert nbrs.cell_list_capacity is not None
    assert edge_set(*edges(nbrs, len(x), self_edges=False)) == want
    # after moving every point (update inside jit), still exactly the brute-force pairs
    y = np.clip(x + rng.normal(0, 0.004, x.shape), 0, [0.2, 0.1, 0.2]).astype(np.float32)
    nbrs = jax.jit(cells.update, compiler_options=FAST)(y, nbrs)
    assert not bool(did_overflow(nbrs))
    assert edge_set(*edges(nbrs, len(y), self_edges=False)) == brute_force_edges(y, 0.03)
    pairs = NeighborBuilder(BOX3, 0.03).allocate(x)  # all pairs (N <= 1024)
    assert pairs.cell_list_capacity is None
    assert edge_set(*edges(pairs, len(x), self_edges=False)) == want


def test_3d_wall_obstacle_and_edge_features_of_known_points():
    R = 0.05
    walls = ((0.0, 1.0), (0.0, 0.5), (0.0, 0.4))
    box = [0.4, 0.0, 0.4, 0.6, 0.1, 0.6]  # [x0, y0, z0, x1, y1, z1]
    x = np.float32([[0.1, 0.02, 0.38], [0.5, 0.25, 0.2]])
    p = np.float32([[0.5, 0.12, 0.5],  # 2 cm above the box's top face
                    [0.5, 0.09, 0.5],  # 1 cm below it, inside
                    [0.38, 0.05, 0.5],  # 2 cm left of its x0 face
                    [0.9, 0.3, 0.1]])  # far away
    hist = _history(5)
    vn = Normalizer.identity(3)

    @jax.jit  # one compilation for every feature (eager ops compile one by one)
    def features(x, p, hist):
        return dict(
            walls=wall_distances(x, walls, R), walls2=wall_distances(x[:, :2], walls[:2], R),
            obstacle=obstacle_distances(p, jnp.asarray([box]), R),
            none=obstacle_distances(p, jnp.zeros((0, 6)), R),
            parked=obstacle_distances(p, jnp.asarray(obstacle_array([], 1, 3)), R),
            edges=edge_features(p, jnp.asarray([0, 1]), jnp.asarray([1, 1]),
                                jnp.asarray([True, True]), R),
            nodes=node_features(hist, BOX3, R, vn, jnp.float32(0.6)),
            nodes_obstacles=node_features(hist, BOX3, R, vn, None, jnp.asarray([box])))

    f = jax.tree.map(np.asarray, features(x, p, hist))
    np.testing.assert_allclose(f["walls"], [[1.0, 0.4, 1.0, 1.0, 1.0, 0.4],  # (x - lo)/R,
                                            [1.0, 1.0, 1.0, 1.0, 1.0, 1.0]],  # (hi - x)/R
                               atol=1e-6)
    # the x and y columns are the 2D features of the same point in the x-y face
    np.testing.assert_array_equal(f["walls"][:, [0, 1, 3, 4]], f["walls2"])
    np.testing.assert_allclose(f["obstacle"], [[0.4, 0.0, 0.6, 0.0], [-0.2, 0.0, 1.0, 0.0],
                                               [0.4, -0.6, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]],
                               atol=1e-5)
    np.testing.assert_array_equal(f["none"], np.tile([1.0, 0.0, 0.0, 0.0], (4, 1)))
    np.testing.assert_array_equal(f["parked"], f["none"])  # a padding box is no obstacle
    # edge features (E, d + 1): offset / R and its norm
    np.testing.assert_allclose(f["edges"], [[0.0, 0.6, 0.0, 0.6], [0.0, 0.0, 0.0, 0.0]],
                               atol=1e-5)
    # node features: 3C velocities, 6 walls, (4 obstacle,) 1 material
    assert f["nodes"].shape == (5, n_node_features(C, True, False, 3)) == (5, 3 * C + 7)
    assert f["nodes_obstacles"].shape == (5, n_node_features(C, False, True, 3)) == (
        5, 3 * C + 10)
    assert n_node_features(5, True, True) == 2 * 5 + 4 + 3 + 1  # 2D unchanged
    assert obstacle_array([box], 2, 3).shape == (2, 6) and parked(3)[:3] == (1e3,) * 3
    with pytest.raises(ValueError, match="6 numbers"):
        obstacle_array([[0.1, 0.0, 0.2, 0.1]], 0, 3)  # a 2D box in 3D
    with pytest.raises(ValueError, match="do not match 3D"):
        obstacle_distances(p, np.float32([[0.1, 0.0, 0.2, 0.1]]), R)
    with pytest.raises(ValueError, match="do not match 3D"):
        wall_distances(p, walls[:2], R)


def test_3d_coarse_graining_bins_2x2x2_particles_per_node():
    h = 0.005  # particles of an MPM cell of 1 cm with 8 particles per cell
    g = np.stack(np.meshgrid(*[np.arange(6)] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = ((g + 0.5) * h + np.array([0.05, 0.0, 0.07])).astype(np.float32)
    cid = coarse_grain_map(x, 8)
    assert cid.max() + 1 == 27 and np.all(np.bincount(cid) == 8)
    # every node is a 2 x 2 x 2 block of the lattice
    for c in range(27):
        assert np.ptp(g[cid == c], axis=0).tolist() == [1, 1, 1]
    traj = Trajectory(positions=np.stack([x, x + 0.001]), velocities=np.zeros((2, *x.shape)),
                      particle_type=np.full(len(x), 6, np.int32),
                      material=np.full(len(x), 0.6, np.float32), bounds=BOX3)
    nodes = coarse_grain(traj, 8)
    assert nodes.positions.shape == (2, 27, 3) and nodes.bounds == BOX3
    np.testing.assert_allclose(np.sort(np.asarray(nodes.positions[0])[:, 0])[::9],
                               0.05 + np.array([1, 3, 5]) * h, atol=1e-6)
    # padding nodes are parked below the floor, at z = zmin, out of reach
    w, p, m = pad_nodes(np.asarray(nodes.positions), np.asarray(nodes.particle_type),
                        np.asarray(nodes.material), 32, BOX3, 0.02)
    assert w.shape == (2, 32, 3) and np.all(w[:, 27:, 1] == -0.04) and np.all(p[27:] == 3)


# ------------------------------------------------------------------------ the 3D network
def test_3d_acceleration_is_translation_invariant_along_x_and_z(small3d):
    gns, net, hist, ptype, material = small3d
    n = len(hist)
    acc = jax.jit(gns.acceleration, compiler_options=FAST)
    nbrs = gns.allocate(hist[:, -1])
    s, r, m = edges(nbrs, n)
    a0 = np.asarray(acc(net, hist, ptype, material, s, r, m))
    assert a0.shape == (n, 3) and np.isfinite(a0).all()
    scale = np.abs(a0).max()
    shift = np.float32([0.03, 0.0, -0.04])  # every wall stays farther than R = 0.025
    a1 = np.asarray(acc(net, hist + shift, ptype, material, s, r, m))
    np.testing.assert_allclose(a1, a0, rtol=0, atol=1e-4 * scale)  # float32 round-off
    # closer than R to the back wall (z = 0), the wall feature changes the prediction
    a2 = np.asarray(acc(net, hist + np.float32([0.0, 0.0, -0.07]), ptype, material, s, r, m))
    assert np.abs(a2 - a0).max() > 1e-2 * scale


def test_3d_checkpointed_rollout_equals_plain(small3d):
    gns, net, hist, ptype, material = small3d
    params = GNSParams(net, jnp.float32(0.6))
    state = gns.init(hist[:16], ptype[:16])
    assert state.geometry.walls.shape == (3, 2)
    n = 3

    def loss(p, block):
        frames, _ = rollout(gns, p, state, n, checkpoint_block=block)
        return jnp.sum(frames.positions[-1] ** 2), frames

    (g0, f0), (g1, f1) = (jax.jit(jax.grad(lambda p, b=b: loss(p, b), has_aux=True),
                                  compiler_options=FAST)(params) for b in (None, 2))
    x = np.asarray(f0.positions)
    assert x.shape == (n + 1, 16, 3) and np.isfinite(x).all()
    assert not np.asarray(f0.overflow).any() and np.abs(x[-1] - x[0]).max() > 0
    np.testing.assert_allclose(np.asarray(f1.positions), x, rtol=0, atol=1e-6)
    for a, b in zip(jax.tree.leaves(g1), jax.tree.leaves(g0)):
        b = np.asarray(b)
        assert np.isfinite(b).all()
        np.testing.assert_allclose(np.asarray(a), b, rtol=0,
                                   atol=1e-2 * np.abs(b).max() + 1e-12)
    assert np.abs(np.asarray(g0.material)) > 0


@pytest.mark.slow  # eager JAX compiles every op of the step one by one: ~2 min under load
def test_3d_rollout_jit_equals_eager(small3d):
    gns, net, hist, ptype, material = small3d
    params = GNSParams(net, jnp.float32(0.6))
    state = gns.init(hist[:12], ptype[:12])
    jitted, _ = rollout_jit(gns, params, state, n_frames=2)
    with jax.disable_jit():
        eager, _ = rollout(gns, params, state, 2)
    np.testing.assert_allclose(np.asarray(jitted.positions), np.asarray(eager.positions),
                               rtol=0, atol=1e-6)


def test_3d_obstacles_and_scene_geometry():
    from diffgns.scene.builders3d import axisymmetric_column
    from diffgns.scene.core import BoxObstacle

    gns = _small_gns(use_obstacles=True)
    hist = _history(12)
    ptype = np.full(12, 6, np.int32)
    net = gns.init_network(jax.random.key(3), (hist, ptype, np.zeros(12, np.float32)))
    box = (0.09, 0.0, 0.09, 0.11, 0.04, 0.11)
    geo = gns.geometry([box], pad_to=2)
    assert geo.obstacles.shape == (2, 6)
    state = gns.init(hist, ptype, geometry=geo)
    frames, _, _ = rollout_safe(gns, GNSParams(net, jnp.float32(0.6)), state, 2)
    assert frames.positions.shape == (3, 12, 3)
    far = gns.init(hist, ptype, geometry=gns.geometry([], pad_to=2))
    moved, _, _ = rollout_safe(gns, GNSParams(net, jnp.float32(0.6)), far, 2)
    assert np.abs(np.asarray(moved.positions) - np.asarray(frames.positions)).max() > 0
    # a 3D scene's box obstacles become (K, 6) rows of the geometry
    scene = axisymmetric_column(radius=0.03, aspect_ratio=1.0, cells_across=3).replace(
        obstacles=(BoxObstacle(0.01, 0.0, 0.02, 0.02, z0=0.01, z1=0.02),))
    g3, geometry = _small_gns(bounds=scene.domain, use_obstacles=True).for_scene(scene)
    np.testing.assert_allclose(geometry.obstacles, [[0.01, 0.0, 0.01, 0.02, 0.02, 0.02]])
    assert geometry.walls.shape == (3, 2) and g3.config.dim == 3


# ----------------------------------------------------------------------------- refusals
def test_models_refuse_data_of_the_other_dimension(small3d):
    from diffgns.graph.support import UnsupportedSceneError, check_scene
    from diffgns.scene.builders import column_collapse
    from diffgns.scene.builders3d import axisymmetric_column

    gns3 = small3d[0]
    gns2 = _small_gns(bounds=BOX2)
    assert (gns2.config.dim, gns3.config.dim) == (2, 3)
    h3 = _history(6)
    with pytest.raises(ValueError, match="3D but this GNS is a 2D model"):
        gns2.init(h3, np.full(6, 6, np.int32))
    with pytest.raises(ValueError, match="2D but this GNS is a 3D model"):
        gns3.init(h3[..., :2], np.full(6, 6, np.int32))
    with pytest.raises(ValueError, match="is 3D but this GNS is a 2D model"):
        gns2.for_box(BOX3)
    with pytest.raises(ValueError, match="2D but this GNS is a 3D model"):
        gns3.geometry(bounds=BOX2)
    scene3 = axisymmetric_column(radius=0.03, aspect_ratio=1.0, cells_across=3)
    with pytest.raises(ValueError, match="the scene is 3D"):
        gns2.for_scene(scene3)
    info = {"gns": {"bounds": [list(b) for b in BOX2]}, "factor": 1, "frame_stride": 1}
    with pytest.raises(UnsupportedSceneError, match="it is 3D but the model is 2D"):
        check_scene(scene3, info)
    info3 = {"gns": {"bounds": [list(b) for b in BOX3]}, "factor": 1, "frame_stride": 1}
    with pytest.raises(UnsupportedSceneError, match="it is 2D but the model is 3D"):
        check_scene(column_collapse(cells_across=4), info3)
    with pytest.raises(ValueError, match="mix dimensions"):
        WindowSampler(_synthetic(3, 1) + _synthetic(2, 1), history=C)
    assert Geometry.of(BOX3).walls.shape == (3, 2)


def test_train_refuses_mixed_dimensions_and_a_model_of_the_other(tmp_path, capsys):
    d3 = _write(tmp_path / "d3.h5", _synthetic(3, 1, 12))
    d2 = _write(tmp_path / "d2.h5", _synthetic(2, 1, 12))
    args = ["train", "--out", str(tmp_path / "run"), "--steps", "2", "--latent", "8",
            "--mp-steps", "1", "--radius", "0.025"]
    assert main([*args, "--data", str(d3), str(d2)]) == 2
    err = capsys.readouterr().err
    assert "--data: the datasets mix dimensions" in err and "3D" in err and "2D" in err
    assert main([*args, "--data", str(d3), "--valid", str(d2)]) == 2
    assert "--valid" in capsys.readouterr().err and not (tmp_path / "run" / "model").exists()
    assert main([*args, "--data", str(d3), "--init-from", "gns_small"]) == 2
    err = capsys.readouterr().err
    assert "--init-from: model gns_small is 2D but the training data are 3D" in err


# ---------------------------------------------------------------- training and rollout
@pytest.fixture(scope="module")
def trained3d(tmp_path_factory):
    """``diffgns train`` on a small synthetic 3D dataset: 200 steps of a tiny network."""
    tmp = tmp_path_factory.mktemp("gns3d")
    data = _write(tmp / "train3d.h5", _synthetic(3, 3, 25))
    rc = main(["train", "--data", str(data), "--out", str(tmp / "run"), "--steps", "200",
               "--latent", "16", "--mp-steps", "1", "--mlp-layers", "1", "--radius", "0.025",
               "--noise-std", "1e-5", "--lr", "3e-3", "--lr-final", "1e-3",
               "--checkpoint-every", "1000"])
    assert rc == 0
    return tmp, data


def test_3d_training_loss_decreases_and_rollout_stays_in_the_box(trained3d, capsys):
    tmp, data = trained3d
    rows = list(csv.DictReader((tmp / "run" / "train_log.csv").open()))
    losses = [float(r["loss"]) for r in rows]
    assert len(losses) == 4 and losses[-1] < 0.5 * losses[0], losses
    info = json.loads((tmp / "run" / "model" / "config.json").read_text())
    assert info["gns"]["bounds"] == [list(b) for b in BOX3]
    assert len(info["normalizer"]["acc_std"]) == 3
    capsys.readouterr()
    assert main(["rollout", "--model", str(tmp / "run" / "model"), "--data", str(data),
                 "--index", "1"]) == 0
    out = capsys.readouterr().out
    s, _ = json.JSONDecoder().raw_decode(out[out.index("{"):])
    assert s["finite"] and s["inside_domain"]
    assert s["final_position_error_rel_displacement"] < 0.5, s


def test_rollout_refuses_a_model_of_the_other_dimension(trained3d, tmp_path, capsys):
    tmp, data = trained3d
    d2 = _write(tmp_path / "d2.h5", _synthetic(2, 1, 12))
    assert main(["rollout", "--model", str(tmp / "run" / "model"), "--data", str(d2)]) == 2
    assert "is 2D but the model" in capsys.readouterr().err
    assert main(["rollout", "--model", "gns_small", "--data", str(data)]) == 2
    err = capsys.readouterr().err
    assert "is 3D but the model" in err and "gns_small is 2D" in err


@pytest.mark.slow  # an MPM run, training and a 3D animation: minutes on 2 loaded cores
def test_3d_mpm_column_simulate_train_rollout(tmp_path, capsys):
    """The issue's path end to end: ``diffgns simulate`` of a small 3D granular cylinder
    writes trajectory.h5; ``diffgns train`` on it with 2 x 2 x 2 particles per node (8) and
    a frame stride of 2; ``diffgns rollout`` scores and animates it."""
    from diffgns.scene.builders3d import axisymmetric_column
    from diffgns.scene.files import save_scene

    scene = axisymmetric_column(radius=0.03, aspect_ratio=1.0, cells_across=3, E=2e5)
    save_scene(scene, tmp_path / "column3d.toml")
    assert main(["simulate", "--scene", str(tmp_path / "column3d.toml"), "--frames", "40",
                 "--vtk-every", "40", "--out", str(tmp_path / "sim")]) == 0
    data = tmp_path / "sim" / "trajectory.h5"
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "run"), "--steps",
                 "300", "--latent", "16", "--mp-steps", "2", "--mlp-layers", "1",
                 "--radius", "0.025", "--noise-std", "3e-5", "--lr", "3e-3", "--lr-final",
                 "1e-3", "--coarse-grain", "8", "--frame-stride", "2",
                 "--checkpoint-every", "1000"]) == 0
    losses = [float(r["loss"]) for r in
              csv.DictReader((tmp_path / "run" / "train_log.csv").open())]
    assert losses[-1] < losses[0], losses
    info = json.loads((tmp_path / "run" / "model" / "config.json").read_text())
    assert info["factor"] == 8 and len(info["gns"]["bounds"]) == 3
    capsys.readouterr()
    assert main(["rollout", "--model", str(tmp_path / "run" / "model"), "--data", str(data),
                 "--out", str(tmp_path / "rollout")]) == 0
    out = capsys.readouterr().out
    s, _ = json.JSONDecoder().raw_decode(out[out.index("{"):])
    assert s["finite"] and s["inside_domain"], s
    assert (tmp_path / "rollout" / "rollout.gif").stat().st_size > 0
