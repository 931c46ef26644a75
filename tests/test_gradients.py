"""Gradients through MPM kernels and whole rollouts: AD against finite differences (float64)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from diffgns import MPM, Body, Elastic, Rectangle, Scene, Wall, Walls
from diffgns.interface import rollout_jit
from diffgns.metrics import runout
from diffgns.mpm import boundaries, constitutive
from diffgns.mpm.shape import bspline_weights, stencil
from diffgns.mpm.transfer import g2p, grid_velocity, p2g
from diffgns.scene.builders import column_collapse


def test_kernel_gradients(x64):
    check_grads(bspline_weights, (jnp.linspace(0.55, 1.45, 7),), order=2, modes=("fwd", "rev"))
    rng = np.random.default_rng(0)
    # a plastically loaded (sheared and compressed) state, away from the apex kink
    F = jnp.asarray(np.array([[1.02, 0.2], [0.0, 0.99]])[:, :, None]
                    + 0.01 * rng.normal(size=(2, 2, 5)))
    n = 5
    E, nu = jnp.full(n, 2e6), jnp.full(n, 0.3)
    phi, c = jnp.full(n, 30.0), jnp.zeros(n)
    _, Fp = constitutive.drucker_prager(F, E, nu, phi, c)
    assert not np.allclose(np.asarray(Fp), np.asarray(F))  # the return map is active
    check_grads(lambda F, phi: constitutive.drucker_prager(F, E, nu, phi, c), (F, phi),
                order=1, modes=("fwd", "rev"), eps=1e-7, rtol=1e-4, atol=1e-4)
    check_grads(lambda F: constitutive.elastic_corotated(F, E, nu)[0], (F,), order=1,
                modes=("rev",), eps=1e-7, rtol=1e-4)
    # Coulomb wall friction with sliding nodes moving into the wall
    vx, vy = jnp.asarray([0.5, -0.3, 0.2]), jnp.asarray([-0.2, -0.1, -0.4])
    check_grads(lambda vx, vy, mu: boundaries.wall_friction((vx, vy), (0.0, 1.0), mu),
                (vx, vy, 0.3), order=1, modes=("fwd", "rev"))


def test_transfer_gradients(x64):
    rng = np.random.default_rng(1)
    X = jnp.asarray(4.0 + 3.0 * rng.random((2, 6)))
    shape = (10, 10)

    def roundtrip(X, v):
        idx, w, dpos = stencil(X, shape)
        m = jnp.ones(X.shape[1])
        grid = p2g(idx, w, dpos, m, m * v, jnp.zeros((2, 2, X.shape[1])), 100, 0.1)
        return g2p(idx, w, dpos, grid_velocity(grid).reshape(2, *shape), 0.1)

    check_grads(roundtrip, (X, jnp.asarray(rng.normal(size=(2, 6)))), order=1,
                modes=("rev",), eps=1e-6, rtol=1e-4, atol=1e-6)


def _column_grad(name, value, frames=30, cells=4):
    scene = column_collapse(width=0.1, aspect_ratio=1.0, friction_angle=35.0,
                            cells_across=cells)
    sim = MPM(scene, dtype="float64")
    base, state = sim.params(), sim.init()

    def f(v):
        p = base.replace(**{name: jnp.reshape(v, (1,))})
        pos = rollout_jit(sim, p, state, n_frames=frames, checkpoint_block=10)[0].positions
        return runout(pos[-1], method="softmax")

    g = jax.grad(f)(value)
    h = 1e-4 * value
    fd = (f(value + h) - f(value - h)) / (2 * h)
    return float(g), float(fd)


@pytest.mark.parametrize("name,value", [
    ("friction_angle", 35.0), pytest.param("E", 2e6, marks=pytest.mark.slow)])
def test_column_runout_gradient_matches_finite_differences(name, value, x64):
    g, fd = _column_grad(name, value)
    assert abs(fd) > 0
    assert g == pytest.approx(fd, rel=0.01)


@pytest.mark.parametrize("flip", [0.0, 0.99])
def test_sliding_distance_gradient_wrt_wall_mu(x64, flip):
    th = np.deg2rad(30.0)
    body = Body(Rectangle(0.1, 0.0, 0.2, 0.04), Elastic(E=2e6, nu=0.3, rho=1000.0))
    scene = Scene(domain=((0.0, 1.0), (0.0, 0.2)), dx=0.02, bodies=(body,),
                  gravity=(9.81 * np.sin(th), -9.81 * np.cos(th)),
                  walls=Walls(bottom=Wall("friction", 0.3)), flip=flip)
    sim = MPM(scene, dtype="float64")
    base, state = sim.params(), sim.init()

    def dist(mu):
        p = base.replace(wall_mu=base.wall_mu.at[2].set(mu))
        pos = rollout_jit(sim, p, state, n_frames=40)[0].positions
        return jnp.mean(pos[-1, :, 0] - pos[0, :, 0])

    g = float(jax.grad(dist)(0.3))
    fd = float((dist(0.3 + 1e-5) - dist(0.3 - 1e-5)) / 2e-5)
    assert g < 0 and g == pytest.approx(fd, rel=0.01)


@pytest.mark.slow  # float32 63 s in the full suite (2026-12-03, loaded machine)
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_gradient_finite_through_1000_substeps_of_sand(dtype, x64):
    """From F = I (repeated singular values), particles at rest, empty nodes, walls."""
    scene = column_collapse(width=0.1, aspect_ratio=1.0, cells_across=4,
                            friction_angle=30.0)
    sim = MPM(scene, dtype=dtype)
    frames = -(-1000 // scene.substeps) + 1
    assert frames * scene.substeps >= 1000
    base, state = sim.params(), sim.init()

    def loss(p, s):
        pos = rollout_jit(sim, p, s, n_frames=frames, checkpoint_block=16)[0].positions
        return runout(pos[-1], method="softmax") + jnp.mean(pos[-1, :, 1])

    # the state carries an int32 clamp count (diffgns.clamp): its cotangent is float0
    gp, gs = jax.grad(loss, argnums=(0, 1), allow_int=True)(base, state)
    floats = [leaf for leaf in jax.tree.leaves((gp, gs))
              if jnp.issubdtype(leaf.dtype, jnp.floating)]
    assert len(floats) >= 5
    for leaf in floats:
        assert np.isfinite(np.asarray(leaf)).all()
    assert float(jnp.abs(gp.friction_angle).sum()) > 0
    assert float(jnp.linalg.norm(gs.x)) > 0


@pytest.mark.slow  # 28 s in the full suite beside a 2-process CFD job (2026-12-03)
def test_gradients_wrt_density_poisson_velocity_and_geometry(x64):
    """value_and_grad and jvp w.r.t. rho, nu, a per-body initial velocity and the column's
    aspect ratio (a vertical stretch of the initial particles and their volumes)."""
    scene = column_collapse(width=0.1, aspect_ratio=1.0, friction_angle=35.0, cells_across=4)
    sim = MPM(scene, dtype="float64")
    base, state = sim.params(), sim.init()

    def f(theta):
        p = base.replace(rho=base.rho * theta["rho_scale"], nu=base.nu * 0 + theta["nu"])
        s = state.replace(x=state.x.at[1].multiply(theta["stretch"]),
                          vol=state.vol * theta["stretch"],
                          v=state.v + jnp.stack([theta["vx"], 0.0])[:, None])
        pos = rollout_jit(sim, p, s, n_frames=20, checkpoint_block=10)[0].positions
        return runout(pos[-1], method="softmax")

    theta = {k: jnp.asarray(v) for k, v in
             dict(rho_scale=1.0, nu=0.3, stretch=1.0, vx=0.1).items()}
    val, g = jax.value_and_grad(f)(theta)
    steps = dict(rho_scale=1e-4, nu=1e-5, stretch=1e-5, vx=1e-5)
    for k, h in steps.items():
        fd = (f(dict(theta, **{k: theta[k] + h})) - f(dict(theta, **{k: theta[k] - h}))) / (2 * h)
        assert float(g[k]) == pytest.approx(float(fd), rel=0.02, abs=1e-9), k
    assert float(g["stretch"]) > 0 and float(g["vx"]) > 0  # taller/faster runs farther
    tangent = {k: jnp.asarray(1.0 if k == "vx" else 0.0) for k in theta}
    _, jv = jax.jvp(f, (theta,), (tangent,))
    assert float(jv) == pytest.approx(float(g["vx"]), rel=1e-6)
    assert np.isfinite(float(val))


def test_wall_friction_and_empty_node_gradients_finite_at_rest(x64):
    """Zero velocity at a frictional wall and empty grid nodes: finite (zero) gradients."""
    g = jax.grad(lambda v, mu: sum(jnp.sum(c) for c in boundaries.wall_friction(
        (v[0], v[1]), (0.0, 1.0), mu)), argnums=(0, 1))(jnp.zeros((2, 4)), 0.4)
    assert all(np.isfinite(np.asarray(x)).all() for x in g)
    empty = jnp.zeros((5, 3))  # no mass anywhere
    gv = jax.grad(lambda grid: grid_velocity(grid).sum())(empty)
    assert np.isfinite(np.asarray(gv)).all()


def test_grid_velocity_derivative_bounded_at_a_stencil_corner_node():
    """A node only the far corner of one particle's stencil reaches (mass ~3e-20 kg in
    float32): the cotangent reaching it through G2P carries the same tiny weight, so the
    mass and momentum cotangents are bounded; computed through 1 / m^2 (~1e39) they were
    inf. Checked against float64, and against finite differences at ordinary masses."""
    m_small, w_small, v = 3e-20, 1.6e-18, np.array([0.3, -0.7])
    grid = np.array([[0.02, -0.01, 0.01],          # an ordinary node
                     [*(m_small * v), m_small],    # the corner node
                     [0.0, 0.0, 0.0]])             # an empty node
    cot = np.array([[0.5, 1.0 * w_small, 0.2],     # G2P: the corner node's cotangent
                    [-0.4, -2.0 * w_small, 0.1]])  # carries the particle's weight

    def vjp(dtype):
        g, pull = jax.vjp(grid_velocity, jnp.asarray(grid, dtype))
        return np.asarray(g), np.asarray(pull(jnp.asarray(cot, dtype))[0])

    with jax.enable_x64(True):
        v64, g64 = vjp(jnp.float64)
        check_grads(grid_velocity, (jnp.asarray([[0.6, -0.3, 1.5], [0.2, 0.1, 0.7]]),),
                    order=2, modes=["fwd", "rev"], eps=1e-6)
    v32, g32 = vjp(jnp.float32)
    assert np.isfinite(g32).all()
    np.testing.assert_allclose(v32[:, 1], v, rtol=1e-6)
    np.testing.assert_array_equal(v32[:, 2], 0.0)   # empty: at rest, zero gradient
    np.testing.assert_array_equal(g32[2], 0.0)
    np.testing.assert_allclose(g32, g64, rtol=1e-5, atol=1e-30)
    assert 10 < abs(g32[1, 2]) < 1e3  # -v . cot / m = -91 kg^-1 m/s: bounded, not zero


@pytest.mark.slow  # ~60 s: 100 frames of a 2,560-particle column, float32 and float64
def test_jitted_gradient_through_a_column_finite_where_it_once_was_nan():
    """The inverse sweep's case (gns_cg16_pfn's column a = 2.5, phi = 45): under jit the
    float32 gradient of the runout through 100 frames was NaN (a corner-stencil node at
    frame 92); it is finite and within 1% of float64."""
    from diffgns.inverse.simulators import Column, ColumnCase, model_info

    def grad(dtype):
        col = Column(ColumnCase.from_model(model_info("gns_cg16_pfn"), 2.5), dtype=dtype)

        def f(phi):
            x = col.mpm_positions({"friction_angle": phi}, 100, 25)[-1, :, 0]
            return jax.nn.logsumexp(x / 0.002) * 0.002
        return float(jax.jit(jax.grad(f))(jnp.asarray(45.0, dtype)))

    g32 = grad(jnp.float32)
    with jax.enable_x64(True):
        g64 = grad(jnp.float64)
    assert np.isfinite(g32) and g64 < 0
    assert g32 == pytest.approx(g64, rel=1e-2)
