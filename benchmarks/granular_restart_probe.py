"""Restart probe of a particle GNS: when in a rollout is its final error made?

    .venv/bin/python benchmarks/granular_restart_probe.py --model gns_general \
        --data data/granular_valid.h5 [--n 24] [--families squares ...] \
        [--restarts 0 25 50 100 150 200] [--out granular_restart_probe]

For every trajectory and every restart frame k, the model is rolled out from the MPM's own
nodes at frames k-C .. k (its history; k = 0 starts, as the held-out tables do, from frames
0 .. C) to the last frame, and the final mean node position error is divided by the
trajectory's whole mean displacement (frame 0 to the last frame), the held-out tables'
normalisation, so the columns of one case compare: the error left when the truth is given
up to frame k. If restarting after the impacts (the thrown masses strike walls, obstacles
or each other within the first ~100 frames of 2.5 ms) still leaves most of the error, it is
made in the slower flow after them; if it falls away, it is made before k.

Per case: ``error_from`` (restart frame -> final error / whole displacement) and the final
error in m. Accuracy only (the protocol records the load, never refuses). Writes
``benchmarks/results/<out>.json``.
"""
from __future__ import annotations

import argparse

import numpy as np
import protocol


def restarted(ref, k: int, history: int):
    """``ref`` (a node :class:`~diffgns.trajectory.Trajectory`) from frame ``k - history``
    on, so a rollout from its first ``history + 1`` frames restarts from the truth at frame
    ``k``. ValueError when k is not in ``[history, T - 2]`` (k = history is the usual start;
    a restart needs at least one frame to predict)."""
    T = len(ref.positions)
    if not history <= k <= T - 2:
        raise ValueError(f"restart frame {k}: needs {history} <= k <= {T - 2} (history "
                         f"{history}, {T} frames)")
    s = k - history
    return ref.replace(positions=ref.positions[s:], velocities=ref.velocities[s:])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", required=True, help="model folder or shipped name")
    ap.add_argument("--data", required=True, help="dataset (.h5 with families)")
    ap.add_argument("--n", type=int, default=None, help="first n trajectories only")
    ap.add_argument("--families", nargs="+", default=None, metavar="FAMILY")
    ap.add_argument("--restarts", nargs="+", type=int, default=[0, 25, 50, 100, 150, 200],
                    help="restart frames k (model frames; 0 means the usual start, frame "
                    "C); default 0 25 50 100 150 200")
    ap.add_argument("--out", default="granular_restart_probe.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "granular_restart_probe", timed=False)  # accuracy only

    from granular_heldout import select_cases

    from diffgns.graph.data import load_trajectories
    from diffgns.graph.evaluate import rollout_reference, score
    from diffgns.graph.train_loop import load_model
    from diffgns.io.families_data import read_families

    gns, params, info = load_model(args.model)
    C = gns.config.history
    trajs, _ = load_trajectories(args.data, int(info.get("factor", 1)),
                                 int(info.get("frame_stride", 1)))
    families = list(read_families(args.data).values())
    rows = []
    for i in select_cases(families, args.n, args.families):
        ref = trajs[i]
        x = np.asarray(ref.positions)
        disp = float(np.sqrt(((x[-1] - x[0]) ** 2).sum(-1)).mean())
        row = dict(case=i, family=families[i], displacement_m=disp, error_from={},
                   error_m_from={})
        for k in args.restarts:
            k_eff = max(k, C)
            if k_eff > len(x) - 2:
                continue
            part = restarted(ref, k_eff, C)
            traj, _ = rollout_reference(gns, params, part, timed=False)
            err = score(traj, part, start=C)["final_mean_position_error_m"]
            row["error_m_from"][k] = err
            row["error_from"][k] = err / max(disp, 1e-12)
        rows.append(row)
        run.print(f"case {i:>2} {families[i]:<10} final error / displacement, restarted at "
                  + ", ".join(f"{k}: {e:.3f}" for k, e in row["error_from"].items()), tag=False)
    table = {}
    for fam in [*dict.fromkeys(r["family"] for r in rows), "all"]:
        mine = [r for r in rows if fam in ("all", r["family"])]
        table[fam] = {k: float(np.mean([r["error_from"][k] for r in mine
                                        if k in r["error_from"]]))
                      for k in args.restarts if any(k in r["error_from"] for r in mine)}
        run.print(f"{fam:<10} mean final error / displacement, restarted at "
                  + ", ".join(f"{k}: {e:.3f}" for k, e in table[fam].items()))
    path = run.finish(args.out, dict(model=str(args.model), data=str(args.data),
                                     restarts=args.restarts, rows=rows, table=table))
    run.print(f"wrote {path}")


if __name__ == "__main__":
    main()
