"""GNS training throughput (samples/s) on 1 and 2 host devices, same batch, same machine.

    .venv/bin/python benchmarks/gns_train_throughput.py --data data/columns_train.h5

Each device count runs in its own worker process (XLA's host device count is fixed at
start-up) with ``--xla_force_host_platform_device_count``; the batch is split across the
devices. A training step (forward + backward + Adam) is timed with ``benchmarks/timing.py``
(first call = compile apart, median of ``--repeats``, wall and CPU time) under
``benchmarks/protocol.py``. Writes benchmarks/results/gns_train_throughput.json.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import protocol

TAG = "GNS_TRAIN_THROUGHPUT_RESULT "


def train_step_call(data: str, batch: int):
    """(zero-argument jitted training step on one sampled batch, nodes per window). The one
    place this benchmark calls the simulator and its trainer."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from diffgns.graph.data import WindowSampler
    from diffgns.graph.train_loop import build
    from diffgns.graph.training import TrainConfig, Trainer

    gns, trajs, _ = build([data], dict(radius=0.032, latent=64, mp_steps=5, noise_std=3e-4),
                          factor=4, frame_stride=2)
    sampler = WindowSampler([t for t in trajs if t.n_particles == trajs[-1].n_particles], 5)
    b = sampler.sample(np.random.default_rng(0), batch)
    tr = Trainer(gns, TrainConfig(batch_size=batch), devices=jax.devices())  # all n devices
    C = 5
    history = jnp.swapaxes(jnp.asarray(b["positions"][0, :C + 1]), 0, 1)
    p = gns.init_network(jax.random.PRNGKey(0), (history, jnp.asarray(b["particle_type"][0]),
                                                 jnp.asarray(b["material"][0])))
    o = tr.opt.init(p)
    nb = gns.allocate(jnp.asarray(b["positions"][0, C]), extra_capacity=4)
    key = jax.random.PRNGKey(0)
    return (lambda: tr.step(p, o, b, nb, key)), int(b["positions"].shape[2])


def worker(data: str, batch: int, repeats: int) -> dict:
    import jax

    from diffgns.timing import time_call

    call, nodes = train_step_call(data, batch)
    t = time_call(call, repeats)[0]
    return dict(devices=len(jax.devices()), batch=batch, nodes=nodes, step_s=t["median_s"],
                samples_per_s=batch / t["median_s"], compile_s=t["compile_s"], timing=t)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default="data/columns_train.h5")
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--out", default="gns_train_throughput.json")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    if args.worker:  # the parent checked the load
        print(TAG + json.dumps(worker(args.data, args.batch, args.repeats)), flush=True)
        return
    run = protocol.start(args, "gns_train_throughput")
    rows = []
    for n in (1, 2):
        res, code = protocol.run_worker(
            run, [str(Path(__file__).resolve()), "--worker", "--data", args.data, "--batch",
                  str(args.batch), "--repeats", str(args.repeats)], TAG,
            xla_flags=f"--xla_force_host_platform_device_count={n}")
        if res is None:
            raise SystemExit(f"worker with {n} device(s) failed (exit {code})")
        rows.append(res)
        run.print(f"{n} device(s): {res['samples_per_s']:.2f} samples/s (step "
                  f"{res['step_s']:.3f} s, CPU {res['timing']['cpu_median_s']:.3f} s, "
                  f"compile {res['compile_s']:.1f} s)")
    payload = dict(data=args.data, rows=rows,
                   speedup_2_vs_1=rows[1]["samples_per_s"] / rows[0]["samples_per_s"])
    path = run.finish(args.out, payload)
    run.print(f"2 devices / 1 device: {payload['speedup_2_vs_1']:.2f}x; wrote {path}")


if __name__ == "__main__":
    main()
