"""Accuracy of a trained GNS on held-out column collapses (2D, or axisymmetric in 3D), and
its cost per simulated second against the MPM (at its stable dt and at the dt = 1e-5 s of
the published training data), measured in one run on this machine.

    .venv/bin/python benchmarks/gns_accuracy_speed.py --model models/gns_columns \
        --data data/columns_test.h5 --out benchmarks/results/gns_accuracy_speed.json

The reference for accuracy is the MPM trajectory of each test case, coarse-grained and
strided exactly as the GNS sees it. Timings (``benchmarks/timing.py``, under
``benchmarks/protocol.py``) are steady-state (first call = compile, timed apart), with
block_until_ready, wall and CPU time; the MPM is timed on each case's own scene. The GNS and
the stable-dt MPM are timed in interleaved rounds (order alternating), and a case's speed-up
is the median of its per-round ratios, so that a change in a shared machine's load hits both
sides; the summary gives the medians over cases.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import protocol
from protocol import warm_up_jax

from diffgns import MPM, rollout_jit
from diffgns.graph.data import load_trajectories
from diffgns.graph.evaluate import reference_inputs, rollout_reference, score
from diffgns.graph.train_loop import load_model
from diffgns.interface import rollout_safe
from diffgns.scene.recipes import column_scene
from diffgns.timing import interleave, time_call


# ---------------------------------------------------------------- simulator calls
def mpm_call(scene, n_frames: int):
    """Zero-argument jitted MPM rollout of ``n_frames`` frames of ``scene``."""
    sim = MPM(scene)
    p, s = sim.params(), sim.init()
    return lambda: rollout_jit(sim, p, s, n_frames=n_frames)[0].positions


def gns_call(gns, params, ref):
    """Zero-argument GNS rollout from the first frames of ``ref`` (compiled, with the
    neighbour list that a first call sized), in ``ref``'s box."""
    gns = gns.for_box(ref.bounds)
    p, state, n_steps = reference_inputs(gns, params, ref)
    _, _, start = rollout_safe(gns, p, state, n_steps)  # sizes the neighbour list
    return lambda: rollout_jit(gns, p, start, n_frames=n_steps)[0].positions


def gns_prediction(gns, params, ref):
    """The GNS trajectory on the frames of ``ref`` (accuracy)."""
    return rollout_reference(gns, params, ref, timed=False)[0]


# ---------------------------------------------------------------- measurement
def accuracy_rows(run, gns, params, refs, attrs) -> list[dict]:
    rows = []
    for ref, at in zip(refs, attrs):
        row = score(gns_prediction(gns, params, ref), ref, start=gns.config.history)
        row.update(aspect_ratio=at.get("aspect_ratio"), friction_angle=at.get("friction_angle"),
                   nodes=ref.n_particles)
        rows.append(row)
        run.print(f"a={row['aspect_ratio']} phi={row['friction_angle']}: runout err "
                  f"{row['runout_rel_error']:.3f}, final pos err/disp "
                  f"{row['final_position_error_rel_displacement']:.3f}")
    return rows


def stable_speed(gns, params, ref, scene, repeats: int, n: int = 100) -> dict:
    """Cost per simulated second of the GNS (rolled out from ``ref``'s first frames) and of
    the MPM at its stable dt on ``scene`` (``n`` frames), in ``repeats`` interleaved rounds;
    the speed-up is the median over rounds of the ratio of the two costs."""
    gns_sim_s = (ref.n_frames - gns.config.history - 1) * ref.frame_dt
    mpm_sim_s = n * scene.frame_dt
    res = interleave({"gns": gns_call(gns, params, ref), "mpm": mpm_call(scene, n)}, repeats)
    tg, tm = res.summary("gns"), res.summary("mpm")
    return dict(
        gns_s=tg["median_s"], gns_s_per_sim_s=tg["median_s"] / gns_sim_s, gns_timing=tg,
        mpm_particles=scene.n_particles, mpm_substeps_stable=scene.substeps,
        mpm_stable_s_per_sim_s=tm["median_s"] / mpm_sim_s, mpm_stable_timing=tm,
        mpm_stable_compile_s=tm["compile_s"], rounds=res.to_json()["rounds"],
        # median over rounds of (t_mpm / sim s) / (t_gns / sim s)
        speedup_vs_mpm_stable=res.ratio("mpm", "gns") * gns_sim_s / mpm_sim_s)


