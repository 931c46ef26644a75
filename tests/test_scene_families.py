"""Random scenes of the granular families (issue 21): deterministic from the seed, valid by
construction (inside the box, apart from each other and from the obstacles, on the lattice of
the coarse-graining), and each family runs in the MPM without NaN and without a clamp."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from diffgns.errors import SceneError
from diffgns.graph.data import coarse_grain_map
from diffgns.scene.families import (
    ALL_FAMILIES,
    FAMILIES,
    FamilyRanges,
    random_sample,
    random_scene,
)
from diffgns.scene.recipes import FAMILY_SEED_STRIDE, family_plan

R = FamilyRanges()
U = R.unit
TOL = 1e-9


def _gap(a, b) -> float:
    """Chebyshev gap between rectangles [x0, y0, x1, y1] (<= 0 when they overlap)."""
    return max(b[0] - a[2], a[0] - b[2], b[1] - a[3], a[1] - b[3])


@pytest.mark.parametrize("family", ALL_FAMILIES)
def test_deterministic_from_seed(family):
    a, da = random_sample(family, 7)
    b, db = random_sample(family, 7)
    assert a == b and da == db
    assert np.array_equal(a.particles()["x"], b.particles()["x"])
    others = [random_sample(family, s)[1] for s in range(8, 14)]
    assert any(o["bodies"] != da["bodies"] for o in others)  # the seed matters
    # the family is part of the stream: the same seed draws another scene in another family
    assert all(random_sample(f, 7)[1]["friction_angle"] != da["friction_angle"]
               for f in ALL_FAMILIES if f != family)


def test_adding_held_out_families_leaves_every_training_draw_unchanged():
    """The particle counts of the first 8 scenes of the validation set
    (``data/granular_valid.h5``, generated before the held-out families existed): the
    training families' random streams have not moved, so existing files stay reproducible."""
    plan = family_plan(FAMILIES, 8, seed=1)
    counts = [random_scene(f, s).n_particles for f, s in plan]
    assert counts == [2112, 1280, 4224, 1856, 1424, 2048, 576, 1936]


@pytest.mark.parametrize("family", FAMILIES)
def test_young_modulus_and_flip_leave_the_draw_unchanged(family):
    """A stiffer-sand set (``--young-modulus``) is the same draw as the default one: only the
    sand's E differs, and the MPM takes the smaller stable substep that E calls for; a set
    with another transfer (``--flip``) differs only in the scene's ``flip``."""
    soft, d_soft = random_sample(family, 3)
    stiff, d_stiff = random_sample(family, 3, young_modulus=2.0e7)
    assert d_soft == d_stiff and soft.n_particles == stiff.n_particles
    assert {b.material.E for b in soft.bodies} == {2.0e6}
    assert {b.material.E for b in stiff.bodies} == {2.0e7}
    assert all(b.material.friction_angle == d_soft["friction_angle"] for b in stiff.bodies)
    # c_p grows by sqrt(10) (the speed bound adds to it): more than twice the substeps
    assert stiff.substeps > 2 * soft.substeps and stiff.frame_dt == soft.frame_dt
    # the transfer likewise: the same draw, the MPM's Scene.flip set
    flip, d_flip = random_sample(family, 3, flip=0.99)
    assert d_flip == d_soft and flip.flip == 0.99 and soft.flip == 0.0
    assert flip.replace(flip=0.0) == soft

