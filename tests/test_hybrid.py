"""Hybrid GNS/MPM rollout: schedules, hand-off, limits, gradients."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns import MPM
from diffgns.graph.gns import GNSParams
from diffgns.graph.train_loop import load_model
from diffgns.hybrid.handoff import (
    BOUNDARY_SLIP_CELLS,
    LSQ_RIDGE,
    boundary_slip,
    lsq_gradient,
    node_means,
    particles_from_nodes,
    within_reach,
)
from diffgns.hybrid.simulator import GNS_MODE, MPM_MODE, Hybrid, HybridParams, Schedule
from diffgns.interface import rollout, rollout_jit, rollout_safe
from diffgns.metrics import runout
from diffgns.models import model_path
from diffgns.scene.builders import column_collapse

MODEL = model_path("gns_columns")


def small_scene(phi=30.0, aspect_ratio=0.5):
    return column_collapse(width=0.1, aspect_ratio=aspect_ratio, friction_angle=phi,
                           cells_across=8, domain_length=0.8, domain_height=0.35)


@pytest.fixture(scope="module")
def model():
    gns, params, info = load_model(MODEL)
    return gns, params, info


def modes_of(sched, n):
    """The frame-by-frame simulator a fixed schedule should use."""
    out = []
    out += [MPM_MODE] * sched.warmup
    while len(out) < n:
        out += [GNS_MODE] * sched.gns_frames + [MPM_MODE] * sched.mpm_frames
    return np.array(out[:n])


def test_schedule_rejects_invalid_input():
    with pytest.raises(ValueError, match="handoff"):
        Schedule(handoff="teleport")
    with pytest.raises(ValueError, match="gns_frames \\+ mpm_frames > 0"):
        Schedule(gns_frames=0, mpm_frames=0)
    with pytest.raises(ValueError, match="adaptive_tol > 0"):
        Schedule(adaptive_tol=-1.0)
    for bad in (0.0, 1.0, -0.2, float("nan")):
        with pytest.raises(ValueError, match="0 < warmup_settle < 1"):
            Schedule(warmup_settle=bad)


def test_warmup_shorter_than_history_rejected(model):
    gns, params, _ = model
    with pytest.raises(ValueError, match="warmup"):
        Hybrid(MPM(small_scene()), gns, 2, 4, Schedule(warmup=2))


def test_lsq_gradient_exact_for_linear_field():
    """Plain least squares (ridge 0) recovers a linear field's gradient exactly; the default
    ridge shrinks a well-spread neighbourhood's by at most 1 / (1 + 2 ridge)."""
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.uniform(0, 1, (30, 2)))
    G = jnp.array([[0.3, -1.2], [2.0, 0.5]])
    u = x @ G.T + 0.7
    s, r = np.meshgrid(np.arange(30), np.arange(30))
    s, r = jnp.asarray(s.ravel()), jnp.asarray(r.ravel())
    out = lsq_gradient(u, x, s, r, jnp.ones(s.shape, bool), ridge=0.0)
    np.testing.assert_allclose(out, np.broadcast_to(G, (30, 2, 2)), atol=1e-4)
    shrunk = np.asarray(lsq_gradient(u, x, s, r, jnp.ones(s.shape, bool)))
    assert LSQ_RIDGE > 0
    dx = np.asarray(x)[None] - np.asarray(x)[:, None]  # (30, 30, 2), node i's edges
    A = np.einsum("ija,ijb->iab", dx, dx)
    mu = LSQ_RIDGE * np.trace(A, axis1=1, axis2=2)[:, None, None] * np.eye(2)
    want = np.einsum("ab,ibc,icd->iad", np.asarray(G), A, np.linalg.inv(A + mu))
    np.testing.assert_allclose(shrunk, want, rtol=1e-3, atol=1e-4)
    # a node in the middle of a square lattice (isotropic): shrunk by exactly 1 / (1 + 2 ridge)
    g = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0)), -1).reshape(-1, 2) * 0.01
    ul = g @ np.asarray(G).T
    c = 12  # the centre
    nb = np.array([k for k in range(25) if k != c and np.abs(g[k] - g[c]).max() < 0.015])
    out = lsq_gradient(jnp.asarray(ul), jnp.asarray(g), jnp.asarray(nb), jnp.full(len(nb), c),
                       jnp.ones(len(nb), bool))
    np.testing.assert_allclose(out[c], np.asarray(G) / (1 + 2 * LSQ_RIDGE), rtol=1e-4)
    assert int(s[0]) == int(r[0]) == 0
    lonely = lsq_gradient(u, x, s[:1], r[:1], jnp.ones(1, bool))  # a self-edge only
    assert np.all(np.asarray(lonely) == 0)
    # one neighbour (and the self-edge the GNS graph carries): the derivative along the edge,
    # shrunk by 1 / (1 + ridge), and none across it; plain least squares gives none at all
    one = jnp.asarray([1, 0]), jnp.asarray([0, 0]), jnp.ones(2, bool)
    g1 = np.asarray(lsq_gradient(u, x, *one)[0])
    d = np.asarray(x[1] - x[0])
    np.testing.assert_allclose(g1 @ d, np.asarray(u[1] - u[0]) / (1 + LSQ_RIDGE), rtol=1e-4)
    np.testing.assert_allclose(g1 @ np.array([-d[1], d[0]]), 0.0, atol=1e-5)
    assert np.all(np.asarray(lsq_gradient(u, x, *one, ridge=0.0)[0]) == 0)
    with pytest.raises(ValueError, match="ridge"):
        lsq_gradient(u, x, s, r, jnp.ones(s.shape, bool), ridge=-0.1)


