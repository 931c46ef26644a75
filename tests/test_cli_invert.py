"""``diffgns invert`` end to end on a scene that is not a column collapse (small, float64)."""
import dataclasses
import json
from pathlib import Path

import pytest

from diffgns.cli import build_parser, main
from diffgns.cli import invert as cli_invert
from diffgns.inverse import job

ROOT = Path(__file__).resolve().parents[1]

# A 0.1 m sand square launched at 1 m/s along a frictional floor into a low box: 64
# particles, 16 x 8 cells, 40 frames of 5 ms (its front moves ~2 mm per degree of phi).
TINY = """
[scene]
domain = [[0.0, 0.4], [0.0, 0.2]]
dx = 0.025
frame_dt = 5e-3
[walls]
bottom = {kind = "friction", mu = 0.5}
[[bodies]]
name = "mass"
shape = {type = "rectangle", x0 = 0.05, y0 = 0.0, x1 = 0.15, y1 = 0.1}
material = {type = "sand", friction_angle = 30.0}
velocity = [1.0, 0.0]
[[obstacles]]
x0 = 0.25
y0 = 0.0
x1 = 0.3
y1 = 0.025
surface = {kind = "friction", mu = 0.5}
"""


@pytest.mark.slow  # ~2 min; the GNS and column inversions stay in the default suite
def test_invert_recovers_the_friction_angle_of_a_sliding_mass_with_the_mpm(
        tmp_path, x64, capsys):
    scene = tmp_path / "slide.toml"
    scene.write_text(TINY)
    obs = tmp_path / "obs"
    assert main(["simulate", "--scene", str(scene), "--frames", "40", "--dtype", "float64",
                 "--vtk-every", "40", "--out", str(obs)]) == 0
    out = tmp_path / "inv"
    rc = main(["invert", str(scene), "--fit", "friction_angle=40:0:90", "--observation",
               str(obs / "trajectory.h5"), "--simulator", "mpm", "--dtype", "float64",
               "--step-tol", "0.001", "--max-iter", "10", "--truth", "friction_angle=30",
               "--out", str(out)])
    assert rc == 0
    lines = capsys.readouterr().out.strip().splitlines()
    iters = [ln for ln in lines if ln.startswith("iter ")]
    assert iters[0].startswith("iter  0  phi= 40.000 deg") and len(iters) >= 3
    assert lines[-1].startswith("recovered friction angle: ")
    s = json.loads((out / "summary.json").read_text())
    assert s["recovered"]["friction_angle"] == pytest.approx(30.0, abs=0.02)
    assert s["error_deg"] == pytest.approx(s["recovered"]["friction_angle"] - 30.0)
    assert s["converged"] and s["particles"] == 64 and s["frames"] == 41
    assert s["history"][0]["loss"] > 1e3 * s["history"][-1]["loss"]
    assert (out / "convergence.png").exists() and (out / "deposits.png").exists()
    # the same from the measured runout alone (the farthest particle, as `simulate` reports)
    runout = json.loads((obs / "summary.json").read_text())["final_runout_m"]
    rc = main(["invert", str(scene), "--fit", "friction_angle=40:0:90", "--observed-runout",
               str(runout), "--frames", "40", "--dtype", "float64", "--step-tol", "0.001",
               "--out", str(tmp_path / "inv_runout")])
    s = json.loads((tmp_path / "inv_runout" / "summary.json").read_text())
    assert rc == 0 and s["objective"] == "runout-max" and s["target"] is None
    assert s["recovered"]["friction_angle"] == pytest.approx(30.0, abs=0.02)
    # refined from the best two of a scan (forward runs at 20, 35, 50 deg)
    rc = main(["invert", str(scene), "--fit", "friction_angle=40:0:90", "--observed-runout",
               str(runout), "--frames", "40", "--dtype", "float64", "--step-tol", "0.001",
               "--scan", "friction_angle=20:50:3", "--starts", "2",
               "--out", str(tmp_path / "inv_scan")])
    s = json.loads((tmp_path / "inv_scan" / "summary.json").read_text())
    assert rc == 0 and [p["theta"]["friction_angle"] for p in s["scan"]] == \
        pytest.approx([20.0, 35.0, 50.0])
    best = min(s["scan"], key=lambda p: p["loss"])["theta"]["friction_angle"]
    assert s["history"][0]["theta"]["friction_angle"] == pytest.approx(best)
    assert s["recovered"]["friction_angle"] == pytest.approx(30.0, abs=0.02)
    ranked = sorted(s["scan"], key=lambda p: p["loss"])[:2]
    assert [r["start"] for r in s["starts"]] == [p["theta"] for p in ranked]
    assert all(r["theta"]["friction_angle"] == pytest.approx(30.0, abs=0.02)
               for r in s["starts"])


