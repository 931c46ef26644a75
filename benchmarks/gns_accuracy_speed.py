"""Accuracy of a trained GNS on held-out column collapses, and its cost per simulated second
against the MPM (at its stable dt and at the dt = 1e-5 s of the published training data),
measured in one run on this machine.

    python benchmarks/gns_accuracy_speed.py --model src/diffgns/models/gns_columns \
        --data data/columns_test.h5 --out benchmarks/results/gns_accuracy_speed.json

The reference for accuracy is the MPM trajectory of each test case, coarse-grained and
strided exactly as the GNS sees it. Timings are steady-state (compile separated), median of
``--repeats`` runs, with block_until_ready; the MPM is timed on each case's own scene. The
GNS and the stable-dt MPM are timed alternately, repeat by repeat, and a case's speed-up is
the median of its per-repeat ratios, so that a change in a shared machine's load between
repeats hits both sides; the summary gives the medians over cases.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from functools import partial
from pathlib import Path

import jax
import numpy as np

from diffgns import MPM
from diffgns.graph.data import load_trajectories
from diffgns.graph.evaluate import reference_inputs, rollout_reference, score
from diffgns.graph.train_loop import load_model
from diffgns.scene.builders import column_collapse


def _seconds(fn) -> float:
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - t0


def mpm_runner(scene, n_frames: int):
    """(compile s, zero-argument function running an MPM rollout of n_frames)."""
    sim = MPM(scene)
    p, s = sim.params(), sim.init_state()
    run = partial(sim.rollout_full, p, s, n_frames=n_frames)
    first = _seconds(run)
    return first - _seconds(run), run


def gns_runner(gns, params, ref):
    """Zero-argument function running the GNS rollout of :func:`rollout_reference` (compiled,
    with the neighbour list that the first call sized)."""
    hist, ptype, mat, n_steps = reference_inputs(gns, ref)
    _, nbrs = gns.rollout_safe(params, hist, ptype, mat, n_steps)
    return lambda: gns.rollout_safe(params, hist, ptype, mat, n_steps, nbrs)[0]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default="src/diffgns/models/gns_columns")
    ap.add_argument("--data", default="data/columns_test.h5")
    ap.add_argument("--out", default="benchmarks/results/gns_accuracy_speed.json")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--mpm-1e-5-frames", type=int, default=40,
                    help="frames timed for the dt = 1e-5 s MPM (cost scales linearly)")
    args = ap.parse_args()

    gns, params, info = load_model(args.model)
    factor, stride = info.get("factor", 1), info.get("frame_stride", 1)
    refs, _ = load_trajectories(args.data, factor, stride)
    attrs = _attrs(args.data)
    rows = []
    for ref, at in zip(refs, attrs):
        pred, _ = rollout_reference(gns, params, ref, timed=False)
        row = score(pred, ref, start=gns.config.history)
        row.update(aspect_ratio=at.get("aspect_ratio"), friction_angle=at.get("friction_angle"),
                   nodes=ref.n_particles)
        rows.append(row)
        print(f"a={row['aspect_ratio']} phi={row['friction_angle']}: runout err "
              f"{row['runout_rel_error']:.3f}, final pos err/disp "
              f"{row['final_position_error_rel_displacement']:.3f}", flush=True)
    # Cost per simulated second on every case's own scene (same run, same machine). The GNS
    # and the stable-dt MPM are timed alternately, repeat by repeat, so that a change in the
    # machine's load hits both; a case's speed-up is the median of its per-repeat ratios.
    meta = json.loads(Path(args.data).with_suffix(".metadata.json").read_text())
    for row, at, ref in zip(rows, attrs, refs):
        kw = dict(width=meta.get("width", 0.1), aspect_ratio=at["aspect_ratio"],
                  friction_angle=at["friction_angle"], cells_across=meta.get("cells_across", 8),
                  domain_length=0.8, domain_height=0.35)
        scene = column_collapse(**kw)
        n = 100
        gns_run = gns_runner(gns, params, ref)
        gns_sim_s = (ref.n_frames - gns.config.history - 1) * ref.frame_dt
        c_stable, mpm_run = mpm_runner(scene, n)
        tg, tm = [], []
        for _ in range(args.repeats):
            tg.append(_seconds(gns_run) / gns_sim_s)
            tm.append(_seconds(mpm_run) / (n * scene.frame_dt))
        scene5 = column_collapse(**kw, dt=1e-5)
        c5, mpm5_run = mpm_runner(scene5, args.mpm_1e_5_frames)
        t5 = float(np.median([_seconds(mpm5_run) for _ in range(max(1, args.repeats - 2))]))
        g = float(np.median(tg))
        row.update(gns_s=g * gns_sim_s, gns_s_per_sim_s=g, gns_s_per_sim_s_repeats=tg,
                   mpm_particles=scene.n_particles, mpm_substeps_stable=scene.substeps,
                   mpm_stable_s_per_sim_s=float(np.median(tm)), mpm_stable_repeats=tm,
                   mpm_stable_compile_s=c_stable, mpm_dt1e5_substeps=scene5.substeps,
                   mpm_dt1e5_s_per_sim_s=t5 / (args.mpm_1e_5_frames * scene.frame_dt))
        row["speedup_vs_mpm_stable"] = float(np.median(np.array(tm) / np.array(tg)))
        row["speedup_vs_mpm_dt1e5"] = row["mpm_dt1e5_s_per_sim_s"] / g
        print(f"a={at['aspect_ratio']}: MPM {row['mpm_stable_s_per_sim_s']:.2f} s/sim-s "
              f"(stable dt), {row['mpm_dt1e5_s_per_sim_s']:.2f} (dt=1e-5); GNS "
              f"{row['gns_s_per_sim_s']:.2f}", flush=True)
    mpm = dict(cells_across=meta.get("cells_across", 8),
               stable_s_per_sim_s=[r["mpm_stable_s_per_sim_s"] for r in rows],
               dt1e5_s_per_sim_s=[r["mpm_dt1e5_s_per_sim_s"] for r in rows])
    summary = dict(
        mean_runout_rel_error=float(np.mean([r["runout_rel_error"] for r in rows])),
        max_runout_rel_error=float(np.max([r["runout_rel_error"] for r in rows])),
        mean_final_position_error_rel_displacement=float(np.mean(
            [r["final_position_error_rel_displacement"] for r in rows])),
        gns_s_per_sim_s=float(np.median([r["gns_s_per_sim_s"] for r in rows])),
        speedup_vs_mpm_stable=float(np.median([r["speedup_vs_mpm_stable"] for r in rows])),
        speedup_vs_mpm_dt1e5=float(np.median([r["speedup_vs_mpm_dt1e5"] for r in rows])))
    out = dict(command=" ".join(sys.argv), model=args.model, model_info=info.get("gns"),
               factor=factor, frame_stride=stride, rows=rows, mpm=mpm, summary=summary,
               devices=str(jax.devices()), date=time.strftime("%Y-%m-%d %H:%M"))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2, default=float))
    print(json.dumps(dict(mpm=mpm, summary=summary), indent=2))


def _attrs(path):
    import h5py

    with h5py.File(path, "r") as f:
        return [dict(f[k].attrs) for k in sorted(k for k in f.keys() if k.isdigit())]


if __name__ == "__main__":
    main()
