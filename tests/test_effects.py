"""Only the effects a scene declares are traced: inspect the jaxpr of one substep."""
import jax
import pytest

from diffgns import (
    MPM,
    Body,
    BoxObstacle,
    Elastic,
    Fluid,
    Rectangle,
    Sand,
    Scene,
    Wall,
    Walls,
)


def _scene(material, walls=Walls(), obstacles=(), gravity=(0.0, -9.81)):
    return Scene(domain=((0, 1), (0, 1)), dx=0.05, gravity=gravity, walls=walls,
                 obstacles=obstacles, bodies=(Body(Rectangle(0.2, 0.2, 0.4, 0.4), material),))


def _jaxpr(scene) -> str:
    sim = MPM(scene)
    return str(jax.make_jaxpr(sim.substep)(sim.params(), sim.init()))


NAMES = ["drucker_prager", "elastic_corotated", "elastic_linear", "fluid", "wall_friction",
         "wall_sticky", "obstacle_sticky", "obstacle_friction"]


def _traced(jaxpr: str) -> set:
    return {n for n in NAMES if f"name={n}" in jaxpr}


def test_fluid_scene_traces_no_svd_or_return_map():
    jp = _jaxpr(_scene(Fluid()))
    assert _traced(jp) == {"fluid"}
    assert "atan2" not in jp and "log" not in jp  # no SVD, no Hencky strain


def test_elastic_scene_traces_no_plasticity():
    jp = _jaxpr(_scene(Elastic()))
    assert _traced(jp) == {"elastic_corotated"}
    assert " log" not in jp and "atan2" not in jp


def test_sand_scene_traces_return_map_and_only_declared_walls():
    jp = _jaxpr(_scene(Sand(), walls=Walls(bottom=Wall("friction", 0.4))))
    assert _traced(jp) == {"drucker_prager", "wall_friction"}


def test_flip_traced_only_when_declared():
    """A FLIP update scatters the momentum before the forces beside the usual one (2 d + 1
    grid channels instead of d + 1) and gathers the grid's velocity change with the
    velocity (2 d channels instead of d); APIC alone traces neither."""
    apic = _jaxpr(_scene(Elastic()))
    flip = _jaxpr(_scene(Elastic()).replace(flip=0.99))
    assert "slice_sizes=(3, 2)" in apic and "slice_sizes=(3, 4)" not in apic
    assert "slice_sizes=(3, 4)" in flip and "slice_sizes=(3, 2)" not in flip


def test_obstacles_traced_only_when_declared():
    obs = (BoxObstacle(0.6, 0.0, 0.7, 0.2, Wall("friction", 0.2)),)
    assert "obstacle_friction" in _traced(_jaxpr(_scene(Elastic(), obstacles=obs)))
    assert not {"obstacle_friction", "obstacle_sticky"} & _traced(_jaxpr(_scene(Elastic())))


@pytest.mark.parametrize("gravity,expected", [((0.0, 0.0), False), ((0.0, -9.81), True)])
def test_gravity_traced_only_when_nonzero(gravity, expected):
    sim = MPM(_scene(Elastic(), gravity=gravity))
    closed = jax.make_jaxpr(sim.substep)(sim.params(), sim.init())
    # gravity is the only use of params.gravity: its input variable is used iff traced
    flat, _ = jax.tree.flatten(sim.params())
    g_var = closed.jaxpr.invars[[i for i, f in enumerate(flat) if f.shape == (2,)][0]]
    used = any(g_var in eqn.invars for eqn in closed.jaxpr.eqns)
    assert used == expected
