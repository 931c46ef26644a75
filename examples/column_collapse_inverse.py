"""Identify the friction angle of a granular column from its observed runout.

    python examples/column_collapse_inverse.py --out results/inverse            # GNS (default)
    python examples/column_collapse_inverse.py --simulator mpm                   # the MPM
    python examples/column_collapse_inverse.py --compare --out results/compare   # table

The observation is an MPM column collapse (the physical truth: phi = 30 deg, aspect ratio
1.75, in the 0.8 x 0.35 m box of the shipped GNS, at the MPM resolution the model emulates)
seen as the GNS sees it: nodes = means of particles (16 per node for the default model),
every 2nd frame (5 ms), 0.625 s to rest. Starting from 45 deg, phi is recovered by
minimising (runout - observed runout)^2 with optax and exact gradients through the whole
rollout: the GNS (default ``gns_cg16_pfn``, the most accurate shipped model: held-out runout
error 1.4% mean, 4.4% max on its card; its first 6 frames are the observed ones, tan(phi) is
its material feature; 120 GNS steps in jax.checkpoint blocks of 10), or the MPM
(checkpointed substeps). ``--model gns_columns`` runs the older 8-cell model. phi is
optimised as u = logit(phi / 90), so it stays in (0, 90); the default step is Gauss-Newton
(the Newton step on the one residual). Writes convergence.png, deposits.png and
summary.json; the last line states the recovered angle.
``--compare`` runs every simulator (and AD against finite differences) in fresh processes and
writes compare.json / compare.md.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from diffgns.inverse.job import OBJECTIVES, make_objective, make_simulator, solve
from diffgns.inverse.simulators import DEFAULT_MODEL, Column, ColumnCase, load_gns, model_info

GNS_PHI_RANGE = (20.0, 45.0)  # friction angles of the shipped model's training data
GNS_ASPECT_RANGE = (0.5, 3.0)


def angle(text: str) -> float:
    v = float(text)
    if not 0.0 < v < 90.0:
        raise argparse.ArgumentTypeError(f"{v:g} deg is not a friction angle: use 0 < phi < 90")
    return v


def parse(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="results/inverse")
    ap.add_argument("--simulator", default="gns", choices=["gns", "mpm", "hybrid"])
    ap.add_argument("--model", default=str(DEFAULT_MODEL), help="GNS model folder or name")
    ap.add_argument("--target-phi", type=angle, default=30.0, help="degrees, in (0, 90)")
    ap.add_argument("--start-phi", type=angle, default=45.0, help="degrees, in (0, 90)")
    ap.add_argument("--aspect-ratio", type=float, default=1.75,
                    help="column height / width (a multiple of 1/8; GNS trained on 0.5-3)")
    ap.add_argument("--objective", default="runout", choices=list(OBJECTIVES),
                    help="runout: smooth (soft-max) final runout; runout-max: farthest node; "
                         "runout-frame: smooth runout at --frame; deposit: deposit profile")
    ap.add_argument("--frame", type=int, default=-1, help="observed frame for the objective")
    ap.add_argument("--optimizer", default="gauss-newton", choices=["gauss-newton", "adam", "sgd"])
    ap.add_argument("--lr", type=float, default=None,
                    help="gauss-newton: step scale (1); adam/sgd: learning rate on u = logit")
    ap.add_argument("--max-iter", type=int, default=20)
    ap.add_argument("--step-tol", type=float, default=0.01, help="stop below this step, deg")
    ap.add_argument("--gradient", default="auto", choices=["auto", "ad", "fd"],
                    help="ad: reverse mode; fd: central finite differences (comparison); "
                    "auto: ad, differences once a step raises the loss")
    ap.add_argument("--block", type=int, default=None,
                    help="frames per jax.checkpoint block (default GNS/hybrid 10, MPM 25); "
                         "0 = none (the MPM still checkpoints its substeps)")
    ap.add_argument("--fd-check", action="store_true",
                    help="also time the AD gradient against finite differences at the start")
    ap.add_argument("--compare", action="store_true",
                    help="run gns, mpm, hybrid and gns with FD gradients; write a table")
    args = ap.parse_args(argv)
    if args.max_iter < 0:
        ap.error("--max-iter must be >= 0")
    return args


def run(args) -> dict:
    t_start = time.perf_counter()
    if args.simulator == "gns":
        lo, hi = GNS_PHI_RANGE
        for name, v in (("target", args.target_phi), ("start", args.start_phi)):
            if not lo <= v <= hi:
                print(f"warning: {name} phi {v:g} is outside the GNS training range "
                      f"{lo:g}-{hi:g} deg", flush=True)
        if not GNS_ASPECT_RANGE[0] <= args.aspect_ratio <= GNS_ASPECT_RANGE[1]:
            print(f"warning: aspect ratio {args.aspect_ratio:g} is outside the GNS training "
                  f"range {GNS_ASPECT_RANGE}", flush=True)
    # the column of the model's training data (box, width, resolution, nodes, frame stride)
    column = Column(ColumnCase.from_model(model_info(args.model), args.aspect_ratio))
    truth = {"friction_angle": args.target_phi}
    observed = column.observation(truth)  # the MPM: physical truth, seen as nodes
    print(f"observation: MPM, {column.scene.n_particles} particles -> {column.n_nodes} nodes, "
          f"{column.n_obs} frames of {column.frame_dt * 1e3:g} ms "
          f"({column.n_frames * column.scene.substeps} MPM substeps); "
          f"{time.perf_counter() - t_start:.1f} s", flush=True)
    loaded = load_gns(args.model) if args.simulator != "mpm" else None
    theta0 = {"friction_angle": args.start_phi}
    sim = make_simulator(args.simulator, column, args.model, loaded=loaded, observed=observed,
                         block=args.block, theta0=theta0)
    objective = make_objective(args.objective, column, observed=observed, frame=args.frame)
    return solve(sim, objective, theta0, column, args.out,
                 optimizer=args.optimizer, lr=args.lr, max_iter=args.max_iter,
                 step_tol=args.step_tol, gradient=args.gradient, observed=observed,
                 truth=truth, label=args.simulator, fd_check=args.fd_check,
                 t_start=t_start, extra=dict(
                     objective=args.objective, aspect_ratio=args.aspect_ratio,
                     model=args.model if args.simulator != "mpm" else None))


COMPARE = [("gns", ["--simulator", "gns"]), ("mpm", ["--simulator", "mpm"]),
           ("hybrid", ["--simulator", "hybrid"]),
           ("gns, FD gradients", ["--simulator", "gns", "--gradient", "fd"])]


def compare(args) -> None:
    """Each case in a fresh process (own compile, own peak RSS); AD vs FD at the start."""
    out = Path(args.out)
    common = ["--target-phi", str(args.target_phi), "--start-phi", str(args.start_phi),
              "--aspect-ratio", str(args.aspect_ratio), "--max-iter", str(args.max_iter),
              "--objective", args.objective, "--model", args.model]
    rows = []
    for name, extra in COMPARE:
        sub = out / name.replace(", ", "_").replace(" ", "_")
        fd = ["--fd-check"] if name in ("gns", "mpm", "hybrid") else []
        cmd = [sys.executable, __file__, "--out", str(sub), *common, *extra, *fd]
        print(f"--- {name}: {' '.join(cmd[1:])}", flush=True)
        t0 = time.perf_counter()
        p = subprocess.run(cmd, capture_output=True, text=True)
        if p.returncode != 0:
            err = (p.stderr.strip().splitlines() or ["?"])[-1]
            print(f"    failed: {err}", flush=True)
            rows.append(dict(simulator=name, error=err, wall_time_s=time.perf_counter() - t0))
            continue
        s = json.loads((sub / "summary.json").read_text())
        s["simulator"] = name
        rows.append(s)
        print("    " + p.stdout.strip().splitlines()[-1], flush=True)
    table = ["| simulator | recovered phi (deg) | error (deg) | iterations | total time (s) | "
             "compile (s) | s / iteration | XLA grad temp (MB) | peak RSS (MB) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            table.append(f"| {r['simulator']} | not available: {r['error']} |||||||")
            continue
        table.append(
            f"| {r['simulator']} | {r['recovered']['friction_angle']:.2f} | "
            f"{r['error_deg']:+.2f} | {r['iterations']} | {r['wall_time_s']:.1f} | "
            f"{r['compile_s']:.1f} | {r['time_per_iteration_s']:.2f} | "
            f"{r['xla_gradient_memory'].get('temp_size_in_bytes', 0) / 1e6:.0f} | "
            f"{r['peak_rss_mb']:.0f} |")
    table += ["", f"AD against finite differences of the loss at phi = {args.start_phi:g} deg "
              "(central steps of 1e-2, 1e-3, 1e-4 x phi; slopes of 20 successive intervals of "
              "1e-4 x phi: median and share within 2 % of AD); times: median of 3 compiled "
              "calls, an FD gradient = 2 forward runs", "",
              "| simulator | AD dL/dphi | central FD | rel. diff | median slope (rel. diff) | "
              "slopes within 2 % | AD time (s) | forward (s) | FD time (s) |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        g = r.get("gradient_check")
        if not g:
            continue
        fds = ", ".join(f"{v['friction_angle']:.4e}" for v in g["fd"].values())
        rel = ", ".join(f"{v['friction_angle']:.1e}" for v in g["rel_diff"].values())
        sl = g["slopes"]["friction_angle"]
        table.append(f"| {r['simulator']} | {g['ad']['friction_angle']:.4e} | {fds} | {rel} | "
                     f"{sl['median']:.4e} ({sl['median_rel_diff']:.1e}) | "
                     f"{sl['within_2pct']:.0%} | {g['ad_time_s']:.2f} | "
                     f"{g['forward_time_s']:.2f} | {g['fd_time_s']:.2f} |")
    text = "\n".join(table)
    print(text)
    (out / "compare.md").write_text(text + "\n")
    (out / "compare.json").write_text(json.dumps(rows, indent=2))


def main(argv=None):
    args = parse(argv)
    if args.compare:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        compare(args)
    else:
        try:
            run(args)
        except NotImplementedError as e:
            sys.exit(f"error: {e}")


if __name__ == "__main__":
    main()
