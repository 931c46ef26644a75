"""The hybrid GNS/MPM against the GNS alone on every scene of a family dataset (issue 21).

    .venv/bin/python benchmarks/hybrid_families.py --model runs/general_fs/soup4 \
        --data data/granular_valid.h5 [--schedules GNS K2M5 K4M4] [--cases 0 6 8] \
        [--out hybrid_families]

Every trajectory of ``--data`` (a dataset of ``diffgns dataset --families``: the MPM run of
a random scene, with its family and scene seed) is redrawn as its scene (``random_scene``,
checked against the stored particle count: :func:`granular_heldout.scene_of`) and run by
every schedule with :func:`diffgns.hybrid.compare.run_hybrid` - the code ``diffgns hybrid``
runs: ``warmup`` MPM frames (the GNS history), then GNS frames only (``GNS``) or K MPM
frames after every M GNS frames (``K<k>M<m>``, hybrid_pareto's names). The schedule's nodes
(the means of the same ``factor`` particles the dataset is coarse-grained to) are scored
against the dataset's own MPM run with :func:`diffgns.graph.evaluate.score`, the metric of
``granular_heldout.py``: final position error relative to the mean displacement, the runout
from the back of the mass, inside the domain, finite. This is the learned error: the MPM
the hybrid runs is the one that made the data. Every row also carries the run's position
clamps (MPM substeps, GNS nodes and the particle map: ``clamped_positions``), split by the
simulator that made the frame, and, every 25 frames, the mean node error (m) and the
centroids of the nodes and of the reference's (m): where a run parts from the MPM.

Printed and written (``benchmarks/results/<out>.json``): every case's errors per schedule,
the per-family table of each schedule (:func:`~diffgns.graph.evaluate.per_family`), and for
each hybrid schedule the cases where it is worse than the GNS alone (issue 21: never) and
the clamp count (issue 21: zero). Accuracy only (the protocol records the load and never
refuses the run); the accuracy-versus-time front is ``hybrid_pareto.py``'s.
"""
from __future__ import annotations

import argparse

import jax
import numpy as np
import protocol
from granular_heldout import samples, scene_of
from hybrid_pareto import DEFAULT_SCHEDULES, parse_schedule, schedule_name

