"""The diffgns command: simulate and dataset (small, fast)."""
import json

import h5py
import numpy as np
import pytest

from diffgns.cli import main
from diffgns.io.dataset import load_dataset, read_metadata


def test_simulate_column_writes_outputs(tmp_path):
    out = tmp_path / "sim"
    rc = main(["simulate", "--column", "--aspect-ratio", "1", "--cells-across", "5",
               "--frames", "20", "--vtk-every", "10", "--out", str(out)])
    assert rc == 0
    for f in ["animation.gif", "runout.png", "deposit.png", "trajectory.h5", "summary.json",
              "vtk/particles.pvd"]:
        assert (out / f).exists(), f
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"] == 21 and s["final_runout_m"] > 0.095  # outermost particle starts at 0.095
    # both runouts are named: the farthest particle (the plot's curve) and the deposit front
    assert set(s["runout_definitions"]) == {"final_runout_m", "deposit_front_m"}
    assert 0 < s["deposit_front_m"] <= s["final_runout_m"] + 0.02  # one 0.02 m bin at most
    assert {"clamped_positions", "clamped_frames", "first_clamped_frame",
            "max_clamp_shift_m"} <= set(s)  # clamps are reported (diffgns.clamp)


def test_run_mpm_measures_compile_apart_and_matches_one_rollout():
    """run_mpm compiles each chunk length ahead of time: compile_s is measured even for a
    run of one chunk (it used to be inferred from the first chunk and read 0 then), and the
    chunked trajectory is the one-program rollout's."""
    from diffgns import MPM
    from diffgns.io.outputs import run_mpm
    from diffgns.scene.builders import column_collapse

    scene = column_collapse(aspect_ratio=1.0, cells_across=5)
    one, t_one = run_mpm(scene, 3, chunk=50, progress=False)  # one chunk
    assert t_one["compile_s"] > 0 and t_one["run_s"] > 0
    chunked, t = run_mpm(scene, 5, chunk=2, progress=False)  # chunks of 2, 2 and 1
    assert t["compile_s"] > 0 and t["run_s"] > 0 and t["particle_substeps_per_s"] > 0
    sim = MPM(scene)
    ref, _ = sim.run(sim.params(), sim.init(), 5)
    assert chunked.positions.shape == ref.positions.shape
    np.testing.assert_allclose(np.asarray(chunked.positions), np.asarray(ref.positions),
                               rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(one.positions), np.asarray(ref.positions[:4]),
                               rtol=0, atol=1e-6)