def test_lsq_gradient_of_a_one_node_layer_stays_bounded():
    """Nodes in a row one node thick (1 cm apart, 0.1 mm of vertical scatter) carrying a
    field u = 0.01 x plus 0.1 mm of noise (a GNS frame on a deposit spread thin): plain least
    squares divides the noise by the scatter and reports vertical gradients of order 1; the
    ridge keeps them at the noise over the spacing, and the along-row gradient intact."""
    rng = np.random.default_rng(1)
    n = 40
    x = np.stack([0.01 * np.arange(n), 1e-4 * rng.standard_normal(n)], -1)
    u = np.stack([0.01 * x[:, 0], np.zeros(n)], -1) + 1e-4 * rng.standard_normal((n, 2))
    i, j = np.meshgrid(np.arange(n), np.arange(n))
    near = (np.abs(i - j) <= 3) & (i != j)
    s, r = jnp.asarray(i[near]), jnp.asarray(j[near])
    m = jnp.ones(s.shape, bool)
    plain = np.asarray(lsq_gradient(jnp.asarray(u), jnp.asarray(x), s, r, m, ridge=0.0))
    ridged = np.asarray(lsq_gradient(jnp.asarray(u), jnp.asarray(x), s, r, m))
    assert np.abs(plain[:, :, 1]).max() > 0.5  # d u / d y: noise / scatter
    assert np.abs(ridged[:, :, 1]).max() < 0.1
    np.testing.assert_allclose(np.median(ridged[:, 0, 0]), 0.01, rtol=0.15)


def test_handoff_moves_particles_with_their_node_and_sets_F():
    sim = MPM(small_scene())
    st = sim.init()
    n = st.n_particles
    cluster = jnp.asarray(np.arange(n) % 3)
    counts = jnp.bincount(cluster)
    x_node = node_means(st.x, cluster, counts)
    disp = jnp.array([[0.01, 0.0], [0.0, 0.02], [0.005, 0.005]])  # stays inside
    vel = disp / 0.005
    gv = jnp.broadcast_to(jnp.array([[0.0, 1.0], [0.0, 0.0]]), (3, 2, 2))
    gu = jnp.broadcast_to(jnp.array([[0.1, 0.0], [0.0, 0.0]]), (3, 2, 2))
    lo, hi = jnp.asarray(sim.lo), jnp.asarray(sim.hi)
    st = st.replace(F=st.F * 1.01)
    for mode in ("reset", "carry", "reconstruct"):
        new, clamp, kept = particles_from_nodes(st, cluster, x_node, disp, vel, gv, gu, mode,
                                                lo, hi, particle_map="rigid")
        assert int(clamp.moved) == 0 and int(kept) == 0
        np.testing.assert_allclose(new.x - st.x, disp[cluster].T, atol=1e-7)
        np.testing.assert_allclose(new.v, vel[cluster].T, rtol=1e-6)
        np.testing.assert_allclose(new.C[0, 1], 1.0)
        detF = new.F[0, 0] * new.F[1, 1] - new.F[0, 1] * new.F[1, 0]
        want = {"reset": 1.0, "carry": 1.01**2, "reconstruct": 1.01**2}[mode]
        np.testing.assert_allclose(detF, want, rtol=1e-5)  # reconstruct is isochoric
    np.testing.assert_allclose(x_node, [st.x[:, np.arange(n) % 3 == k].mean(1)
                                        for k in range(3)], rtol=1e-6)
    with pytest.raises(ValueError, match="particle_map"):
        particles_from_nodes(st, cluster, x_node, disp, vel, gv, gu, "carry", lo, hi, "warp")


def test_reconstruct_keeps_and_counts_F_where_the_node_field_folds_or_explodes():
    """A node field that changes a cluster's area by more than 4x either way in one frame
    (or inverts it) has no credible isochoric part: those particles keep their F and are
    counted; the others get exactly the isochoric update (never a clipped Jacobian)."""
    sim = MPM(small_scene())
    st = sim.init()
    n = st.n_particles
    cluster = jnp.asarray(np.arange(n) % 4)
    x_node = node_means(st.x, cluster, jnp.bincount(cluster))
    zero = jnp.zeros((4, 2))
    # det(I + G): 1.1 * 0.95 (credible), 0.1 (folds 10x), 5.0 (explodes), -0.5 (inverts)
    gu = jnp.stack([jnp.diag(jnp.array(d)) for d in
                    ([0.1, -0.05], [-0.9, 0.0], [4.0, 0.0], [-1.5, 0.0])])
    lo, hi = jnp.asarray(sim.lo), jnp.asarray(sim.hi)
    st = st.replace(F=st.F * 1.01)
    new, _, kept = particles_from_nodes(st, cluster, x_node, zero, zero, gu * 0, gu,
                                        "reconstruct", lo, hi, particle_map="rigid")
    c = np.asarray(cluster)
    assert int(kept) == int(np.sum(c != 0))
    F, F0 = np.asarray(new.F), np.asarray(st.F)
    np.testing.assert_array_equal(F[:, :, c != 0], F0[:, :, c != 0])
    L = np.diag([1.1, 0.95]) / np.sqrt(1.1 * 0.95)
    np.testing.assert_allclose(F[:, :, c == 0],
                               np.einsum("ab,bcn->acn", L, F0[:, :, c == 0]), rtol=1e-6)
    assert np.isfinite(F).all()


