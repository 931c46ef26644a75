"""Inference cost of one GNS step across configurations (latent, message-passing steps,
attention, coarse-graining) on the same particle block, in one run.

    python benchmarks/gns_configs_cost.py

A block of N particles on a lattice; coarse-graining factor g keeps N/g nodes with spacing
sqrt(g) times larger and the radius scaled alike (same ~20 neighbours). Median of
``--repeats`` jitted steps (neighbour update + network), compile reported apart.
Writes benchmarks/results/gns_configs_cost.json. Accuracy per configuration needs a trained
model each and is not measured here.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.graph.features import Normalizers
from diffgns.graph.gns import GNS, GNSConfig

CONFIGS = [  # (latent, mp_steps, attention, coarse-grain factor)
    (128, 10, False, 1), (128, 10, True, 1), (64, 5, False, 1), (64, 5, True, 1),
    (32, 3, False, 1), (64, 5, False, 4), (128, 10, False, 4),
]


def block(n_side: int, spacing: float) -> np.ndarray:
    g = np.stack(np.meshgrid(np.arange(n_side), np.arange(n_side), indexing="ij"), -1)
    return (0.1 + spacing * (g.reshape(-1, 2) + 0.5)).astype(np.float32)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--side", type=int, default=44, help="particles per side (N = side^2)")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", default="benchmarks/results/gns_configs_cost.json")
    args = ap.parse_args()
    h, rows = 0.005, []
    for latent, mp, att, g in CONFIGS:
        side = int(round(args.side / np.sqrt(g)))
        sp = h * np.sqrt(g)
        x = block(side, sp)
        hist = np.repeat(x[:, None], 6, 1)
        cfg = GNSConfig(bounds=((0.0, 1.0), (0.0, 1.0)), radius=2.5 * sp, latent=latent,
                        mp_steps=mp, attention=att)
        gns = GNS(cfg, Normalizers.identity())
        pt, mat = np.full(len(x), 6, np.int32), np.full(len(x), 0.6, np.float32)
        params = gns.init(jax.random.PRNGKey(0), (jnp.asarray(hist), pt, mat))
        nbrs = gns.allocate(jnp.asarray(x))
        step = jax.jit(lambda p, hh, nb, gns=gns, pt=pt, mat=mat: gns.step(p, hh, pt, mat, nb)[0])
        t0 = time.perf_counter()
        jax.block_until_ready(step(params, hist, nbrs))
        first = time.perf_counter() - t0
        ts = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(step(params, hist, nbrs))
            ts.append(time.perf_counter() - t0)
        med = float(np.median(ts))
        n_edges = int(np.asarray(nbrs.idx[0] < len(x)).sum()) + len(x)
        rows.append(dict(latent=latent, mp_steps=mp, attention=att, coarse_grain=g,
                         nodes=len(x), edges=n_edges, step_ms=1e3 * med,
                         compile_s=first - med))
        print(f"latent {latent:3d} mp {mp:2d} attention {att!s:5} g {g}: {len(x):5d} nodes "
              f"{n_edges:6d} edges  {1e3 * med:8.1f} ms/step  (compile {first - med:.1f} s)",
              flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(dict(command=" ".join(sys.argv), rows=rows,
                                              load=os.getloadavg(),
                                              date=time.strftime("%Y-%m-%d %H:%M")), indent=2))


if __name__ == "__main__":
    main()
