"""Inverse problems on any scene: parameter names, the observation operator of a
non-column scene, and learned simulators refusing scenes their model does not support."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns.graph.support import UnsupportedSceneError
from diffgns.inverse import Bounded
from diffgns.inverse.job import make_objective, make_simulator, runout_value_loss
from diffgns.inverse.observation import SceneObservation, coarse_grain_positions
from diffgns.inverse.parameters import parse_fit, set_params
from diffgns.inverse.simulators import check_fit, gns_simulator, hybrid_simulator, load_gns
from diffgns.mpm import MPM
from diffgns.scene import Body, BoxObstacle, Elastic, Rectangle, Sand, Scene, Wall, Walls


def _two_bodies():
    return Scene(domain=((0.0, 0.4), (0.0, 0.2)), dx=0.025,
                 bodies=(Body(Rectangle(0.05, 0.0, 0.15, 0.05), Sand(30.0), name="left"),
                         Body(Rectangle(0.25, 0.0, 0.3, 0.1), Elastic(), name="block")),
                 walls=Walls(bottom=Wall("friction", 0.5)),
                 obstacles=(BoxObstacle(0.2, 0.0, 0.225, 0.05),
                            BoxObstacle(0.35, 0.0, 0.375, 0.05)))


def _obstacle_scene(**kw):
    """A sand square sliding into a box, in the box and at the resolution of gns_columns."""
    body = Body(Rectangle(0.05, 0.0, 0.15, 0.1), Sand(30.0), velocity=(1.0, 0.0), name="mass")
    args = dict(domain=((0.0, 0.8), (0.0, 0.35)), dx=0.0125, bodies=(body,),
                walls=Walls(bottom=Wall("friction", 0.5)),
                obstacles=(BoxObstacle(0.25, 0.0, 0.35, 0.05, Wall("friction", 0.5)),))
    args.update(kw)
    return Scene(**args)


def test_parse_fit_reads_start_and_bounds():
    name, start, tf = parse_fit("friction_angle=40:0:90")
    assert (name, start, tf) == ("friction_angle", 40.0, Bounded(0.0, 90.0))
    assert parse_fit("wall_mu[bottom]=0.3") == ("wall_mu[bottom]", 0.3, None)
    for bad, msg in [("friction_angle", "name=start"), ("friction_angle=95:0:90", "inside"),
                     ("E=1:2", "start:lo:hi"), ("E=a:0:1", "numbers"), ("E[=1", "malformed")]:
        with pytest.raises(ValueError, match=msg):
            parse_fit(bad)


def test_set_params_writes_any_leaf_by_name_and_passes_gradients():
    scene = _two_bodies()
    p0 = MPM(scene).params()
    theta = {"friction_angle[left]": 25.0, "E[block]": 3e6, "rho": 1500.0,
             "wall_mu[left]": 0.2, "floor_mu": 0.7, "obstacle_mu[1]": 0.4,
             "gravity[y]": -5.0, "damping": 2.0, "aspect_ratio": 3.0}
    p = set_params(p0, scene, theta)
    np.testing.assert_allclose(p.friction_angle, [25.0, 30.0])
    np.testing.assert_allclose(p.E, [p0.E[0], 3e6])
    np.testing.assert_allclose(p.rho, [1500.0, 1500.0])
    np.testing.assert_allclose(p.wall_mu, [0.2, 0.0, 0.7, 0.0], atol=1e-7)
    np.testing.assert_allclose(p.obstacle_mu, [0.0, 0.4], atol=1e-7)
    np.testing.assert_allclose(p.gravity, [0.0, -5.0])
    assert float(p.damping) == 2.0  # aspect_ratio is a state quantity: MPMParams untouched
    g = jax.grad(lambda th: sum(jnp.sum(leaf) for leaf in jax.tree.leaves(
        set_params(p0, scene, th))))({"rho": 1.0, "wall_mu": 0.1, "E[1]": 1.0})
    assert g == {"rho": 2.0, "wall_mu": 4.0, "E[1]": 1.0}  # one leaf entry per use
    # without a scene: bodies by index, the same values
    by_index = {k: v for k, v in theta.items() if k not in ("friction_angle[left]",
                                                             "E[block]")}
    q = set_params(p0, None, by_index | {"friction_angle[0]": 25.0, "E[1]": 3e6})
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(p), jax.tree.leaves(q)))
    for bad, msg in [("friction_angle[right]", "no body 'right'; this scene has bodies "
                      r"\['left', 'block'\]"), ("wall_mu[front]", "no wall"),
                     ("stiffness", "unknown parameter 'stiffness'"), ("gravity", "component")]:
        with pytest.raises(ValueError, match=msg):
            set_params(p0, scene, {bad: 1.0})


def test_observation_of_a_non_column_scene():
    obs = SceneObservation(_obstacle_scene(), n_frames=6, coarse_grain=4, frame_stride=2)
    assert (obs.n_nodes, obs.n_obs, obs.frame_dt) == (64, 4, 5e-3)
    x0 = np.asarray(obs.state.x.T)
    traj = np.stack([x0 + 0.001 * t for t in range(7)])  # (7, N, 2) at MPM frames
    nodes = np.asarray(obs.observe(jnp.asarray(traj)))
    np.testing.assert_allclose(nodes[1] - nodes[0], 0.002, atol=1e-6)
    # a recorded trajectory at MPM frames or at observed frames gives the same nodes
    np.testing.assert_allclose(obs.observe_trajectory(traj, 2.5e-3), nodes, atol=1e-6)
    np.testing.assert_allclose(obs.observe_trajectory(traj[::2], 5e-3), nodes, atol=1e-6)
    assert obs.same_particles(traj[0]) and not obs.same_particles(traj[0, :10])
    with pytest.raises(ValueError, match="frames of 0.001 s"):
        obs.observe_trajectory(traj, 1e-3)
    with pytest.raises(ValueError, match="4 are needed"):
        obs.observe_trajectory(traj[:5], 2.5e-3)
    # other particle sets are grouped by their own first frame (here: the particles reversed)
    rev = coarse_grain_positions(traj[:, ::-1], 4)
    np.testing.assert_allclose(np.sort(rev[0], axis=0), np.sort(nodes[0], axis=0), atol=1e-6)
    # aspect_ratio of the one rectangular body: stretched about its base (y0 = 0 here)
    st = obs.initial_state({"aspect_ratio": 2.0})
    assert float(st.x[1].max()) == pytest.approx(2.0 * float(obs.state.x[1].max()), rel=1e-6)
    two = SceneObservation(_two_bodies(), n_frames=2)
    with pytest.raises(ValueError, match="aspect_ratio is defined for a scene of one "
                       "rectangular body"):
        two.check_names(["aspect_ratio"])


def test_raised_body_stretches_about_its_base():
    body = Body(Rectangle(0.1, 0.05, 0.2, 0.1), Sand(30.0))
    obs = SceneObservation(Scene(domain=((0.0, 0.4), (0.0, 0.3)), dx=0.025, bodies=(body,)), 1)
    assert obs.aspect_ratio == pytest.approx(0.5)
    st = obs.initial_state({"aspect_ratio": 1.0})
    y, y0 = np.asarray(st.x[1]), np.asarray(obs.state.x[1])
    np.testing.assert_allclose(y - 0.05, 2.0 * (y0 - 0.05), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(st.vol), 2.0 * np.asarray(obs.state.vol), rtol=1e-6)


def test_objectives_for_a_trajectory_or_a_measured_runout():
    obs = SceneObservation(_obstacle_scene(), n_frames=4)
    x = jnp.asarray(np.stack([np.asarray(obs.state.x.T)] * 5))
    L = runout_value_loss(0.2, obs.n_obs, method="max")
    assert float(L(x)) == pytest.approx((0.15 - 0.2 - (0.0125 / 4)) ** 2, rel=1e-4)
    with pytest.raises(ValueError, match="exactly one observation"):
        make_objective("runout", obs)
    with pytest.raises(ValueError, match="deposit objective needs an observed trajectory"):
        make_objective("deposit", obs, observed_runout=0.3)
    D = make_objective("deposit", obs, observed=np.asarray(x))
    assert float(D(x)) == pytest.approx(0.0, abs=1e-12)


def test_learned_simulators_refuse_unsupported_scenes_and_parameters():
    loaded = load_gns("gns_columns")
    wide = _obstacle_scene(domain=((0.0, 1.0), (0.0, 0.35)))
    with pytest.raises(UnsupportedSceneError, match=r"box \[0, 1\] x \[0, 0.35\] m is not "
                       "the training box"):
        SceneObservation.for_model(wide, loaded[2], 10)
    fine = SceneObservation(_obstacle_scene(dx=0.00625), 10, 4, 2)
    for build in (lambda: gns_simulator(fine, loaded=loaded, observed=np.zeros((6, 256, 2))),
                  lambda: hybrid_simulator(fine, loaded=loaded)):
        with pytest.raises(UnsupportedSceneError, match="dx = 0.00625 m is not the 0.0125 m"):
            build()
    obs = SceneObservation.for_model(_obstacle_scene(), loaded[2], 20)
    assert (obs.coarse_grain, obs.frame_stride, obs.n_obs) == (4, 2, 11)
    assert any("obstacle" in w for w in obs.warnings)
    with pytest.raises(ValueError, match=r"the GNS cannot fit \['E'\]: its only material "
                       "input is tan\\(friction_angle\\)"):
        check_fit(["friction_angle", "E"], "gns")
    check_fit(["E", "aspect_ratio"], "hybrid")  # the hybrid's MPM frames see every leaf
    with pytest.raises(ValueError, match="no obstacles"):
        make_simulator("mpm", SceneObservation(_obstacle_scene(obstacles=()), 2),
                       theta0={"obstacle_mu": 0.3})


def test_column_case_from_a_model_folder_is_a_scene_the_model_supports():
    from diffgns.graph.support import check_scene
    from diffgns.inverse.observation import Column, ColumnCase
    from diffgns.inverse.simulators import model_info

    info = model_info("gns_columns")
    assert ColumnCase.from_model(info, 1.75) == ColumnCase(aspect_ratio=1.75)
    cg16 = model_info("gns_cg16")
    case = ColumnCase.from_model(cg16, 1.0, n_frames=10)
    assert (case.cells_across, case.coarse_grain, case.frame_stride) == (16, 16, 2)
    col = Column(case)
    assert col.scene.n_cells == (128, 56) and col.n_nodes == 64  # 1024 particles / 16
    assert check_scene(col.scene, cg16).factor == 16
    with pytest.raises(ValueError, match="not trained on column collapses"):
        ColumnCase.from_model({"source": {"kind": "squares"}, "gns": {"bounds": [[0, 1]] * 2}})


def test_an_inversion_through_a_model_warns_when_it_ends_outside_the_training_range(
        tmp_path, capsys):
    """The learned adapters know their model's training range (gns_columns: 20-45 deg) and
    the MPM has none; ``solve`` puts a recovered angle outside it in ``parameter_warnings``
    and ``warnings`` and prints it before the result line; one inside gives none."""
    from diffgns.inverse.job import solve
    from diffgns.inverse.simulators import mpm_simulator

    loaded = load_gns("gns_columns")
    obs = SceneObservation.for_model(_obstacle_scene(), loaded[2], 20)
    n = obs.n_nodes
    gns = gns_simulator(obs, loaded=loaded, observed=np.zeros((obs.n_obs, n, 2)))
    hyb = hybrid_simulator(obs, loaded=loaded)
    for sim in (gns, hyb):
        assert sim.parameter_warnings({"friction_angle": 30.0}) == []
        (w,) = sim.parameter_warnings({"friction_angle": 52.0, "E": 1.0})
        assert w.startswith("the friction_angle = 52.00 deg is outside the 20.0-45.0 deg")
    assert mpm_simulator(obs).parameter_warnings({"friction_angle": 52.0}) == []

    class Linear:  # positions linear in phi: the loss's minimum is where the target puts it
        parameter_warnings = gns.parameter_warnings

        def simulate(self, theta):
            x = jnp.zeros((obs.n_obs, n, 2)) + 1e-3 * theta["friction_angle"]
            return x, jnp.asarray(False)

        def reallocate(self, theta):
            pass

    for target, warned in ((0.052, True), (0.035, False)):
        s = solve(Linear(), lambda x, t=target: (x[-1, 0, 0] - t) ** 2,
                  {"friction_angle": 40.0}, obs, tmp_path / str(target), max_iter=10,
                  step_tol=1e-4)
        assert s["recovered"]["friction_angle"] == pytest.approx(1e3 * target, abs=0.01)
        assert bool(s["parameter_warnings"]) == warned
        assert s["warnings"] == list(obs.warnings) + s["parameter_warnings"]
        lines = capsys.readouterr().out.strip().splitlines()
        assert lines[-1].startswith("recovered friction angle:")
        assert lines[-2].startswith("warning: the friction_angle = 52.00 deg") == warned
