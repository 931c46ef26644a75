"""Cost of a GNS rollout under different neighbour-list settings, in one process.

    .venv/bin/python benchmarks/gns_neighbor_list.py --model models/gns_cg16_pfn \
        --data data/columns16_test.h5 --out benchmarks/results/gns_neighbor_list.json

Settings (all give the same edge set; only the candidate search and the edge-buffer head-room
differ): jax-md's cell list or the all-pairs candidate list, each with capacity multiplier
1.25 (the GNSConfig default) and the multiplier recorded in the model's config. For every
held-out case all settings are compiled first (re-allocations on overflow included, counted
as the final edge capacity), then timed in interleaved rounds (``benchmarks/timing.py``; the
order alternates round by round), so that a change in a shared machine's load hits every
setting alike, under ``benchmarks/protocol.py``. Reported per case: steady rollout seconds
(median over rounds, wall and CPU), the edge capacity used, the largest position difference
against the first setting (summation order only), and each setting's time relative to the
first one (median of per-round ratios). Writes JSON and a bar plot next to it.
"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import protocol
from protocol import warm_up_jax

from diffgns.graph.data import load_trajectories
from diffgns.graph.evaluate import reference_inputs
from diffgns.graph.gns import GNS
from diffgns.graph.neighbors import NeighborBuilder
from diffgns.graph.train_loop import load_model
from diffgns.interface import rollout_jit, rollout_safe
from diffgns.timing import interleave


def _variant(gns: GNS, multiplier: float, cell_list: bool) -> GNS:
    cfg = dataclasses.replace(gns.config, capacity_multiplier=multiplier)
    g = GNS(cfg, gns.normalizer, gns.frame_dt)
    # swap the builder before the first (tracing) call; the jitted rollout reads it then
    g.neighbors = NeighborBuilder(cfg.bounds, cfg.radius, multiplier,
                                  all_pairs_max=0 if cell_list else 10**9)
    return g


def rollout_call(gns: GNS, params, ref, multiplier: float, cell_list: bool):
    """(zero-argument compiled rollout with a sized neighbour list, edge capacity, positions
    of the sizing run). The one place this benchmark calls the simulator."""
    g = _variant(gns, multiplier, cell_list)
    p, state, n_steps = reference_inputs(g, params, ref)
    frames, _, start = rollout_safe(g, p, state, n_steps)  # sizes the neighbour list
    call = lambda: rollout_jit(g, p, start, n_frames=n_steps)[0].positions  # noqa: E731
    xs = np.asarray(frames.positions[1:])
    return call, int(start.nbrs.idx.shape[1]), xs, int(xs.shape[1]), int(n_steps)


def measure_case(gns, params, ref, settings, names, rounds: int) -> dict:
    calls, caps, outs = {}, [], []
    for name, (m, cl) in zip(names, settings):
        calls[name], cap, xs, nodes, steps = rollout_call(gns, params, ref, m, cl)
        caps.append(cap)
        outs.append(xs)
    res = interleave(calls, rounds)
    return dict(nodes=nodes, steps=steps,
                seconds={k: res.summary(k)["median_s"] for k in names},
                cpu_seconds={k: res.summary(k)["cpu_median_s"] for k in names},
                capacity=dict(zip(names, caps)),
                max_position_diff_m=dict(zip(names, [float(np.abs(o - outs[0]).max())
                                                     for o in outs])),
                time_vs_first={k: res.ratio(k, names[0]) for k in names},
                rounds=res.to_json()["rounds"])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", default="models/gns_cg16_pfn")
    ap.add_argument("--data", default="data/columns16_test.h5")
    ap.add_argument("--out", default="benchmarks/results/gns_neighbor_list.json")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--cases", type=int, default=None, help="only the first N cases")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "gns_neighbor_list")
    warm_up_jax()
    gns, params, info = load_model(args.model)
    refs, _ = load_trajectories(args.data, info.get("factor", 1), info.get("frame_stride", 1))
    mults = sorted({1.25, gns.config.capacity_multiplier}, reverse=True)
    settings = [(m, cl) for cl in (True, False) for m in mults]
    names = [f"{'cell list' if cl else 'all pairs'}, x{m:g}" for m, cl in settings]
    rows = []
    for ref in refs[: args.cases]:
        rows.append(measure_case(gns, params, ref, settings, names, args.rounds))
        run.print(rows[-1]["nodes"], "nodes, time vs first:",
                  {k: round(v, 3) for k, v in rows[-1]["time_vs_first"].items()})
    summary = {k: float(np.median([r["time_vs_first"][k] for r in rows])) for k in names}
    payload = dict(model=args.model, data=args.data, settings=names, rows=rows,
                   summary_time_vs_first=summary)
    path = run.finish(args.out, payload, lambda p: _plot(rows, names, p.with_suffix(".png")))
    run.print("median time vs first:", {k: round(v, 3) for k, v in summary.items()})
    run.print(f"wrote {path}")


def _plot(rows, names, path):
    plt = protocol.use_agg()
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
