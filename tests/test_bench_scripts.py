"""Pure helpers of the protocol-wrapped benchmark scripts (issue 22): schedule names of
``hybrid_pareto.py``, its per-round aggregation, and the CFD settings
``meshnet_accuracy_speed.py`` re-times. Nothing here times anything."""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import granular_front as gf  # noqa: E402
import granular_heldout as gh  # noqa: E402
import granular_impact_probe as gip  # noqa: E402
import granular_node_tracers as gnt  # noqa: E402
import granular_restart_probe as grp  # noqa: E402
import granular_truth_spread as gts  # noqa: E402
import hybrid_families as hf  # noqa: E402
import hybrid_pareto as hp  # noqa: E402
import inverse_sweep as isw  # noqa: E402
import meshnet_accuracy_speed as mas  # noqa: E402
import meshnet_runaway as mr  # noqa: E402

from diffgns.graph.evaluate import per_family  # noqa: E402
from diffgns.hybrid.simulator import Schedule  # noqa: E402
from diffgns.timing import Interleaved, Sample  # noqa: E402


def test_schedule_names_give_the_schedules_of_the_published_table():
    """FULL names exactly the schedules the 2026-12-01 table ran for its first model."""
    before = [Schedule(gns_frames=1, mpm_frames=0)]
    before += [Schedule(gns_frames=m, mpm_frames=k) for k, m in
               ((1, 10), (2, 10), (2, 5), (4, 4), (4, 2), (8, 2))]
    before += [Schedule(gns_frames=20, mpm_frames=2, adaptive_tol=t) for t in (0.02, 0.005)]
    before += [Schedule(gns_frames=4, mpm_frames=4, handoff=h) for h in ("reset", "reconstruct")]
    before += [Schedule(gns_frames=1, mpm_frames=0, particle_map="rigid"),
               Schedule(gns_frames=4, mpm_frames=4, particle_map="rigid")]
    assert [hp.parse_schedule(x) for x in hp.FULL] == before
    assert hp.parse_schedule("K8M2").label == "hybrid K=8 M=2 (carry)"
    assert hp.parse_schedule("GNS:rigid").label == "GNS rigid"
    # a warm-up other than the default is part of the name: tables key their rows by it
    assert hp.parse_schedule("GNS:W100").label == "GNS after 100 MPM frames"
    assert hp.parse_schedule("K8M2:W40").label == "hybrid K=8 M=2 (carry) after 40 MPM frames"
    assert len({hp.parse_schedule(n).label for n in ("GNS", "GNS:W100", "GNS:W150")}) == 3


@pytest.mark.parametrize("name", ["GNS", "K2M5", "K4M4:reset", "K2A0.02", "K4M4:rigid",
                                  "GNS:rigid", "K4M4:reconstruct:rigid", "GNS:W100",
                                  "K8M2:rigid:W40"])
def test_a_schedule_name_reads_back_as_the_same_schedule(name):
    assert hp.schedule_name(hp.parse_schedule(name)) == name


def test_a_warmup_option_sets_the_mpm_frames_before_the_first_gns_frame():
    from diffgns.hybrid.simulator import Schedule

    s = hp.parse_schedule("GNS:W100")
    assert (s.warmup, s.mpm_frames) == (100, 0)
    assert hp.parse_schedule("K8M2").warmup == Schedule().warmup  # no option: the default
    with pytest.raises(argparse.ArgumentTypeError, match="unknown option 'W'"):
        hp.parse_schedule("GNS:W")


