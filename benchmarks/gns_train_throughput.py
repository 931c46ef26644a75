"""GNS training throughput (samples/s) on 1 and 2 host devices, same batch, same machine.

    python benchmarks/gns_train_throughput.py --data data/columns_train.h5

Each device count runs in its own process (XLA's host device count is fixed at start-up)
with ``--xla_force_host_platform_device_count``; the batch is split across the devices.
Writes benchmarks/results/gns_train_throughput.json.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

CHILD = r"""
import json, os, sys, time
import jax, jax.numpy as jnp, numpy as np
from diffgns.graph.data import WindowSampler
from diffgns.graph.train_loop import build
from diffgns.graph.training import Trainer, TrainConfig
data, batch, reps = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
gns, trajs, _ = build([data], dict(radius=0.032, latent=64, mp_steps=5, noise_std=3e-4),
                      factor=4, frame_stride=2)
sampler = WindowSampler([t for t in trajs if t.n_particles == trajs[-1].n_particles], 5)
b = sampler.sample(np.random.default_rng(0), batch)
tr = Trainer(gns, TrainConfig(batch_size=batch))
C = 5
p = gns.init(jax.random.PRNGKey(0), (jnp.swapaxes(jnp.asarray(b["positions"][0, :C + 1]), 0, 1),
                                     jnp.asarray(b["particle_type"][0]),
                                     jnp.asarray(b["material"][0])))
o = tr.opt.init(p)
nb = gns.allocate(jnp.asarray(b["positions"][0, C]), extra_capacity=4)
key = jax.random.PRNGKey(0)
t0 = time.perf_counter(); jax.block_until_ready(tr.step(p, o, b, nb, key))
first = time.perf_counter() - t0
ts = []
for _ in range(reps):
    t0 = time.perf_counter(); jax.block_until_ready(tr.step(p, o, b, nb, key))
    ts.append(time.perf_counter() - t0)
med = float(np.median(ts))
print(json.dumps(dict(devices=len(jax.devices()), batch=batch, nodes=int(b["positions"].shape[2]),
                      step_s=med, samples_per_s=batch / med, compile_s=first - med)))
"""


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="data/columns_train.h5")
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--out", default="benchmarks/results/gns_train_throughput.json")
    args = ap.parse_args()
    rows = []
    for n in (1, 2):
        env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={n}")
        r = subprocess.run([sys.executable, "-c", CHILD, args.data, str(args.batch),
                            str(args.repeats)], capture_output=True, text=True, env=env)
        if r.returncode:
            sys.exit(r.stderr[-3000:])
        rows.append(json.loads(r.stdout.strip().splitlines()[-1]))
        print(rows[-1], flush=True)
    out = dict(command=" ".join(sys.argv), rows=rows, load=os.getloadavg(),
               speedup_2_vs_1=rows[1]["samples_per_s"] / rows[0]["samples_per_s"],
               date=time.strftime("%Y-%m-%d %H:%M"))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2))
    print(f"2 devices / 1 device: {out['speedup_2_vs_1']:.2f}x")


if __name__ == "__main__":
    main()
