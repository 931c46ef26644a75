"""Two processes against one on this machine: GNS training throughput and dataset generation.

    python benchmarks/distributed_scaling.py --steps 20 --out benchmarks/results/distributed.json

Training: ``--processes`` 1 and 2 (jax.distributed on localhost, gloo CPU collectives, one CPU
device per process), the same global batch; each process times ``--steps`` optimiser steps
after two warm-up steps (compilation), process 0 reports. Dataset: ``diffgns dataset --kind
squares`` in one process against two ``--shard i/2`` processes plus the merge, wall time.
Also prints the bytes all-reduced per step (parameter count x 4, float32). The figures are
indicative: ``uptime`` is recorded before and after, and a loaded machine distorts them.
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time

import protocol


def _port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _worker(args) -> None:
    """One process of the training measurement."""
    from diffgns.distributed import initialize, is_main, process_count

    if args.num_processes > 1:
        initialize(args.coordinator, args.num_processes, args.process_id)
    import jax
    import jax.numpy as jnp

    from diffgns.graph.data import WindowSampler
    from diffgns.graph.fit import TrainConfig, step_rng
    from diffgns.graph.train_loop import build
    from diffgns.graph.training import NeighborLists, Trainer, step_with_reallocation

    tcfg = TrainConfig(steps=args.steps + 2, batch_size=args.batch)
    gns_kw = dict(radius=args.radius, latent=args.latent, mp_steps=args.mp_steps,
                  mlp_layers=2, noise_std=6.7e-4)
    gns, trajs, _ = build([args.data], gns_kw, args.coarse_grain)
    C = gns.config.history
    t0 = trajs[0]
    params = gns.init_network(jax.random.PRNGKey(0), (
        jnp.swapaxes(jnp.asarray(t0.positions[: C + 1]), 0, 1), jnp.asarray(t0.particle_type),
        jnp.asarray(t0.material)))
    n_params = sum(int(x.size) for x in jax.tree.leaves(params))
    trainer, nbrs = Trainer(gns, tcfg), NeighborLists()
    sampler = WindowSampler(trajs, C, 0)
    opt = trainer.opt.init(params)
    times = []
    for step in range(tcfg.steps):
        rng, key = step_rng(0, step)
        batch = sampler.sample(rng, tcfg.batch_size)
        t = time.perf_counter()
        params, opt, loss = step_with_reallocation(trainer, params, opt, batch, nbrs, key)
        jax.block_until_ready(params)
        times.append(time.perf_counter() - t)
    if is_main():
        steady = times[2:]
        print(json.dumps(dict(processes=process_count(), batch=args.batch,
                              n_params=n_params, allreduce_bytes=4 * n_params,
                              nodes=int(t0.positions.shape[1]) // args.coarse_grain,
                              step_s_median=sorted(steady)[len(steady) // 2],
                              steps_per_s=len(steady) / sum(steady))), flush=True)


def _run(cmd: list[list[str]], cwd=None) -> tuple[float, list[str]]:
    t = time.perf_counter()
    procs = [subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              cwd=cwd) for c in cmd]
    outs = [p.communicate()[0] for p in procs]
    for p, o in zip(procs, outs):
        if p.returncode:
            raise SystemExit(f"failed ({p.returncode}):\n{o[-2000:]}")
    return time.perf_counter() - t, outs


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--coordinator"), p.add_argument("--process-id", type=int, default=0)
    p.add_argument("--num-processes", type=int, default=1)
    p.add_argument("--data", default=None, help="training .h5 (default: a squares set made "
                   "by the dataset measurement)")
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--batch", type=int, default=2)
    p.add_argument("--latent", type=int, default=128)
    p.add_argument("--mp-steps", type=int, default=10)
    p.add_argument("--radius", type=float, default=0.025)
    p.add_argument("--coarse-grain", type=int, default=1)
    p.add_argument("--n", type=int, default=4, help="squares flows of the dataset measurement")
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--dx", type=float, default=0.02, help="squares: grid cell size, m")
    p.add_argument("--out", default="distributed_scaling.json",
                   help="JSON results file (benchmarks/results/<out> unless it has a folder)")
    protocol.add_arguments(p)
    args = p.parse_args()
    if args.worker:
        return _worker(args)
    run = protocol.start(args, "distributed_scaling")  # load, steal, commit; refuses if loaded
    py = [sys.executable]
    res: dict = {}
    with tempfile.TemporaryDirectory() as d:
        ds = py + ["-m", "diffgns.cli", "dataset", "--kind", "squares", "--n", str(args.n),
                   "--frames", str(args.frames), "--dx", str(args.dx)]
        one, _ = _run([ds + ["--out", f"{d}/one.h5"]])
        two, _ = _run([ds + ["--out", f"{d}/two.h5", "--shard", f"{i}/2"] for i in range(2)])
        merge, _ = _run([py + ["-m", "diffgns.cli", "dataset", "--merge",
                               f"{d}/two.shard-0-of-2.h5", f"{d}/two.shard-1-of-2.h5",
                               "--out", f"{d}/two.h5"]])
        res["dataset"] = dict(n=args.n, frames=args.frames, one_process_s=one,
                              two_processes_s=two, merge_s=merge)
        data = args.data or f"{d}/one.h5"
        worker = py + [__file__, "--worker", "--data", data, "--steps", str(args.steps),
                       "--batch", str(args.batch), "--latent", str(args.latent),
                       "--mp-steps", str(args.mp_steps), "--radius", str(args.radius),
                       "--coarse-grain", str(args.coarse_grain)]
        _, outs = _run([worker])
        res["train_1"] = json.loads(outs[0].strip().splitlines()[-1])
        port = _port()
        _, outs = _run([worker + ["--coordinator", f"localhost:{port}", "--num-processes",
                                  "2", "--process-id", str(i)] for i in range(2)])
        res["train_2"] = json.loads([ln for ln in outs[0].splitlines()
                                     if ln.startswith("{")][-1])
    run.print(json.dumps(res, indent=2))
    run.print(f"wrote {run.finish(args.out, res)}")


if __name__ == "__main__":
    os.environ.pop("XLA_FLAGS", None)
    main()
