"""Cost of a GNS rollout under different neighbour-list settings, in one process.

    python benchmarks/gns_neighbor_list.py --model src/diffgns/models/gns_cg16_pfn \
        --data data/columns16_test.h5 --out benchmarks/results/gns_neighbor_list.json

Settings (all give the same edge set; only the candidate search and the edge-buffer head-room
differ): jax-md's cell list or the all-pairs candidate list, each with capacity multiplier
1.25 (the GNSConfig default) and the multiplier recorded in the model's config. For every
held-out case all settings are compiled first (re-allocations on overflow included, counted
as the final edge capacity), then timed in turn, round after round, so that a change in a
shared machine's load hits every setting alike. Reported per case: steady rollout seconds
(median over rounds), the edge capacity used, the largest position difference against the
first setting (summation order only), and each setting's time relative to the first one
(median of per-round ratios). Writes JSON and a bar plot next to it.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from functools import partial
from pathlib import Path

import jax
import numpy as np

from diffgns.graph.data import load_trajectories
from diffgns.graph.evaluate import reference_inputs
from diffgns.graph.gns import GNS
from diffgns.graph.neighbors import NeighborBuilder
from diffgns.graph.train_loop import load_model


def _variant(gns: GNS, multiplier: float, cell_list: bool) -> GNS:
    cfg = dataclasses.replace(gns.config, capacity_multiplier=multiplier)
    g = GNS(cfg, gns.normalizer)
    # swap the builder before the first (tracing) call; the jitted rollout reads it then
    g.neighbors = NeighborBuilder(cfg.bounds, cfg.radius, multiplier,
                                  all_pairs_max=0 if cell_list else 10**9)
    return g


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default="src/diffgns/models/gns_cg16_pfn")
    ap.add_argument("--data", default="data/columns16_test.h5")
    ap.add_argument("--out", default="benchmarks/results/gns_neighbor_list.json")
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()

    gns, params, info = load_model(args.model)
    refs, _ = load_trajectories(args.data, info.get("factor", 1), info.get("frame_stride", 1))
    mults = sorted({1.25, gns.config.capacity_multiplier}, reverse=True)
    settings = [(m, cl) for cl in (True, False) for m in mults]
    names = [f"{'cell list' if cl else 'all pairs'}, x{m:g}" for m, cl in settings]
    rows = []
    for ref in refs:
        hist, pt, mat, n_steps = reference_inputs(gns, ref)
        runs, caps, outs = [], [], []
        for m, cl in settings:
            g = _variant(gns, m, cl)
            xs, nbrs = g.rollout_safe(params, hist, pt, mat, n_steps)
            caps.append(int(nbrs.idx.shape[1]))
            outs.append(np.asarray(xs))
            runs.append(partial(g.rollout_safe, params, hist, pt, mat, n_steps, nbrs))
        times = np.zeros((args.rounds, len(settings)))
        for r in range(args.rounds):
            for i, run in enumerate(runs):
                t0 = time.perf_counter()
                jax.block_until_ready(run()[0])
                times[r, i] = time.perf_counter() - t0
        row = dict(nodes=int(hist.shape[0]), steps=int(n_steps),
                   seconds=dict(zip(names, np.median(times, 0).tolist())),
                   capacity=dict(zip(names, caps)),
                   max_position_diff_m=dict(zip(names, [float(np.abs(o - outs[0]).max())
                                                        for o in outs])),
                   time_vs_first=dict(zip(names, np.median(times / times[:, :1], 0).tolist())))
        rows.append(row)
        print(row["nodes"], {k: round(v, 3) for k, v in row["time_vs_first"].items()},
              flush=True)
    summary = {k: float(np.median([r["time_vs_first"][k] for r in rows])) for k in names}
    out = dict(command=" ".join(sys.argv), model=args.model, settings=names, rows=rows,
               summary_time_vs_first=summary, devices=str(jax.devices()),
               date=time.strftime("%Y-%m-%d %H:%M"))
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2))
    _plot(rows, names, path.with_suffix(".png"))
    print(json.dumps(summary, indent=2))


def _plot(rows, names, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.5))
    w = 0.8 / len(names)
    for i, k in enumerate(names):
        ax.bar(np.arange(len(rows)) + i * w, [r["seconds"][k] for r in rows], w, label=k)
    ax.set_xticks(np.arange(len(rows)) + 0.4 - w / 2, [f"{r['nodes']} nodes" for r in rows])
    ax.set_ylabel("steady rollout time (s)")
    ax.set_title("GNS rollout cost by neighbour-list setting (same run)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
