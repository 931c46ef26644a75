"""The MPM in 3D: the same code path as 2D, checked against analytic results and 2D."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from diffgns import MPM, Body, BoxObstacle, Elastic, Fluid, Sand, Scene, Wall, Walls
from diffgns.errors import SceneError
from diffgns.mpm import constitutive
from diffgns.mpm import linalg as la
from diffgns.mpm.shape import stencil
from diffgns.mpm.transfer import g2p, p2g
from diffgns.scene import Box, Cylinder, Rectangle
from diffgns.scene.builders3d import axisymmetric_column, slab_column
from diffgns.scene.files import scene_from_dict, scene_to_dict
from test_mpm_physics import _check_p2g_against_loops


def block3d(gravity=(0.0, -9.81, 0.0), velocity=(0.0, 0.0, 0.0), material=None,
            box=(0.08, 0.06, 0.08, 0.14, 0.1, 0.14), dx=0.02, domain=None, **kw):
    material = material or Elastic(E=1e5, nu=0.3, rho=1000.0)
    domain = domain or ((0, 0.22), (0, 0.2), (0, 0.22))
    return Scene(domain=domain, dx=dx, bodies=(Body(Box(*box), material, velocity=velocity),),
                 gravity=gravity, **kw)


def _mats(rng, n, scale=0.3):
    return jnp.asarray(np.eye(3)[:, :, None] + scale * rng.normal(size=(3, 3, n)))


# ------------------------------------------------------------------ linear algebra
def test_svd3_reconstructs_with_rotations(x64):
    rng = np.random.default_rng(0)
    F = _mats(rng, 50)
    F = F.at[:, :, 0].set(jnp.diag(jnp.asarray([1.0, 1.0, -0.5])))  # det < 0
    U, s, V = la.svd3(F)
    rec = la.matmul(la.matmul(U, la.diag(s[0], s[1], s[2])), la.transpose(V))
    np.testing.assert_allclose(np.asarray(rec), np.asarray(F), atol=1e-12)
    np.testing.assert_allclose(np.asarray(la.det(U)), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(la.det(V)), 1.0, atol=1e-12)
    assert float(s[2, 0]) == pytest.approx(-0.5)


def test_svd3_jvp_matches_finite_differences(x64):
    rng = np.random.default_rng(1)
    check_grads(la.svd3, (_mats(rng, 6),), order=1, modes=("fwd", "rev"), atol=1e-5,
                rtol=1e-5, eps=1e-6)


def _hencky_loss(F):
    U, s, V = la.svd3(F)
    return jnp.sum(la.matmul(la.matmul(U, la.diag(*[jnp.log(s[i]) for i in range(3)])),
                             la.transpose(U)) ** 2)


@pytest.mark.parametrize("diag", [(1.0, 1.0, 1.0), (1.2, 1.0, 1.0), (0.9, 1.1, 1.1)])
def test_svd3_gradient_finite_and_exact_at_repeated_values(x64, diag):
    """At F = I and uniaxial F (two or three equal singular values) the gradient of an
    isotropic function of F is finite and equals central differences (|log F|^2 here)."""
    F = la.diag(*[jnp.full(1, v) for v in diag])
    g = np.asarray(jax.grad(_hencky_loss)(F))
    assert np.isfinite(g).all()
    h = 1e-6
    fd = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            E = np.zeros((3, 3, 1))
            E[i, j] = h
            fd[i, j] = (_hencky_loss(F + E) - _hencky_loss(F - E)) / (2 * h)
    np.testing.assert_allclose(g[:, :, 0], fd, atol=1e-6)


def test_polar_rotation_3d(x64):
    rng = np.random.default_rng(2)
    F = _mats(rng, 20)
    R = la.polar_rotation(F)
    RtR = la.matmul(la.transpose(R), R)
    np.testing.assert_allclose(np.asarray(RtR), np.asarray(la.eye(20, jnp.float64, 3)),
                               atol=1e-12)
    S = la.matmul(la.transpose(R), F)  # symmetric positive definite
    np.testing.assert_allclose(np.asarray(S), np.asarray(la.transpose(S)), atol=1e-12)
    g = jax.grad(lambda F: la.polar_rotation(F).sum())(la.eye(1, jnp.float64, 3))
    assert np.isfinite(np.asarray(g)).all()


# ------------------------------------------------------------------ Drucker–Prager in 3D
def _dp(F, phi=30.0, c=0.0):
    n = F.shape[-1]
    one = jnp.ones(n, F.dtype)
    return constitutive.drucker_prager(F, 2e6 * one, 0.3 * one, phi * one, c * one)


def test_drucker_prager_3d_lands_on_the_shear_meridian_cone(x64):
    """A sheared, compressed state is returned onto |dev tau| = -alpha tr tau with
    alpha = sqrt(2) sin(phi)/3, volume kept (non-dilatant flow)."""
    F = jnp.asarray(np.array([[0.98, 0.08, 0.0], [0.0, 0.99, 0.03], [0.01, 0.0, 0.985]]))[..., None]
    tau, Fn = _dp(F)
    t = np.asarray(tau)[:, :, 0]
    dev = t - np.trace(t) / 3 * np.eye(3)
    alpha = np.sqrt(2) * np.sin(np.deg2rad(30.0)) / 3
    assert np.linalg.norm(dev) == pytest.approx(-alpha * np.trace(t), rel=1e-9)
    assert np.linalg.det(np.asarray(Fn)[:, :, 0]) == pytest.approx(np.linalg.det(F[:, :, 0]),
                                                                 rel=1e-12)


def test_drucker_prager_3d_plane_strain_matches_2d_mohr_coulomb(x64):
    """In plane-strain flow (sigma_zz = mean), the 3D cone gives (s1 - s2)/2 = sin(phi) p:
    the same Mohr–Coulomb angle as the 2D law."""
    phi = np.deg2rad(30.0)
    alpha = float(constitutive.cone_slope(30.0, 3))
    # principal Kirchhoff stresses (s1, s2, mean) on the cone: |dev| = sqrt(2) R = 3 alpha p
    p = 1.0
    R = 3 * alpha * p / np.sqrt(2)
    assert R == pytest.approx(np.sin(phi) * p, rel=1e-12)
    alpha2 = float(constitutive.cone_slope(30.0, 2))
    assert np.sqrt(2) * np.sin(phi) / 2 == pytest.approx(alpha2, rel=1e-12)


@pytest.mark.parametrize("F", [np.eye(3), np.diag([0.97, 1.0, 1.0]), np.diag([1.02, 1, 1])])
def test_drucker_prager_3d_gradient_finite_at_repeated_singular_values(x64, F):
    Fj = jnp.asarray(F)[..., None]

    def loss(F, phi):
        tau, Fn = _dp(F, phi)
        return jnp.sum(tau ** 2) * 1e-12 + jnp.sum(Fn ** 2)

    gF, gphi = jax.grad(loss, argnums=(0, 1))(Fj, 30.0)
    assert np.isfinite(np.asarray(gF)).all() and np.isfinite(float(gphi))


def test_drucker_prager_3d_gradient_matches_finite_differences(x64):
    """Away from the apex kink, plastic and elastic states, forward and reverse mode."""
    F_plastic = jnp.asarray([[0.98, 0.08, 0.0], [0.0, 0.99, 0.03], [0.01, 0.0, 0.985]])
    F_elastic = jnp.asarray([[0.99, 0.002, 0.0], [0.001, 0.995, 0.0], [0.0, 0.001, 0.993]])
    F = jnp.stack([F_plastic, F_elastic], -1)
    check_grads(lambda F, phi: _dp(F, phi)[0] * 1e-5, (F, 30.0), order=1,
                modes=("fwd", "rev"), atol=1e-5, rtol=1e-5, eps=1e-7)


# ------------------------------------------------------------------ transfers
def test_p2g_mass_exact_and_row_transfers_equal_27_node_loops(x64):
    rng = np.random.default_rng(3)
    shape = (6, 7, 8)
    X = jnp.asarray(np.stack([rng.uniform(0.5, n - 1.5, 100) for n in shape]))
    X = X.at[:, 0].set(jnp.asarray([0.5, 0.5, 0.5])).at[:, 1].set(
        jnp.asarray([4.49, 5.49, 6.49]))
    idx, w, dpos = stencil(X, shape)
    assert idx.shape == (27, 100)
    np.testing.assert_allclose(np.asarray(w.sum(0)), 1.0, rtol=1e-13)
    m = jnp.asarray(rng.uniform(1, 2, 100))
    grid = p2g(idx, w, dpos, m, jnp.zeros((3, 100)), jnp.zeros((3, 3, 100)), 6 * 7 * 8, 0.1)
    assert float(grid[:, 3].sum()) == pytest.approx(float(m.sum()), rel=1e-13)
    gv = jnp.asarray(rng.normal(size=(3, *shape)))
    v, C = g2p(idx, w, dpos, gv, 0.1)
    g = gv.reshape(3, -1)[:, idx]
    np.testing.assert_allclose(np.asarray(v), np.asarray((w * g).sum(1)), rtol=1e-12)
    C_ref = 40.0 * jnp.einsum("aon,bon->abn", w * g, dpos)
    np.testing.assert_allclose(np.asarray(C), np.asarray(C_ref), rtol=1e-11, atol=1e-11)
    _check_p2g_against_loops(rng, idx, w, dpos, 6 * 7 * 8, 0.1)


# ------------------------------------------------------------------ whole solver
def test_momentum_conserved_in_free_flight_3d(x64):
    scene = block3d(gravity=(0.0, 0.0, 0.0), velocity=(0.2, -0.1, 0.15))
    sim = MPM(scene)
    p, s = sim.params(), sim.init()
    c = s.x.mean(1, keepdims=True)
    spin = 2.0 * jnp.stack([-(s.x[1] - c[1]), s.x[0] - c[0], jnp.zeros_like(s.x[2])])
    s = s.replace(v=s.v + spin)
    traj = sim.run(p, s, 4, check=False)[0]
    m = np.asarray(sim.mass(p, s))
    mom = np.einsum("n,tnd->td", m, np.asarray(traj.velocities))
    np.testing.assert_allclose(mom, np.broadcast_to(mom[0], mom.shape), rtol=0,
                               atol=1e-12 * m.sum())


def test_free_fall_3d(x64):
    scene = block3d(gravity=(1.0, -9.81, 2.0))
    sim = MPM(scene)
    traj = sim.run(sim.params(), sim.init(), 4, check=False)[0]
    n = 4 * sim.n_sub  # symplectic Euler: x_n - x_0 = g dt^2 n (n + 1) / 2, exactly
    disp = np.asarray(traj.positions[-1] - traj.positions[0])
    expect = np.array([1.0, -9.81, 2.0]) * sim.dt**2 * n * (n + 1) / 2
    np.testing.assert_allclose(disp, np.broadcast_to(expect, disp.shape), rtol=1e-9)


def test_block_slides_down_tilted_floor_3d():
    """Gravity tilted by 30 deg in x (the floor tilted), Coulomb floor mu = 0.3: the block's
    acceleration is g (sin 30 - mu cos 30) within 5%; it does not move in z."""
    th, mu, g = np.deg2rad(30.0), 0.3, 9.81
    scene = block3d(gravity=(g * np.sin(th), -g * np.cos(th), 0.0),
                    box=(0.04, 0.0, 0.04, 0.12, 0.04, 0.12), dx=0.02,
                    domain=((0, 0.6), (0, 0.1), (0, 0.16)),
                    material=Elastic(E=2e6, nu=0.3, rho=1000.0),
                    walls=Walls(bottom=Wall("friction", mu)))
    sim = MPM(scene)
    traj = sim.run(sim.params(), sim.init(), 40, check=False)[0]
    x = np.asarray(traj.positions).mean(1)
    t = np.asarray(traj.times)
    a_fit = 2 * np.polyfit(t, x[:, 0] - x[0, 0], 2)[0]
    assert a_fit == pytest.approx(g * (np.sin(th) - mu * np.cos(th)), rel=0.05)
    assert abs(x[-1, 2] - x[0, 2]) < 1e-5


@pytest.mark.slow  # 33 s in the full suite beside a 2-process CFD job (2026-12-03)
def test_jit_equals_eager_3d():
    scene = block3d(material=Sand(), walls=Walls.all("friction", 0.3),
                    obstacles=(BoxObstacle(0.16, 0.0, 0.2, 0.04, z0=0.0, z1=0.22),))
    sim = MPM(scene)
    p, s = sim.params(), sim.init()
    s = s.replace(v=s.v.at[1].set(-1.0))
    eager = s
    with jax.disable_jit():
        for _ in range(2):
            eager = sim.substep(p, eager)
    jitted = jax.jit(lambda p, s: sim.substep(p, sim.substep(p, s)))(p, s)
    np.testing.assert_allclose(np.asarray(jitted.x), np.asarray(eager.x), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(np.asarray(jitted.F), np.asarray(eager.F), rtol=1e-5, atol=1e-6)


def _traced(scene) -> set:
    sim = MPM(scene)
    jp = str(jax.make_jaxpr(sim.substep)(sim.params(), sim.init()))
    names = ["drucker_prager", "elastic_corotated", "elastic_linear", "fluid", "wall_friction",
             "wall_sticky", "wall_slip", "obstacle_sticky", "obstacle_friction", "svd3"]
    return {n for n in names if f"name={n}" in jp}


def test_effects_declared_in_3d():
    assert _traced(block3d(material=Fluid())) == {"fluid", "wall_slip"}
    assert _traced(block3d(material=Elastic(model="linear"))) == {"elastic_linear", "wall_slip"}
    assert _traced(block3d(material=Elastic())) == {"elastic_corotated", "svd3", "wall_slip"}
    sand = block3d(material=Sand(), walls=Walls(Wall("slip"), Wall("slip"),
                                                Wall("friction", 0.4), Wall("slip"),
                                                Wall("sticky"), Wall("slip")),
                   obstacles=(BoxObstacle(0.16, 0.0, 0.2, 0.04, Wall("friction", 0.2),
                                          z0=0.0, z1=0.1),))
    assert _traced(sand) == {"drucker_prager", "svd3", "wall_slip", "wall_friction",
                             "wall_sticky", "obstacle_friction"}


# ------------------------------------------------------------------ scenes
def test_scene_3d_dimension_walls_and_toml_round_trip():
    sc = axisymmetric_column(radius=0.04, aspect_ratio=1.0, cells_across=2)
    assert sc.dim == 3 and len(sc.grid_shape) == 3 and sc.gravity == (0.0, -9.81, 0.0)
    assert [w.kind for w in sc.wall_list] == ["slip", "slip", "friction", "slip", "slip",
                                              "slip"]
    x = sc.particles()["x"]
    assert x.shape[1] == 3
    vol = sc.particles()["vol"].sum()
    assert vol == pytest.approx(np.pi * 0.04**2 * 0.04, rel=1e-12)
    assert scene_from_dict(scene_to_dict(sc)) == sc
    assert MPM(sc).params().wall_mu.shape == (6,)


@pytest.mark.parametrize("bad,match", [
    (dict(bodies=(Body(Rectangle(0, 0, 0.1, 0.1), Sand()),)), "2D shape"),
    (dict(gravity=(0.0, -9.81)), "3 finite numbers"),
    (dict(obstacles=(BoxObstacle(0.0, 0.0, 0.1, 0.1),)), "give z0 and z1"),
])
def test_scene_3d_errors_name_the_field(bad, match):
    kw = dict(domain=((0, 0.2), (0, 0.2), (0, 0.2)), dx=0.02,
              bodies=(Body(Box(0.0, 0.0, 0.0, 0.1, 0.1, 0.1), Sand()),))
    kw.update(bad)
    with pytest.raises(SceneError, match=match):
        Scene(**kw)


def test_scene_body_errors_3d():
    with pytest.raises(SceneError, match="perfect cube"):
        Body(Cylinder(0.1, 0.1, 0.05, 0.0, 0.1), Sand(), particles_per_cell=4)
    with pytest.raises(SceneError, match="3 finite numbers"):
        Body(Box(0, 0, 0, 1, 1, 1), Sand(), velocity=(1.0, 0.0))
    with pytest.raises(SceneError, match="depth walls"):
        Scene(bodies=(Body(Rectangle(0, 0, 0.1, 0.1), Sand()),),
              walls=Walls(back=Wall("sticky")))
    with pytest.raises(SceneError, match="'box' or 'cylinder'"):
        scene_from_dict({"scene": {"domain": [[0, 1], [0, 1], [0, 1]]},
                         "bodies": [{"shape": {"type": "sphere"}, "material": {"type": "sand"}}]})


def test_2d_scene_api_unchanged():
    """2D scenes keep four walls, (4,) wall_mu and a 2D gravity default."""
    sc = Scene(bodies=(Body(Rectangle(0.1, 0.1, 0.2, 0.2), Sand()),),
               walls=Walls.all("friction", 0.3))
    assert sc.dim == 2 and sc.gravity == (0.0, -9.81) and len(sc.wall_list) == 4
    assert MPM(sc).params().wall_mu.shape == (4,)
    assert sc.bodies[0].particles_per_cell == 4 and sc.bodies[0].velocity == (0.0, 0.0)


@pytest.mark.slow
def test_quasi_2d_slab_matches_2d_collapse():
    """A thin 3D slab between frictionless walls collapses like the 2D column (plane strain):
    runout and mean height within 5%."""
    from diffgns.scene.builders import column_collapse

    kw = dict(width=0.1, aspect_ratio=1.0, friction_angle=30.0, cells_across=10)
    two = column_collapse(particles_per_cell=4, **kw)
    three = slab_column(depth_cells=2, particles_per_cell=8, **kw)
    out = []
    for sc in (two, three):
        sim = MPM(sc)
        traj = sim.run(sim.params(), sim.init(), 80)[0]
        x = np.asarray(traj.positions[-1])
        out.append((np.percentile(x[:, 0], 99), x[:, 1].mean()))
    assert out[1][0] == pytest.approx(out[0][0], rel=0.05)
    assert out[1][1] == pytest.approx(out[0][1], rel=0.05)


def test_vtk_writes_3d_points(tmp_path):
    """write_vtk keeps z of a 3D trajectory: the .vtu holds the (N, 3) points as written."""
    from diffgns.io.figures import write_vtk
    from diffgns.trajectory import Trajectory

    rng = np.random.default_rng(0)
    pos = rng.uniform(size=(2, 5, 3))
    traj = Trajectory(positions=pos, velocities=rng.normal(size=(2, 5, 3)),
                      particle_type=np.full(5, 6, np.int32), material=np.zeros(5),
                      frame_dt=0.01, bounds=((0, 1), (0, 1), (0, 1)))
    paths = write_vtk(traj, tmp_path, every=1)
    raw = paths[1].read_bytes()
    assert b'NumberOfPoints="5"' in raw
    assert np.ascontiguousarray(pos[1], np.float64).tobytes() in raw
    assert paths[-1].exists()


@pytest.mark.slow
@pytest.mark.parametrize("a", [
    pytest.param(0.5, marks=pytest.mark.xfail(
        strict=True, reason="measured p99 0.384 vs 0.62 (-38%) at R0 = 12 cells, 2026-12-04 "
        "(collapse_resolution_3d_12cells.json): the short column's thin deposit edge needs a "
        "finer grid (docs/guides/mpm.md)")),
    1.0, 1.5, 2.0])
def test_axisymmetric_column_runout_scaling(a):
    """Axisymmetric collapse against Lube et al. (2004): (R_inf - R0)/R0 = 1.24 a (a <= 1.7),
    1.6 a^(1/2) above, within 30%; the deposit stays axisymmetric (the 99th-percentile
    radius of eight 45-degree sectors within 15% of each other). R0 = 12 cells (5 cells
    gave -37 to -72%: the runout grows with resolution); 22k-87k particles, minutes each."""
    from diffgns.scene.builders3d import axisymmetric_runout_estimate

    R0 = 0.05
    sc = axisymmetric_column(radius=R0, aspect_ratio=a, cells_across=12)
    sim = MPM(sc)
    frames = int(np.ceil(4.0 * np.sqrt(a * R0 / 9.81) / sc.frame_dt)) + 40
    traj = sim.run(sim.params(), sim.init(), frames)[0]
    x = np.asarray(traj.positions[-1])
    assert np.abs(np.asarray(traj.velocities[-1])).max() < 0.05  # at rest
    c = np.array([sc.domain[0][1] / 2, sc.domain[2][1] / 2])
    d = x[:, [0, 2]] - c
    r, th = np.hypot(d[:, 0], d[:, 1]), np.arctan2(d[:, 1], d[:, 0])
    run = (np.percentile(r, 99) - R0) / R0
    assert run == pytest.approx(axisymmetric_runout_estimate(a), rel=0.3)
    sectors = [np.percentile(r[(th >= lo) & (th < lo + np.pi / 4)], 99)
               for lo in np.arange(-np.pi, np.pi - 1e-9, np.pi / 4)]
    assert (max(sectors) - min(sectors)) / np.mean(sectors) < 0.15
