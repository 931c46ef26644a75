"""MeshGraphNet against our CFD on held-out cylinder flows: cost per simulated second (timed
in interleaved rounds), and accuracy, shedding and stability, in one run.

    python benchmarks/meshnet_accuracy_speed.py --model runs/meshnet_halving/model \
        --data data/sweep_heldout.h5 [--rounds 3] [--cfd-frames 5] [--threads both]

Cost. For every held-out trajectory (``--cases``: the first N) the MeshGraphNet rollout over
the trajectory's frames (``rollout_jit``, from its first frame) and our CFD on the same case
(its own mesh and time step, rebuilt from the dataset's recipe: ``diffgns.mesh.datagen``'s
``case_setup`` and ``cfd.run_case``, ``--cfd-frames`` frames from the Stokes start) are timed
in the same ``--rounds`` interleaved rounds (``diffgns.timing.interleave``: one call of each
per round, the order reversed every other round; ``block_until_ready``; wall and CPU time;
medians). The model's first call (compile) is timed apart. The CFD's seconds per simulated
second are its time loop's (``CaseResult.wall_time_s``: assembly and factorisation excluded,
they are recorded beside it), as when the data was made; the model's are its whole rollout
call. A case's speed-up is the median of its per-round ratios CFD / model (per simulated
second); the summary gives the median over cases. The time recorded when the data was made is
kept beside it (``cfd_s_per_sim_s_stored``).

Accuracy (``diffgns.mesh.evaluate.evaluate_trajectory``, after the rounds; ``--no-accuracy``
skips it): velocity RMSE at 1, 50 and all frames, Strouhal number of the pressure lift against
the CFD's, a rollout ``--long-factor`` x as long checked for boundedness and periodicity. Also
writes a lift plot and a side-by-side vorticity GIF of the first trajectory next to the JSON.
Under ``benchmarks/protocol.py``, by default ``--threads both`` (2 threads, then the rounds
again pinned to one core: the CFD and the network use a second core differently, so the ratio
is given for both; ~4-5 min with ``--no-accuracy`` on 5 cases on a quiet 2-core machine).
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

import numpy as np
import protocol
from protocol import warm_up_jax

from diffgns import rollout_jit
from diffgns.mesh.cfd import run_case
from diffgns.mesh.datagen import CylinderRun, case_setup
from diffgns.mesh.evaluate import evaluate_trajectory, pressure_force_coefficients
from diffgns.mesh.figures import animate_vorticity, plot_lift, vorticity
from diffgns.mesh.train import graph_of, load_cylinder, load_model
from diffgns.timing import block, interleave, measure, no_sync


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


def dataset_run(data: str | Path) -> CylinderRun:
    """The CFD settings a cylinder dataset was made with (``<stem>.metadata.json``: ``run``
    for ``diffgns dataset --kind cylinder``, ``sweep.run`` for ``diffgns.mesh.sweep``)."""
    meta = json.loads(Path(data).with_suffix(".metadata.json").read_text())
    run = meta.get("run") or (meta.get("sweep") or {}).get("run")
    if not run:
        raise SystemExit(f"{data}: its metadata records no CFD settings ('run' or 'sweep.run'); "
                         "the CFD cannot be re-timed on its meshes (use --cfd-frames 0)")
    return CylinderRun(**run)


def cfd_call(traj: dict, run_cfg: CylinderRun, n_frames: int, log: list):
    """(zero-argument call of our CFD on ``traj``'s case for ``n_frames`` frames, simulated
    seconds); every call appends its ``CaseResult`` times to ``log``. The mesh is built here,
    once, and checked against the dataset's."""
    a = traj["attrs"]
    mesh, prm = case_setup(a, run_cfg)
    if mesh.n_nodes != int(a["n_vertices"]) or abs(prm.dt - float(a["dt"])) > 1e-12:
        raise SystemExit(f"case {traj['key']}: the rebuilt CFD has {mesh.n_nodes} vertices, dt "
                         f"{prm.dt:g}; the data was made on {int(a['n_vertices'])}, dt "
                         f"{float(a['dt']):g}")
    t_end = n_frames * run_cfg.frame_dt

    def call():
        res = run_case(mesh, prm, t_end, run_cfg.frame_dt)
        log.append(dict(wall_s=res.wall_time_s, setup_s=res.setup_s,
                        s_per_sim_s=res.wall_per_sim_second))
        return res

    return call, t_end


