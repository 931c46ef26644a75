"""A/B of commit 6920902 (before the simulator interface, old API) against HEAD (the one
interface): steady time of the same MPM rollout and the same GNS rollout, each round in
fresh processes, old/new alternating.

Prepare the old tree once:
    mkdir -p /tmp/old && git archive 6920902 src models | tar -x -C /tmp/old
then: python benchmarks/interface_ab.py [rounds]   (writes
benchmarks/results/interface_ab.json under the quiet-machine protocol of protocol.py)
"""
import argparse
import json
import os
import subprocess
import sys

import numpy as np
import protocol

OLD_SRC = "/tmp/old/src"
WORKER = r'''
import json, time, os, sys
import jax, jax.numpy as jnp, numpy as np
which = sys.argv[1]
old = which == "old"
from diffgns.mpm import MPM
if old:
    from diffgns.scene_builders import column_collapse
    from diffgns.graph.train_loop import load_model
else:
    from diffgns.scene.builders import column_collapse
    from diffgns.graph.train_loop import load_model
    from diffgns import rollout_jit, rollout_safe
    from diffgns.graph.gns import GNSParams
from diffgns.graph.data import coarse_grain
def med(f, n=5):
    f(); ts = []
    for _ in range(n):
        t = time.perf_counter(); jax.block_until_ready(f()); ts.append(time.perf_counter() - t)
    return float(np.median(ts))
sc = column_collapse(width=0.1, aspect_ratio=1.75, friction_angle=30.0, cells_across=16,
                     domain_length=0.8, domain_height=0.35)
sim = MPM(sc)
p = sim.params()
if old:
    s = sim.init_state()
    mpm = lambda: sim.rollout_full(p, s, n_frames=50)[0]
else:
    s = sim.init()
    mpm = lambda: rollout_jit(sim, p, s, n_frames=50)[0].positions
t_mpm = med(mpm)
model = "/tmp/old/models/gns_cg16_pfn" if old else "gns_cg16_pfn"
gns, params, info = load_model(model)
ref = (sim.rollout(p, s, 10) if old else sim.run(p, s, 10)[0])
nodes = coarse_grain(ref, info["factor"], info["frame_stride"])
hist = jnp.swapaxes(jnp.asarray(nodes.positions[:6]), 0, 1)
pt, mat = jnp.asarray(nodes.particle_type), jnp.asarray(nodes.material)
if old:
    xs, nbrs = gns.rollout_safe(params, hist, pt, mat, 120)
    g = lambda: gns.rollout_safe(params, hist, pt, mat, 120, nbrs)[0]
else:
    st = gns.init(hist, pt)
    fr, _, start = rollout_safe(gns, GNSParams(params, mat), st, 120)
    g = lambda: rollout_jit(gns, GNSParams(params, mat), start, 120)[0].positions
    xs = fr.positions[1:]
t_gns = med(g)
print(json.dumps(dict(which=which, mpm_50_frames_s=t_mpm, gns_120_frames_s=t_gns,
                      gns_final_max_x=float(np.asarray(g())[-1][..., 0].max()))))
'''

def worker(which):
    env = dict(os.environ)
    if which == "old":
        env["PYTHONPATH"] = OLD_SRC
    r = subprocess.run([sys.executable, "-c", WORKER, which], capture_output=True, text=True,
                       env=env, cwd="/tmp" if which == "old" else None)
    if r.returncode:
        raise SystemExit(r.stderr[-3000:])
    return json.loads(r.stdout.strip().splitlines()[-1])

def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rounds", type=int, nargs="?", default=3, help="A/B rounds")
    ap.add_argument("--out", default="interface_ab.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "interface_ab")
    out = dict(rows=[])
    for r in range(args.rounds):
        for w in (("old", "new") if r % 2 == 0 else ("new", "old")):
            row = worker(w)
            row["round"] = r
            out["rows"].append(row)
            run.print(row)
    for k in ("mpm_50_frames_s", "gns_120_frames_s"):
        ratios = [next(x[k] for x in out["rows"] if x["which"] == "new" and x["round"] == r) /
                  next(x[k] for x in out["rows"] if x["which"] == "old" and x["round"] == r)
                  for r in range(args.rounds)]
        out[k + "_new_over_old"] = dict(per_round=ratios, median=float(np.median(ratios)))
        run.print(k, "new/old per round", [f"{x:.3f}" for x in ratios],
                  "median", f"{np.median(ratios):.3f}")
    run.finish(args.out, out)


if __name__ == "__main__":
    main()
