"""Inference cost of one GNS step across configurations (latent, message-passing steps,
attention, coarse-graining) on the same particle block, in one run.

    .venv/bin/python benchmarks/gns_configs_cost.py [--side 44] [--repeats 7]

A block of N particles on a lattice; coarse-graining factor g keeps N/g nodes with spacing
sqrt(g) times larger and the radius scaled alike (same ~20 neighbours). Every configuration
is compiled first (first call timed apart), then timed in interleaved rounds (one jitted
step -- neighbour update + network -- of each configuration per round, the order
alternating), median per configuration, wall and CPU time (``benchmarks/timing.py``), under
``benchmarks/protocol.py``. Writes benchmarks/results/gns_configs_cost.json. Accuracy per
configuration needs a trained model each and is not measured here.
"""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np
import protocol
from protocol import warm_up_jax

from diffgns.graph.features import ParticleStats
from diffgns.graph.gns import GNS, GNSConfig
from diffgns.timing import interleave

CONFIGS = [  # (latent, mp_steps, attention, coarse-grain factor)
    (128, 10, False, 1), (128, 10, True, 1), (64, 5, False, 1), (64, 5, True, 1),
    (32, 3, False, 1), (64, 5, False, 4), (128, 10, False, 4),
]
SPACING = 0.005  # m, before coarse-graining


def lattice(n_side: int, spacing: float) -> np.ndarray:
    g = np.stack(np.meshgrid(np.arange(n_side), np.arange(n_side), indexing="ij"), -1)
    return (0.1 + spacing * (g.reshape(-1, 2) + 0.5)).astype(np.float32)


def step_call(latent: int, mp: int, att: bool, x: np.ndarray, radius: float):
    """(zero-argument jitted GNS step at rest on the nodes ``x``, edge count). The one place
    this benchmark calls the simulator."""
    hist = np.repeat(x[:, None], 6, 1)
    cfg = GNSConfig(bounds=((0.0, 1.0), (0.0, 1.0)), radius=radius, latent=latent,
                    mp_steps=mp, attention=att)
    gns = GNS(cfg, ParticleStats.identity())
    pt, mat = np.full(len(x), 6, np.int32), np.full(len(x), 0.6, np.float32)
    params = gns.init_network(jax.random.PRNGKey(0), (jnp.asarray(hist), pt, mat))
    nbrs = gns.allocate(jnp.asarray(x))
    step = jax.jit(lambda p, hh, nb: gns.advance(p, hh, pt, mat, nb)[0])
    n_edges = int(np.asarray(nbrs.idx[0] < len(x)).sum()) + len(x)
    return (lambda: step(params, hist, nbrs)), n_edges


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--side", type=int, default=44, help="particles per side (N = side^2)")
    ap.add_argument("--repeats", type=int, default=7, help="interleaved rounds")
    ap.add_argument("--out", default="gns_configs_cost.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "gns_configs_cost")
    warm_up_jax()
    calls, rows = {}, {}
    for latent, mp, att, g in CONFIGS:
        side = int(round(args.side / np.sqrt(g)))
        sp = SPACING * np.sqrt(g)
        x = lattice(side, sp)
        name = f"latent{latent}_mp{mp}_{'attention' if att else 'sum'}_g{g}"
        calls[name], n_edges = step_call(latent, mp, att, x, 2.5 * sp)
        rows[name] = dict(latent=latent, mp_steps=mp, attention=att, coarse_grain=g,
                          nodes=len(x), edges=n_edges)
    res = interleave(calls, args.repeats)
    for name, row in rows.items():
        t = res.summary(name)
        row.update(step_ms=1e3 * t["median_s"], step_cpu_ms=1e3 * t["cpu_median_s"],
                   compile_s=t["compile_s"], timing=t)
        run.print(f"latent {row['latent']:3d} mp {row['mp_steps']:2d} attention "
                  f"{row['attention']!s:5} g {row['coarse_grain']}: {row['nodes']:5d} nodes "
                  f"{row['edges']:6d} edges  {row['step_ms']:8.1f} ms/step "
                  f"(CPU {row['step_cpu_ms']:.1f} ms; compile {row['compile_s']:.1f} s)")
    payload = dict(rows=list(rows.values()), rounds=res.to_json()["rounds"],
                   repeats=args.repeats, side=args.side)
    run.print(f"wrote {run.finish(args.out, payload)}")


if __name__ == "__main__":
    main()
