"""Stiff materials, fast impacts, particles at walls, long runs: finite and inside the domain."""
import numpy as np
import pytest

from diffgns import MPM, Body, Elastic, Rectangle, Sand, Scene, Wall, Walls
from diffgns.mpm.solver import max_speed


def _finite_inside(sim, traj):
    x = np.asarray(traj.positions)
    assert np.isfinite(x).all() and np.isfinite(np.asarray(traj.velocities)).all()
    (x0, x1), (y0, y1) = sim.scene.domain
    assert (x[..., 0] >= x0).all() and (x[..., 0] <= x1).all()
    assert (x[..., 1] >= y0).all() and (x[..., 1] <= y1).all()


DTYPES = ["float32", "float64"]


@pytest.mark.parametrize("dtype", DTYPES)
def test_stiff_material(dtype, x64):
    body = Body(Rectangle(0.3, 0.0, 0.5, 0.2), Elastic(E=1e8, nu=0.3, rho=1000.0))
    scene = Scene(domain=((0, 0.8), (0, 0.4)), dx=0.02, bodies=(body,),
                  walls=Walls(bottom=Wall("friction", 0.3)), frame_dt=1e-3)
    sim = MPM(scene, dtype=dtype)
    traj, _ = sim.run(sim.params(), sim.init(), 10)
    _finite_inside(sim, traj)


@pytest.mark.parametrize("dtype", DTYPES)
def test_impact_at_20_m_per_s(dtype, x64):
    body = Body(Rectangle(0.3, 0.1, 0.4, 0.2), Sand(friction_angle=35.0), velocity=(20.0, -5.0))
    scene = Scene(domain=((0, 0.6), (0, 0.4)), dx=0.01, bodies=(body,),
                  walls=Walls.all("friction", 0.4))
    sim = MPM(scene, dtype=dtype)
    traj, _ = sim.run(sim.params(), sim.init(), 40)
    speed = max_speed(traj.velocities)
    _finite_inside(sim, traj)
    assert float(speed[-1]) < 20.0  # the wall absorbed the impact


@pytest.mark.parametrize("dtype", DTYPES)
def test_particles_starting_at_the_padding_boundary(dtype, x64):
    # bodies touching every wall of the domain, i.e. the edge of the grid padding
    bodies = (Body(Rectangle(0.0, 0.0, 0.1, 0.3), Sand(), velocity=(-3.0, -3.0)),
              Body(Rectangle(0.2, 0.2, 0.3, 0.3), Elastic(), velocity=(3.0, 3.0)))
    scene = Scene(domain=((0, 0.3), (0, 0.3)), dx=0.01, bodies=bodies,
                  walls=Walls(left=Wall("sticky"), bottom=Wall("friction", 0.5)), padding=2)
    sim = MPM(scene, dtype=dtype)
    traj, _ = sim.run(sim.params(), sim.init(), 40)
    _finite_inside(sim, traj)


@pytest.mark.parametrize("dtype", DTYPES)
def test_2000_frames(dtype, x64):
    body = Body(Rectangle(0.0, 0.0, 0.1, 0.1), Sand(friction_angle=30.0), velocity=(1.0, 0.0))
    scene = Scene(domain=((0, 0.3), (0, 0.2)), dx=0.02, bodies=(body,),
                  walls=Walls(bottom=Wall("friction", 0.5)), frame_dt=2.5e-3)
    sim = MPM(scene, dtype=dtype)
    traj, _ = sim.run(sim.params(), sim.init(), 2000)
    speed = max_speed(traj.velocities)
    _finite_inside(sim, traj)
    assert float(speed[-1]) < 0.05  # came to rest
