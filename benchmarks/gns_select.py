"""Score candidate GNS models on validation collapses for model selection.

    python benchmarks/gns_select.py src/diffgns/models/gns_cg16_pfn runs/s9_avg_k4 \
        --data data/columns16_valid.h5 data/columns16_valid2.h5 --out selection.json

For every model: its rollouts on every collapse of every ``--data`` file (from the first
``history + 1`` node frames), the mean runout error and the mean final position error over
all of them, and their sum -- the selection rule used for the shipped ``gns_cg16_pfn``
stages (smaller sum wins). No timing: the models share one network cost, and the protocol
(``benchmarks/protocol.py``) records the load, commit and machine without refusing a loaded
machine.
"""
from __future__ import annotations

import argparse

import numpy as np
import protocol

from diffgns.graph.data import load_trajectories
from diffgns.graph.evaluate import evaluate
from diffgns.graph.train_loop import load_model


def model_rows(path: str, data: list[str]) -> list[dict]:
    """Per-collapse scores of model ``path`` on every file of ``data``. The one place this
    script calls the simulator."""
    gns, params, info = load_model(path)
    rows = []
    for f in data:
        refs, _ = load_trajectories(f, info.get("factor", 1), info.get("frame_stride", 1))
        rows += evaluate(gns, params, refs)["rows"]
    return rows


def score_model(path: str, data: list[str]) -> dict:
    """Mean runout / final position error of model ``path`` over all collapses in ``data``."""
    rows = model_rows(path, data)
    runout = float(np.mean([r["runout_rel_error"] for r in rows]))
    position = float(np.mean([r["final_position_error_rel_displacement"] for r in rows]))
    return dict(model=path, cases=len(rows), runout=runout, position=position,
                sum=runout + position, rows=rows)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("models", nargs="+")
    ap.add_argument("--data", nargs="+", required=True, help="validation datasets (.h5)")
    ap.add_argument("--out", default=None, help="optional JSON with per-case rows")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "gns_select", timed=False)
    results = []
    for m in args.models:
        r = score_model(m, args.data)
        results.append(r)
        run.print(f"{m}: {r['cases']} cases, runout {r['runout']:.5f}, position "
                  f"{r['position']:.5f}, sum {r['sum']:.5f}")
    best = min(results, key=lambda r: r["sum"])
    run.print(f"smallest sum: {best['model']}")
    if args.out:
        run.write(args.out, dict(data=args.data, results=results, best=best["model"]))


if __name__ == "__main__":
    main()