def test_simulate_rejects_invalid_scene_file(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[scene]\ndx = 0.01\n[[bodies]]\nshape = {type='rectangle', x0=0, y0=0, "
                   "x1=0.1, y1=0.1}\nmaterial = {type='sand', friction_angle=95}\n")
    assert main(["simulate", "--scene", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "friction_angle" in capsys.readouterr().err


def test_dataset_columns_batched_and_resumable(tmp_path):
    path = tmp_path / "cols.h5"
    args = ["dataset", "--kind", "column", "--aspect-ratios", "0.5", "--friction-angles", "25",
            "40", "--frames", "12", "--cells-across", "4", "--out", str(path)]
    assert main(args) == 0
    trajs = load_dataset(path)
    assert len(trajs) == 2 and trajs[0].positions.shape[0] == 13
    # the lower friction angle runs out farther
    assert trajs[0].positions[-1, :, 0].max() >= trajs[1].positions[-1, :, 0].max()
    np.testing.assert_allclose(np.asarray(trajs[1].material), np.tan(np.deg2rad(40.0)),
                               rtol=1e-6)
    # resume: delete one trajectory, rerun: it is regenerated identically, the other kept
    with h5py.File(path, "a") as f:
        kept = f["00000/position"][...]
        del f["00001"]
    assert main(args) == 0
    again = load_dataset(path)
    np.testing.assert_array_equal(np.asarray(again[0].positions), kept)
    np.testing.assert_allclose(np.asarray(again[1].positions), np.asarray(trajs[1].positions))
    meta = read_metadata(path)
    assert meta["n_trajectories"] == 2 and meta["dt"] == 2.5e-3


def test_dataset_squares(tmp_path):
    path = tmp_path / "sq.h5"
    assert main(["dataset", "--kind", "squares", "--n", "2", "--frames", "5", "--dx", "0.05",
                 "--out", str(path)]) == 0
    assert len(load_dataset(path)) == 2


@pytest.mark.slow
def test_hybrid_command_writes_comparison(tmp_path):
    out = tmp_path / "hyb"
    rc = main(["hybrid", "--model", "gns_columns", "--aspect-ratio", "0.75", "--frames", "20",
               "--gns-frames", "4", "--mpm-frames", "2", "--warmup-settle", "none",
               "--reference-cells", "12", "--out", str(out)])
    assert rc == 0
    rows = json.loads((out / "hybrid_comparison.json").read_text())
    labels = [r["label"] for r in rows]
    assert labels == ["MPM 12 cells (reference)", "MPM 8 cells", "GNS",
                      "hybrid K=2 M=4 (carry)"]
    assert rows[0]["mean_position_error_m"] == 0.0
    assert all(r["finite"] and r["mean_position_error_m"] < 0.01 for r in rows)
    assert all(r["clamped_positions"] == 0 for r in rows[2:])  # the GNS and hybrid maps
    assert abs(rows[3]["mpm_fraction"] - 9 / 20) < 1e-9  # 5 warm-up + 2 x 2 refinement
    assert (out / "hybrid.gif").stat().st_size > 0


def test_hybrid_command_defaults_are_the_schedule_defaults_and_the_best_model(capsys):
    """``diffgns hybrid`` without schedule options runs ``DEFAULT_SCHEDULE`` (never worse
    than the GNS alone on the held-out family sets), its help states its counts,
    and without ``--model`` it takes the most accurate shipped model (as ``invert``)."""
    import re

    from diffgns.cli import build_parser
    from diffgns.cli.evaluate import hybrid_schedule
    from diffgns.hybrid.simulator import DEFAULT_SCHEDULE, Schedule

    args = build_parser().parse_args(["hybrid"])
    assert args.model is None
    assert hybrid_schedule(args) == DEFAULT_SCHEDULE
    given = build_parser().parse_args(["hybrid", "--gns-frames", "5", "--mpm-frames", "0",
                                       "--warmup", "6"])
    assert hybrid_schedule(given) == Schedule(warmup=6, warmup_settle=0.05, gns_frames=5,
                                              mpm_frames=0)
    fixed = build_parser().parse_args(["hybrid", "--warmup-settle", "none", "--warmup", "150"])
    assert hybrid_schedule(fixed) == Schedule(warmup=150, gns_frames=8, mpm_frames=2)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["hybrid", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    d = DEFAULT_SCHEDULE
    for flag, value in (("--warmup", d.warmup), ("--gns-frames", d.gns_frames),
                        ("--mpm-frames", d.mpm_frames), ("--warmup-settle", d.warmup_settle),
                        ("--handoff", d.handoff), ("--particle-map", d.particle_map)):
        assert re.search(rf"{flag} \S+ (?:(?! --).)*?\(default {value}\b", text), flag


def test_hybrid_reference_defaults_to_twice_the_model_cells(monkeypatch):
    """Without ``--reference-cells`` the reference MPM has twice the cells across of the runs
    it scores (for gns_cg16_pfn, 32 against its 16), never the model's own resolution."""
    from diffgns.cli import build_parser
    from diffgns.hybrid import compare as cmp
    from diffgns.inverse.simulators import model_info

    assert build_parser().parse_args(["hybrid"]).reference_cells is None
    seen = {}

    def fake(model, scene, reference, schedule, n_frames, repeats, labels, cells_across):
        seen.update(scene_dx=scene.dx, reference_dx=reference.dx, labels=labels)
        return {}

    monkeypatch.setattr(cmp, "compare_scene", fake)
    info = model_info("gns_cg16_pfn")
    cmp.compare((None, None, info), 1.75, 27.5, None, 10)
    assert seen["labels"] == ("MPM 32 cells (reference)", "MPM 16 cells")
    assert seen["reference_dx"] == pytest.approx(seen["scene_dx"] / 2)
    cmp.compare((None, None, info), 1.75, 27.5, None, 10, reference_cells=24)
    assert seen["labels"][0] == "MPM 24 cells (reference)"


def test_hybrid_command_prints_what_the_model_was_not_trained_on(tmp_path, monkeypatch,
                                                                   capsys):
    """``diffgns hybrid`` states the model's warnings for the scene (here a friction angle
    outside gns_columns' 20-45 deg) before its table, and none for a scene inside them. The
    runs are stubbed: this checks the reporting, not the simulators."""
    import numpy as np

    from diffgns.hybrid import compare as cmp

    def fake_mpm(scene, n_frames, stride, repeats=3):
        return np.ones((n_frames + 1, scene.n_particles, 2)), dict(seconds=1.0,
                                                                    clamped_positions=0)

    def fake_hybrid(scene, gns, network, info, schedule, n_frames, repeats=3,
                    cells_across=None):
        class R:
            positions = np.ones((n_frames + 1, scene.n_particles, 2))
        return R(), dict(seconds=0.5, clamped_positions=0, mpm_fraction=0.0, warmup_frames=1)

    monkeypatch.setattr(cmp, "run_mpm", fake_mpm)
    monkeypatch.setattr(cmp, "run_hybrid", fake_hybrid)
    for phi, warned in ((50.0, True), (30.0, False)):
        out = tmp_path / f"h{phi:g}"
        assert main(["hybrid", "--model", "gns_columns", "--friction-angle", str(phi),
                     "--frames", "2", "--reference-cells", "12", "--out", str(out)]) == 0
        text = capsys.readouterr().out
        line = ("warning: gns_columns body friction_angle[column] = 50.00 deg is outside the "
                "20.0-45.0 deg of the model's training data")
        assert (line in text) == warned
        assert text.index("simulator") > (text.index(line) if warned else 0)
