"""MPM physics against analytic results."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns import MPM, Body, Elastic, Rectangle, Sand, Scene, Wall, Walls
from diffgns.interface import rollout_jit
from diffgns.mpm.shape import stencil
from diffgns.mpm.transfer import g2p, p2g


def elastic_block(gravity=(0.0, -9.81), velocity=(0.0, 0.0), domain=((0, 1), (0, 1)),
                  rect=(0.4, 0.4, 0.6, 0.5), walls=Walls(), E=1e5, dx=0.02, **kw):
    body = Body(Rectangle(*rect), Elastic(E=E, nu=0.3, rho=1000.0), velocity=velocity)
    return Scene(domain=domain, dx=dx, bodies=(body,), gravity=gravity, walls=walls, **kw)


def test_mass_transfer_exact():
    """P2G partitions mass exactly: grid mass equals particle mass."""
    sim = MPM(elastic_block())
    p, s = sim.params(), sim.init()
    s = s.replace(x=s.x + 0.003 * jnp.sin(37 * s.x[::-1]))  # irregular positions
    X = (s.x - jnp.asarray(sim.origin, s.x.dtype)[:, None]) / sim.dx
    idx, w, dpos = stencil(X, sim.grid_shape)
    m = sim.mass(p, s)
    grid = p2g(idx, w, dpos, m, m * s.v, jnp.zeros_like(s.C), int(np.prod(sim.grid_shape)), sim.dx)
    np.testing.assert_allclose(float(grid[:, 2].sum()), float(m.sum()), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(w.sum(0)), 1.0, rtol=1e-6)


def test_row_transfers_equal_nine_node_loops(x64):
    """The row gather of g2p reads exactly the nine stencil nodes of every particle, and the
    row scatter of p2g adds the MLS contributions to exactly those nodes (references: one
    gather / one np.add.at per offset at idx), near all four grid edges too."""
    rng = np.random.default_rng(3)
    shape = (7, 11)
    X = jnp.asarray(np.stack([rng.uniform(0.5, shape[0] - 1.5, 200),
                              rng.uniform(0.5, shape[1] - 1.5, 200)]))
    X = X.at[:, :4].set(jnp.asarray([[0.5, 5.49, 0.5, 5.49], [0.5, 9.49, 9.49, 0.5]]))
    idx, w, dpos = stencil(X, shape)
    gv = jnp.asarray(rng.normal(size=(2, *shape)))
    v, C = g2p(idx, w, dpos, gv, 0.1)
    g = gv.reshape(2, -1)[:, idx]  # (2, 9, N)
    np.testing.assert_allclose(np.asarray(v), np.asarray((w * g).sum(1)), rtol=1e-13)
    C_ref = 40.0 * jnp.einsum("aon,bon->abn", w * g, dpos)
    np.testing.assert_allclose(np.asarray(C), np.asarray(C_ref), rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="nx, ny"):
        g2p(idx, w, dpos, gv.reshape(2, -1), 0.1)
    _check_p2g_against_loops(rng, idx, w, dpos, int(np.prod(shape)), 0.1)


def _check_p2g_against_loops(rng, idx, w, dpos, n_nodes, dx):
    """p2g's grid equals per-offset np.add.at of w (m v + A (dpos dx)) and w m."""
    d, S, n = dpos.shape
    m, mv = rng.uniform(1, 2, n), rng.normal(size=(d, n))
    A = rng.normal(size=(d, d, n))
    grid = np.asarray(p2g(idx, w, dpos, jnp.asarray(m), jnp.asarray(mv), jnp.asarray(A),
                          n_nodes, dx))
    ref = np.zeros((n_nodes, d + 1))
    W, D, I = np.asarray(w), np.asarray(dpos) * dx, np.asarray(idx)
    for k in range(S):
        contrib = mv + np.einsum("abn,bn->an", A, D[:, k])
        for c in range(d):
            np.add.at(ref[:, c], I[k], W[k] * contrib[c])
        np.add.at(ref[:, d], I[k], W[k] * m)
    np.testing.assert_allclose(grid, ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("flip", [0.0, 0.99])
def test_momentum_conserved_in_free_flight(x64, flip):
    """No gravity, no wall contact: linear momentum of a spinning, moving body is conserved,
    with APIC alone and with a FLIP update."""
    scene = elastic_block(gravity=(0.0, 0.0), velocity=(0.3, -0.2), flip=flip)
    sim = MPM(scene)
    p, s = sim.params(), sim.init()
    c = s.x.mean(1, keepdims=True)
    spin = 2.0 * jnp.stack([-(s.x[1] - c[1]), s.x[0] - c[0]])
    s = s.replace(v=s.v + spin)
    traj = sim.run(p, s, 20, check=False)[0]
    m = np.asarray(sim.mass(p, s))
    mom = np.einsum("n,tnd->td", m, np.asarray(traj.velocities))
    tol = 1e-12 * m.sum()
    np.testing.assert_allclose(mom, np.broadcast_to(mom[0], mom.shape), rtol=0, atol=tol)
    assert np.asarray(traj.positions)[-1, :, 0].mean() > np.asarray(traj.positions)[0, :, 0].mean()


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_free_fall(dtype, x64):
    scene = elastic_block(rect=(0.4, 0.7, 0.5, 0.8))
    sim = MPM(scene, dtype=dtype)
    traj = sim.run(sim.params(), sim.init(), 100, check=False)[0]
    y = np.asarray(traj.positions)[:, :, 1].mean(1)
    t = np.asarray(traj.times)
    drop = y[0] - y
    expect = 0.5 * 9.81 * t**2
    # first-order time stepping lags by g t dt / 2: negligible once t >> dt
    np.testing.assert_allclose(drop[40:], expect[40:], rtol=0.01)


def _sliding_block(theta_deg, mu, frames=80):
    th = np.deg2rad(theta_deg)
    g = 9.81
    scene = elastic_block(
        gravity=(g * np.sin(th), -g * np.cos(th)), rect=(0.1, 0.0, 0.2, 0.04), E=2e6,
        domain=((0.0, 1.0), (0.0, 0.2)), dx=0.01,
        walls=Walls(bottom=Wall("friction", mu)))
    sim = MPM(scene)
    traj = sim.run(sim.params(), sim.init(), frames, check=False)[0]
    x = np.asarray(traj.positions)[:, :, 0].mean(1)
    return np.asarray(traj.times), x - x[0], g * (np.sin(th) - mu * np.cos(th))


def test_block_slides_with_coulomb_acceleration():
    t, dx, a_expect = _sliding_block(30.0, 0.3)
    a_fit = 2 * np.polyfit(t, dx, 2)[0]
    assert a_fit == pytest.approx(a_expect, rel=0.05)


def test_block_sticks_below_friction_angle():
    t, dx, _ = _sliding_block(15.0, 0.4)  # tan 15 deg = 0.27 < 0.4
    free = 0.5 * 9.81 * np.sin(np.deg2rad(15.0)) * t[-1] ** 2
    assert abs(dx[-1]) < 0.01 * free


@pytest.mark.parametrize("dt_factor", [1.0, 0.25])
def test_coulomb_floor_stops_a_block_at_v0_squared_over_2_mu_g_at_any_substep(dt_factor):
    """A block launched at 1 m/s along a mu = 0.5 floor stops after v0^2 / (2 mu g): the
    frictional wall's impulse is consistent in the substep (at the stable one and at a
    quarter of it; ``benchmarks/mpm_substep_dissipation.py`` case ``slide``)."""
    scene = elastic_block(velocity=(1.0, 0.0), rect=(0.1, 0.0, 0.2, 0.04), E=2e6,
                          domain=((0.0, 1.0), (0.0, 0.2)), dx=0.01,
                          walls=Walls(bottom=Wall("friction", 0.5)))
    scene = scene.replace(dt=dt_factor * scene.substep_dt)
    sim = MPM(scene)
    x = np.asarray(sim.run(sim.params(), sim.init(), 100)[0].positions)[:, :, 0]
    assert x[-1].mean() - x[0].mean() == pytest.approx(1.0 / (2 * 0.5 * 9.81), rel=0.01)


def _rebound_energy_kept(dt_factor: float, flip: float) -> float:
    """Kinetic energy kept by two elastic blocks meeting head-on at +-0.5 m/s in free space
    (``benchmarks/mpm_substep_dissipation.py`` case ``collision``), at substeps
    ``dt_factor`` x the stable one."""
    m = Elastic(E=1e5, nu=0.3, rho=1000.0)
    bodies = (Body(Rectangle(0.3, 0.4, 0.45, 0.55), m, velocity=(0.5, 0.0)),
              Body(Rectangle(0.55, 0.4, 0.7, 0.55), m, velocity=(-0.5, 0.0)))
    scene = Scene(domain=((0, 1), (0, 1)), dx=0.02, bodies=bodies, gravity=(0.0, 0.0),
                  flip=flip)
    scene = scene.replace(dt=dt_factor * scene.substep_dt)
    sim = MPM(scene)
    v = np.asarray(sim.run(sim.params(), sim.init(), 120)[0].velocities)
    ke = (v ** 2).sum(-1).mean(-1)
    return float(ke[-1] / ke[0])


@pytest.mark.xfail(strict=True, reason="known (2026-12-06): with APIC alone (Scene.flip = 0, "
                   "the default) every particle-grid round trip dissipates, so at a fixed dx "
                   "the energy kept falls with the substeps per second (0.77 of it at the "
                   "stable substep, 0.41 at a quarter; docs/validation.md 'The answer "
                   "depends on the substep too'); a default transfer without that loss makes "
                   "this pass: then drop the mark")
def test_an_elastic_rebound_keeps_the_same_energy_at_a_quarter_of_the_substep():
    stable, quarter = _rebound_energy_kept(1.0, 0.0), _rebound_energy_kept(0.25, 0.0)
    assert 0.5 < stable < 1.0  # an elastic rebound, not a merger
    assert quarter == pytest.approx(stable, rel=0.2)


def test_a_flip_update_keeps_an_elastic_rebound_whatever_the_substep():
    """Scene.flip = 0.99: the rebound keeps > 90% of its energy at the stable substep and
    at a quarter of it, within 2% of each other (APIC alone: 0.77 and 0.41)."""
    stable, quarter = _rebound_energy_kept(1.0, 0.99), _rebound_energy_kept(0.25, 0.99)
    assert stable > 0.9 and quarter > 0.9
    assert quarter == pytest.approx(stable, rel=0.02)


def test_geostatic_stress():
    """A sand layer at rest carries sigma_yy = -rho g (h - y); base stress rho g h within 5%."""
    h, rho, g = 0.2, 1800.0, 9.81
    body = Body(Rectangle(0.0, 0.0, 0.2, h), Sand(friction_angle=30.0, E=5e6, rho=rho))
    scene = Scene(domain=((0.0, 0.2), (0.0, 0.3)), dx=0.01, bodies=(body,), damping=20.0,
                  walls=Walls(bottom=Wall("sticky")))
    sim = MPM(scene)
    p = sim.params()
    _, state = sim.run(p, sim.init(), 200)
    sig = np.asarray(sim.cauchy_stress(p, state))[:, 1, 1]
    y = np.asarray(state.x[1])
    slope, base = np.polyfit(h - y, -sig, 1)
    assert slope == pytest.approx(rho * g, rel=0.05)
    assert slope * h + base == pytest.approx(rho * g * h, rel=0.05)


# 17 s on a quiet machine (2026-12-06, 23:53 UTC); the default suite keeps jit = eager and no
# recompilation for the MPM through test_interface_conformance.py (every float parameter changed)
@pytest.mark.slow
def test_jit_equals_eager_and_no_recompilation():
    scene = elastic_block()
    sim = MPM(scene)
    p, s = sim.params(), sim.init()
    eager = s
    with jax.disable_jit():
        for _ in range(3):
            eager = sim.substep(p, eager)
    jitted = jax.jit(lambda p, s: sim.substep(p, sim.substep(p, sim.substep(p, s))))(p, s)
    np.testing.assert_allclose(np.asarray(jitted.x), np.asarray(eager.x), rtol=1e-6, atol=1e-7)
    sim.run(p, s, 3, check=False)[0]
    n = rollout_jit._cache_size()
    p2 = p.replace(E=p.E * 1.1, gravity=p.gravity * 0.5)
    sim.run(p2, s.replace(v=s.v + 0.1), 3, check=False)[0]
    assert rollout_jit._cache_size() == n