def test_hybrid_families_lists_exactly_the_cases_where_the_hybrid_is_worse():
    pos = hf.POS
    rows = [dict(case=c, family=f, schedule=s, **{pos: e}) for c, f, s, e in (
        (0, "squares", "GNS", 0.20), (0, "squares", "K2M5", 0.10),
        (1, "columns", "GNS", 0.10), (1, "columns", "K2M5", 0.12),
        (2, "obstacles", "GNS", 0.30), (2, "obstacles", "K2M5", 0.30))]
    worse = hf.worse_than_gns(rows, "K2M5")
    assert worse == [dict(case=1, family="columns", error=0.12, gns_error=0.10)]
    assert hf.worse_than_gns(rows, "K2M5", tol=0.05) == []
    # the printed table counts the cases within issue 21's per-case bar
    for r in rows:
        r.update(flow_runout_rel_error=0.01, clamped_positions=0)
    tables = {n: per_family([r for r in rows if r["schedule"] == n],
                            [r["family"] for r in rows if r["schedule"] == n])
              for n in ("GNS", "K2M5")}
    printed = []
    hf.print_tables(type("Run", (), {"print": lambda self, s: printed.append(s)})(),
                    tables, {"K2M5": worse}, rows)
    assert tables["K2M5"]["all"]["cases_met"] == 0 and printed[-1].startswith("K2M5: worse")
    assert any(line.startswith("K2M5") and line.rstrip().endswith("0/3") for line in printed)


def test_hybrid_result_splits_clamps_by_the_simulator_that_made_the_frame():
    import numpy as np

    from diffgns.hybrid.simulator import HybridResult

    # frames 0..4; frame t is made by step t - 1 of mode[t - 1] (0 GNS, 1 MPM)
    res = HybridResult(positions=None, nodes=None, mode=np.array([1, 0, 0, 1]),
                       indicator=None, final_state=None, frame_dt=0.0025,
                       clamped=np.array([0, 5, 2, 1, 7]),
                       clamp_shift=np.array([0.0, 1e-8, 2e-3, 5e-4, 3e-8]),
                       f_kept=np.zeros(5, np.int32))
    split = dict(clamped_positions_mpm_frames=12, max_clamp_shift_mpm_frames_m=3e-8,
                 clamped_positions_gns_frames=3, max_clamp_shift_gns_frames_m=2e-3)
    assert res.clamps_by_mode() == split
    summary = res.clamp_summary()  # what hybrid_families and run_hybrid record
    assert {k: summary[k] for k in split} == split and summary["clamped_positions"] == 15


@pytest.mark.parametrize("bad", ["K4", "M4K4", "K4M4:fast", "hybrid"])
def test_bad_schedule_names_are_refused(bad):
    with pytest.raises(argparse.ArgumentTypeError):
        hp.parse_schedule(bad)


def test_case_names():
    c = hp.parse_case("1.75:27.5")
    assert (c.a, c.phi, c.family) == (1.75, 27.5, "")
    f = hp.parse_case("obstacles:9100001")
    assert (f.family, f.seed) == ("obstacles", 9100001)
    for bad in ("1.75", "squares:x", "squares:-1", "sqaures:3"):
        with pytest.raises(argparse.ArgumentTypeError):
            hp.parse_case(bad)


def test_family_case_is_one_scene_at_every_resolution():
    """A family case keeps its box, bodies and obstacles when the MPM is refined (the front's
    references and coarser MPMs simulate the same scene); only dx and the particles change."""
    from diffgns.errors import SceneError
    from diffgns.hybrid.compare import model_cells

    case = hp.parse_case("obstacles:9100001")
    scenes = {c: case.scene(c, {}) for c in (8, 16, 32)}
    base = scenes[16]
    assert base == hp.parse_case("obstacles:9100001").scene(16, {})
    for c, s in scenes.items():
        assert s.dx == pytest.approx(0.1 / c)
        assert (s.domain, s.obstacles, s.walls) == (base.domain, base.obstacles, base.walls)
        assert [b.shape for b in s.bodies] == [b.shape for b in base.bodies]
        assert s.n_particles == base.n_particles * (c / 16) ** 2
    with pytest.raises(ValueError, match="integer >= 1"):
        case.scene(0, {})
    with pytest.raises(SceneError, match="whole number"):  # 0.35 m is 24.5 cells of 1/70 m
        hp.parse_case("squares:9100000").scene(7, {})
    assert model_cells({"source": {"dx": 0.1 / 16}}) == 16
    assert model_cells({"source": {"cells_across": 12, "dx": 1.0}}) == 12
    with pytest.raises(ValueError, match="whole number"):
        model_cells({"source": {"dx": 0.03}})