def speed_of_case(gns, params, ref, kw: dict, repeats: int, mpm5_frames: int) -> dict:
    """:func:`stable_speed` on one column case's own scene (``kw``:
    :func:`~diffgns.scene.recipes.column_scene`'s arguments, 2D or 3D), and the MPM at the
    dt = 1e-5 s of the published training data."""
    scene = column_scene(**kw)
    out = stable_speed(gns, params, ref, scene, repeats)
    scene5 = column_scene(**kw, dt=1e-5)
    t5 = time_call(mpm_call(scene5, mpm5_frames), max(1, repeats - 2))[0]
    mpm5 = t5["median_s"] / (mpm5_frames * scene.frame_dt)
    out.update(mpm_dt1e5_substeps=scene5.substeps, mpm_dt1e5_s_per_sim_s=mpm5,
               mpm_dt1e5_timing=t5, speedup_vs_mpm_dt1e5=mpm5 / out["gns_s_per_sim_s"])
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default="models/gns_columns")
    ap.add_argument("--data", default="data/columns_test.h5")
    ap.add_argument("--out", default="benchmarks/results/gns_accuracy_speed.json")
    ap.add_argument("--repeats", type=int, default=3, help="interleaved rounds per case")
    ap.add_argument("--cases", type=int, default=None, help="only the first N cases")
    ap.add_argument("--mpm-1e-5-frames", type=int, default=40,
                    help="frames timed for the dt = 1e-5 s MPM (cost scales linearly)")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "gns_accuracy_speed")
    warm_up_jax()
    gns, params, info = load_model(args.model)
    factor, stride = info.get("factor", 1), info.get("frame_stride", 1)
    refs, _ = load_trajectories(args.data, factor, stride)
    attrs = _attrs(args.data)
    refs, attrs = refs[: args.cases], attrs[: args.cases]
    rows = accuracy_rows(run, gns, params, refs, attrs)
    meta = json.loads(Path(args.data).with_suffix(".metadata.json").read_text())
    dim = int(meta.get("dim", 2))  # a 3D column's box follows from its runout estimate
    box = dict(domain_length=0.8, domain_height=0.35) if dim == 2 else {}
    for row, at, ref in zip(rows, attrs, refs):
        kw = dict(width=meta.get("width", 0.1), aspect_ratio=at["aspect_ratio"],
                  friction_angle=at["friction_angle"], cells_across=meta.get("cells_across", 8),
                  dim=dim, **box)
        row.update(speed_of_case(gns, params, ref, kw, args.repeats, args.mpm_1e_5_frames))
        run.print(f"a={at['aspect_ratio']}: MPM {row['mpm_stable_s_per_sim_s']:.2f} s/sim-s "
                  f"(stable dt), {row['mpm_dt1e5_s_per_sim_s']:.2f} (dt=1e-5); GNS "
                  f"{row['gns_s_per_sim_s']:.2f}; speed-up {row['speedup_vs_mpm_stable']:.1f}x")
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
    payload = dict(model=args.model, data=args.data, model_info=info.get("gns"),
                   factor=factor, frame_stride=stride, rows=rows, mpm=mpm, summary=summary)
    path = run.finish(args.out, payload)
    run.print(json.dumps(dict(mpm=mpm, summary=summary), indent=2))
    run.print(f"wrote {path}")


def _attrs(path):
    import h5py

    with h5py.File(path, "r") as f:
        return [dict(f[k].attrs) for k in sorted(k for k in f.keys() if k.isdigit())]


if __name__ == "__main__":
    main()
