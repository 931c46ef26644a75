"""MeshGraphNet against our CFD on held-out cylinder flows: accuracy, shedding, stability and
cost per simulated second, in one run.

    python benchmarks/meshnet_accuracy_speed.py --model src/diffgns/models/meshnet_cylinder/model \
        --data data/cylinder_test.h5 --out benchmarks/results/meshnet_accuracy_speed.json

Per trajectory (rollout from its first frame; see ``diffgns.mesh.evaluate``): velocity
RMSE at 1, 50 and all frames, Strouhal number of the pressure lift against the CFD's, a
rollout 3x as long checked for boundedness and periodicity, and the steady-state rollout time
per simulated second (``benchmarks/timing.py``: first call = compile, timed apart; median of
--repeats; wall and CPU) against the CFD's wall time per simulated second, timed in the same
run on each case's own mesh and time step (``--cfd-frames`` frames from the Stokes start,
median of --repeats, assembly excluded, by ``diffgns.mesh.datagen.time_case``; 0 falls back
to the time recorded when the data was made). Under ``benchmarks/protocol.py``. Also writes a
lift plot and a side-by-side vorticity GIF of the first trajectory next to the JSON.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import protocol
from protocol import warm_up_jax

from diffgns import rollout_jit
from diffgns.mesh.datagen import CylinderRun, time_case
from diffgns.mesh.evaluate import evaluate_trajectory, pressure_force_coefficients
from diffgns.mesh.figures import animate_vorticity, plot_lift, vorticity
from diffgns.mesh.train import graph_of, load_cylinder, load_model
from diffgns.timing import measure, no_sync, time_call


def rollout_call(model, params, traj: dict, padding):
    """(zero-argument jitted MeshGraphNet rollout over the frames of ``traj``, simulated
    seconds). The one place this benchmark calls the simulator for timing."""
    n = len(traj["mesh_pos"])
    v0 = np.zeros((padding[0], 2), np.float32)
    v0[:n] = traj["velocity"][0]
    state = model.init(graph_of(traj, padding), v0)
    F = len(traj["velocity"])
    sim_s = (F - 1) * float(traj["attrs"]["frame_dt"])
    return (lambda: rollout_jit(model, params, state, n_frames=F - 1)[0]), sim_s


def evaluate_case(model, params, traj, info, run_cfg, args) -> dict:
    """Accuracy (``evaluate_trajectory``) and cost of one case, timed here."""
    call, sim_s = rollout_call(model, params, traj, info["padding"])
    t = time_call(call, args.repeats)[0]
    r = evaluate_trajectory(model, params, traj, info["padding"], args.long_factor, 1)
    r.update(compile_s=t["compile_s"], model_s_per_sim_s=t["median_s"] / sim_s,
             model_cpu_s_per_sim_s=t["cpu_median_s"] / sim_s, model_timing=t)
    r["cfd_s_per_sim_s_stored"] = r["cfd_s_per_sim_s"]
    if args.cfd_frames > 0:
        cfd, r["cfd_s_per_sim_s"] = measure(
            lambda: time_case(traj["attrs"], run_cfg, args.cfd_frames, args.repeats),
            sync=no_sync)
        r["cfd_timing_total"] = {"wall_s": cfd.wall_s, "cpu_s": cfd.cpu_s,
                                 "note": "all CFD runs of time_case, assembly included"}
    r["speedup_vs_cfd"] = r["cfd_s_per_sim_s"] / r["model_s_per_sim_s"]
    return r


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="meshnet_cylinder")
    ap.add_argument("--data", default="data/cylinder_test.h5")
    ap.add_argument("--out", default="meshnet_accuracy_speed.json")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--long-factor", type=int, default=3)
    ap.add_argument("--no-figures", action="store_true")
    ap.add_argument("--cases", type=int, default=None, help="evaluate only the first N cases")
    ap.add_argument("--cfd-frames", type=int, default=50,
                    help="frames of CFD timed per case in this run (0: use the stored time)")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "meshnet_accuracy_speed")
    warm_up_jax()
    model, params, info = load_model(args.model)
    trajs = load_cylinder(args.data)[: args.cases]
    cfd_run = CylinderRun(**json.loads(Path(args.data).with_suffix(".metadata.json").read_text())
                          .get("run", {}))
    rows, first = [], None
    for traj in trajs:
        r = evaluate_case(model, params, traj, info, cfd_run, args)
        if first is None:
            first = (traj, r)
        rows.append({k: v for k, v in r.items()
                     if k not in ("velocity", "pressure", "long_pressure")})
        run.print(f"{r['key']} Re {r['reynolds']:.0f}: RMSE {r['rmse']}, St cfd "
                   f"{r['strouhal_cfd']:.4f} model {r['strouhal_model']:.4f}, stable "
                   f"{r['stable']}, model {r['model_s_per_sim_s']:.2f} s/sim-s vs CFD "
                   f"{r['cfd_s_per_sim_s']:.2f}")
    mean = lambda k: float(np.mean([r[k] for r in rows]))
    horizons = sorted({h for r in rows for h in r["rmse"]}, key=int)
    summary = dict(
        rmse_mean={str(h): float(np.mean([r["rmse"][h] for r in rows if h in r["rmse"]]))
                   for h in horizons},
        strouhal_rel_error_mean=mean("strouhal_rel_error"),
        strouhal_rel_error_max=float(max(r["strouhal_rel_error"] for r in rows)),
        all_stable=all(r["stable"] for r in rows),
        model_s_per_sim_s_median=float(np.median([r["model_s_per_sim_s"] for r in rows])),
        cfd_s_per_sim_s_median=float(np.median([r["cfd_s_per_sim_s"] for r in rows])))
    summary["speedup_vs_cfd"] = summary["cfd_s_per_sim_s_median"] / \
        summary["model_s_per_sim_s_median"]
    payload = dict(model=args.model, data=args.data,
                   cfd_timing=dict(frames=args.cfd_frames, same_run=args.cfd_frames > 0),
                   model_info=dict(config=info["config"], steps=info.get("steps")),
                   cases=rows, summary=summary)
    path = run.finish(args.out, payload)
    run.print(f"summary: {summary}\nwritten {path}")
    if not args.no_figures and first is not None and not run.result_to:
        traj, r = first
        dt = float(traj["attrs"]["frame_dt"])
        stem = path.with_suffix("")
        cl_cfd = pressure_force_coefficients(traj, traj["pressure"][1:])[1]
        cl_gnn = pressure_force_coefficients(traj, r["long_pressure"])[1]
        plot_lift(np.arange(1, len(cl_gnn) + 1) * dt, {"CFD": cl_cfd, "MeshGraphNet": cl_gnn},
                  f"{stem}_lift.png")
        n = len(traj["mesh_pos"])
        om_cfd = vorticity(traj["mesh_pos"], traj["cells"], traj["velocity"])
        om_gnn = vorticity(traj["mesh_pos"], traj["cells"], r["velocity"][:, :n])
        animate_vorticity(traj["mesh_pos"], traj["cells"], om_cfd, om_gnn,
                          f"{stem}_vorticity.gif", frame_dt=dt)
        run.print(f"figures: {stem}_lift.png, {stem}_vorticity.gif")
    return 0


if __name__ == "__main__":
    sys.exit(main())