def test_invert_with_a_gns_refuses_a_scene_its_model_does_not_support(tmp_path, capsys):
    scene = tmp_path / "slide.toml"
    scene.write_text(TINY)
    rc = main(["invert", str(scene), "--fit", "friction_angle=40:0:90", "--observed-runout",
               "0.3", "--frames", "40", "--simulator", "gns", "--model", "gns_columns",
               "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "gns_columns cannot simulate this scene" in err
    assert "box [0, 0.4] x [0, 0.2] m is not the training box [0, 0.8] x [0, 0.35] m" in err
    assert "dx = 0.025 m is not the 0.0125 m" in err and "frame_dt = 0.005 s" in err
    assert not (tmp_path / "o").exists()


def test_invert_argument_errors_name_the_fix(tmp_path, capsys):
    scene = tmp_path / "slide.toml"
    scene.write_text(TINY)
    base = ["invert", str(scene), "--observed-runout", "0.3", "--out", str(tmp_path / "o")]
    assert main(base + ["--fit", "friction_angle=40:0:90"]) == 2
    assert "--observed-runout needs --frames" in capsys.readouterr().err
    assert main(base + ["--fit", "friction_angle=95:0:90", "--frames", "4"]) == 2
    assert "must lie strictly inside (0, 90)" in capsys.readouterr().err
    assert main(base + ["--fit", "friction_angle=40:0:90", "--frames", "4", "--scan",
                        "friction_angle=20:50"]) == 2
    assert "--scan 'friction_angle=20:50': use name=lo:hi:n" in capsys.readouterr().err
    assert main(base + ["--fit", "friction_angle=40:0:90", "--frames", "4", "--starts",
                        "2"]) == 2
    assert "> 1 only with a scan" in capsys.readouterr().err
    assert main(base + ["--fit", "obstacle_mu[3]=0.3:0:1", "--frames", "4"]) == 2
    assert "no obstacle '3'" in capsys.readouterr().err
    assert main(base + ["--fit", "E=1e6:1e5:1e7", "--frames", "4", "--simulator", "gns",
                        "--coarse-grain", "2"]) == 2
    assert "--coarse-grain and --frame-stride are for the MPM alone" in capsys.readouterr().err
    # the hybrid's schedule options with another simulator: refused, not ignored
    fit = ["--fit", "friction_angle=40:0:90", "--frames", "4"]
    assert main(base + fit + ["--warmup-settle", "0.05"]) == 2
    assert ("--warmup-settle set the hybrid's schedule; use them with --simulator hybrid"
            in capsys.readouterr().err)
    assert main(base + fit + ["--simulator", "gns", "--mpm-frames", "4", "--particle-map",
                              "rigid"]) == 2
    assert "--mpm-frames, --particle-map set the hybrid's" in capsys.readouterr().err


def test_parser_lists_every_command_and_the_invert_choices_match_the_library():
    p = build_parser(["--help"])
    cmds = set(p._subparsers._group_actions[0].choices)
    assert cmds == {"simulate", "dataset", "train", "average", "rollout", "hybrid", "invert",
                    "symbolic"}
    assert cli_invert.SIMULATORS == job.SIMULATORS and cli_invert.OBJECTIVES == job.OBJECTIVES


def test_shipped_obstacle_scene_is_supported_by_the_shipped_8_cell_models():
    from diffgns.graph.support import UnsupportedSceneError, check_scene
    from diffgns.inverse.simulators import load_gns
    from diffgns.scene.files import load_scene

    scene = load_scene(ROOT / "scenes/sand_into_obstacle.toml")
    assert scene.obstacles and scene.bodies[0].velocity == (1.0, 0.0)
    for name in ("gns_columns", "gns_small"):
        assert check_scene(scene, load_gns(name)[2]).factor == 4
    with pytest.raises(UnsupportedSceneError, match="0.00625 m the model emulates"):
        check_scene(scene, load_gns("gns_cg16")[2])


def test_default_model_is_the_most_accurate_shipped_model_that_supports_the_scene():
    """gns_cg16_pfn (held-out runout error 1.4% mean, 4.4% max: the best card) for its own
    16-cell columns; the shipped 8-cell obstacle scene falls back to gns_columns, the best
    8-cell model; the main example and ``diffgns invert`` both use this choice."""
    from diffgns.hybrid.compare import column_scene
    from diffgns.inverse.simulators import (
        DEFAULT_MODEL,
        MODELS_BY_ACCURACY,
        default_model,
        model_info,
    )
    from diffgns.scene.families import random_scene
    from diffgns.scene.files import load_scene

    assert DEFAULT_MODEL == MODELS_BY_ACCURACY[0] == "gns_cg16_pfn"
    info = model_info(DEFAULT_MODEL)
    assert default_model(column_scene(2.0, 30.0, 16, info)) == "gns_cg16_pfn"
    assert default_model(load_scene(ROOT / "scenes/sand_into_obstacle.toml")) == "gns_columns"
    # at the 16-cell resolution, what gns_cg16_pfn only warns about goes to gns_general
    obstacle = dataclasses.replace(load_scene(ROOT / "scenes/sand_into_obstacle.toml"),
                                   dx=0.1 / 16)
    assert default_model(obstacle) == "gns_general"
    left, right = (random_scene("columns", s, boxes=((0.8, 0.35),)) for s in (0, 1))
    assert left.bodies[0].shape.lower[0] == 0 and right.bodies[0].shape.upper[0] == 0.8
    assert (default_model(left), default_model(right)) == ("gns_cg16_pfn", "gns_general")
    ex = (ROOT / "examples/column_collapse_inverse.py").read_text()
    assert "default=str(DEFAULT_MODEL)" in ex and "default ``gns_cg16_pfn``" in ex


def test_invert_through_the_hybrid_takes_the_hybrid_commands_schedule(monkeypatch, capsys):
    """Without schedule options ``diffgns invert --simulator hybrid`` runs
    ``DEFAULT_SCHEDULE``, the default of ``diffgns hybrid``; the options change it the same
    way. The simulator is stubbed: this checks the plumbing."""
    from diffgns.hybrid.simulator import DEFAULT_SCHEDULE

    seen = []

    def fake(kind, obs, model, **kw):
        seen.append((kind, kw["schedule"]))
        raise ValueError("stop; stubbed")

    monkeypatch.setattr(job, "make_simulator", fake)
    base = ["invert", str(ROOT / "scenes/sand_into_obstacle.toml"), "--fit",
            "friction_angle=40:0:90", "--observed-runout", "0.3", "--frames", "4",
            "--simulator", "hybrid"]
    assert main(base) == 2 and main(base + ["--warmup-settle", "0.05", "--mpm-frames",
                                            "3"]) == 2
    assert seen[0] == ("hybrid", DEFAULT_SCHEDULE)
    assert seen[1][1] == dataclasses.replace(DEFAULT_SCHEDULE, warmup_settle=0.05,
                                             mpm_frames=3)
    assert f"hybrid schedule: {DEFAULT_SCHEDULE.label}" in capsys.readouterr().out
