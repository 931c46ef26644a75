"""The inverse-problem loop, parameter transforms, objectives and parameter plumbing."""
import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns import MPM, inverse
from diffgns.inverse import objectives
from diffgns.scene.builders import column_collapse
from diffgns.scene.materials import friction_feature

ROOT = Path(__file__).resolve().parents[1]


def _example():
    spec = importlib.util.spec_from_file_location(
        "column_collapse_inverse", ROOT / "examples/column_collapse_inverse.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_optimize_recovers_minimum_and_records_history():
    res = inverse.optimize(lambda th: (th["a"] - 3.0) ** 2 + (th["b"] + 1.0) ** 2,
                           {"a": 0.0, "b": 0.0}, inverse.make_optimizer("adam", 0.5, 0.95),
                           max_iter=200, loss_tol=1e-6,
                           transforms={"b": inverse.Bounded(-0.5, 1.0)})
    assert res.theta["a"] == pytest.approx(3.0, abs=0.05)
    assert -0.5 < res.theta["b"] < -0.45  # pushed against its bound, never past it
    h = res.history[0]
    assert set(h) >= {"iteration", "theta", "loss", "grad", "grad_u", "time_s", "rss_mb",
                      "peak_rss_mb"}
    assert h["grad"]["a"] == pytest.approx(-6.0)
    assert h["grad"]["b"] == pytest.approx(2.0, rel=1e-5)  # physical gradient, not d/du
    assert res.compile_s > 0 and "temp_size_in_bytes" in res.xla_memory


def test_transform_keeps_friction_angle_inside_0_90():
    tf = inverse.FRICTION_ANGLE
    for u in (-1e6, -40.0, -3.0, 0.0, 3.0, 40.0, 1e6):
        phi = float(tf.forward(jnp.float32(u)))
        assert 0.0 < phi < 90.0
    assert float(tf.forward(jnp.asarray(tf.inverse(30.0)))) == pytest.approx(30.0, rel=1e-6)
    # a wildly large step stays inside the range
    res = inverse.optimize(lambda th: -th["friction_angle"], {"friction_angle": 45.0},
                           inverse.make_optimizer("sgd", 1e6), max_iter=3)
    assert all(0 < h["theta"]["friction_angle"] < 90 for h in res.history)


@pytest.mark.parametrize("start", [0.0, 90.0, 95.0, -10.0, float("nan")])
def test_start_outside_physical_range_is_rejected(start):
    with pytest.raises(ValueError, match="friction_angle = .* outside its physical range"):
        inverse.optimize(lambda th: th["friction_angle"] ** 2, {"friction_angle": start},
                         inverse.make_optimizer("adam", 0.1))


def test_example_cli_rejects_invalid_angles(capsys):
    ex = _example()
    for bad in (["--start-phi", "95"], ["--target-phi", "0"], ["--max-iter", "-1"]):
        with pytest.raises(SystemExit):
            ex.parse(bad)
    assert "use 0 < phi < 90" in capsys.readouterr().err
    assert ex.parse([]).simulator == "gns"  # the GNS is the default simulator


def test_gauss_newton_stops_by_step_rule():
    """One residual r(phi) = 0.15 - 0.006 phi + 2e-5 phi^2: Newton converges in a few steps."""
    r = lambda th: 0.15 - 0.006 * th["friction_angle"] + 2e-5 * th["friction_angle"] ** 2
    res = inverse.optimize(lambda th: r(th) ** 2, {"friction_angle": 45.0},
                           inverse.make_optimizer("gauss-newton"), max_iter=20, step_tol=1e-3)
    root = (0.006 - np.sqrt(0.006**2 - 8e-5 * 0.15)) / 4e-5  # 27.5 deg
    assert res.converged and res.stop_reason == "step < step_tol"
    assert len(res.history) <= 7
    assert res.theta["friction_angle"] == pytest.approx(root, abs=2e-3)


def test_loop_stops_by_loss_tol_and_max_iter():
    f = lambda th: (th["x"] - 1.0) ** 2
    res = inverse.optimize(f, {"x": 0.0}, inverse.make_optimizer("sgd", 0.4), max_iter=50,
                           loss_tol=1e-4)
    assert res.converged and res.stop_reason.startswith("loss <=")
    assert res.history[-1]["loss"] <= 1e-4 < res.history[-2]["loss"]
    res = inverse.optimize(f, {"x": 0.0}, inverse.make_optimizer("sgd", 1e-3), max_iter=4)
    assert not res.converged and len(res.history) == 5 and res.stop_reason == "max_iter = 4"


def test_finite_difference_option_and_gradient_check_match_ad():
    f = lambda th: jnp.sin(th["x"]) * th["y"] ** 2
    th = {"x": jnp.asarray(0.3), "y": jnp.asarray(1.5)}
    ad = jax.grad(f)(th)
    fd = inverse.finite_difference_grad(f, th)
    for k in th:
        assert fd[k] == pytest.approx(float(ad[k]), rel=1e-3)
    res = inverse.optimize(f, {"x": 0.3, "y": 1.5}, inverse.make_optimizer("sgd", 0.0),
                           max_iter=0, gradient="fd", fd_rel_step=1e-3)
    for k in th:
        assert res.history[0]["grad"][k] == pytest.approx(float(ad[k]), rel=1e-3)
    chk = inverse.gradient_check(f, {"x": 0.3, "y": 1.5}, rel_steps=(1e-3,), repeats=1)
    assert max(chk["rel_diff"]["0.001"].values()) < 1e-3
    assert chk["ad_time_s"] > 0 and chk["fd_time_s"] > 0


def test_fd_step_rule_has_a_unit_floor_and_stays_inside_bounds():
    assert inverse.fd_step(30.0, 1e-3) == pytest.approx(0.03)
    assert inverse.fd_step(0.0, 1e-3) == pytest.approx(1e-3)  # floor: 1 unit, not 0
    assert inverse.fd_step(-0.2, 1e-3) == pytest.approx(1e-3)
    assert inverse.fd_step(1e-4, 1e-2, lo=0.0, hi=2.0) == pytest.approx(5e-5)  # half-way
    assert inverse.fd_step(1.9999, 1e-2, lo=0.0, hi=2.0) == pytest.approx(5e-5, rel=1e-6)
    assert inverse.central_difference(lambda x: x**3, 2.0, 1e-3) == pytest.approx(12.0,
                                                                                 rel=1e-6)


def test_fd_gradient_at_zero_and_next_to_a_bound_matches_ad():
    """float32: at x = 0 a purely relative step (1e-6 with the old 1e-3 floor) left ~1 %
    rounding error in the difference; next to a bound the step must not leave the range."""
    f = lambda th: (th["x"] - 0.5) ** 2 + 3.0 * th["mu"]
    res = inverse.optimize(f, {"x": 0.0, "mu": 2e-4}, inverse.make_optimizer("sgd", 0.0),
                           max_iter=0, gradient="fd", fd_rel_step=1e-3,
                           transforms={"mu": inverse.Bounded(0.0, 2.0)})
    assert res.history[0]["grad"]["x"] == pytest.approx(-1.0, rel=1e-4)
    assert res.history[0]["grad"]["mu"] == pytest.approx(3.0, rel=1e-3)
    fd = inverse.finite_difference_grad(lambda th: (th["x"] - 0.5) ** 2, {"x": 0.0},
                                        rel_step=1e-3)
    assert fd["x"] == pytest.approx(-1.0, rel=1e-4)


def test_levenberg_marquardt_solves_two_residuals_and_rejects_bad_steps():
    from diffgns.inverse.lsq import least_squares

    def residuals(th):  # root at phi = 30, a = 1.75; strongly nonlinear in phi
        p, a = th["friction_angle"], th["aspect_ratio"]
        return jnp.stack([friction_feature(p) - friction_feature(30.0),
                          0.3 * a - 0.01 * p - (0.3 * 1.75 - 0.3)])

    res = least_squares(residuals, {"friction_angle": 60.0, "aspect_ratio": 3.0},
                        max_iter=30, step_tol=1e-4)
    assert res.converged and res.stop_reason == "step < step_tol" and len(res.history) < 15
    assert res.theta["friction_angle"] == pytest.approx(30.0, abs=1e-3)
    assert res.theta["aspect_ratio"] == pytest.approx(1.75, abs=1e-4)
    h = res.history[0]
    assert len(h["residuals"]) == 2 and h["accepted"] and "damping" in h
    losses = [r["loss"] for r in res.history if r["accepted"]]
    assert all(b <= a for a, b in zip(losses, losses[1:]))  # accepted steps never go up


def test_overflow_triggers_reallocation_and_redo():
    calls = []
    flag = {"overflow": True}

    def loss(th):
        return (th["x"] - 2.0) ** 2, {"overflow": jnp.asarray(flag["overflow"])}

    def grow(theta):
        calls.append(theta)
        flag["overflow"] = False  # the retraced loss sees the grown capacity

    res = inverse.optimize(loss, {"x": 0.0}, inverse.make_optimizer("sgd", 0.1), max_iter=2,
                           has_aux=True, on_overflow=grow)
    assert len(calls) == 1 and all(h["aux"]["overflow"] == 0.0 for h in res.history)
    with pytest.raises(RuntimeError, match="overflow"):
        flag["overflow"] = True
        inverse.optimize(loss, {"x": 0.0}, inverse.make_optimizer("sgd", 0.1), has_aux=True)


def test_objectives_on_any_trajectory():
    rng = np.random.default_rng(0)
    target = rng.uniform(0, 0.3, (5, 20, 2))
    moved = jnp.asarray(target).at[:, :, 0].add(0.01)
    L = objectives.runout_loss(target, method="max")
    assert float(L(jnp.asarray(target))) == 0.0
    assert float(L(moved)) == pytest.approx(1e-4, rel=1e-4)
    L2 = objectives.runout_loss(target, frame=2, method="softmax")
    assert L2.frame == 2 and float(jax.grad(lambda p: L2(p))(moved)[2, :, 0].sum()) > 0
    T = objectives.tracks_loss(target, particles=[0, 3], frames=[1, -1])
    assert float(T(moved)) == pytest.approx(1e-4, rel=1e-4)
    D = objectives.deposit_loss(target, np.linspace(0, 0.4, 9), sharpness=400.0)
    assert float(D(jnp.asarray(target))) == pytest.approx(0.0, abs=1e-12)
    assert float(D(moved)) > 0
    with pytest.raises(ValueError, match="outside the target trajectory"):
        objectives.runout_loss(target, frame=5)
    with pytest.raises(ValueError, match="runout method"):
        objectives.runout_loss(target, method="mean")
    with pytest.raises(ValueError, match=r"\(T, N, 2\)"):
        objectives.runout_loss(target[0])
    with pytest.raises(ValueError, match="particles"):
        objectives.tracks_loss(target, particles=[20])


def test_set_params_sets_leaves_and_passes_gradients():
    sim = MPM(column_collapse(cells_across=4))
    p = sim.params()
    q = inverse.set_params(p, None, {"friction_angle": 40.0, "floor_mu": 0.2, "E": 3e6})
    assert float(q.friction_angle[0]) == 40.0 and float(q.wall_mu[2]) == pytest.approx(0.2)
    assert float(q.E[0]) == 3e6 and float(q.wall_mu[0]) == float(p.wall_mu[0])
    g = jax.grad(lambda t: inverse.set_params(p, None, t).wall_mu.sum())({"floor_mu": 0.3})
    assert float(g["floor_mu"]) == 1.0
    with pytest.raises(ValueError, match="phi"):
        inverse.set_params(p, None, {"phi": 1.0})


def test_frames_to_rest():
    speed = np.r_[np.linspace(1, 0.1, 50), np.full(30, 0.001)]
    assert inverse.frames_to_rest(speed, threshold=0.02, margin=10, multiple=25) == 75


@pytest.mark.slow
@pytest.mark.parametrize("simulator,tol", [("gns", 1.0), ("mpm", 0.5)])
def test_inverse_example_recovers_friction_angle(tmp_path, simulator, tol):
    out = tmp_path / simulator
    r = subprocess.run([sys.executable, str(ROOT / "examples/column_collapse_inverse.py"),
                        "--out", str(out), "--simulator", simulator],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    last = r.stdout.strip().splitlines()[-1]
    assert last.startswith("recovered friction angle:")
    s = json.loads((out / "summary.json").read_text())
    assert abs(s["recovered"]["friction_angle"] - 30.0) <= tol
    assert s["iterations"] <= 20 and s["wall_time_s"] < 300
    assert (out / "convergence.png").exists() and (out / "deposits.png").exists()


@pytest.mark.slow
def test_joint_example_identifies_friction_angle_and_aspect_ratio_with_the_mpm(tmp_path):
    out = tmp_path / "joint"
    r = subprocess.run([sys.executable, str(ROOT / "examples/column_collapse_inverse_joint.py"),
                        "--out", str(out), "--simulator", "mpm"],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    s = json.loads((out / "summary.json").read_text())
    assert abs(s["recovered"]["friction_angle"] - 30.0) <= 0.5
    assert abs(s["recovered"]["aspect_ratio"] - 1.75) <= 0.02
    assert s["identifiability"]["front_condition_number"] < 100


def test_a_step_back_to_an_earlier_iterate_stops_as_a_cycle():
    """A gradient of the wrong sign at the start (a noisy objective): Gauss-Newton's clipped
    step goes up to ~65.8 deg, the next comes back to 45 exactly; the loop says so and stops
    instead of repeating the two points until max_iter."""
    @jax.custom_jvp
    def residual(phi):
        return 0.02 * (phi - 30.0)

    @residual.defjvp
    def _jvp(p, t):  # true slope 0.02/deg, but of the wrong sign at and near 45 deg
        (phi,), (dphi,) = p, t
        slope = jnp.where(jnp.abs(phi - 45.0) < 0.5, -1e-4, 0.02)
        return residual(phi), slope * dphi

    res = inverse.optimize(lambda th: residual(th["friction_angle"]) ** 2,
                           {"friction_angle": 45.0}, inverse.make_optimizer("gauss-newton"),
                           max_iter=20, step_tol=0.01)
    phis = [h["theta"]["friction_angle"] for h in res.history]
    assert len(phis) == 2 and phis[1] > 60.0
    assert not res.converged and res.stop_reason.startswith("cycle: ")
    assert "iteration 0" in res.stop_reason
    # "auto": the step to 65.8 raised the loss, so it restarts from 45 deg with differences
    # (restarting from 65.8, where the exact slope is right, cycled back to 45 on the MPM)
    auto = inverse.optimize(lambda th: residual(th["friction_angle"]) ** 2,
                            {"friction_angle": 45.0}, inverse.make_optimizer("gauss-newton"),
                            max_iter=20, step_tol=0.01, gradient="auto")
    assert auto.history[1]["rejected"]["restart_iteration"] == 0
    assert auto.history[2]["theta"]["friction_angle"] < 45.0
    assert auto.converged and abs(auto.theta["friction_angle"] - 30.0) < 0.01
    ok = inverse.optimize(lambda th: (0.02 * (th["friction_angle"] - 30.0)) ** 2,
                          {"friction_angle": 45.0}, inverse.make_optimizer("gauss-newton"),
                          max_iter=20, step_tol=0.01)
    assert ok.converged and abs(ok.theta["friction_angle"] - 30.0) < 0.01


def _rough_loss(th):
    """A misfit whose trend has its root at 30 deg and whose exact slope, from a ripple of
    0.01 deg period, changes sign every 0.005 deg (amplitude 0.06/deg against the trend's
    0.02/deg): AD is exact and misleading, as on the MPM's runout of a tall collapse."""
    phi = th["friction_angle"]
    return (0.02 * (phi - 30.0) + 2e-4 * jnp.sin(2 * jnp.pi * phi / 0.01)) ** 2


def test_auto_gradient_turns_to_differences_where_the_exact_slope_misleads():
    gn = inverse.make_optimizer("gauss-newton")
    ad = inverse.optimize(_rough_loss, {"friction_angle": 45.0}, gn, max_iter=12,
                          step_tol=0.01)
    assert not ad.converged  # wanders on the ripple's slopes
    auto = inverse.optimize(_rough_loss, {"friction_angle": 45.0}, gn, max_iter=12,
                            step_tol=0.01, gradient="auto")
    modes = [h["gradient"] for h in auto.history]
    turn = next(i for i, h in enumerate(auto.history) if "rejected" in h)
    assert set(modes[:turn + 1]) == {"ad"} and set(modes[turn + 1:]) == {"fd"}
    losses = auto.series("loss")
    assert losses[turn] > losses[:turn].min()  # the trigger: the loss rose
    j = auto.history[turn]["rejected"]["restart_iteration"]
    assert losses[j] == losses[:turn + 1].min()  # restarted from the lowest-loss iterate
    phi = auto.series("theta", "friction_angle")
    assert np.sign(phi[turn + 1] - phi[j]) == np.sign(30.0 - phi[j])  # trend, not ripple
    assert auto.converged and abs(auto.theta["friction_angle"] - 30.0) < 0.02
    # on a smooth loss "auto" never turns and takes exactly the steps of "ad"
    smooth = lambda th: (0.02 * (th["friction_angle"] - 30.0)) ** 2
    a = inverse.optimize(smooth, {"friction_angle": 45.0}, gn, max_iter=20, step_tol=0.01)
    b = inverse.optimize(smooth, {"friction_angle": 45.0}, gn, max_iter=20, step_tol=0.01,
                         gradient="auto")
    assert {h["gradient"] for h in b.history} == {"ad"}
    assert a.series("theta", "friction_angle").tolist() == \
        b.series("theta", "friction_angle").tolist()
    with pytest.raises(ValueError, match="smooth_rel_step"):
        inverse.optimize(smooth, {"friction_angle": 45.0}, gn, gradient="auto",
                         smooth_rel_step=0.0)


def test_an_unconverged_loop_returns_its_lowest_loss_iterate():
    res = inverse.optimize(_rough_loss, {"friction_angle": 45.0},
                           inverse.make_optimizer("gauss-newton"), max_iter=6, step_tol=0.01)
    losses = res.series("loss")
    best = int(np.argmin(losses))
    assert not res.converged and best != len(losses) - 1
    assert res.theta == res.history[best]["theta"]
    assert f"returned iteration {best}" in res.stop_reason


def test_auto_rejects_an_overshoot_and_shrinks_the_step_instead_of_cycling():
    """A loss with a floor (the model cannot fit every residual) and a steep rise below the
    truth (20 deg), as the deposit of a thrown square through the MPM: Gauss-Newton's
    clipped step goes 45 -> 24.2 -> 10.7 (loss 14x higher) and back to 24.2, a cycle.
    "auto" rejects the overshoot, halves its step from the best iterate until the loss
    falls, never repeats a point, and ends at the minimum."""
    def loss(th):
        phi = th["friction_angle"]
        return 2e-4 * (phi - 20.0) ** 2 + 0.02 + 0.01 * jnp.maximum(20.0 - phi, 0.0) ** 1.5

    gn = inverse.make_optimizer("gauss-newton")
    ad = inverse.optimize(loss, {"friction_angle": 45.0}, gn, max_iter=30, step_tol=0.01)
    assert ad.stop_reason.startswith("cycle")
    auto = inverse.optimize(loss, {"friction_angle": 45.0}, gn, max_iter=30, step_tol=0.01,
                            gradient="auto")
    phi = auto.series("theta", "friction_angle")
    rejected = [i for i, h in enumerate(auto.history) if "rejected" in h]
    assert phi[rejected[0]] < 15.0  # the overshoot was evaluated, then refused
    radii = [auto.history[i]["rejected"]["radius_u"] for i in rejected]
    assert radii[0] == 0.5 and all(b < a for a, b in zip(radii, radii[1:]))
    assert len({round(p, 6) for p in phi}) == len(phi)  # no point evaluated twice
    # after the first rejection a point whose loss rose costs one forward run: no differences
    later = [auto.history[i] for i in rejected[1:] if auto.history[i]["loss"] >
             min(auto.series("loss")[:i])]
    assert later and all(np.isnan(h["grad_u"]["friction_angle"]) for h in later)
    assert auto.converged and abs(auto.theta["friction_angle"] - 20.0) < 0.1


def test_auto_with_no_step_tolerance_still_stops():
    """step_tol = 0 (the default): the shrinking of a rejected step cannot end on a small
    step; it ends on a cycle or at max_iter, in bounded time."""
    def loss(th):
        phi = th["friction_angle"]
        return 2e-4 * (phi - 20.0) ** 2 + 0.02 + 0.01 * jnp.maximum(20.0 - phi, 0.0) ** 1.5

    res = inverse.optimize(loss, {"friction_angle": 45.0},
                           inverse.make_optimizer("gauss-newton"), max_iter=40,
                           gradient="auto")
    assert len(res.history) <= 41 and abs(res.theta["friction_angle"] - 20.0) < 0.5


def test_a_scan_starts_the_local_method_in_the_right_basin():
    """Two minima (20 deg, the global one, and 44 deg, next to the start): from 45 deg the
    local method ends in the near one; a scan over 15-50 deg starts it in the global one's
    basin. Scan values outside the parameter's range, or of a name not fitted, are refused."""
    def loss(th):
        phi = th["friction_angle"]
        return jnp.minimum(1e-3 * (phi - 20.0) ** 2, 0.002 + 1e-2 * (phi - 44.0) ** 2)

    gn = inverse.make_optimizer("gauss-newton")
    local = inverse.optimize(loss, {"friction_angle": 45.0}, gn, max_iter=30, step_tol=0.01,
                             gradient="auto")
    assert abs(local.theta["friction_angle"] - 44.0) < 0.5
    grid = [15.0, 20.0, 25.0, 30.0, 35.0, 40.0, 45.0, 50.0]
    res = inverse.optimize(loss, {"friction_angle": 45.0}, gn, max_iter=30, step_tol=0.01,
                           gradient="auto", scan={"friction_angle": grid})
    assert [t["friction_angle"] for t, _ in res.scan] == pytest.approx(grid, abs=1e-4)
    assert res.history[0]["theta"]["friction_angle"] == pytest.approx(20.0, abs=1e-4)
    assert res.converged and abs(res.theta["friction_angle"] - 20.0) < 0.01
    with pytest.raises(ValueError, match="inside"):
        inverse.optimize(loss, {"friction_angle": 45.0}, gn, scan={"friction_angle": [95.0]})
    with pytest.raises(ValueError, match="not fitted"):
        inverse.optimize(loss, {"friction_angle": 45.0}, gn, scan={"cohesion": [1.0]})


def test_progress_line_says_a_rejected_trial_point_has_no_gradient_rather_than_nan():
    """A trial point rejected on its loss alone records nan gradients (never computed); the
    progress line names that instead of printing a NaN a user would take for a failure."""
    from diffgns.inverse.job import format_record

    rec = dict(iteration=4, theta={"friction_angle": 13.475}, loss=0.45, time_s=0.4,
               rss_mb=1293.0, grad={"friction_angle": float("nan")})
    line = format_record(rec)
    assert "nan" not in line.lower() and "not computed" in line and "phi= 13.475" in line
    rec["grad"] = {"friction_angle": 0.06128}
    assert "dloss/dphi=+6.128e-02" in format_record(rec)
    rec.update(theta={"cohesion": 2.0}, grad={"cohesion": float("nan")})
    assert "dloss/dcohesion=(not computed" in format_record(rec)


def test_summary_history_is_strict_json_with_rejected_points_as_null():
    """summary.json's history writes a rejected trial point's gradients (nan, never computed)
    as null, so a strict parser reads the file; computed gradients and the rest are kept."""
    from diffgns.inverse.job import history_for_json

    nan = float("nan")
    hist = [dict(iteration=0, theta={"friction_angle": 45.0}, loss=0.66,
                 grad={"friction_angle": 0.061}, grad_u={"friction_angle": 1.2}, aux={"a": 1.0}),
            dict(iteration=1, theta={"friction_angle": 13.5}, loss=0.45,
                 grad={"friction_angle": nan}, grad_u={"friction_angle": nan}, aux={})]
    out = history_for_json(hist)
    text = json.dumps(out, allow_nan=False)  # raises on any NaN left
    back = json.loads(text)
    assert back[1]["grad"] == {"friction_angle": None} and back[1]["grad_u"] == {
        "friction_angle": None}
    assert back[0]["grad"] == {"friction_angle": 0.061} and "aux" not in back[0]
    assert back[1]["loss"] == 0.45 and math.isnan(hist[1]["grad"]["friction_angle"])


def test_starts_refine_the_lowest_scan_points_and_keep_the_lowest_end():
    """A narrow global basin (32 deg, loss 0) between grid points and a broad local one (26
    deg, loss 0.02): the lowest grid point (25) leads to 26; the second (30) to 32. With
    ``starts=2`` both are refined with the programs compiled once, the run ending lower is
    returned and both are summarised; starts > 1 without a scan is refused."""
    traces = []

    def loss(th):
        traces.append(1)
        phi = th["friction_angle"]
        broad = 0.02 + 1e-4 * (phi - 26.0) ** 2
        narrow = 0.025 * (1.0 - jnp.exp(-(((phi - 32.0) / 1.5) ** 2)))
        return jnp.minimum(broad, narrow)

    gn = inverse.make_optimizer("gauss-newton")
    grid = [15.0, 20.0, 25.0, 30.0, 35.0, 40.0, 45.0, 50.0]
    kw = dict(max_iter=30, step_tol=0.01, gradient="auto", scan={"friction_angle": grid})
    one = inverse.optimize(loss, {"friction_angle": 45.0}, gn, **kw)
    assert abs(one.theta["friction_angle"] - 26.0) < 0.1 and one.starts[0]["loss"] > 0.019
    traces.clear()
    two = inverse.optimize(loss, {"friction_angle": 45.0}, gn, starts=2, **kw)
    assert len(traces) == 2  # one forward and one gradient program for both starts
    assert [s["start"]["friction_angle"] for s in two.starts] == pytest.approx([25.0, 30.0],
                                                                             abs=1e-4)
    assert abs(two.starts[0]["theta"]["friction_angle"] - 26.0) < 0.1
    assert abs(two.theta["friction_angle"] - 32.0) < 0.05 and two.starts[1]["loss"] < 1e-4
    assert two.history[0]["start"] == 1 and two.history[0]["theta"]["friction_angle"] == \
        pytest.approx(30.0, abs=1e-4)
    assert "start 1 of 2" in two.stop_reason
    with pytest.raises(ValueError, match="only with a scan"):
        inverse.optimize(loss, {"friction_angle": 45.0}, gn, starts=2)
    with pytest.raises(ValueError, match="starts must be"):
        inverse.optimize(loss, {"friction_angle": 45.0}, gn, starts=0, **kw)


def test_check_mappings_warns_near_the_kernel_limit_and_reads_this_process():
    """The warning names the remedy when a process holds more than the fraction of
    vm.max_map_count; below it, or where the limit is unknown, nothing. The live reading
    counts this process's mappings (a Python process with JAX holds hundreds)."""
    import warnings

    from diffgns.memory import check_mappings, mappings

    with pytest.warns(ResourceWarning, match="jax.clear_caches"):
        assert check_mappings(counts=(50_000, 65_530))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert not check_mappings(counts=(49_000, 65_530))
        assert not check_mappings(counts=(10, 0))
        n, limit = mappings()
        assert 100 < n < limit
        assert not check_mappings()