def _row(name, label, family, a, err, own_cells=None):
    r = dict(name=name, label=label, family=family, case=[a, 30.0], compile_s=1.0,
             runout_error=err, mean_position_error_m=err, final_position_error_m=err,
             own_mpm_position_error_m=err, own_mpm_runout_error=err, mpm_fraction=1.0)
    if own_cells:
        r["own_cells"] = own_cells
    return r


def test_aggregate_sums_cases_per_round_and_takes_median_ratios():
    """Time = median over rounds of the per-round sums over the cases; the speed-up over
    the own-resolution MPM is the median of per-round ratios of those sums."""
    rows = [_row("m1", "MPM 16 cells", "MPM", 1, 0.0), _row("m2", "MPM 16 cells", "MPM", 2, 0.0),
            _row("g1", "GNS [x]", "GNS", 1, 2e-3, 16), _row("g2", "GNS [x]", "GNS", 2, 2e-3, 16)]
    walls = [{"m1": 4, "m2": 6, "g1": 1, "g2": 1},   # MPM 10, GNS 2: 5x
             {"m1": 5, "m2": 7, "g1": 2, "g2": 2},   # MPM 12, GNS 4: 3x
             {"m1": 4, "m2": 4, "g1": 1, "g2": 1}]   # MPM 8, GNS 2: 4x
    rounds = Interleaved(names=list(walls[0]),
                         rounds=[{k: Sample(v, v / 2) for k, v in w.items()} for w in walls])
    table = {r["label"]: r for r in hp.aggregate(rows, rounds)}
    assert table["MPM 16 cells"]["seconds"] == 10
    assert table["GNS [x]"]["seconds"] == 2 and table["GNS [x]"]["cpu_seconds"] == 1
    assert table["GNS [x]"]["speedup_vs_own_mpm"] == 4.0
    assert table["GNS [x]"]["seconds_per_round"] == [2, 4, 2]
    assert "speedup_vs_own_mpm" not in table["MPM 16 cells"]


def test_meshnet_cfd_settings_from_either_kind_of_dataset(tmp_path):
    run = {"n_frames": 201, "frame_dt": 0.02, "spinup": 20.0, "cfl": 0.075}
    for name, meta in (("sweep", {"sweep": {"run": run}}), ("plain", {"run": run})):
        (tmp_path / f"{name}.metadata.json").write_text(json.dumps(meta))
        got = mas.dataset_run(tmp_path / f"{name}.h5")
        assert (got.frame_dt, got.cfl, got.n_frames) == (0.02, 0.075, 201)
    (tmp_path / "none.metadata.json").write_text(json.dumps({"kind": "cylinder"}))
    with pytest.raises(SystemExit, match="no CFD settings"):
        mas.dataset_run(tmp_path / "none.h5")


