"""Differentiating 3D collapses: the radial runout, its gradient against central finite
differences (float64), and the friction angle recovered from a 3D runout by ``diffgns
invert`` (issue 24)."""
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns import MPM
from diffgns.cli import main
from diffgns.interface import rollout_jit
from diffgns.inverse.job import default_center, make_objective
from diffgns.inverse.observation import SceneObservation
from diffgns.metrics import runout
from diffgns.scene import Body, Box, Sand, Scene
from diffgns.scene.builders3d import axisymmetric_column, slab_column
from diffgns.scene.files import save_scene


def _small_column(**kw):
    """R0 = 3 cm in 3 cells, H0 = R0: 672 particles on a 24 x 6 x 24 grid; a soft sand
    (E = 0.2 MPa) so that a frame takes 10 substeps."""
    args = dict(radius=0.03, aspect_ratio=1.0, cells_across=3, friction_angle=30.0, E=2e5)
    args.update(kw)
    return axisymmetric_column(**args)


def test_radial_runout_is_the_distance_from_the_axis_with_a_finite_gradient_on_it():
    x = jnp.asarray([[0.5, 0.0, 0.5], [0.8, 0.1, 0.9], [0.2, 0.3, 0.5]])
    r = runout(x, method="max", center=(0.5, 0.5))
    assert float(r) == pytest.approx(0.5, rel=1e-6)  # (0.3, 0.4) from the axis
    soft = runout(x, method="softmax", center=(0.5, 0.5), temperature=1e-3)
    assert float(soft) == pytest.approx(0.5 - 1e-3 * np.log(3), rel=1e-5)
    g = jax.grad(lambda x: runout(x, method="softmax", center=(0.5, 0.5)).sum())(x)
    assert np.isfinite(np.asarray(g)).all()
    np.testing.assert_allclose(np.asarray(g)[1], [0.6, 0.0, 0.8], atol=1e-4)  # d|h|/dh
    np.testing.assert_array_equal(np.asarray(g)[0], 0.0)  # the particle on the axis
    # without a centre: x from the origin, as in 2D; a centre needs 3D positions
    assert float(runout(x, origin=0.1)) == pytest.approx(0.7)
    with pytest.raises(ValueError, match="needs 3D positions"):
        runout(x[:, :2], center=(0.5, 0.5))


def test_3d_objectives_measure_the_radius_about_the_cylinder_axis():
    sc = _small_column()
    c = default_center(sc)
    assert c == pytest.approx((sc.domain[0][1] / 2, sc.domain[2][1] / 2))
    obs = SceneObservation(sc, 2)
    x0 = jnp.asarray(sc.particles()["x"])[None].repeat(3, 0)
    loss = make_objective("runout-max", obs, observed_runout=0.03)  # R0 itself
    assert float(loss(x0)) < (0.03 / 3 / 2) ** 2  # within half a particle spacing of R0
    # a slab (boxes) keeps the x runout; the deposit profile is 2D only; a centre is 3D only
    assert default_center(slab_column(cells_across=2)) is None
    assert default_center(Scene(domain=((0, 0.2), (0, 0.1), (0, 0.2)), dx=0.02,
                                bodies=(Body(Box(0.0, 0.0, 0.0, 0.1, 0.04, 0.1), Sand()),))
                          ) is None
    with pytest.raises(ValueError, match="deposit objective is a 2D height profile"):
        make_objective("deposit", obs, observed=np.asarray(x0))
    from diffgns.scene.builders import column_collapse
    obs2 = SceneObservation(column_collapse(cells_across=2), 2)
    with pytest.raises(ValueError, match="for 3D scenes"):
        make_objective("runout", obs2, observed_runout=0.1, center=(0.1, 0.1))
    with pytest.raises(ValueError, match="not both"):
        make_objective("runout", obs, observed_runout=0.1, center=c, origin=0.0)


@pytest.mark.slow  # ~1-3 min: a checkpointed float64 3D rollout and its gradient
def test_3d_collapse_runout_gradient_matches_finite_differences(x64):
    sc = _small_column()
    sim = MPM(sc, dtype="float64")
    base, state = sim.params(), sim.init()
    c = default_center(sc)

    def f(phi):
        p = base.replace(friction_angle=jnp.reshape(phi, (1,)))
        pos = rollout_jit(sim, p, state, n_frames=40, checkpoint_block=10)[0].positions
        return runout(pos[-1], method="softmax", center=c)

    g = float(jax.grad(f)(30.0))
    h = 1e-4 * 30.0
    fd = float((f(30.0 + h) - f(30.0 - h)) / (2 * h))
    assert fd < 0  # a stronger sand spreads less
    assert g == pytest.approx(fd, rel=1e-3)


@pytest.mark.slow  # ~5-10 min: Gauss-Newton iterations through a 3D MPM rollout
def test_invert_recovers_the_friction_angle_from_a_3d_runout(tmp_path, x64, capsys):
    sc = _small_column(aspect_ratio=2.0)
    frames = 40
    sim = MPM(sc, dtype="float64")
    traj = sim.run(sim.params(), sim.init(), frames)[0]
    observed = float(runout(jnp.asarray(traj.positions[-1]), center=default_center(sc)))
    path = tmp_path / "axi.toml"
    save_scene(sc, path)
    out = tmp_path / "inv"
    rc = main(["invert", str(path), "--fit", "friction_angle=38:10:60", "--observed-runout",
               str(observed), "--frames", str(frames), "--dtype", "float64",
               "--step-tol", "0.01", "--max-iter", "8", "--truth", "friction_angle=30",
               "--out", str(out)])
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["objective"] == "runout-max"
    assert s["recovered"]["friction_angle"] == pytest.approx(30.0, abs=0.1)
    assert s["history"][0]["loss"] > 1e3 * s["history"][-1]["loss"]
    assert "recovered friction angle" in capsys.readouterr().out