def accuracy(model, params, traj, info, long_factor: int) -> dict:
    """``evaluate_trajectory``'s metrics (its own timing keys dropped: the rounds time)."""
    r = evaluate_trajectory(model, params, traj, info["padding"], long_factor, 1)
    for k in ("compile_s", "model_s_per_sim_s", "model_cpu_s_per_sim_s", "model_timing",
              "cfd_s_per_sim_s"):
        r.pop(k, None)
    return r


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="meshnet_cylinder")
    ap.add_argument("--data", default="data/cylinder_test.h5")
    ap.add_argument("--out", default="meshnet_accuracy_speed.json")
    ap.add_argument("--rounds", "--repeats", type=int, default=3, dest="rounds",
                    help="interleaved rounds (one model rollout and one CFD run per case each)")
    ap.add_argument("--long-factor", type=int, default=3)
    ap.add_argument("--no-accuracy", action="store_true",
                    help="time only (no RMSE, Strouhal, long rollout, figures)")
    ap.add_argument("--no-figures", action="store_true")
    ap.add_argument("--cases", type=int, default=None, help="only the first N cases")
    ap.add_argument("--cfd-frames", type=int, default=5,
                    help="frames of CFD timed per case and round (0: no CFD timing, the time "
                         "recorded when the data was made only)")
    protocol.add_arguments(ap, threads="both")  # the CFD and the model use threads unlike
    args = ap.parse_args(argv)
    run = protocol.start(args, "meshnet_accuracy_speed")
    warm_up_jax()
    model, params, info = load_model(args.model)
    trajs = load_cylinder(args.data)[: args.cases]
    frame_dts = {float(t["attrs"]["frame_dt"]) for t in trajs}
    if frame_dts != {float(model.frame_dt)}:
        raise SystemExit(f"{args.model} steps {model.frame_dt:g} s per frame, {args.data} has "
                         f"frames of {sorted(frame_dts)} s: not the data of this model")
    cfd_run = dataset_run(args.data) if args.cfd_frames > 0 else None
    calls, syncs, firsts, sims, cfd_logs = {}, {}, {}, {}, {}
    for traj in trajs:
        k = traj["key"]
        calls[f"model {k}"], sims[f"model {k}"] = rollout_call(model, params, traj,
                                                               info["padding"])
        syncs[f"model {k}"] = block
        firsts[f"model {k}"], _ = measure(calls[f"model {k}"])  # compile (once per padding)
        if cfd_run is not None:
            cfd_logs[k] = []
            calls[f"cfd {k}"], sims[f"cfd {k}"] = cfd_call(traj, cfd_run, args.cfd_frames,
                                                           cfd_logs[k])
            syncs[f"cfd {k}"] = no_sync
    rounds = interleave(calls, max(1, args.rounds), sync=syncs, warmup=False)
    rounds.first.update(firsts)
    rows = []
    for traj in trajs:
        k, a = traj["key"], traj["attrs"]
        t = rounds.summary(f"model {k}")
        model_sim = sims[f"model {k}"]
        r = dict(key=k, reynolds=float(a["reynolds"]), frames=len(traj["velocity"]),
                 n_vertices=int(a["n_vertices"]), model_timing=t, compile_s=t["compile_s"],
                 model_s_per_sim_s=t["median_s"] / model_sim,
                 model_cpu_s_per_sim_s=t["cpu_median_s"] / model_sim,
                 cfd_s_per_sim_s_stored=float(a.get("cfd_wall_per_sim_second", np.nan)))
        if cfd_run is not None:
            log = cfd_logs[k]  # one entry per round, in round order
            per_round = [c["s_per_sim_s"] / (rd[f"model {k}"].wall_s / model_sim)
                         for c, rd in zip(log, rounds.rounds)]
            c = rounds.summary(f"cfd {k}")
            r.update(cfd_frames=args.cfd_frames, cfd_steps_per_call=round(
                         sims[f"cfd {k}"] / float(a["dt"])),
                     cfd_s_per_sim_s=float(np.median([x["s_per_sim_s"] for x in log])),
                     cfd_setup_s=float(np.median([x["setup_s"] for x in log])),
                     cfd_call_timing=c,
                     cfd_cpu_over_wall=c["cpu_over_wall"],
                     cfd_rounds=log, speedup_per_round=per_round,
                     speedup_vs_cfd=float(np.median(per_round)))
        else:
            r.update(cfd_s_per_sim_s=r["cfd_s_per_sim_s_stored"],
                     speedup_vs_cfd=r["cfd_s_per_sim_s_stored"] / r["model_s_per_sim_s"])
        rows.append(r)
        run.print(f"{k} Re {r['reynolds']:.0f}: model {r['model_s_per_sim_s']:.3f} s/sim-s "
                  f"(CPU {r['model_cpu_s_per_sim_s']:.3f}), CFD {r['cfd_s_per_sim_s']:.2f} "
                  f"s/sim-s; CFD/model {r['speedup_vs_cfd']:.1f}x")
    first = None
    if not args.no_accuracy:
        for traj, r in zip(trajs, rows):
            acc = accuracy(model, params, traj, info, args.long_factor)
            if first is None:
                first = (traj, acc)
            r.update({k: v for k, v in acc.items()
                      if k not in ("velocity", "pressure", "long_pressure")})
            run.print(f"{r['key']} Re {r['reynolds']:.0f}: RMSE {r['rmse']}, St cfd "
                      f"{r['strouhal_cfd']:.4f} model {r['strouhal_model']:.4f}, stable "
                      f"{r['stable']}", tag=False)
    med = lambda k: float(np.median([r[k] for r in rows]))  # noqa: E731
    summary = dict(model_s_per_sim_s_median=med("model_s_per_sim_s"),
                   cfd_s_per_sim_s_median=med("cfd_s_per_sim_s"),
                   speedup_vs_cfd_median=med("speedup_vs_cfd"))
    summary["speedup_vs_cfd"] = summary["cfd_s_per_sim_s_median"] / \
        summary["model_s_per_sim_s_median"]
    if not args.no_accuracy:
        horizons = sorted({h for r in rows for h in r["rmse"]}, key=int)
        summary.update(
            rmse_mean={str(h): float(np.mean([r["rmse"][h] for r in rows if h in r["rmse"]]))
                       for h in horizons},
            strouhal_rel_error_mean=float(np.mean([r["strouhal_rel_error"] for r in rows])),
            strouhal_rel_error_max=float(max(r["strouhal_rel_error"] for r in rows)),
            all_stable=all(r["stable"] for r in rows))
    payload = dict(model=args.model, data=args.data, rounds=max(1, args.rounds),
                   cfd_timing=dict(frames=args.cfd_frames, same_run=cfd_run is not None,
                                   run=None if cfd_run is None else asdict(cfd_run)),
                   model_info=dict(config=info["config"], steps=info.get("steps"),
                                   frame_dt=float(model.frame_dt)),
                   cases=rows, summary=summary,
                   interleaved=rounds.to_json()["rounds"])
    run.print(f"median over {len(rows)} cases: model {summary['model_s_per_sim_s_median']:.3f} "
              f"s/sim-s, CFD {summary['cfd_s_per_sim_s_median']:.2f} s/sim-s, CFD/model "
              f"{summary['speedup_vs_cfd_median']:.1f}x (median of the per-case, per-round "
              "ratios)")
    if run.mode == "both" and not run.pinned:
        payload["one_thread_pinned"] = child = run.pinned_child()
        one = (child.get("summary") or {}).get("speedup_vs_cfd_median")
        run.print("CFD/model: " + protocol.both_ratios(summary["speedup_vs_cfd_median"], one,
                                                        child, 2))
    path = run.finish(args.out, payload)
    run.print(f"written {path}")
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