POS = "final_position_error_rel_displacement"
TRACE_EVERY = 25  # frames between the recorded mean node errors and centroids


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", required=True, help="model folder or shipped name")
    ap.add_argument("--data", required=True, help="dataset of random family scenes (.h5)")
    ap.add_argument("--schedules", nargs="+", default=list(DEFAULT_SCHEDULES),
                    help=f"schedules, hybrid_pareto's names (default "
                         f"{' '.join(DEFAULT_SCHEDULES)}); GNS is always run")
    ap.add_argument("--cases", type=int, nargs="+", default=None,
                    help="trajectory indices of --data (default: all)")
    ap.add_argument("--out", default="hybrid_families.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    scheds = [parse_schedule(s) for s in dict.fromkeys(["GNS", *args.schedules])]
    run = protocol.start(args, "hybrid_families", timed=False)

    from diffgns.graph.data import load_trajectories
    from diffgns.graph.evaluate import per_family
    from diffgns.graph.train_loop import load_model
    from diffgns.io.families_data import read_families

    gns, params, info = load_model(args.model)
    refs, _ = load_trajectories(args.data, int(info.get("factor", 1)),
                                int(info.get("frame_stride", 1)))
    families = list(read_families(args.data).values())
    cases = args.cases if args.cases is not None else list(range(len(refs)))
    bad = [c for c in cases if not 0 <= c < len(refs)]
    if bad:
        raise SystemExit(f"--cases {bad}: {args.data} has trajectories 0-{len(refs) - 1}")
    every = samples(args.data)
    rows = []
    for c in cases:
        # every scene has its own particle count, so its own compiled programs: free the last
        # scene's, or XLA's JIT mappings exhaust vm.max_map_count (65,530 by default) after
        # ~20 scenes of 4 schedules ("LLVM ERROR: Unable to allocate section memory")
        jax.clear_caches()
        scene = scene_of(every[c])
        for sched in scheds:
            row = dict(case=c, family=families[c], schedule=schedule_name(sched),
                       **run_case(scene, gns, params, info, sched, refs[c]))
            rows.append(row)
            run.print(f"case {c:>2} {families[c]:<10} {row['schedule']:<6} position error "
                      f"{row[POS]:.3f}, runout {row['flow_runout_rel_error']:.3f}, MPM "
                      f"{100 * row['mpm_fraction']:.0f}% of frames (warm-up "
                      f"{row['warmup_frames']}), clamped "
                      f"{row['clamped_positions_mpm_frames']} in MPM frames (by up to "
                      f"{1e3 * row['max_clamp_shift_mpm_frames_m']:.3g} mm), "
                      f"{row['clamped_positions_gns_frames']} in GNS frames (by up to "
                      f"{1e3 * row['max_clamp_shift_gns_frames_m']:.3g} mm)", tag=False)
    tables, worse = {}, {}
    for sched in scheds:
        name = schedule_name(sched)
        mine = [r for r in rows if r["schedule"] == name]
        tables[name] = per_family(mine, [r["family"] for r in mine])
        if sched.mpm_frames:
            worse[name] = worse_than_gns(rows, name)
    print_tables(run, tables, worse, rows)
    path = run.finish(args.out, dict(model=str(args.model), data=str(args.data),
                                     schedules=[schedule_name(s) for s in scheds], rows=rows,
                                     tables=tables, worse_than_gns=worse))
    run.print(f"wrote {path}")


def run_case(scene, gns, params, info: dict, sched, ref) -> dict:
    """Scores (:func:`~diffgns.graph.evaluate.score`) of one schedule's nodes on ``scene``
    against ``ref`` (the dataset's node trajectory of that scene), with the run's MPM
    fraction and clamp summary."""
    from diffgns.graph.evaluate import score
    from diffgns.hybrid.compare import run_hybrid

    n_frames = len(ref.positions) - 1
    res, t = run_hybrid(scene, gns, params, info, sched, n_frames, repeats=1)
    nodes = np.asarray(res.nodes)
    if nodes.shape != np.shape(ref.positions):
        raise SystemExit(f"the hybrid's nodes {nodes.shape} do not match the dataset's "
                         f"{np.shape(ref.positions)}: another coarse-graining or frame count")
    s = score(ref.replace(positions=nodes), ref, start=res.warmup_frames)
    x_ref = np.asarray(ref.positions)
    err = np.sqrt(((nodes - x_ref) ** 2).sum(-1)).mean(-1)
    every = np.arange(0, len(nodes), TRACE_EVERY)
    trace = dict(trace_frames=every.tolist(), node_error_m=err[every].tolist(),
                 centroid_m=nodes[every].mean(1).tolist(),
                 centroid_ref_m=x_ref[every].mean(1).tolist())
    return dict(s, mpm_fraction=float(t["mpm_fraction"]), warmup_frames=t["warmup_frames"],
                **res.clamp_summary(), **trace)


def worse_than_gns(rows: list[dict], name: str, tol: float = 0.0) -> list[dict]:
    """Cases where schedule ``name``'s final position error exceeds the GNS alone's by more
    than ``tol`` (relative to the mean displacement)."""
    gns = {r["case"]: r for r in rows if r["schedule"] == "GNS"}
    return [dict(case=r["case"], family=r["family"], error=r[POS], gns_error=gns[r["case"]][POS])
            for r in rows if r["schedule"] == name and r[POS] > gns[r["case"]][POS] + tol]


def print_tables(run, tables: dict, worse: dict, rows: list[dict]) -> None:
    run.print(f"{'schedule':<10} {'family':<12} {'cases':>5} {'pos err mean/max':>17} "
              f"{'runout mean/max':>16} {'outside':>7} {'clamped':>12} {'NaN':>4} {'met':>6}")
    for name, table in tables.items():
        for fam, t in table.items():
            run.print(f"{name:<10} {fam:<12} {t['cases']:>5} "
                      f"{t[POS + '_mean']:>8.3f}/{t[POS + '_max']:<8.3f} "
                      f"{t['flow_runout_rel_error_mean']:>7.3f}/"
                      f"{t['flow_runout_rel_error_max']:<8.3f} {t['outside_domain']:>7} "
                      f"{t['clamped_positions']:>5} in {t['clamped_cases']:>3} "
                      f"{t['not_finite']:>4} {t['cases_met']:>3}/{t['cases']:<2}")
    for name, w in worse.items():
        clamps = sum(r["clamped_positions"] for r in rows if r["schedule"] == name)
        run.print(f"{name}: worse than the GNS alone on {len(w)} case(s) "
                  f"{[x['case'] for x in w]}; {clamps} clamped positions")


if __name__ == "__main__":
    main()
