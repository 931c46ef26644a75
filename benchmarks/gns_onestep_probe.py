"""One-step probe of a particle GNS: does it predict the vertical acceleration of a
collapsing column's top nodes from the true history?

    .venv/bin/python benchmarks/gns_onestep_probe.py --model checkpoints/general/s2/model \
        --data data/granular_valid.h5 --cases 1 5 9 [--starts 0 4 10 20] [--top 8]

For every case and start frame t0, the model takes the reference's frames t0 .. t0+C (its
own nodes and frame stride; C + 1 = history + 1 frames) and makes one step; printed are the
mean vertical acceleration (mm/frame^2) of the ``--top`` highest nodes of the initial frame,
predicted and the reference's (x_{t0+C+1} - 2 x_{t0+C} + x_{t0+C-1}). A rollout error that
one step already shows is the model's fit, not an accumulation. Accuracy only (the protocol
records the load, never refuses). Writes ``benchmarks/results/<out>``.
"""
from __future__ import annotations

import argparse

import numpy as np
import protocol


def probe(model: str, data: str, cases: list[int], starts: list[int], top: int) -> list[dict]:
    """Rows (case, start, predicted and reference mean vertical acceleration, mm/frame^2).
    The one place this script calls the simulator."""
    from diffgns.graph.data import load_trajectories
    from diffgns.graph.evaluate import teacher_forced
    from diffgns.graph.train_loop import load_model

    gns0, params, info = load_model(model)
    refs, _ = load_trajectories(data, int(info.get("factor", 1)),
                                int(info.get("frame_stride", 1)))
    C = gns0.config.history
    rows = []
    for i in cases:
        ref = refs[i]
        p = np.asarray(ref.positions)
        ids = np.argsort(p[0, :, 1])[-top:]
        frames, x = teacher_forced(gns0, params, ref, [t0 + C + 1 for t0 in starts])
        for t0, t, xt in zip(starts, frames, x):
            last, prev = p[t - 1, ids, 1], p[t - 2, ids, 1]
            rows.append(dict(case=i, start=t0,
                             predicted_mm=1e3 * float(np.mean(xt[ids, 1] - 2 * last + prev)),
                             reference_mm=1e3 * float(np.mean(p[t, ids, 1]
                                                              - 2 * last + prev))))
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--cases", type=int, nargs="+", required=True)
    ap.add_argument("--starts", type=int, nargs="+", default=[0, 4, 10, 20])
    ap.add_argument("--top", type=int, default=8)
    ap.add_argument("--out", default="gns_onestep_probe.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "gns_onestep_probe", timed=False)
    rows = probe(args.model, args.data, args.cases, args.starts, args.top)
    for r in rows:
        run.print(f"case {r['case']:3d} start {r['start']:3d}: predicted "
                  f"{r['predicted_mm']:+.3f}  reference {r['reference_mm']:+.3f} mm/frame^2")
    run.print(f"wrote {run.finish(args.out, dict(model=args.model, data=args.data, rows=rows))}")


if __name__ == "__main__":
    main()
