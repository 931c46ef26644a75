"""Scene description, validation, TOML I/O, particle filling, time step and builders.

Fast: no MPM rollouts, only scene construction.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from diffgns import (
    Body,
    BoxObstacle,
    Elastic,
    Fluid,
    Polygon,
    Rectangle,
    Sand,
    Scene,
    SceneError,
    Wall,
    Walls,
)
from diffgns.scene.builders import column_collapse, granular_squares
from diffgns.scene.files import load_scene, save_scene, scene_from_dict, scene_to_dict

SCENE_DIR = Path(__file__).resolve().parents[1] / "scenes"
SCENES = sorted(SCENE_DIR.glob("*.toml"))
DOMAIN = ((0.0, 1.0), (0.0, 1.0))


def block(x0=0.2, y0=0.2, x1=0.4, y1=0.4, material=None, **kw) -> Body:
    return Body(Rectangle(x0, y0, x1, y1), material or Elastic(), **kw)


def scene(*bodies, **kw) -> Scene:
    kw.setdefault("domain", DOMAIN)
    kw.setdefault("dx", 0.02)
    return Scene(bodies=bodies or (block(),), **kw)


def scene_dict(**overrides) -> dict:
    d = {
        "scene": {"domain": [[0.0, 1.0], [0.0, 1.0]], "dx": 0.02},
        "walls": {"bottom": {"kind": "friction", "mu": 0.5}},
        "bodies": [{"shape": {"type": "rectangle", "x0": 0.2, "y0": 0.2, "x1": 0.4, "y1": 0.4},
                    "material": {"type": "sand", "friction_angle": 30.0}}],
    }
    d.update(overrides)
    return d


# ------------------------------------------------------------------ validation: materials
@pytest.mark.parametrize("rho", [0.0, -1000.0])
@pytest.mark.parametrize("cls", [Elastic, Sand, Fluid])
def test_density_must_be_positive(cls, rho):
    with pytest.raises(SceneError, match=rf"{cls.__name__}\.rho = {rho}"):
        cls(rho=rho)


@pytest.mark.parametrize("E", [0.0, -1.0e6])
@pytest.mark.parametrize("cls", [Elastic, Sand])
def test_youngs_modulus_must_be_positive(cls, E):
    with pytest.raises(SceneError, match=rf"{cls.__name__}\.E = "):
        cls(E=E)


@pytest.mark.parametrize("nu", [0.5, -0.1])
@pytest.mark.parametrize("cls", [Elastic, Sand])
def test_poisson_ratio_range(cls, nu):
    with pytest.raises(SceneError, match=rf"{cls.__name__}\.nu = {nu}"):
        cls(nu=nu)


@pytest.mark.parametrize("phi", [0.0, 90.0, -5.0])
def test_friction_angle_range(phi):
    with pytest.raises(SceneError, match=rf"Sand\.friction_angle = {phi}"):
        Sand(friction_angle=phi)


def test_valid_materials_construct():
    assert Elastic(nu=0.0).nu == 0.0
    assert Sand(friction_angle=89.0).friction_angle == 89.0
    assert Fluid(viscosity=0.0).viscosity == 0.0


# ----------------------------------------------------------------- validation: geometry
def test_body_outside_domain():
    with pytest.raises(SceneError, match=r"bodies\[0\].*outside the domain"):
        scene(block(1.2, 0.2, 1.4, 0.4))


@pytest.mark.parametrize("corners", [(-0.06, 0.2, 0.1, 0.4),   # into the left padding
                                     (0.2, -0.04, 0.4, 0.2),   # into the bottom padding
                                     (0.9, 0.9, 1.04, 1.0)])   # past the right wall
def test_body_crossing_domain_boundary_into_padding(corners):
    with pytest.raises(SceneError, match=r"bodies\[0\].*outside the domain"):
        scene(block(*corners))


def test_body_touching_domain_boundary_is_allowed():
    s = scene(block(0.0, 0.0, 0.2, 1.0))
    assert s.n_particles > 0


def test_overlapping_bodies():
    with pytest.raises(SceneError, match=r"bodies\[0\] and Scene\.bodies\[1\] overlap"):
        scene(block(0.2, 0.2, 0.4, 0.4), block(0.3, 0.3, 0.5, 0.5, material=Sand()))


def test_adjacent_bodies_do_not_overlap():
    s = scene(block(0.2, 0.2, 0.4, 0.4), block(0.4, 0.2, 0.6, 0.4, material=Sand()))
    assert len(s.bodies) == 2


def test_body_overlapping_obstacle():
    with pytest.raises(SceneError, match=r"bodies\[0\] overlaps Scene\.obstacles\[0\]"):
        scene(block(0.2, 0.2, 0.4, 0.4), obstacles=(BoxObstacle(0.35, 0.0, 0.5, 0.25),))


def test_particles_per_cell_must_be_square():
    with pytest.raises(SceneError, match="particles_per_cell = 3"):
        block(particles_per_cell=3)
    with pytest.raises(SceneError, match="particles_per_cell"):
        scene_from_dict(scene_dict(bodies=[{**scene_dict()["bodies"][0],
                                            "particles_per_cell": 8}]))


def test_domain_extent_must_be_multiple_of_dx():
    with pytest.raises(SceneError, match=r"domain extent along x .*dx = 0\.03"):
        scene(dx=0.03)
    with pytest.raises(SceneError, match=r"domain extent along y"):
        scene(domain=((0.0, 1.0), (0.0, 0.99)))


# -------------------------------------------------------------------- validation: walls
def test_unknown_wall_kind():
    with pytest.raises(SceneError, match=r"Wall\.kind = 'bouncy'"):
        Wall("bouncy")
    with pytest.raises(SceneError, match=r"Wall\.kind = 'bouncy'"):
        scene_from_dict(scene_dict(walls={"left": {"kind": "bouncy"}}))


def test_mu_on_slip_wall():
    with pytest.raises(SceneError, match=r"Wall\.mu = 0\.5 given for a 'slip' wall"):
        Wall("slip", 0.5)
    with pytest.raises(SceneError, match=r"Wall\.mu .*'sticky'"):
        scene_from_dict(scene_dict(walls={"top": {"kind": "sticky", "mu": 0.2}}))


def test_negative_mu():
    with pytest.raises(SceneError, match=r"Wall\.mu = -0\.1"):
        Wall("friction", -0.1)


def test_unknown_wall_name():
    with pytest.raises(SceneError, match=r"\[walls\] has unknown field.*floor"):
        scene_from_dict(scene_dict(walls={"floor": {"kind": "slip"}}))


# ------------------------------------------------------------------ validation: time step
def test_user_dt_above_cfl_limit():
    s = scene()
    with pytest.raises(SceneError, match=r"Scene\.dt = .* exceeds the stability limit"):
        scene(dt=2.0 * s.stable_dt())


@pytest.mark.parametrize("flip", [-0.1, 1.5, float("nan"), "0.9", True])
def test_flip_outside_zero_one_is_rejected(flip):
    with pytest.raises(SceneError, match=r"Scene\.flip = .* must be a fraction in \[0, 1\]"):
        scene(flip=flip)


def test_flip_is_an_effect_only_when_declared():
    assert "flip" not in scene().effects and "flip" not in scene(flip=0.0).effects
    assert "flip" in scene(flip=0.99).effects


def test_nonpositive_dt():
    with pytest.raises(SceneError, match=r"Scene\.dt"):
        scene(dt=0.0)


# ------------------------------------------------------------------- validation: dict/TOML
def test_unknown_material_type():
    bad = scene_dict()
    bad["bodies"][0]["material"] = {"type": "rubber", "E": 1.0e6}
    with pytest.raises(SceneError, match=r"material\.type = 'rubber' is unknown"):
        scene_from_dict(bad)


def test_unknown_material_type_in_toml(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('[scene]\ndomain = [[0.0, 1.0], [0.0, 1.0]]\ndx = 0.02\n[[bodies]]\n'
                 'shape = {type = "rectangle", x0 = 0.2, y0 = 0.2, x1 = 0.4, y1 = 0.4}\n'
                 'material = {type = "jelly"}\n')
    with pytest.raises(SceneError, match=r"material\.type = 'jelly'"):
        load_scene(p)


def test_unknown_material_field():
    bad = scene_dict()
    bad["bodies"][0]["material"] = {"type": "sand", "angle": 30.0}
    with pytest.raises(SceneError, match=r"material has unknown field.*angle"):
        scene_from_dict(bad)


def test_malformed_toml(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text('[scene\ndx = 0.02\n[[bodies]]\nshape = {type = "rectangle", x0 = \n')
    with pytest.raises(SceneError, match=r"broken\.toml is not valid TOML"):
        load_scene(p)


def test_unknown_scene_key():
    bad = scene_dict()
    bad["scene"]["timestep"] = 1e-4
    with pytest.raises(SceneError, match=r"\[scene\] has unknown field.*timestep"):
        scene_from_dict(bad)


def test_unknown_top_level_table():
    with pytest.raises(SceneError, match=r"unknown field.*particles"):
        scene_from_dict(scene_dict(particles={}))


def test_body_missing_shape():
    bad = scene_dict()
    del bad["bodies"][0]["shape"]
    with pytest.raises(SceneError, match=r"\[\[bodies\]\]\[0\] needs both 'shape'"):
        scene_from_dict(bad)


def test_unknown_shape_type():
    bad = scene_dict()
    bad["bodies"][0]["shape"] = {"type": "circle", "r": 0.1}
    with pytest.raises(SceneError, match=r"shape\.type = 'circle'"):
        scene_from_dict(bad)


def test_rectangle_missing_corner():
    bad = scene_dict()
    del bad["bodies"][0]["shape"]["y1"]
    with pytest.raises(SceneError, match=r"shape is missing \['y1'\]"):
        scene_from_dict(bad)


def test_obstacle_missing_corner():
    with pytest.raises(SceneError, match=r"\[\[obstacles\]\]\[0\] is missing \['y1'\]"):
        scene_from_dict(scene_dict(obstacles=[{"x0": 0.5, "y0": 0.0, "x1": 0.6}]))


def test_material_not_a_table():
    bad = scene_dict()
    bad["bodies"][0]["material"] = "sand"
    with pytest.raises(SceneError, match=r"\[\[bodies\]\]\[0\]\.material must be a table"):
        scene_from_dict(bad)


@pytest.mark.parametrize("velocity", [1.0, [1.0, 2.0, 3.0]])
def test_body_velocity_not_a_pair(velocity):
    bad = scene_dict()
    bad["bodies"][0]["velocity"] = velocity
    with pytest.raises(SceneError, match=r"\[\[bodies\]\]\[0\]\.velocity"):
        scene_from_dict(bad)


def test_no_bodies():
    with pytest.raises(SceneError, match=r"Scene\.bodies is empty"):
        scene_from_dict(scene_dict(bodies=[]))


def test_nonexistent_file(tmp_path):
    with pytest.raises(SceneError, match=r"nope\.toml does not exist"):
        load_scene(tmp_path / "nope.toml")


# ------------------------------------------------------------------------ valid scenes
def test_shipped_scenes_exist():
    names = {p.name for p in SCENES}
    assert {"column_collapse.toml", "sand_and_water.toml", "elastic_polygon.toml"} <= names


@pytest.mark.parametrize("path", SCENES, ids=lambda p: p.stem)
def test_shipped_scene_loads(path):
    s = load_scene(path)
    assert isinstance(s, Scene)
    assert s.n_particles > 0
    assert s.substeps >= 1 and s.substep_dt <= s.stable_dt() * (1 + 1e-9)


def test_column_collapse_scene_file():
    s = load_scene(SCENE_DIR / "column_collapse.toml")
    assert s.domain == ((0.0, 1.0), (0.0, 0.5)) and s.dx == 0.01
    (body,) = s.bodies
    assert isinstance(body.material, Sand)
    assert body.shape.bbox == (0.0, 0.0, 0.2, 0.4)
    assert s.walls.bottom == Wall("friction", 0.5)
    assert all(w.kind == "slip" for w in (s.walls.left, s.walls.right, s.walls.top))


def test_sand_and_water_scene_file():
    s = load_scene(SCENE_DIR / "sand_and_water.toml")
    assert {type(b.material) for b in s.bodies} == {Sand, Fluid}
    assert s.walls.bottom.kind == "sticky"
    assert s.obstacles and s.obstacles[0].surface.kind == "friction"
    assert {"sand", "fluid", "obstacles", "sticky_walls"} <= s.effects


def test_elastic_polygon_scene_file():
    s = load_scene(SCENE_DIR / "elastic_polygon.toml")
    (body,) = s.bodies
    assert isinstance(body.shape, Polygon) and isinstance(body.material, Elastic)
    assert body.velocity != (0.0, 0.0)
    assert s.walls.bottom.kind == "slip"


def mixed_scene(**kw) -> Scene:
    return Scene(
        domain=((0.0, 1.0), (0.0, 0.6)), dx=0.02,
        bodies=(
            Body(Rectangle(0.0, 0.0, 0.2, 0.3), Sand(friction_angle=33.0), name="sand"),
            Body(Polygon(((0.4, 0.3), (0.6, 0.3), (0.5, 0.5))), Elastic(E=5e5, model="linear"),
                 velocity=(0.5, -1.0), particles_per_cell=9, name="tri"),
            Body(Rectangle(0.8, 0.0, 1.0, 0.2), Fluid(viscosity=0.01), name="water"),
        ),
        walls=Walls(left=Wall("slip"), right=Wall("sticky"), bottom=Wall("friction", 0.4),
                    top=Wall("slip")),
        obstacles=(BoxObstacle(0.45, 0.0, 0.55, 0.1, Wall("friction", 0.2)),),
        gravity=(0.0, -9.81), frame_dt=2e-3, damping=0.5, **kw,
    )


@pytest.mark.parametrize("kw", [{}, {"max_speed": 3.0}, {"dt": 1e-5}, {"flip": 0.99}])
def test_round_trip_through_toml(tmp_path, kw):
    s = mixed_scene(**kw)
    d = scene_to_dict(s)
    assert scene_from_dict(d) == s
    p = tmp_path / "scene.toml"
    save_scene(s, p)
    back = load_scene(p)
    assert back == s
    assert back.n_particles == s.n_particles
    np.testing.assert_array_equal(back.particles()["x"], s.particles()["x"])


@pytest.mark.parametrize("path", SCENES, ids=lambda p: p.stem)
def test_shipped_scene_round_trip(tmp_path, path):
    s = load_scene(path)
    save_scene(s, tmp_path / "copy.toml")
    assert load_scene(tmp_path / "copy.toml") == s


def test_scene_is_hashable_and_equal_by_value():
    a, b = mixed_scene(), mixed_scene()
    a.particles()  # filling the cache must not affect equality or hashing
    assert a == b and hash(a) == hash(b)
    assert a != a.replace(dx=0.01)


# -------------------------------------------------------------------- particle filling
@pytest.mark.parametrize("ppc", [1, 4, 9])
def test_rectangle_filling(ppc):
    dx, (x0, y0, x1, y1) = 0.02, (0.1, 0.2, 0.3, 0.5)
    s = scene(block(x0, y0, x1, y1, particles_per_cell=ppc), dx=dx)
    p = s.particles()
    k = math.isqrt(ppc)
    assert len(p["x"]) == round((x1 - x0) / dx * k) * round((y1 - y0) / dx * k)
    area = (x1 - x0) * (y1 - y0)
    assert p["vol"].sum() == pytest.approx(area, rel=1e-12)
    assert np.all((p["x"] > [x0, y0]) & (p["x"] < [x1, y1]))


def test_rectangle_filling_ppc4_count():
    w, h, dx = 0.2, 0.4, 0.01
    s = Scene(domain=((0.0, 1.0), (0.0, 0.5)), dx=dx,
              bodies=(Body(Rectangle(0.0, 0.0, w, h), Sand(), particles_per_cell=4),))
    assert s.n_particles == round(w / dx * 2) * round(h / dx * 2) == 3200
    assert s.particles()["vol"].sum() == pytest.approx(w * h, rel=1e-12)


def test_polygon_filling():
    tri = Polygon(((0.2, 0.2), (0.7, 0.25), (0.35, 0.8)))
    s = scene(Body(tri, Elastic(), particles_per_cell=4), dx=0.02)
    p = s.particles()
    assert len(p["x"]) > 100
    assert p["vol"].sum() == pytest.approx(tri.area, rel=1e-12)
    assert tri.area == pytest.approx(0.5 * abs(0.5 * 0.6 - 0.05 * 0.15), rel=1e-12)
    assert np.all(tri.contains(p["x"]))
    # the particle count matches the area to within the boundary cells
    assert len(p["x"]) * (0.02 / 2) ** 2 == pytest.approx(tri.area, rel=0.1)


def test_initial_velocity_and_body_index():
    s = mixed_scene()
    p = s.particles()
    for i, b in enumerate(s.bodies):
        sel = p["body"] == i
        assert sel.any()
        np.testing.assert_array_equal(p["v"][sel], np.broadcast_to(b.velocity, (sel.sum(), 2)))


def test_particles_grouped_by_material():
    # declared out of group order: fluid, sand, elastic, sand
    s = Scene(domain=DOMAIN, dx=0.02, bodies=(
        block(0.0, 0.0, 0.2, 0.2, material=Fluid()),
        block(0.3, 0.0, 0.5, 0.2, material=Sand()),
        block(0.6, 0.0, 0.8, 0.2, material=Elastic()),
        block(0.3, 0.4, 0.5, 0.6, material=Sand(friction_angle=40.0)),
    ))
    groups = s.material_groups()
    assert list(groups) == ["elastic_corotated", "sand", "fluid"]
    n, start = s.n_particles, 0
    body = s.particles()["body"]
    for eff, sl in groups.items():
        assert sl.start == start and sl.stop > sl.start
        start = sl.stop
        assert {s.bodies[b].material.effect for b in np.unique(body[sl])} == {eff}
    assert start == n == len(body)
    # within the sand group, bodies keep declaration order
    np.testing.assert_array_equal(np.unique(body[groups["sand"]]), [1, 3])
    assert np.all(np.diff(body[groups["sand"]]) >= 0)


# ----------------------------------------------------------------------------- effects
def test_effects_elastic_only_slip_walls():
    s = scene(walls=Walls.all("slip"))
    assert s.effects == {"elastic_corotated", "gravity", "slip_walls"}
    assert not {"sand", "fluid", "friction_walls", "sticky_walls", "obstacles"} & s.effects


def test_effects_zero_gravity():
    s = scene(gravity=(0.0, 0.0))
    assert "gravity" not in s.effects
    assert "gravity" in scene(gravity=(1.0, 0.0)).effects


def test_effects_mixed_scene():
    s = mixed_scene()
    assert s.effects == {"elastic_linear", "sand", "fluid", "gravity", "slip_walls",
                         "sticky_walls", "friction_walls", "obstacles", "damping"}


# ---------------------------------------------------------------------------- time step
@pytest.mark.parametrize("make", [lambda: scene(), mixed_scene,
                                  lambda: load_scene(SCENE_DIR / "column_collapse.toml")])
def test_substeps_divide_frame(make):
    s = make()
    assert s.substeps * s.substep_dt == pytest.approx(s.frame_dt, rel=1e-12)
    assert s.substep_dt <= s.stable_dt()
    # one substep fewer would break the limit
    if s.substeps > 1:
        assert s.frame_dt / (s.substeps - 1) > s.stable_dt()


def test_stiffer_material_needs_more_substeps():
    soft = scene(block(material=Elastic(E=1e5)))
    stiff = scene(block(material=Elastic(E=1e8)))
    assert stiff.stable_dt() < soft.stable_dt()
    assert stiff.substeps > soft.substeps


def test_viscous_limit():
    thin = scene(block(material=Fluid(viscosity=0.0)))
    thick = scene(block(material=Fluid(viscosity=1e3)))
    assert thick.stable_dt() < thin.stable_dt()


def test_valid_user_dt_is_used():
    s = scene()
    dt = 0.5 * s.stable_dt()
    u = scene(dt=dt)
    assert u.dt == dt
    assert u.substep_dt <= dt * (1 + 1e-12)
    assert u.substeps == math.ceil(u.frame_dt / dt * (1 - 1e-9))
    assert u.substeps * u.substep_dt == pytest.approx(u.frame_dt, rel=1e-12)
    assert u.substeps >= s.substeps


def test_user_dt_at_the_limit_is_accepted():
    s = scene()
    assert scene(dt=s.stable_dt()).substep_dt <= s.stable_dt() * (1 + 1e-9)


# ----------------------------------------------------------------------------- builders
def test_column_collapse_builder():
    s = column_collapse(width=0.1, aspect_ratio=2, cells_across=10)
    assert s.dx == pytest.approx(0.01)
    (body,) = s.bodies
    assert isinstance(body.material, Sand)
    x0, y0, x1, y1 = body.shape.bbox
    (dx0, dx1), (dy0, dy1) = s.domain
    assert x0 == dx0 and y0 == dy0  # against the left wall, on the floor
    assert x1 - x0 == pytest.approx(0.1) and y1 - y0 == pytest.approx(0.2)
    assert dy1 > y1 and dx1 > 3 * x1  # room above and for the runout
    assert s.walls.bottom == Wall("friction", 0.5)
    assert "friction_walls" in s.effects and "sand" in s.effects
    assert s.n_particles == (10 * 2) * (20 * 2)


def test_column_collapse_builder_rejects_off_lattice():
    with pytest.raises(SceneError, match="multiples of dx"):
        column_collapse(width=0.1, aspect_ratio=1.25, cells_across=10)


def _squares(s: Scene) -> list[Rectangle]:
    return [b.shape for b in s.bodies]


@pytest.mark.parametrize("seed", range(6))
def test_granular_squares(seed):
    speed = 2.0
    s = granular_squares(seed, speed=speed)
    again = granular_squares(seed, speed=speed)
    assert s == again
    np.testing.assert_array_equal(s.particles()["x"], again.particles()["x"])
    assert len(s.bodies) in (1, 2)
    (x0, x1), (y0, y1) = s.domain
    for b in s.bodies:
        assert isinstance(b.material, Sand)
        bx0, by0, bx1, by1 = b.shape.bbox
        assert x0 <= bx0 < bx1 <= x1 and y0 <= by0 < by1 <= y1
        assert bx1 - bx0 == pytest.approx(0.2) and by1 - by0 == pytest.approx(0.2)
        assert all(abs(v) <= speed for v in b.velocity)
    if len(s.bodies) == 2:
        a, b = _squares(s)
        assert a.x1 <= b.x0 or b.x1 <= a.x0 or a.y1 <= b.y0 or b.y1 <= a.y0


def test_granular_squares_seeds_differ():
    scenes = [granular_squares(seed) for seed in range(8)]
    assert len({s.bodies for s in scenes}) == len(scenes)
    assert {len(s.bodies) for s in scenes} == {1, 2}


def test_granular_squares_two_masses():
    s = granular_squares(3, n_masses=2)
    assert len(s.bodies) == 2
    with pytest.raises(SceneError, match="n_masses = 3"):
        granular_squares(0, n_masses=3)


def test_friction_feature_is_tan_phi_with_its_derivative():
    import jax
    import jax.numpy as jnp

    from diffgns.scene.materials import friction_feature

    assert float(friction_feature(45.0)) == pytest.approx(1.0, rel=1e-6)
    assert float(friction_feature(30.0)) == pytest.approx(1 / math.sqrt(3), rel=1e-6)
    phis = jnp.asarray([[20.0, 30.0], [40.0, 50.0]], jnp.float32)
    f = friction_feature(phis)
    assert f.shape == (2, 2) and f.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(f), np.tan(np.radians(np.asarray(phis))), rtol=1e-6)
    d = jax.grad(lambda p: friction_feature(p))(30.0)  # (pi/180) / cos^2(phi)
    assert float(d) == pytest.approx(math.pi / 180 / math.cos(math.radians(30.0)) ** 2,
                                     rel=1e-5)


def test_scene_file_docstring_example_is_valid_toml_and_loads(tmp_path):
    """The layout example in diffgns.scene.files' docstring is a complete scene file."""
    import textwrap

    import diffgns.scene.files as files

    doc = files.__doc__
    block = doc.split("::\n\n", 1)[1].split("\n\n", 1)[0]
    text = textwrap.dedent(block)
    assert "[[obstacles]]" in text and "[[bodies]]" in text
    path = tmp_path / "example.toml"
    path.write_text(text)
    scene = load_scene(path)
    assert scene.domain == ((0.0, 1.0), (0.0, 0.5)) and scene.dx == 0.01
    (body,) = scene.bodies
    assert body.material.friction_angle == 30.0 and body.shape.x1 == 0.2
    (obstacle,) = scene.obstacles
    assert (obstacle.x0, obstacle.y1, obstacle.surface.kind) == (0.5, 0.05, "sticky")
    assert scene.walls.bottom.kind == "friction" and scene.walls.bottom.mu == 0.5
    assert scene.n_particles > 0