def _check_valid(family: str, seed: int, ranges: FamilyRanges, **kw) -> None:
    scene, d = random_sample(family, seed, **kw)
    L, H = d["box"]
    assert tuple(d["box"]) in ranges.boxes
    assert scene.domain == ((0.0, L), (0.0, H))
    assert ranges.friction_angle[0] <= d["friction_angle"] <= ranges.friction_angle[1]
    g = ranges.gap * ranges.unit
    rects = d["bodies"] + d["obstacles"]
    for r in rects:  # inside the box, corners on the lattice
        assert -TOL <= r[0] < r[2] <= L + TOL and -TOL <= r[1] < r[3] <= H + TOL
        assert all(abs(c / ranges.unit - round(c / ranges.unit)) < 1e-6 for c in r)
    for a, b in itertools.combinations(rects, 2):
        assert _gap(a, b) >= g - TOL, (a, b)
    for (vx, vy) in d["velocities"]:
        assert abs(vx) <= ranges.speed[0] and abs(vy) <= ranges.speed[1]
    for r in d["obstacles"]:
        assert r[1] == 0.0  # standing on the floor
    moving = [r for r, v in zip(d["bodies"], d["velocities"]) if v != [0.0, 0.0]]
    for r in moving:  # thrown masses start off every wall
        assert r[0] >= g - TOL and r[1] >= g - TOL and r[2] <= L - g + TOL and r[3] <= H - g + TOL
    if family == "squares":
        assert ranges.n_masses[0] <= len(d["bodies"]) <= ranges.n_masses[1] and not d["obstacles"]
    if family == "columns" or (family == "obstacles" and d["mass"] == "column"):
        (x0, y0, x1, y1), = d["bodies"]
        assert y0 == 0.0 and (x0 == 0.0 if d["side"] == "left" else abs(x1 - L) < TOL)
        assert d["velocities"] == [[0.0, 0.0]]
        assert math.isclose(d["aspect_ratio"], (y1 - y0) / (x1 - x0))
    if family == "obstacles":
        assert ranges.n_obstacles[0] <= len(d["obstacles"]) <= ranges.n_obstacles[1]
        (b,), (v,) = d["bodies"], d["velocities"]
        for o in d["obstacles"]:  # downstream of the mass, which moves (if thrown) toward them
            assert (o[0] >= b[2]) if d["side"] == "left" else (o[2] <= b[0])
            assert v[0] * (1 if d["side"] == "left" else -1) >= 0
    if family == "collision":
        (a, b), (va, vb) = d["bodies"], d["velocities"]
        assert a[2] <= L / 2 <= b[0] and va[0] > 0 > vb[0]  # thrown at each other
        assert a[1] < b[3] and b[1] < a[3]  # at overlapping heights
    if family == "column_pair":  # a column at rest on each wall, near enough to meet
        (a, va), (b, vb) = sorted(zip(d["bodies"], d["velocities"]))
        assert a[0] == 0.0 and abs(b[2] - L) < TOL and a[1] == b[1] == 0.0
        assert va == vb == [0.0, 0.0]
        assert math.isclose(d["gap"], b[0] - a[2]) and d["gap"] <= a[3] + b[3] + TOL
    if family == "column_hit":  # a column on a wall, a mass thrown down at it from below its top
        (c, m), (vc, vm) = d["bodies"], d["velocities"]
        assert c[1] == 0.0 and (c[0] == 0.0 if d["side"] == "left" else abs(c[2] - L) < TOL)
        assert vc == [0.0, 0.0] and vm[1] <= 0.0
        toward = (m[0] >= c[2] and vm[0] < 0) if d["side"] == "left" else (
            m[2] <= c[0] and vm[0] > 0)
        assert toward and m[1] < c[3]


@settings(max_examples=100, deadline=None)
@given(family=st.sampled_from(ALL_FAMILIES), seed=st.integers(0, 2**40))
def test_valid_by_construction(family, seed):
    _check_valid(family, seed, R)


@settings(max_examples=40, deadline=None)
@given(family=st.sampled_from([f for f in ALL_FAMILIES if f != "column_pair"]),
       seed=st.integers(0, 2**20))
def test_valid_in_a_longer_box(family, seed):
    """The held-out box of issue 21: 1.75 x today's length. (Two columns 0.35 m high cannot
    stand near enough to meet in it: ``column_pair`` is refused there, tested below.)"""
    kw = dict(boxes=((1.4, 0.35),), friction_angle=(20.0, 25.0))
    _check_valid(family, seed, FamilyRanges(**kw), **kw)


