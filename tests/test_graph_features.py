"""Model inputs of the general GNS (issue 21): obstacle distances against analytic cases,
translation invariance (particles, box and obstacles shifted together give the same
features and accelerations), a longer box gives exactly the same accelerations, the shipped
models' features are unchanged, and per-family window sampling follows its weights."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import enable_x64

from diffgns.graph.features import (
    ParticleStats,
    n_node_features,
    node_features,
    obstacle_distances,
    velocities,
    wall_distances,
)
from diffgns.graph.gns import GNS
from diffgns.graph.sampling import FamilyWindowSampler, pad_nodes
from diffgns.trajectory import KINEMATIC, SAND, Trajectory

BOX = [0.2, 0.1, 0.3, 0.2]
R = 0.05


@pytest.mark.parametrize("p, want", [
    ((0.18, 0.15), (0.4, -0.6, 0.0)),  # 0.02 m left of the left face
    ((0.25, 0.23), (0.6, 0.0, 0.4)),  # 0.03 m above the top face
    # 0.01 m right of and above the top-right corner: d = 0.01 sqrt 2, normal (1, 1)/sqrt 2
    ((0.31, 0.21), (0.2 * 2**0.5, *[(1 - 0.2 * 2**0.5) / 2**0.5] * 2)),
    ((0.33, 0.24), (1.0, 0.0, 0.0)),  # exactly R from the corner
    ((0.29, 0.15), (-0.2, 1.0, 0.0)),  # inside, 0.01 m from the right face
    ((0.25, 0.12), (-0.4, 0.0, -1.0)),  # inside, 0.02 m from the bottom face
    ((0.24, 0.155), (-0.8, -1.0, 0.0)),  # inside, 0.04 m from the left face
    ((0.9, 0.9), (1.0, 0.0, 0.0)),  # far
])
def test_obstacle_distances_analytic(p, want):
    with enable_x64():
        got = obstacle_distances(jnp.asarray([p], jnp.float64), [BOX], R)[0]
        np.testing.assert_allclose(np.asarray(got), want, atol=1e-12)


def test_obstacle_distances_nearest_of_two_and_none():
    x = jnp.asarray([[0.18, 0.15], [0.42, 0.15], [0.36, 0.15]])
    two = [BOX, [0.4, 0.0, 0.5, 0.3]]
    got = np.asarray(obstacle_distances(x, two, R))
    np.testing.assert_allclose(got[0], [0.4, -0.6, 0.0], atol=1e-6)  # first box
    np.testing.assert_allclose(got[1], [-0.4, -1.0, 0.0], atol=1e-6)  # inside the second
    np.testing.assert_allclose(got[2], [0.8, -0.2, 0.0], atol=1e-6)  # 0.04 from the second
    for none in (np.zeros((0, 4)), []):  # no obstacle = far from every obstacle, exactly
        assert np.array_equal(np.asarray(obstacle_distances(x, none, R)),
                              np.tile([1.0, 0.0, 0.0], (3, 1)))


def test_obstacle_distances_gradient():
    """Finite everywhere (surface, corner, inside) and equal to central differences off
    the kinks."""
    with enable_x64():
        f = jax.jit(lambda x: jnp.sum(obstacle_distances(x, [BOX], R)
                                      * jnp.asarray([1.0, 0.7, -0.3])))
        pts = jnp.asarray([[0.2, 0.15], [0.3, 0.2], [0.29, 0.15], [0.32, 0.22], [0.18, 0.13]])
        g = jax.grad(f)(pts)
        assert np.isfinite(np.asarray(g)).all()
        x = jnp.asarray([[0.318, 0.226]])  # outside, off the corner diagonal
        h = 1e-7
        fd = [(f(x.at[0, i].add(h)) - f(x.at[0, i].add(-h))) / (2 * h) for i in range(2)]
        np.testing.assert_allclose(np.asarray(jax.grad(f)(x))[0], fd, rtol=1e-6)


def _history(rng, origin=(0.0125, 0.00625), shape=(8, 6), spacing=0.0125, C=5):
    """(N, C+1, 2) node positions on a lattice by the floor and the left wall, moving."""
    ij = np.stack(np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij"), -1)
    x0 = np.asarray(origin) + spacing * ij.reshape(-1, 2) + rng.normal(0, 1e-3, (ij.size // 2, 2))
    v = rng.normal(0, 5e-4, (len(x0), C, 2)) + np.asarray([1e-3, -2e-3])
    return np.concatenate([x0[:, None], x0[:, None] + np.cumsum(v, 1)], 1)


def _graph(x: np.ndarray, radius: float):
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    r, s = np.nonzero(d < radius)
    return jnp.asarray(s, jnp.int32), jnp.asarray(r, jnp.int32), jnp.ones(len(s), bool)


def test_features_without_obstacles_are_the_old_features():
    """Shipped models pass no obstacles: velocities, wall distances, material, nothing else."""
    h = jnp.asarray(_history(np.random.default_rng(0)), jnp.float32)
    stats = ParticleStats.from_metadata(dict(vel_mean=[1e-4, -1e-4], vel_std=[1e-3, 2e-3],
                                             acc_mean=[0, 0], acc_std=[1, 1]))
    bounds = ((0.0, 0.8), (0.0, 0.35))
    mat = jnp.full((h.shape[0],), 0.6)
    old = jnp.concatenate([stats.velocity.normalize(velocities(h)).reshape(h.shape[0], -1),
                           wall_distances(h[:, -1], bounds, 0.032), mat[:, None]], -1)
    assert np.array_equal(np.asarray(node_features(h, bounds, 0.032, stats.velocity, mat)),
                          np.asarray(old))
    new = node_features(h, bounds, 0.032, stats.velocity, mat, obstacles=[[0.2, 0, 0.3, 0.1]])
    assert new.shape[1] == n_node_features(5, True, True) == old.shape[1] + 3
    assert np.array_equal(np.asarray(new[:, :14]), np.asarray(old[:, :14]))
    assert np.array_equal(np.asarray(new[:, -1]), np.asarray(old[:, -1]))


def test_features_are_translation_invariant():
    """Particles, box and obstacles shifted together: the same node features (obstacles
    included) and edge features, to float rounding."""
    h = _history(np.random.default_rng(1))
    stats = ParticleStats.identity()
    bounds, obs = np.array([[0.0, 0.8], [0.0, 0.35]]), np.array([[0.12, 0.0, 0.2, 0.05]])
    shift = np.array([0.37, -0.21])
    with enable_x64():
        a = node_features(jnp.asarray(h), bounds, 0.032, stats.velocity, 0.5, obstacles=obs)
        b = node_features(jnp.asarray(h + shift), bounds + shift[:, None], 0.032,
                          stats.velocity, 0.5, obstacles=obs + np.tile(shift, 2))
        assert np.abs(np.asarray(a[:, 10:13])).max() > 0  # walls and obstacle are in reach
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-12)


@pytest.fixture(scope="module")
def shipped():
    from diffgns.graph.train_loop import load_model
    from diffgns.models import model_path

    return load_model(model_path("gns_cg16_pfn"))


def test_shipped_model_accelerations_translation_invariant_and_box_length_free(shipped):
    """gns_cg16_pfn: the box and the nodes shifted together give the same accelerations (to
    float32 rounding of the shifted positions), and a box 1.75x longer (every node farther
    than R from the moved wall) gives exactly the same ones."""
    gns, params, _ = shipped
    cfg = gns.config
    h = _history(np.random.default_rng(2))
    assert h[..., 0].max() < cfg.bounds[0][1] - cfg.radius
    ptype = jnp.full((h.shape[0],), SAND, jnp.int32)
    mat = jnp.full((h.shape[0],), np.tan(np.radians(30.0)), jnp.float32)
    graph = _graph(h[:, -1], cfg.radius)

    def acc(g: GNS, hist):
        return np.asarray(g.acceleration(params, jnp.asarray(hist, jnp.float32), ptype, mat,
                                         *graph))

    def with_bounds(bounds):
        return GNS(dataclasses.replace(cfg, bounds=bounds), gns.normalizer, gns.frame_dt)

    base = acc(gns, h)
    assert np.abs(base).max() > 0
    (x0, x1), (y0, y1) = cfg.bounds
    longer = acc(with_bounds(((x0, x0 + 1.75 * (x1 - x0)), (y0, y1))), h)
    assert np.array_equal(base, longer)
    shift = np.array([0.5, 0.25])  # 0.5 and 0.25 m: exact in binary, positions round once
    shifted = acc(with_bounds(((x0 + 0.5, x1 + 0.5), (y0 + 0.25, y1 + 0.25))), h + shift)
    np.testing.assert_allclose(shifted, base, atol=2e-3 * np.abs(base).max())


def _trajs(n_frames_nodes):
    out = []
    for t, n in n_frames_nodes:
        out.append(Trajectory(positions=np.zeros((t, n, 2), np.float32),
                              velocities=np.zeros((t, n, 2), np.float32),
                              particle_type=np.full(n, SAND), material=np.zeros(n)))
    return out


def test_family_sampler_follows_weights():
    # squares: 3 long trajectories of 2 sizes; columns: one short one; obstacles: one
    trajs = _trajs([(200, 10), (200, 10), (200, 12), (20, 7), (50, 9)])
    fams = ["squares", "squares", "squares", "columns", "obstacles"]
    s = FamilyWindowSampler(trajs, history=5, families=fams,
                            weights=dict(squares=1.0, columns=2.0, obstacles=1.0))
    assert s.family_probabilities() == dict(squares=0.25, columns=0.5, obstacles=0.25)
    rng = np.random.default_rng(0)
    n = np.array([s.sample(rng, 2)["positions"].shape[2] for _ in range(4000)])
    freq = {k: np.mean(n == k) for k in (10, 12, 7, 9)}
    # within squares, node groups by windows: 10 nodes 2x194, 12 nodes 194 -> 2/3, 1/3
    for k, want in {10: 0.25 * 2 / 3, 12: 0.25 / 3, 7: 0.5, 9: 0.25}.items():
        assert abs(freq[k] - want) < 0.03, (k, freq[k], want)
    plain = FamilyWindowSampler(trajs, history=5, families=fams)  # equal family weights
    assert plain.family_probabilities() == pytest.approx(dict.fromkeys(set(fams), 1 / 3))


@pytest.mark.parametrize("kw, match", [
    (dict(families=["squares"]), "one family per trajectory"),
    (dict(families=["a", "b"], weights=dict(c=1.0)), r"\['c'\] have no trajectory"),
    (dict(families=["a", "b"], weights=dict(a=-1.0)), "not finite numbers >= 0"),
    (dict(families=["a", "b"], weights=dict(a=0.0, b=0.0)), "all are 0"),
])
def test_family_sampler_refuses(kw, match):
    with pytest.raises(ValueError, match=match):
        FamilyWindowSampler(_trajs([(20, 5), (20, 5)]), history=5, **kw)


def test_padding_nodes_change_no_prediction(shipped):
    """gns_cg16_pfn on a window padded to 64 nodes: the parked kinematic nodes have no edge
    but their self-edge, and every real node's acceleration is the unpadded one."""
    gns, params, _ = shipped
    cfg = gns.config
    h = _history(np.random.default_rng(3))  # (48, 6, 2)
    n = h.shape[0]
    ptype = np.full(n, SAND, np.int32)
    mat = np.full(n, 0.6, np.float32)
    x, p, m = pad_nodes(np.swapaxes(h, 0, 1).astype(np.float32), ptype, mat, 64, cfg.bounds,
                        cfg.radius)
    assert x.shape == (6, 64, 2) and (p[n:] == KINEMATIC).all() and (m[n:] == 0).all()
    hp = np.swapaxes(x, 0, 1)
    s, r, _ = _graph(hp[:, -1], cfg.radius)
    assert np.all((np.asarray(s) < n) == (np.asarray(r) < n))  # no edge across
    assert np.all(np.asarray(s)[np.asarray(s) >= n] == np.asarray(r)[np.asarray(s) >= n])

    def acc(hist, pt, mt):
        return np.asarray(gns.acceleration(params, jnp.asarray(hist, jnp.float32),
                                           jnp.asarray(pt), jnp.asarray(mt),
                                           *_graph(np.asarray(hist)[:, -1], cfg.radius)))

    np.testing.assert_allclose(acc(hp, p, m)[:n], acc(h, ptype, mat), rtol=1e-5, atol=1e-9)


def test_family_sampler_pads_to_few_shapes():
    trajs = _trajs([(30, 10), (30, 13), (30, 17), (30, 33)])
    s = FamilyWindowSampler(trajs, history=5, families=["a"] * 4, pad_to=16,
                            bounds=((0.0, 0.8), (0.0, 0.35)), radius=0.032)
    members, _ = s._family_groups["a"]
    assert sorted(len(m) for m in members) == [1, 1, 2]  # 10, 13 -> 16; 17 -> 32; 33 -> 48
    shapes = {s.sample(np.random.default_rng(i), 2)["positions"].shape[2] for i in range(40)}
    assert shapes == {16, 32, 48}
    with pytest.raises(ValueError, match="needs bounds"):
        FamilyWindowSampler(trajs, history=5, families=["a"] * 4, pad_to=16)