def test_affine_particle_map_follows_a_linear_node_field():
    """A node field u(x) = u0 + G (x - x0) moves every particle exactly as the field does
    (clusters stretch and shear) and keeps each cluster's mean on its node; each particle
    takes its node's velocity plus the deviation from its cluster's mean velocity it had
    before (the sub-node structure the GNS does not know), so the cluster's mean velocity is
    the node's; the rigid map keeps cluster shapes and gives every particle its node's
    velocity."""
    sim = MPM(small_scene())
    st = sim.init()
    x = np.asarray(st.x)
    cluster = jnp.asarray((x[0] > np.median(x[0])).astype(np.int32)
                          + 2 * (x[1] > np.median(x[1])))
    counts = jnp.bincount(cluster)
    # particle velocities with structure inside each cluster: a stretching, shearing flow
    st = st.replace(v=jnp.asarray([[0.8], [-0.1]]) + jnp.asarray([[3.0, 1.5], [0.0, -2.0]])
                    @ st.x)
    x_node = node_means(st.x, cluster, counts)
    G = jnp.array([[0.02, 0.05], [-0.01, 0.03]])  # displacement gradient over the frame
    u0 = jnp.array([0.004, -0.002])
    x0 = jnp.array([0.05, 0.02])
    disp = u0 + (x_node - x0) @ G.T
    dt = 0.005
    vel, gv, gu = disp / dt, jnp.broadcast_to(G / dt, (4, 2, 2)), jnp.broadcast_to(G, (4, 2, 2))
    lo, hi = jnp.asarray(sim.lo), jnp.asarray(sim.hi)
    new, clamp, _ = particles_from_nodes(st, cluster, x_node, disp, vel, gv, gu, "carry", lo, hi)
    assert int(clamp.moved) == 0
    want = st.x + (u0 + (st.x.T - x0) @ G.T).T
    np.testing.assert_allclose(new.x, want, atol=1e-7)
    np.testing.assert_allclose(node_means(new.x, cluster, counts), x_node + disp, atol=1e-7)
    deviation = st.v - node_means(st.v, cluster, counts)[cluster].T
    assert np.abs(np.asarray(deviation)).max() > 0.05  # the structure is not trivial
    np.testing.assert_allclose(new.v, vel[cluster].T + deviation, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(node_means(new.v, cluster, counts), vel, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(new.C, jnp.moveaxis(gv[cluster], 0, -1), rtol=1e-6)
    rigid, _, _ = particles_from_nodes(st, cluster, x_node, disp, vel, gv, gu, "carry", lo, hi,
                                       particle_map="rigid")
    spread = lambda y: np.asarray(y - node_means(y, cluster, counts)[cluster].T)  # noqa: E731
    np.testing.assert_allclose(spread(rigid.x), spread(st.x), atol=1e-7)
    np.testing.assert_allclose(rigid.v, vel[cluster].T, rtol=1e-6)
    assert np.abs(spread(new.x) - spread(st.x)).max() > 1e-4  # the affine map deforms


def test_within_reach_shortens_far_offsets_and_keeps_clusters_centred():
    """Offsets within reach are kept; a longer one is shortened to the reach along its own
    direction, and the cluster's offsets are re-centred (they still sum to zero)."""
    r = jnp.asarray([[0.01, -0.005, -0.005, 0.4, -0.2, -0.2],
                     [0.0, 0.01, -0.01, 0.0, 0.0, 0.0]])
    cluster, counts = jnp.asarray([0, 0, 0, 1, 1, 1]), jnp.asarray([3.0, 3.0])
    out = np.asarray(within_reach(r, cluster, counts, 0.03))
    np.testing.assert_allclose(out[:, :3], r[:, :3], atol=1e-9)  # within reach: unchanged
    # (0.4, -0.2, -0.2) -> (0.03, -0.03, -0.03), re-centred by their mean -0.01
    np.testing.assert_allclose(out[:, 3:], [[0.04, -0.02, -0.02], [0, 0, 0]], atol=1e-7)
    np.testing.assert_allclose(np.asarray(within_reach(r, cluster, counts, None)), r)
    for bad in (0.0, -0.01):
        with pytest.raises(ValueError, match="reach must be > 0"):
            within_reach(r, cluster, counts, bad)


def test_affine_map_does_not_extrapolate_beyond_its_reach():
    """A particle sheared far from its node (0.3 m) is moved, without a reach, by the node
    field's gradient times 0.3 m (the string of launched particles of a held-out
    collision); with the reach its affine step stays within |grad u| 2 reach, the cluster
    mean stays the node, and clusters within reach follow the affine field as before. No
    velocity is extrapolated at all: the far particle keeps its node's velocity plus its own
    deviation (none here)."""
    sim = MPM(small_scene())
    st = sim.init()
    cluster, counts = _quadrants(st)
    far = int(np.flatnonzero(np.asarray(cluster) == 0)[0])
    st = st.replace(x=st.x.at[:, far].add(jnp.asarray([0.3, 0.05])))
    x_node = node_means(st.x, cluster, counts)
    G = jnp.array([[0.01, 0.02], [-0.01, 0.01]])  # displacement gradient over the frame
    dt, reach = 0.0025, 0.04
    disp = jnp.broadcast_to(jnp.asarray([0.001, 0.0]), (4, 2))
    vel, gv, gu = disp / dt, jnp.broadcast_to(G / dt, (4, 2, 2)), jnp.broadcast_to(G, (4, 2, 2))
    lo, hi = jnp.asarray(sim.lo), jnp.asarray(sim.hi)
    args = (st, cluster, x_node, disp, vel, gv, gu, "carry", lo, hi)
    wide, _, _ = particles_from_nodes(*args)
    near, clamp, _ = particles_from_nodes(*args, reach=reach)
    assert int(clamp.moved) == 0
    g = float(np.linalg.norm(np.asarray(G), 2))
    x_far = np.asarray(st.x)[:, far] + np.asarray(disp)[0]  # moved rigidly with its node
    r_far = np.asarray(st.x)[:, far] - np.asarray(x_node)[0]
    step_wide = np.linalg.norm(np.asarray(wide.x)[:, far] - x_far)
    step_near = np.linalg.norm(np.asarray(near.x)[:, far] - x_far)
    assert step_wide > 0.9 * np.linalg.norm(np.asarray(G) @ r_far)  # extrapolated
    assert step_near <= 2 * reach * g + 1e-6
    for mapped in (wide, near):
        np.testing.assert_allclose(np.asarray(mapped.v)[:, far], np.asarray(vel)[0], rtol=1e-6)
    c = np.asarray(cluster)
    np.testing.assert_allclose(node_means(near.x, cluster, counts), x_node + disp, atol=1e-7)
    mean_v = jax.ops.segment_sum(near.v.T, cluster, num_segments=4) / counts[:, None]
    np.testing.assert_allclose(mean_v, vel, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(near.x)[:, c != 0], np.asarray(wide.x)[:, c != 0],
                               atol=1e-7)


def test_hybrid_affine_map_reaches_as_far_as_the_gns_graph(model, monkeypatch):
    """The hybrid's GNS frames hand the particle map its model's radius as the reach."""
    import diffgns.hybrid.simulator as hybrid_module

    gns, params, _ = model
    seen, bands = [], []

    def spy(*args, **kwargs):
        seen.append(kwargs.get("reach"))
        bands.append(kwargs.get("slip_band"))
        return particles_from_nodes(*args, **kwargs)

    monkeypatch.setattr(hybrid_module, "particles_from_nodes", spy)
    sim = MPM(small_scene())
    hyb = Hybrid(sim, gns, 2, 4, Schedule(warmup=5, gns_frames=1, mpm_frames=1))
    res, _ = hyb.run(HybridParams(sim.params(), params), sim.init(), 7)
    assert seen and all(r == pytest.approx(gns.config.radius) for r in seen)
    # and the boundary slip band: the MPM's B-spline reach
    assert all(b == pytest.approx(BOUNDARY_SLIP_CELLS * sim.scene.dx) for b in bands)
    assert np.isfinite(np.asarray(res.positions)).all()


def test_boundary_slip_removes_only_the_velocity_into_a_nearby_wall_or_face():
    """Within the band of a box wall, or outside an obstacle near one of its faces (within
    the face's span), a particle loses its velocity component into it; the tangential
    component, velocities pointing away and particles farther away are unchanged."""
    lo, hi = jnp.zeros(2), jnp.ones(2)
    obstacles = jnp.array([[0.4, 0.0, 0.6, 0.2]])
    cases = [  # position, velocity, expected velocity
        ((0.2, 0.005), (0.3, -0.1), (0.3, 0.0)),    # on the floor, moving into it
        ((0.2, 0.005), (0.3, 0.1), (0.3, 0.1)),     # on the floor, moving off it
        ((0.2, 0.5), (0.3, -0.1), (0.3, -0.1)),     # far from every boundary
        ((0.995, 0.5), (0.2, 0.1), (0.0, 0.1)),     # at the right wall
        ((0.005, 0.995), (-0.2, 0.1), (0.0, 0.0)),  # in the top-left corner, into both
        ((0.5, 0.205), (0.1, -0.3), (0.1, 0.0)),    # on the obstacle's top
        ((0.395, 0.1), (0.2, 0.1), (0.0, 0.1)),     # at its left face
        ((0.605, 0.1), (-0.2, 0.1), (0.0, 0.1)),    # at its right face
        ((0.35, 0.205), (0.1, -0.3), (0.1, -0.3)),  # above its height, beside its span
        ((0.5, 0.215), (0.1, -0.3), (0.1, -0.3)),   # above its top, outside the band
    ]
    x = jnp.array([c[0] for c in cases]).T
    v = jnp.array([c[1] for c in cases]).T
    want = np.array([c[2] for c in cases]).T
    got = boundary_slip(x, v, lo, hi, 0.01, obstacles)
    np.testing.assert_allclose(np.asarray(got), want, atol=0)
    np.testing.assert_array_equal(np.asarray(boundary_slip(x, v, lo, hi, 0.0, obstacles)), v)
    no_obstacles = boundary_slip(x, v, lo, hi, 0.01, jnp.zeros((0, 4)))
    np.testing.assert_allclose(np.asarray(no_obstacles)[:, 5:8], np.asarray(v)[:, 5:8])
    # the particle map applies it: a column handed over sinking and sliding keeps its
    # sliding speed everywhere and its sinking speed only away from the floor
    sim = MPM(small_scene())
    st = sim.init()
    cluster = jnp.zeros(st.n_particles, jnp.int32)
    x_node = node_means(st.x, cluster, jnp.bincount(cluster))
    vel, zero = jnp.array([[0.3, -0.1]]), jnp.zeros((1, 2, 2))
    band = BOUNDARY_SLIP_CELLS * sim.scene.dx
    new, _, _ = particles_from_nodes(st, cluster, x_node, 0 * vel, vel, zero, zero, "carry",
                                     jnp.asarray(sim.lo), jnp.asarray(sim.hi), "rigid",
                                     slip_band=band)
    floor = np.asarray(st.x[1] - sim.lo[1]) < band
    assert 0 < floor.sum() < st.n_particles
    np.testing.assert_allclose(np.asarray(new.v[0]), 0.3, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(new.v[1]), np.where(floor, 0.0, -0.1), rtol=1e-6)


def _quadrants(st):
    x = np.asarray(st.x)
    cluster = jnp.asarray((x[0] > np.median(x[0])).astype(np.int32)
                          + 2 * (x[1] > np.median(x[1])))
    return cluster, jnp.bincount(cluster)


def _scale_of(new_off, off, step):
    """(s, residual): the least-squares s with new_off = off + s step, and the misfit (m)."""
    d, a = np.ravel(new_off - off), np.ravel(step)
    s = float(d @ a / (a @ a))
    return s, float(np.abs(d - s * a).max())


def test_particle_map_keeps_every_cluster_inside_the_box():
    """A stretch that would carry the wall-side particles of the left clusters through the
    left wall: those clusters fall back towards rigid just enough (one factor per cluster, the
    cluster mean stays the node, the outermost particle ends inside), the right clusters
    follow the affine field exactly; where even the rigid move crosses the wall the cluster
    contracts about its node, along the axis that needs it only. Nothing is clamped."""
    sim = MPM(small_scene())  # column on [0, 0.1] m against the left wall of a 0.8 m box
    st = sim.init()
    cluster, counts = _quadrants(st)
    x_node = node_means(st.x, cluster, counts)
    lo, hi = jnp.asarray(sim.lo), jnp.asarray(sim.hi)
    G = jnp.array([[0.5, 0.0], [0.0, 0.0]])  # 50% stretch in x over the frame
    zero, gu = jnp.zeros((4, 2)), jnp.broadcast_to(G, (4, 2, 2))
    new, clamp, _ = particles_from_nodes(st, cluster, x_node, zero, zero, gu * 0, gu, "carry",
                                      lo, hi)
    assert int(clamp.moved) == 0
    x, x0 = np.asarray(new.x), np.asarray(st.x)
    assert (x >= np.asarray(lo)[:, None]).all() and (x <= np.asarray(hi)[:, None]).all()
    np.testing.assert_allclose(node_means(new.x, cluster, counts), x_node, atol=1e-7)
    r = x0 - np.asarray(x_node)[np.asarray(cluster)].T
    step = np.asarray(G) @ r
    assert (x0[0] + step[0] < 0).any()  # the unlimited affine map would cross the wall
    left = np.asarray(x_node)[:, 0] < 0.05
    for k in range(4):
        m = np.asarray(cluster) == k
        s, resid = _scale_of(x[:, m] - x0[:, m], 0 * r[:, m], step[:, m])
        assert resid < 1e-7  # one factor per cluster: the affine shape, scaled
        if left[k]:
            assert 0.0 < s < 1.0 and x[0, m].min() < 1e-4  # just enough to stay inside
        else:
            assert s == pytest.approx(1.0, abs=1e-6)  # fits: the affine map unchanged
    # with a margin (half a particle spacing in the hybrid) nobody gets closer to a wall than
    # the margin, or than it already was
    near, _, _ = particles_from_nodes(st, cluster, x_node, zero, zero, gu * 0, gu, "carry", lo,
                                   hi, margin=0.002)
    assert np.asarray(near.x)[0].min() >= min(0.002, x0[0].min()) - 1e-9
    np.testing.assert_allclose(node_means(near.x, cluster, counts), x_node, atol=1e-7)
    # a rigid move of 2 cm to the left: the left clusters' wall-side particles would cross
    disp = jnp.asarray([[-0.02, 0.0]] * 4)
    new, clamp, _ = particles_from_nodes(st, cluster, x_node, disp, disp / 0.005, gu * 0, gu * 0,
                                      "carry", lo, hi, particle_map="rigid")
    assert int(clamp.moved) == 0
    x = np.asarray(new.x)
    assert (x >= 0).all()
    np.testing.assert_allclose(node_means(new.x, cluster, counts), x_node + disp, atol=1e-7)
    for k in range(4):
        m = np.asarray(cluster) == k
        off = x[:, m] - np.asarray(x_node + disp)[k][:, None]
        # axis by axis: the cluster contracts along x (towards the wall) only; along y its
        # offsets fit and are kept whole
        lam_x, resid_x = _scale_of(off[0], 0 * r[0, m], r[0, m])
        lam_y, resid_y = _scale_of(off[1], 0 * r[1, m], r[1, m])
        assert resid_x < 1e-7 and resid_y < 1e-7
        assert (0.0 < lam_x < 1.0) if left[k] else lam_x == pytest.approx(1.0, abs=1e-6)
        assert lam_y == pytest.approx(1.0, abs=1e-6)


def test_mpm_only_schedule_is_the_mpm(model):
    gns, params, _ = model
    sim = MPM(small_scene())
    p, st = sim.params(), sim.init()
    hyb = Hybrid(sim, gns, 2, 4, Schedule(warmup=5, gns_frames=0, mpm_frames=1))
    res, _ = hyb.run(HybridParams(p, params), st, 12)
    ref, _ = sim.run(p, st, 24)
    np.testing.assert_allclose(res.positions, np.asarray(ref.positions)[::2], atol=1e-6)
    assert np.all(np.asarray(res.mode) == MPM_MODE)


def test_fixed_schedule_and_gns_frames_match_the_gns(model):
    gns, params, _ = model
    sim = MPM(small_scene())
    p, st = sim.params(), sim.init()
    sched = Schedule(warmup=5, gns_frames=4, mpm_frames=2)
    hyb = Hybrid(sim, gns, 2, 4, sched)
    hp = HybridParams(p, params)
    res, start = hyb.run(hp, st, 20)
    np.testing.assert_array_equal(res.mode, modes_of(sched, 20))
    # The first GNS segment is exactly a GNS rollout from the warm-up history.
    nodes = np.asarray(res.nodes)
    hist = jnp.swapaxes(jnp.asarray(nodes[:6]), 0, 1)
    frames, _, _ = rollout_safe(gns, GNSParams(params, hyb.node_material(p)),
                                gns.init(hist, hyb.node_type), 4)
    np.testing.assert_allclose(nodes[6:10], frames.positions[1:], atol=2e-6)
    # Particles follow their node: node means of the particles are the nodes.
    parts = jnp.asarray(res.positions[9]).T
    np.testing.assert_allclose(hyb.nodes(st.replace(x=parts)), nodes[9], atol=2e-6)
    # A second run reuses the compiled rollout (no recompilation).
    size = rollout_jit._cache_size()
    hyb.run(hp, st, 20, state=start)
    assert rollout_jit._cache_size() == size


def test_settling_warmup_ends_when_the_kinetic_energy_falls_below_its_fraction(model):
    """With ``warmup_settle=f`` the MPM runs until the nodes' kinetic energy per unit mass
    is below f of its peak so far (computed here from an MPM-only run), then the fixed
    alternation starts; the warm-up frames are the MPM's own."""
    gns, params, _ = model
    sim = MPM(small_scene())
    p, st = sim.params(), sim.init()
    hp, n = HybridParams(p, params), 56
    mpm_only = Hybrid(sim, gns, 2, 4, Schedule(gns_frames=0, mpm_frames=1))
    ref = np.asarray(mpm_only.run(hp, st, n)[0].nodes)
    counts = np.asarray(mpm_only.counts)
    v = np.diff(ref, axis=0) / mpm_only.frame_dt
    ke = (counts * 0.5 * (v ** 2).sum(-1)).sum(-1) / counts.sum()  # (n,) after frame 1..n
    settled = ke < 0.5 * np.maximum.accumulate(ke)
    k = 1 + int(np.flatnonzero(settled)[0])  # frames in the warm-up
    assert 5 < k < n - 8  # the column is still collapsing after the 5-frame minimum
    sched = Schedule(warmup=5, warmup_settle=0.5, gns_frames=4, mpm_frames=2)
    res, _ = Hybrid(sim, gns, 2, 4, sched).run(hp, st, n)
    expected = [MPM_MODE] * k
    while len(expected) < n:
        expected += [GNS_MODE] * 4 + [MPM_MODE] * 2
    np.testing.assert_array_equal(res.mode, expected[:n])
    assert res.warmup_frames == k
    np.testing.assert_allclose(np.asarray(res.nodes)[:k + 1], ref[:k + 1], atol=1e-6)
    # the minimum still holds: a fraction met at once waits for ``warmup`` frames
    late = Schedule(warmup=k + 3, warmup_settle=0.5, gns_frames=4, mpm_frames=2)
    assert Hybrid(sim, gns, 2, 4, late).run(hp, st, n)[0].warmup_frames == k + 3
    assert "kinetic energy < 0.5 of its peak" in sched.label


def test_adaptive_switch_fires_on_the_indicator(model):
    gns, params, _ = model
    sim = MPM(small_scene(aspect_ratio=1.0))
    p, st = sim.params(), sim.init()
    loose = Hybrid(sim, gns, 2, 4, Schedule(gns_frames=8, mpm_frames=1,
                                                      adaptive_tol=1e9))
    tight = Hybrid(sim, gns, 2, 4, Schedule(gns_frames=8, mpm_frames=1,
                                                      adaptive_tol=1e-9))
    r_loose, _ = loose.run(HybridParams(p, params), st, 30)
    r_tight, _ = tight.run(HybridParams(p, params), st, 30)
    np.testing.assert_array_equal(r_loose.mode, modes_of(loose.schedule, 30))
    m = np.asarray(r_tight.mode)[5:]
    assert np.all(m[::2] == GNS_MODE) and np.all(m[1::2] == MPM_MODE)  # min segment: 1
    assert np.all(np.asarray(r_tight.indicator)[5:][m == GNS_MODE] > 0)


@pytest.mark.slow
def test_long_hybrid_rollout_stays_in_the_box_and_finite(model):
    gns, params, _ = model
    sim = MPM(small_scene(aspect_ratio=2.0, phi=20.0))
    p, st = sim.params(), sim.init()
    res, _ = Hybrid(sim, gns, 2, 4, Schedule(gns_frames=10, mpm_frames=1)).run(
        HybridParams(p, params), st, 200)
    x = np.asarray(res.positions)
    assert np.isfinite(x).all()
    lo, hi = np.asarray(sim.lo), np.asarray(sim.hi)
    assert (x >= lo - 1e-6).all() and (x <= hi + 1e-6).all()
    v = np.diff(x[-6:], axis=0) / res.frame_dt
    assert np.sqrt((v**2).sum(-1)).mean() < 0.02  # at rest (m/s) after 1 s


@pytest.mark.slow  # ~50 s of compilation on a quiet 2-core machine
@pytest.mark.parametrize("settle,aspect_ratio,n,h", [(None, 1.0, 25, 0.05),
                                                     (0.9, 0.5, 32, 0.01)])
def test_grad_through_hybrid_matches_finite_differences(model, x64, settle, aspect_ratio, n, h):
    """Exact gradients through MPM and GNS frames, with a fixed warm-up and with a settling
    one (the inversion's default schedule settles: its hand-off frame is a discrete choice,
    the same at phi and phi +- h here, so the derivative is that of the frames run; on the
    low column the loss wiggles at h = 0.05 deg: differences of -6.99e-4 there, -6.61e-4 at
    0.01 deg, against AD's -6.60e-4, the same with a fixed warm-up of as many frames)."""
    gns, params, _ = model
    params = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), params)
    sim = MPM(small_scene(phi=30.0, aspect_ratio=aspect_ratio), dtype=jnp.float64)
    st = sim.init()
    hyb = Hybrid(sim, gns, 2, 4, Schedule(warmup=5, warmup_settle=settle, gns_frames=3,
                                          mpm_frames=2))
    p0 = sim.params()
    start = hyb.run(HybridParams(p0, params), st, n)[1]

    def loss(phi):
        p = p0.replace(friction_angle=p0.friction_angle.at[0].set(phi))
        frames, _ = rollout(hyb, HybridParams(p, params), start, n, checkpoint_block=4)
        x = frames.positions
        return (runout(x[-1], method="softmax", temperature=5e-3),
                (jnp.any(frames.overflow), frames.mode))

    (L, (over, mode)), g = jax.jit(jax.value_and_grad(loss, has_aux=True))(30.0)
    assert not bool(over)
    (lp, (_, mode_p)), (lm, (_, mode_m)) = loss(30.0 + h), loss(30.0 - h)
    np.testing.assert_array_equal(mode_p, mode)
    np.testing.assert_array_equal(mode_m, mode)
    assert int(np.sum(np.asarray(mode) != MPM_MODE)) >= 6  # GNS frames were differentiated
    if settle is not None:  # the warm-up outlasted its 5-frame minimum
        assert int(np.argmin(np.asarray(mode) == MPM_MODE)) > 10
    fd = (lp - lm) / (2 * h)
    assert np.isfinite(g) and abs(g) > 1e-6
    np.testing.assert_allclose(g, fd, rtol=0.02)


