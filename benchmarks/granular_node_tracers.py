"""Is a GNS node a material point? Node truth against tracers of the local particle motion.

    .venv/bin/python benchmarks/granular_node_tracers.py --data data/granular_valid.h5 \
        [--factor 16] [--sigma 0.00625] [--neighbours 24] [--n 24] \
        [--out granular_node_tracers_valid.json]

A GNS node's truth is the mean of ``factor`` particles fixed at frame 0
(:func:`diffgns.graph.data.coarse_grain`). After an impact those particles scatter (RMS
13-78 mm from their mean on the thrown-mass families, ``granular_truth_spread.py``), so the
mean might move with material far from the node: a target that no local model can follow.
This measures that directly. Every node also gets a *tracer*: it starts at the node's frame-0
position and moves, frame by frame, with the particle displacement field around it (a
Gaussian-weighted mean over its ``--neighbours`` nearest particles, standard deviation
``--sigma`` m: the continuum's material point at that smoothing scale). The final distance
between each node's truth and its tracer, relative to the mean node displacement, is the
metric of the held-out tables (``final_position_error_rel_displacement``): if it is small
against a model's error, the node truth is a local quantity, and (triangle inequality) a
model's distance from the tracers differs from its score by at most this gap.

Accuracy only (the protocol records the load and never refuses); numpy and scipy, no JAX.
"""
from __future__ import annotations

import argparse

import numpy as np
import protocol


def tracers(x: np.ndarray, start: np.ndarray, sigma: float, k: int) -> np.ndarray:
    """(T, M, d) positions of tracers starting at ``start`` (M, d), moved each frame by the
    Gaussian-weighted (std ``sigma``, m) mean displacement of their ``k`` nearest particles
    of ``x`` (T, N, d), m."""
    from scipy.spatial import cKDTree

    k = min(k, x.shape[1])
    out = np.empty((len(x), *start.shape))
    out[0] = start
    for f in range(len(x) - 1):
        d, idx = cKDTree(x[f]).query(out[f], k=k)
        w = np.exp(-0.5 * (d.reshape(len(start), k) / sigma) ** 2)
        w /= np.maximum(w.sum(1, keepdims=True), 1e-300)
        step = x[f + 1][idx] - x[f][idx]  # (M, k, d)
        out[f + 1] = out[f] + (w[..., None] * step.reshape(len(start), k, -1)).sum(1)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, help="dataset of family scenes (.h5)")
    ap.add_argument("--factor", type=int, default=16, help="particles per node")
    ap.add_argument("--sigma", type=float, default=0.1 / 16,
                    help="tracer kernel standard deviation, m (default one MPM cell)")
    ap.add_argument("--neighbours", type=int, default=24)
    ap.add_argument("--n", type=int, default=None, help="first n trajectories only")
    ap.add_argument("--out", default="granular_node_tracers.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    if not (args.sigma > 0 and args.neighbours >= 1 and args.factor >= 1):
        raise SystemExit("--sigma must be > 0 m, --neighbours and --factor >= 1")
    run = protocol.start(args, "granular_node_tracers", timed=False)

    from diffgns.graph.data import coarse_grain
    from diffgns.graph.evaluate import score
    from diffgns.io.dataset import iter_dataset
    from diffgns.io.families_data import read_families

    families = list(read_families(args.data).values())
    rows = []
    for i, traj in enumerate(iter_dataset(args.data)):
        if args.n is not None and i >= args.n:
            break
        x = np.asarray(traj.positions, np.float64)
        ref = coarse_grain(traj, args.factor)
        nodes = np.asarray(ref.positions, np.float64)
        tr = tracers(x, nodes[0], args.sigma, args.neighbours)
        s = score(ref.replace(positions=tr), ref.replace(positions=nodes))  # the tables' metric
        gap = np.linalg.norm(tr[-1] - nodes[-1], axis=-1)
        rows.append(dict(case=i, family=families[i], nodes=len(nodes[0]),
                         mean_displacement_m=s["final_mean_displacement_m"],
                         tracer_gap_rel_displacement=s["final_position_error_rel_displacement"],
                         tracer_gap_p99_m=float(np.percentile(gap, 99))))
        run.print(f"{i:3d} {families[i]:<10} displacement "
                  f"{1e3 * rows[-1]['mean_displacement_m']:6.1f} mm, node truth to tracer "
                  f"{rows[-1]['tracer_gap_rel_displacement']:.3f} of it "
                  f"(99th percentile {1e3 * rows[-1]['tracer_gap_p99_m']:.1f} mm)", tag=False)
    table = {}
    for fam in [*dict.fromkeys(r["family"] for r in rows), "all"]:
        g = [r["tracer_gap_rel_displacement"] for r in rows if fam in (r["family"], "all")]
        table[fam] = dict(cases=len(g), mean=float(np.mean(g)), max=float(np.max(g)))
        run.print(f"{fam:<10} {len(g):>3} cases: node truth to tracer, mean "
                  f"{table[fam]['mean']:.3f}, max {table[fam]['max']:.3f} of the displacement")
    path = run.finish(args.out, dict(data=args.data, factor=args.factor, sigma_m=args.sigma,
                                     neighbours=args.neighbours, rows=rows, table=table))
    run.print(f"wrote {path}")


if __name__ == "__main__":
    main()