def test_node_spread_is_zero_spread_growth_under_a_rigid_move_and_exact_for_a_split():
    import numpy as np

    from diffgns.graph.data import coarse_grain_map

    g = (np.arange(8) + 0.5) * 0.003
    x0 = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)  # 64 particles
    rms0, _ = gts.node_spread(np.stack([x0, x0]), 16)
    moved = np.stack([x0, x0 + np.array([0.1, -0.02])])
    assert gts.node_spread(moved, 16)[0] == pytest.approx(rms0, rel=1e-9)
    # split every cluster: its first half of particles 2 m to the right of the rest
    cid = coarse_grain_map(x0, 16)
    split = x0.copy()
    for c in range(cid.max() + 1):
        members = np.flatnonzero(cid == c)
        split[members[: len(members) // 2], 0] += 2.0
    rms, p99 = gts.node_spread(np.stack([x0, split]), 16)
    # every particle 1 m from its cluster mean, up to its in-cluster offset (mm)
    assert rms == pytest.approx(1.0, abs=2 * rms0) and p99 == pytest.approx(1.0, abs=0.01)


def test_truth_spread_dt_perturbation_is_a_shorter_substep_not_another_scene():
    from diffgns.mpm import MPM
    from diffgns.scene.families import random_scene

    scene = random_scene("columns", 3)
    base, _ = MPM(scene).run(MPM(scene).params(), MPM(scene).init(), 2)
    other = gts.perturbed_run(scene, "dt", 2)
    import numpy as np

    d = np.abs(np.asarray(other.positions) - np.asarray(base.positions)).max()
    assert 0 < d < 1e-4  # the same flow, not bit-identical: the substep did change


def test_truth_spread_jitter_moves_particles_within_their_nodes_only():
    """The jitter perturbation: another arrangement of the particles within every node, the
    same nodes (positions and velocities) at frame 0, and the run scored with the unperturbed
    run's clusters (binning the jittered frame 0 would assign other clusters)."""
    import numpy as np

    from diffgns.graph.data import coarse_grain, coarse_grain_map
    from diffgns.mpm import MPM
    from diffgns.scene.families import random_scene

    scene = random_scene("squares", 3)
    sim = MPM(scene)
    base, _ = sim.run(sim.params(), sim.init(), 2)
    cid = coarse_grain_map(np.asarray(base.positions[0]), 16)
    other = gts.perturbed_run(scene, "jitter", 2, cid=cid, jitter=0.25)
    x0, y0 = np.asarray(base.positions[0]), np.asarray(other.positions[0])
    spacing = scene.dx / 2  # 4 particles per cell in 2D
    moved = np.abs(y0 - x0).max(axis=-1)
    assert np.median(moved) > 0.05 * spacing and moved.max() <= 0.5 * spacing + 1e-7
    a, b = coarse_grain(base, 16, cid=cid), coarse_grain(other, 16, cid=cid)
    np.testing.assert_allclose(b.positions[0], a.positions[0], atol=1e-6)  # the same nodes
    np.testing.assert_allclose(b.velocities[0], a.velocities[0], atol=1e-6)
    assert np.abs(np.asarray(b.positions[-1]) - a.positions[-1]).max() > 0  # another run
    # the given clusters are the ones coarse_grain would bin from the unperturbed frame 0
    np.testing.assert_array_equal(coarse_grain(base, 16).positions, a.positions)
    with pytest.raises(ValueError, match="3 cluster indices"):
        coarse_grain(base, 16, cid=cid[:3])
    with pytest.raises(ValueError, match="needs the clusters"):
        gts.perturbed_run(scene, "jitter", 2)


def test_truth_spread_stiff_perturbation_is_ten_times_e_at_its_own_stable_dt():
    from diffgns.scene.families import random_scene

    scene = random_scene("squares", 3)
    stiff = gts.perturbed_scene(scene, "stiff")
    assert [b.material.E for b in stiff.bodies] == [10 * b.material.E for b in scene.bodies]
    assert [b.material.friction_angle for b in stiff.bodies] == [
        b.material.friction_angle for b in scene.bodies]
    # c_p grows by sqrt(10): the CFL substep shrinks by more than 2x (the speed bound adds)
    assert stiff.substeps > 2 * scene.substeps and stiff.frame_dt == scene.frame_dt
    assert gts.perturbed_scene(scene, "phi") is scene
    # stiff_dt: stiff's substep at the scene's own sand
    fine = gts.perturbed_scene(scene, "stiff_dt")
    assert fine.substeps == stiff.substeps and fine.substep_dt == stiff.substep_dt
    assert [b.material for b in fine.bodies] == [b.material for b in scene.bodies]
    # dt: a fraction of the stable substep (default 0.8)
    for f in (0.8, 0.1):
        short = gts.perturbed_scene(scene, "dt", f)
        assert short.substep_dt <= f * scene.substep_dt * (1 + 1e-12)
        assert short.substeps <= math.ceil(scene.substeps / f) + 1


def test_heldout_timing_refuses_a_scene_that_does_not_redraw_the_stored_one():
    with pytest.raises(SystemExit, match="redraws .* particles, the data has 7"):
        gh.speed_of_case(None, None, None, ("columns", 3, 7, {}), 1)


def test_heldout_selects_cases_by_family_after_n_and_refuses_unknown_families():
    fams = ["squares", "columns", "obstacles", "collision"] * 2
    assert gh.select_cases(fams, None, None) == list(range(8))
    assert gh.select_cases(fams, 6, None) == list(range(6))
    assert gh.select_cases(fams, None, ["columns", "collision"]) == [1, 3, 5, 7]
    assert gh.select_cases(fams, 4, ["columns"]) == [1]
    with pytest.raises(SystemExit, match="not in the dataset"):
        gh.select_cases(fams, None, ["column"])
    with pytest.raises(SystemExit, match="no case among the first 1"):
        gh.select_cases(fams, 1, ["collision"])


def test_meshnet_drift_windows_and_the_worst_mean_flow_node(tmp_path):
    """The drift of a rollout equal to the data but for one fluid node pushed 0.3 m/s in its
    last window: that node is the worst, by 0.3 m/s, with both mean velocities; the windows tile
    the rollout. (The forces are not checked here: this synthetic mesh has no cylinder; the
    force integral is tested with the CFD.)"""
    import numpy as np

    from diffgns.mesh.train import load_cylinder
    from test_meshnet import _synthetic_dataset

    _synthetic_dataset(tmp_path / "d.h5", n_traj=1, frames=21)
    traj = load_cylinder(tmp_path / "d.h5")[0]
    vel = traj["velocity"].copy()
    vel[-5:, 5] += np.array([0.3, 0.0], np.float32)
    d = mr.drift(traj, vel, traj["pressure"][1:], window=5)
    assert d["window_start"] == [0, 5, 10, 15] and len(d["lift_pp"]) == 4
    assert d["worst_mean_node_m"] == traj["mesh_pos"][5].tolist()
    assert d["worst_mean_error_m_s"] == pytest.approx(0.3, rel=1e-5)
    cfd_mean = traj["velocity"][-5:, 5].mean(0)
    assert d["worst_mean_velocity_cfd"] == pytest.approx(cfd_mean.tolist(), rel=1e-6)
    assert d["worst_mean_velocity_model"] == pytest.approx((cfd_mean + [0.3, 0]).tolist(),
                                                          rel=1e-5)


def test_tracers_follow_the_local_motion_not_a_far_mean():
    """A tracer moves with the particles around it: exactly with a uniform translation, and
    in two blocks sliding apart each tracer follows its own block (a mean over all the
    particles would not move at all)."""
    rng = np.random.default_rng(0)
    g = np.stack(np.meshgrid(np.arange(10), np.arange(10)), -1).reshape(-1, 2) * 0.005
    left, right = g, g + [0.2, 0.0]
    x0 = np.concatenate([left, right])
    T, v = 20, np.array([0.003, -0.001])
    shift = np.arange(T)[:, None, None] * v
    x = x0[None] + shift
    start = x0[rng.choice(len(x0), 7, replace=False)]
    np.testing.assert_allclose(gnt.tracers(x, start, 0.005, 24), start[None] + shift,
                               atol=1e-12)
    sign = np.where(np.arange(len(x0)) < len(left), -1.0, 1.0)[None, :, None]
    x = x0[None] + sign * shift  # the blocks move apart; their joint mean stays put
    start = np.array([left.mean(0), right.mean(0)])
    tr = gnt.tracers(x, start, 0.005, 24)
    np.testing.assert_allclose(tr[-1], start + [-(T - 1) * v, (T - 1) * v], atol=1e-9)


def test_restart_probe_gives_the_model_the_truths_history_up_to_the_restart_frame():
    from diffgns.trajectory import Trajectory

    T, N, C = 12, 3, 5
    x = np.arange(T * N * 2, dtype=float).reshape(T, N, 2)
    ref = Trajectory(positions=x, velocities=-x, particle_type=np.zeros(N, int),
                     material=np.zeros(N), frame_dt=0.0025, bounds=((0.0, 1.0), (0.0, 1.0)))
    assert grp.restarted(ref, C, C).positions.shape == x.shape  # the usual start
    r = grp.restarted(ref, 8, C)
    np.testing.assert_array_equal(r.positions[: C + 1], x[8 - C: 9])  # frames k-C .. k
    np.testing.assert_array_equal(r.positions[-1], x[-1])  # the same last frame
    np.testing.assert_array_equal(r.velocities, -x[8 - C:])
    for k in (C - 1, T - 1):
        with pytest.raises(ValueError, match=f"restart frame {k}"):
            grp.restarted(ref, k, C)


def test_impact_probe_scores_only_the_impact_frames_and_the_share_along_the_truth():
    """Frames whose RMS reference acceleration exceeds the threshold are the impacts: a
    prediction at half the truth there captures 0.5 with relative RMS 0.5, whatever the
    other frames do; an error in a quiet frame moves only the other frames' RMS."""
    g = 1e-4  # m/frame^2
    rng = np.random.default_rng(0)
    ref = np.zeros((6, 5, 2))
    ref[:, :, 1] = -g  # free fall: 1 g, below any threshold
    ref[2] = rng.normal(0, 20 * g, (5, 2))  # an impact frame (~28 g RMS)
    ref[3] = rng.normal(0, 10 * g, (5, 2))
    pred = ref.copy()
    pred[2:4] *= 0.5
    pred[0, 0, 0] += 3 * g  # a quiet-frame error: RMS over that frame's 5 nodes and 4 frames
    out = gip.impact_summary(pred, ref, g, threshold_g=5.0)
    assert out["impact_frames"] == 2
    assert out["captured"] == pytest.approx(0.5)
    assert out["impact_rel_rms"] == pytest.approx(0.5)
    assert out["other_rms_g"] == pytest.approx(3.0 / np.sqrt(4 * 5))
    exact = gip.impact_summary(ref, ref, g, threshold_g=5.0)
    assert exact["captured"] == pytest.approx(1.0) and exact["impact_rel_rms"] == 0.0
    none = gip.impact_summary(ref[:2], ref[:2], g, threshold_g=5.0)
    assert none["impact_frames"] == 0 and none["captured"] is None
    means = gip.family_means([out, none])
    assert means["cases_with_impacts"] == 1 and means["captured_mean"] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="must both be"):
        gip.impact_summary(pred[:, :4], ref, g, threshold_g=5.0)


def _front_records(tmp_path, valid=True, timed_data="data/granular_valid.h5"):
    """An accuracy record of 3 cases and a timed record of 3 cases (2 threads and pinned)."""
    err = gf.ERROR
    acc_rows = [{err: e, "flow_runout_rel_error": r, "inside_domain": True, "finite": True}
                for e, r in ((0.1, 0.1), (0.2, 0.3), (0.6, 0.2))]
    acc = dict(model="m", data="data/granular_valid.h5", rows=acc_rows,
               table=per_family(acc_rows, ["squares", "columns", "squares"]))
    timed_rows = [{err: 0.0, "speedup_vs_mpm_stable": s} for s in (2.0, 9.0, 4.0)]
    timed = dict(model="m", data=timed_data, valid=valid, rows=timed_rows,
                 protocol=dict(date_utc="2026-12-07T00:00:00+00:00",
                               load_before_1_5_15=[0.5 if valid else 3.0, 1, 1]),
                 one_thread_pinned=dict(rows=[{"speedup_vs_mpm_stable": s} for s in (1, 3, 8)]))
    a, t = tmp_path / "acc.json", tmp_path / "timed.json"
    a.write_text(json.dumps(acc))
    t.write_text(json.dumps(timed))
    return str(a), str(t)


def test_front_point_is_the_mean_error_of_all_cases_and_the_median_timed_speedup(tmp_path):
    p = gf.point("m", *_front_records(tmp_path))
    assert p["mean_error"] == pytest.approx(0.3) and p["max_error"] == pytest.approx(0.6)
    assert p["mean_runout_error"] == pytest.approx(0.2)  # all cases, not one family
    assert (p["speedup_median"], p["speedup_min"], p["speedup_max"]) == (4.0, 2.0, 9.0)
    assert p["speedup_median_pinned"] == 3.0 and (p["cases"], p["timed_cases"]) == (3, 3)


def test_front_refuses_a_loaded_timing_and_a_pair_on_different_data(tmp_path):
    with pytest.raises(SystemExit, match="not protocol-valid"):
        gf.point("m", *_front_records(tmp_path, valid=False))
    with pytest.raises(SystemExit, match="different data"):
        gf.point("m", *_front_records(tmp_path, timed_data="data/granular_test2.h5"))


def test_truth_spread_takes_a_stored_datasets_scenes_by_index(monkeypatch):
    """``--data``: the stored scenes redrawn (family, seed, case index kept); a case index
    outside the file is refused."""
    from diffgns.scene.families import random_scene

    stored = [("columns", 3, random_scene("columns", 3).n_particles, {}),
              ("squares", 5, random_scene("squares", 5).n_particles, {})]
    monkeypatch.setattr(gh, "samples", lambda path: stored)
    args = argparse.Namespace(data="x.h5", cases=[1])
    ((i, family, seed, scene),) = list(gts.scenes(args))
    assert (i, family, seed) == (1, "squares", 5)
    assert scene.n_particles == random_scene("squares", 5).n_particles
    with pytest.raises(SystemExit, match="not a trajectory of x.h5"):
        list(gts.scenes(argparse.Namespace(data="x.h5", cases=[2])))


def test_inversion_table_marks_a_recovered_angle_outside_the_training_range():
    """A row whose run warned that its recovered angle lies outside the model's training
    data gets a dagger and the table a footnote; the scene's own warnings do not count."""
    row = dict(simulator="gns", scene="squares:9000009", objective="deposit", true_phi=30.0,
               recovered_phi=2.25, error_deg=-27.75, iterations=18, seconds=100.0,
               load_1min=0.1, warnings=["an obstacle warning"],
               parameter_warnings=["the friction_angle = 2.25 deg is outside ..."])
    inside = dict(row, true_phi=20.0, recovered_phi=20.5, error_deg=0.5,
                  parameter_warnings=[])
    md = isw.markdown([row, inside], "gns_general")
    lines = md.splitlines()
    assert "| 2.25 † | -27.75 | no (±1) |" in next(ln for ln in lines if "| 30 |" in ln)
    assert "| 20.50 | +0.50 | yes (±1) |" in next(ln for ln in lines if "| 20 |" in ln)
    assert lines[-1].startswith("† outside the friction angles of the model's training data")
    assert "†" not in isw.markdown([inside], "gns_general")


def test_benchmark_default_sets_name_the_library_default_schedule():
    """The front and the family sweep run ``DEFAULT_SCHEDULE`` by default, by a name that
    reads back to it (so the benchmarks follow the default when it changes)."""
    from diffgns.hybrid.simulator import DEFAULT_SCHEDULE

    assert hp.DEFAULT_SCHEDULES == hf.DEFAULT_SCHEDULES
    assert hp.parse_schedule(hp.DEFAULT_SCHEDULES[-1]) == DEFAULT_SCHEDULE
    assert hp.DEFAULT_SCHEDULES[-1] == "K2M8:S0.05"


def test_inversion_sweep_with_every_case_done_writes_its_table(tmp_path, monkeypatch):
    """A resumed sweep whose JSON already holds every case (e.g. rows merged from sweeps
    split over the cores) runs nothing and still writes the markdown table it reports."""
    monkeypatch.setattr(isw, "RESULTS", tmp_path)
    row = dict(simulator="mpm", scene="squares:9000009", objective="deposit", true_phi=30.0,
               recovered_phi=30.01, error_deg=0.01, iterations=3, seconds=1.0,
               load_1min=0.1, warnings=[], parameter_warnings=[])
    (tmp_path / "s.json").write_text(json.dumps(dict(rows=[row])))
    isw.main(["--aspect-ratios", "--scenes", "squares:9000009", "--phis", "30",
              "--simulators", "mpm", "--objective", "deposit", "--allow-loaded",
              "--out", "s"])
    md = (tmp_path / "s.md").read_text()
    assert "| 30.01 | +0.01 | yes (±0.5) |" in md