def test_node_factor_keeps_the_trained_node_spacing():
    from diffgns.hybrid.compare import node_factor

    info = {"factor": 16, "source": {"cells_across": 16}}
    assert node_factor(info, 16) == 16
    assert node_factor(info, 32) == 64  # 8 x 8 particles of the finer MPM per node
    assert node_factor({"factor": 4, "source": {"cells_across": 8}}, 12) == 9
    with pytest.raises(ValueError, match="particles per node"):
        node_factor({"factor": 4, "source": {"cells_across": 8}}, 10)


def test_keep_inside_limits_each_axis_apart():
    """A cluster on the floor whose affine term stretches it along x and pushes one particle
    below the floor's margin: only the y part is limited, the x stretch is kept whole, every
    particle ends inside the inset box and the cluster's mean stays its node."""
    from diffgns.hybrid.handoff import keep_inside

    lo, hi, margin = jnp.array([0.0, 0.0]), jnp.array([1.0, 0.5]), 0.01
    node = jnp.array([0.5, 0.02])
    offset = jnp.array([[-0.01, 0.01, -0.01, 0.01], [-0.01, -0.01, 0.01, 0.01]])
    step = jnp.array([[-0.03, 0.03, -0.03, 0.03], [-0.005, 0.0, 0.0, 0.005]])
    cluster = jnp.zeros(4, jnp.int32)
    x_node = jnp.broadcast_to(node[:, None], (2, 4))
    x, stops = keep_inside(x_node, offset, step, cluster, 1, lo, hi, margin=margin)
    assert int(stops.moved) == 0
    np.testing.assert_allclose(x[0], node[0] + offset[0] + step[0], atol=1e-7)  # x kept
    assert float(x[1].min()) >= margin - 1e-7  # y limited to the margin
    assert float(x[1, 0]) < float(node[1] + offset[1, 0]) + 1e-7  # but still stretched
    np.testing.assert_allclose(x.mean(axis=1), node, atol=1e-7)
    # the one-factor limiter would have scaled the x stretch too
    unlimited = node[:, None] + offset + step
    assert float(unlimited[1].min()) < margin


