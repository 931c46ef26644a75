"""Mirror augmentation of GNS training windows (issue 21): the MPM's flow of a scene reflected
about its box's vertical mid-line is the reflection of the scene's flow, so a reflected
window is as true a training sample as the original; the sampler reflects windows with
the given probability and draws exactly as before when the option is off."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from diffgns.graph.data import WindowSampler, mirror_window
from diffgns.scene import BoxObstacle, Rectangle
from diffgns.scene.families import random_sample
from diffgns.trajectory import SAND, Trajectory

BOX = ((0.0, 0.6), (0.0, 0.5))
OBS = ((0.3, 0.0, 0.35, 0.1), (0.4, 0.0, 0.5, 0.05))


def _reflected_scene(scene):
    """The scene with every body, velocity and obstacle reflected about x = (x0 + x1) / 2."""
    s = sum(scene.domain[0])
    bodies = tuple(dataclasses.replace(
        b, shape=Rectangle(s - b.shape.x1, b.shape.y0, s - b.shape.x0, b.shape.y1),
        velocity=(-b.velocity[0], b.velocity[1])) for b in scene.bodies)
    obstacles = tuple(BoxObstacle(s - o.x1, o.y0, s - o.x0, o.y1, surface=o.surface)
                      for o in scene.obstacles)
    return dataclasses.replace(scene, bodies=bodies, obstacles=obstacles)


def test_the_mpm_flow_of_a_reflected_scene_is_the_reflected_flow():
    """A thrown mass running into an obstacle (slip side walls, Coulomb floor and obstacle):
    30 frames (75 ms) of the MPM, reflected scene against reflected flow, particle by
    particle (matched by their reflected initial positions)."""
    from diffgns.mpm import MPM

    scene, d = random_sample("obstacles", 0)
    assert d["obstacles"] and any(abs(v[0]) > 0.1 for v in d["velocities"])
    runs = []
    for sc in (scene, _reflected_scene(scene)):
        sim = MPM(sc)
        traj, _ = sim.run(sim.params(), sim.init(), 30)
        runs.append(np.asarray(traj.positions, float))
    a, b = runs
    s = sum(scene.domain[0])
    ra = a.copy()
    ra[..., 0] = s - ra[..., 0]
    # match particles through their initial positions (the lattices are mirror images)
    order_a = np.lexsort((np.round(ra[0, :, 1], 5), np.round(ra[0, :, 0], 5)))
    order_b = np.lexsort((np.round(b[0, :, 1], 5), np.round(b[0, :, 0], 5)))
    ra, b = ra[:, order_a], b[:, order_b]
    np.testing.assert_allclose(ra[0], b[0], atol=1e-6)  # float32 positions
    moved = np.abs(a[-1] - a[0]).max()
    assert moved > 0.02  # the flow went somewhere (2 cm at least)
    # float32 rounding in a granular flow grows to 2e-5 m over 30 frames (measured); a
    # one-sided MPM (a wall or the grid off by a node) would differ by millimetres
    assert np.abs(ra - b).max() < 1e-4  # m: 3% of the particle spacing, 0.1% of the motion


def test_mirror_window_reflects_positions_and_obstacles_and_is_an_involution():
    rng = np.random.default_rng(0)
    x = rng.uniform([0.0, 0.0], [0.6, 0.5], (7, 11, 2))
    y, o = mirror_window(x, BOX, OBS)
    np.testing.assert_allclose(y[..., 0], 0.6 - x[..., 0])
    np.testing.assert_array_equal(y[..., 1], x[..., 1])
    np.testing.assert_allclose(o, [[0.25, 0.0, 0.3, 0.1], [0.1, 0.0, 0.2, 0.05]])
    z, p = mirror_window(y, BOX, o)
    np.testing.assert_allclose(z, x, atol=1e-12)
    np.testing.assert_allclose(p, OBS, atol=1e-12)
    assert mirror_window(x, BOX, ())[1] == []
    x3 = rng.uniform(0.0, 0.5, (3, 4, 3))
    y3, o3 = mirror_window(x3, ((0.0, 1.0), (0.0, 0.5), (0.0, 0.5)),
                           [(0.1, 0.0, 0.2, 0.3, 0.1, 0.4)])
    np.testing.assert_allclose(y3[..., 1:], x3[..., 1:])
    np.testing.assert_allclose(o3, [[0.7, 0.0, 0.2, 0.9, 0.1, 0.4]])


def _trajs():
    rng = np.random.default_rng(1)
    x = np.cumsum(rng.normal(0.0, 1e-3, (12, 5, 2)), 0) + [0.1, 0.2]
    return [Trajectory(positions=x.astype(np.float32), velocities=x.astype(np.float32),
                       particle_type=np.full(5, SAND), material=np.zeros(5),
                       bounds=BOX, obstacles=OBS)]


def test_sampler_mirrors_with_the_given_probability_and_not_at_all_when_off():
    trajs = _trajs()
    plain = WindowSampler(trajs, 5).sample(np.random.default_rng(3), 8)
    off = WindowSampler(trajs, 5, mirror=0.0).sample(np.random.default_rng(3), 8)
    for k in plain:
        np.testing.assert_array_equal(plain[k], off[k])
    b = WindowSampler(trajs, 5, mirror=1.0).sample(np.random.default_rng(3), 8)
    x = trajs[0].positions
    for w, o in zip(b["positions"], b["obstacles"]):
        start = [s for s in range(len(x) - 6) if np.allclose(0.6 - x[s, :, 0], w[0, :, 0])]
        assert len(start) == 1  # every window is a reflected window of the trajectory
        np.testing.assert_allclose(w[..., 1], x[start[0]:start[0] + 7, :, 1])
        np.testing.assert_allclose(o, [[0.25, 0.0, 0.3, 0.1], [0.1, 0.0, 0.2, 0.05]],
                                   atol=1e-7)
    half = WindowSampler(trajs, 5, mirror=0.5)
    rng = np.random.default_rng(4)
    flipped = [float(half.sample(rng, 1)["obstacles"][0, 0, 0]) < 0.28 for _ in range(400)]
    assert 0.42 < np.mean(flipped) < 0.58  # 400 draws: 3.2 standard deviations
    with pytest.raises(ValueError, match="probability"):
        WindowSampler(trajs, 5, mirror=1.5)


def test_mirror_option_is_parsed_and_rejected_with_a_message(capsys):
    from diffgns.cli import main

    assert main(["train", "--data", "x.h5", "--out", "r", "--mirror", "1.5"]) == 2
    assert "--mirror: 1.5 is not a probability" in capsys.readouterr().err


def test_a_replaced_scene_never_shares_the_particles_of_the_first():
    """dataclasses.replace on a Scene once shared its particle cache: the copy with moved
    bodies returned the original's particles (or the reverse, whichever was asked first)."""
    scene, _ = random_sample("obstacles", 0)
    moved = _reflected_scene(scene)
    xm = np.asarray(moved.particles()["x"])
    xs = np.asarray(scene.particles()["x"])
    assert not np.allclose(np.sort(xm[:, 0]), np.sort(xs[:, 0]))
    b = moved.bodies[0].shape
    assert (xm[:, 0] > b.x0).all() and (xm[:, 0] < b.x1).all()


@pytest.mark.parametrize("families", [None, ["squares"]])
def test_training_passes_the_mirror_probability_to_its_sampler(families):
    """The option reaches the sampler of ``train`` on plain and on family data (a first
    version dropped it on the way: a run with --mirror 0.5 drew unreflected windows)."""
    from types import SimpleNamespace

    from diffgns.graph.fit import TrainConfig
    from diffgns.graph.train_loop import make_sampler

    gns = SimpleNamespace(config=SimpleNamespace(history=5, bounds=BOX, radius=0.05))
    s = make_sampler(gns, _trajs(), TrainConfig(), families, mirror=0.5)
    assert s.mirror == 0.5
    rng = np.random.default_rng(0)
    flipped = [float(s.sample(rng, 1)["obstacles"][0, 0, 0]) < 0.28 for _ in range(100)]
    assert 20 < sum(flipped) < 80
