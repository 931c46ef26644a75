"""Side views of a particle GNS's rollout beside the MPM's, case by case (where it goes wrong).

    .venv/bin/python benchmarks/granular_snapshots.py --model checkpoints/general_warm/g1/model \
        --data data/granular_valid.h5 --cases 8 10 11 6 [--frames 0 10 25 50 -1] \
        [--png docs/results/granular_snapshots_g1.png] [--out granular_snapshots.json]

For each case of ``--data`` the model rolls out from the first ``history + 1`` frames (its own
nodes and frame stride, in the case's box with its obstacles: ``rollout_reference``, as the
held-out tables); one row per case, one panel per frame (GNS frames, -1 the last): the MPM's
nodes in black, the GNS's in red, the obstacles in blue, the box as the axes. Nothing is
timed (accuracy only: the protocol records the load and never refuses the run). Writes the
PNG, and ``benchmarks/results/<out>`` with each case's family and final mean position error
(m), which it also prints.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import protocol


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", required=True, help="model folder or shipped name")
    ap.add_argument("--data", required=True, help="dataset (.h5)")
    ap.add_argument("--cases", type=int, nargs="+", required=True, help="trajectory indices")
    ap.add_argument("--frames", type=int, nargs="+", default=[0, 10, 25, 50, -1],
                    help="GNS frames to draw (-1: the last)")
    ap.add_argument("--png", default="granular_snapshots.png", help="PNG path")
    ap.add_argument("--out", default="granular_snapshots.json", help="results JSON")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "granular_snapshots", timed=False)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffgns.graph.data import load_trajectories
    from diffgns.graph.evaluate import rollout_reference
    from diffgns.graph.train_loop import load_model
    from diffgns.io.families_data import read_families

    gns, params, info = load_model(args.model)
    trajs, _ = load_trajectories(args.data, int(info.get("factor", 1)),
                                 int(info.get("frame_stride", 1)))
    families = list(read_families(args.data).values())
    bad = [c for c in args.cases if not 0 <= c < len(trajs)]
    if bad:
        raise SystemExit(f"--cases {bad}: {args.data} has cases 0..{len(trajs) - 1}")
    nr, nc = len(args.cases), len(args.frames)
    fig, axs = plt.subplots(nr, nc, figsize=(3.2 * nc, 2.0 * nr), squeeze=False)
    rows = []
    for i, c in enumerate(args.cases):
        ref = trajs[c]
        pred, _ = rollout_reference(gns, params, ref, timed=False)
        xr, xp = np.asarray(ref.positions), np.asarray(pred.positions)
        box = np.asarray(ref.bounds, float)
        err = float(np.linalg.norm(xp[-1] - xr[-1], axis=-1).mean())
        rows.append(dict(case=c, family=families[c], final_mean_position_error_m=err))
        run.print(f"case {c} ({families[c]}): final mean position error {err:.4f} m")
        for j, f in enumerate(args.frames):
            f = f % len(xr)
            ax = axs[i, j]
            ax.scatter(*xr[f].T, s=2, c="k")
            ax.scatter(*xp[f].T, s=2, c="tab:red")
            for o in np.asarray(ref.obstacles, float).reshape(-1, 4):
                if np.all(np.abs(o) < 1e2):  # padding boxes are parked 1 km away
                    ax.add_patch(plt.Rectangle(o[:2], o[2] - o[0], o[3] - o[1], fc="none",
                                               ec="tab:blue"))
            ax.set_xlim(*box[0])
            ax.set_ylim(*box[1])
            ax.set_aspect("equal")
            ax.tick_params(labelsize=6)
            ax.set_title(f"case {c} ({families[c]}), frame {f}", fontsize=7)
    fig.suptitle(f"{args.model}: MPM (black) and GNS (red) nodes", fontsize=8)
    fig.tight_layout()
    Path(args.png).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.png, dpi=80)
    path = run.finish(args.out, dict(model=str(args.model), data=str(args.data),
                                     frames=args.frames, png=str(args.png), rows=rows))
    run.print(f"wrote {args.png} and {path}")


if __name__ == "__main__":
    main()