def test_hybrid_reallocation_checks_node_compaction_like_the_gns(model):
    """The hybrid re-allocates its node list through the GNS's one mechanism
    (``GNS.grown_neighbors``): nodes squeezed to a third of their spread warn, nodes
    merely moved do not."""
    import warnings

    from diffgns.graph.gns import CompactionWarning
    from diffgns.hybrid.simulator import HybridFrame

    gns, _, _ = model
    sim = MPM(small_scene())
    hyb = Hybrid(sim, gns, 2, 4, Schedule(gns_frames=8, mpm_frames=1))
    state = hyb.init(sim.init())
    x0 = np.asarray(hyb.nodes(sim.init()))
    centre = x0.mean(0)

    def frames(last):
        nodes = np.stack([x0, x0, last])
        return HybridFrame(None, None, nodes, None, None, None, None, None)

    with warnings.catch_warnings():
        warnings.simplefilter("error", CompactionWarning)
        hyb.reallocate(state, frames(x0 + np.float32([0.01, 0.0])), 3, 0)
    with pytest.warns(CompactionWarning, match="by frame 2"):
        hyb.reallocate(state, frames(centre + (x0 - centre) / 3), 3, 0)


def test_segment_entry_stops_a_path_at_the_face_of_a_box():
    """Largest t in [0, 1] keeping base + t d out of every box: analytic cases."""
    from diffgns.hybrid.handoff import segment_entry

    box = jnp.array([[0.4, 0.0, 0.6, 1.0]])
    base = jnp.array([[0.0, 0.0, 0.5, 0.0, 0.0, 0.0], [0.5, 0.5, 0.5, 0.0, 0.0, 0.5]])
    d = jnp.array([[1.0, 0.3, 1.0, 1.0, 1.0, 1.0], [0.0, 0.0, 0.0, 1.0, 0.1, 0.0]])
    t = segment_entry(base, d, box)
    # straight in at x = 0.4; stops short of it; starts inside; the diagonal (t, t) enters
    # through the left face at t = 0.4
    np.testing.assert_allclose(t[:4], [0.4, 1.0, 0.0, 0.4], atol=1e-7)
    two = jnp.array([[0.4, 0.0, 0.6, 1.0], [0.5, 0.2, 0.7, 0.9]])
    # diagonal from the origin: the second box is entered at t = max(0.5, 0.2) = 0.5 but the
    # first already at x = 0.4 (y = 0.4 is inside [0, 1])
    np.testing.assert_allclose(segment_entry(base[:, 3:4], d[:, 3:4], two), [0.4], atol=1e-7)
    beside = jnp.array([[0.5, 0.2, 0.7, 0.9]])  # y only reaches 0.1: passes under it
    np.testing.assert_allclose(segment_entry(base[:, 4:5], d[:, 4:5], beside), [1.0])
    # exempt from the box it is inside; no box at all; a box parked far away
    exempt = jnp.array([[False, False, True, False, False, False]])
    assert float(segment_entry(base, d, box, exempt)[2]) == 1.0
    assert np.all(np.asarray(segment_entry(base, d, jnp.zeros((0, 4)))) == 1.0)
    parked = jnp.array([[1e3, 1e3, 1e3 + 1, 1e3 + 1]])
    assert np.all(np.asarray(segment_entry(base, d, parked)) == 1.0)