def test_a_column_pair_that_cannot_meet_is_refused_not_drawn_apart():
    with pytest.raises(SceneError, match="could not place a column_pair"):
        random_scene("column_pair", 0, boxes=((1.4, 0.35),))


@pytest.mark.parametrize("family", ALL_FAMILIES)
def test_coarse_graining_16_bins_whole_blocks(family):
    """Every cluster of coarse-graining 16 holds exactly 16 particles of one body."""
    for seed in range(5):
        scene = random_scene(family, seed)
        p = scene.particles()
        cid = coarse_grain_map(p["x"], 16)
        assert np.all(np.bincount(cid) == 16)
        for c in range(cid.max() + 1):
            assert len(set(p["body"][cid == c])) == 1


def test_plan_is_stable_and_held_out_seeds_are_disjoint():
    fams = ["squares", "columns", "obstacles", "collision"]
    small, big = family_plan(fams, 5, seed=0), family_plan(fams, 50, seed=0)
    assert big[:5] == small
    assert [f for f, _ in big[:8]] == fams * 2
    held_out = family_plan(fams, 50, seed=1)
    assert not {s for _, s in big} & {s for _, s in held_out}
    assert held_out[0][1] == FAMILY_SEED_STRIDE


@pytest.mark.parametrize("kw, field", [
    (dict(family="boulders", seed=0), "family"),
    (dict(family="squares", seed=-1), "seed"),
    (dict(family="squares", seed=0, friction_angle=(40.0, 20.0)), "friction_angle"),
    (dict(family="squares", seed=0, friction_angle=(20.0, 95.0)), "friction_angle"),
    (dict(family="squares", seed=0, boxes=((0.81, 0.35),)), "boxes"),
    (dict(family="squares", seed=0, speed=(-1.0, 1.0)), "speed"),
    (dict(family="squares", seed=0, colour=(1, 2)), "colour"),
    (dict(family="squares", seed=0, size=(0.5, 0.6)), "could not place"),
    (dict(family="squares", seed=0, young_modulus=0.0), "young_modulus"),
    (dict(family="squares", seed=0, young_modulus=float("nan")), "young_modulus"),
    (dict(family="squares", seed=0, flip=1.5), "flip"),
])
def test_bad_ranges_are_refused(kw, field):
    with pytest.raises(SceneError, match=field):
        random_scene(**kw)


@pytest.mark.parametrize("family", [pytest.param(f, marks=[] if f == "obstacles" else
                                                 pytest.mark.slow) for f in ALL_FAMILIES])
def test_every_family_runs_in_the_mpm_without_nan_or_clamp(family):
    """A few MPM frames: finite, strictly inside the box (the MPM clamps positions to the
    box, so a clamped particle would sit exactly on a wall) and outside every obstacle; the
    moving masses move as thrown and gravity pulls everything down."""
    from diffgns.mpm import MPM

    # seed 2 of obstacles is a column with two obstacles; others: the first seeds
    scene, d = random_sample(family, 2 if family == "obstacles" else 0)
    sim = MPM(scene)
    traj, _ = sim.run(sim.params(), sim.init(), 6)
    x = np.asarray(traj.positions)
    assert np.isfinite(x).all() and np.isfinite(np.asarray(traj.velocities)).all()
    (x0, x1), (y0, y1) = scene.domain
    assert (x[..., 0] > x0).all() and (x[..., 0] < x1).all()
    assert (x[..., 1] > y0).all() and (x[..., 1] < y1).all()
    for o in scene.obstacles:
        assert not o.contains(x.reshape(-1, 2)).any()
    v = np.asarray(traj.velocities)
    body = scene.particles()["body"]
    for b, (vx, _) in enumerate(d["velocities"]):
        mean_vx = v[-1, body == b, 0].mean()
        assert abs(mean_vx - vx) < 0.2 + 0.2 * abs(vx)  # 15 ms: contact has barely begun
    assert v[-1, :, 1].mean() < v[0, :, 1].mean()  # gravity