def test_keep_inside_keeps_particles_out_of_an_obstacle():
    """A cluster beside an obstacle whose affine term (and, for one cluster, its rigid
    offsets) would carry particles into it: no particle ends inside the obstacle grown by the
    margin. The affine stretch is scaled back (the cluster's mean stays its node); a rigid
    offset that would enter it stops its particle on the grown face, counted, without
    contracting the rest of its cluster; a cluster far from it is mapped unchanged, and a
    particle that was already inside is not pushed out by the map."""
    from diffgns.hybrid.handoff import keep_inside

    lo, hi, margin = jnp.array([0.0, 0.0]), jnp.array([1.0, 0.5]), 0.005
    obstacle = jnp.array([[0.5, 0.0, 0.6, 0.1]])
    # cluster 0 left of the obstacle (node x = 0.47), stretched towards it by the affine term;
    # cluster 1 far away; cluster 2 with its node 1 cm from the face and rigid offsets of 2 cm
    nodes = jnp.array([[0.47, 0.05], [0.2, 0.3], [0.485, 0.05]]).T
    cluster = jnp.array([0, 0, 1, 1, 2, 2], jnp.int32)
    offset = jnp.array([[-0.01, 0.01, -0.01, 0.01, -0.02, 0.02], [0.0] * 6])
    step = jnp.array([[-0.03, 0.03, -0.02, 0.02, 0.0, 0.0], [0.0] * 6])
    x_node = nodes[:, cluster]
    x_old = x_node + 0.25 * offset  # where the particles were: all outside the obstacle
    x, stops = keep_inside(x_node, offset, step, cluster, 3, lo, hi, x_old, margin, obstacle)
    grown_x0 = 0.5 - margin
    assert float(x[0, 1]) == pytest.approx(grown_x0, abs=1e-6)  # stretched up to the face
    np.testing.assert_allclose(x[:, :2].mean(axis=1), nodes[:, 0], atol=1e-6)
    np.testing.assert_allclose(x[:, 2:4], x_node[:, 2:4] + offset[:, 2:4] + step[:, 2:4],
                               atol=1e-7)  # far from the obstacle: unchanged
    # cluster 2: the particle whose rigid offset enters the obstacle stops on its face; the
    # other keeps its full offset (no contraction), and the stop is counted
    assert float(x[0, 5]) == pytest.approx(grown_x0, abs=1e-6)
    assert float(x[0, 4]) == pytest.approx(0.485 - 0.02, abs=1e-7)
    assert int(stops.moved) == 1
    assert float(stops.shift) == pytest.approx(0.505 - grown_x0, abs=1e-6)
    # without the obstacle both clusters would have entered it
    free, free_stops = keep_inside(x_node, offset, step, cluster, 3, lo, hi, x_old, margin)
    assert float(free[0, 1]) > 0.5 and float(free[0, 5]) > 0.5 and int(free_stops.moved) == 0
    # a particle already inside the obstacle is exempt: cluster 0 maps as without it
    inside_old = x_old.at[:, 1].set(jnp.array([0.55, 0.05]))
    y, _ = keep_inside(x_node, offset, step, cluster, 3, lo, hi, inside_old, margin, obstacle)
    np.testing.assert_allclose(y[:, :2], free[:, :2], atol=1e-7)


def test_a_node_inside_an_obstacle_does_not_collapse_its_cluster():
    """A cluster straddling an obstacle's corner has its mean (its node) inside the obstacle,
    as the MPM's own cluster means often have. The map no longer contracts it onto its node
    (16 particles at one point inside a solid, which then sank through it): every particle
    stays out of the grown obstacle, stopped where its own path enters it, each stop is
    counted, and a cluster elsewhere is mapped as before."""
    from diffgns.hybrid.handoff import keep_inside

    lo, hi, margin = jnp.array([0.0, 0.0]), jnp.array([1.0, 0.5]), 0.002
    obstacle = jnp.array([[0.5, 0.0, 0.6, 0.1]])
    # cluster 0: two particles on top of the obstacle, two at its left face; their mean
    # (0.525, 0.0825) is inside it. Cluster 1 far away. Both move 2 cm right, down 2 mm.
    x_old = jnp.array([[0.55, 0.58, 0.48, 0.49, 0.2, 0.21],
                       [0.11, 0.12, 0.05, 0.05, 0.3, 0.3]])
    cluster = jnp.array([0, 0, 0, 0, 1, 1], jnp.int32)
    nodes_old = jnp.stack([x_old[:, :4].mean(1), x_old[:, 4:].mean(1)], 1)
    assert 0.5 < float(nodes_old[0, 0]) < 0.6 and 0 < float(nodes_old[1, 0]) < 0.1
    move = jnp.array([0.02, -0.002])[:, None]
    x_node = nodes_old[:, cluster] + move
    offset = x_old - nodes_old[:, cluster]
    step = 0.01 * offset  # a 1% stretch
    x, stops = keep_inside(x_node, offset, step, cluster, 2, lo, hi, x_old, margin, obstacle)
    g = np.asarray(obstacle[0]) + margin * np.array([-1, -1, 1, 1])
    inside = (np.asarray(x[0]) > g[0]) & (np.asarray(x[0]) < g[2]) \
        & (np.asarray(x[1]) > g[1]) & (np.asarray(x[1]) < g[3])
    assert not inside.any()
    spread = np.linalg.norm(np.asarray(x[:, :4]) - np.asarray(x[:, :4]).mean(1, keepdims=True),
                            axis=0)
    assert spread.min() > 0.01  # not collapsed onto the node
    # the two left-face particles moving right are stopped at the grown face
    np.testing.assert_allclose(np.asarray(x[0, 2:4]), g[0], atol=1e-6)
    assert int(stops.moved) == 2 and 0.01 < float(stops.shift) < 0.015
    # cluster 1, away from the obstacle: the full affine map
    np.testing.assert_allclose(x[:, 4:], x_node[:, 4:] + offset[:, 4:] + step[:, 4:], atol=1e-7)


def test_within_reach_has_a_finite_gradient_at_the_node_and_beyond_reach():
    """A particle exactly at its node (a one-particle cluster) and one beyond reach: the
    shortening's gradient is finite (no 0/0 from the length's square root)."""
    r = jnp.asarray([[0.0, 0.1, -0.1], [0.0, 0.0, 0.0]])
    cluster, counts = jnp.asarray([0, 1, 1]), jnp.asarray([1.0, 2.0])
    g = jax.grad(lambda y: jnp.sum(within_reach(y, cluster, counts, 0.03) ** 2))(r)
    assert np.isfinite(np.asarray(g)).all()
    # beyond reach the shortened offset no longer grows with the offset
    pair = lambda a: jnp.stack([jnp.stack([a, -a]), jnp.zeros(2)])  # noqa: E731
    g1 = jax.grad(lambda a: within_reach(pair(a), jnp.asarray([0, 0]), jnp.asarray([2.0]),
                                         0.03)[0, 0])(0.1)
    assert float(g1) == pytest.approx(0.0, abs=1e-6)
