"""Memory and time of gradients through GNS rollouts, with and without jax.checkpoint.

    .venv/bin/python benchmarks/inverse_gns_memory.py [--frames 30 100 120] [--blocks 10 2]
        [--repeats 3] [--aspect-ratio 1.75] [--model gns_columns] [--note TEXT]

Model: ``--model``, default ``gns_columns`` (latent 64, 5 message-passing steps; the model of
the published table). Scene: the main inverse example's column at the model's resolution
(``ColumnCase.from_model``; for ``gns_columns`` 448 MPM particles -> 112 GNS nodes in the
0.8 x 0.35 m box); the 6 initial frames are observed MPM frames. Loss: the inverse
example's ``(soft runout(x_T) - observed soft runout(x_T))^2`` at the last predicted frame T;
gradient with respect to the friction angle (through tan phi, the material feature of every
node). 120 predicted frames (0.6 s) is the full rollout to rest.

For every frame count and checkpoint in {none, blocks of each of ``--blocks`` frames}, in a fresh
process: the forward and gradient programs are compiled ahead of time (``lower`` +
``compile``, timed on their own) and XLA's ``memory_analysis()`` is stored (temp, argument,
output; MB = 1e6 bytes); then one warm-up call and ``--repeats`` steady calls of each
(``block_until_ready``; median reported, wall and CPU: ``benchmarks/timing.py``); the
process's peak RSS (``getrusage(RUSAGE_SELF).ru_maxrss``) after compiling and at the end. The
load check and thread setting are the parent's (``benchmarks/protocol.py``).

Writes ``benchmarks/results/inverse_gns_memory.json`` and ``.png``.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import protocol
from protocol import warm_up_jax

from diffgns.memory import compile_ahead, peak_rss_mb
from diffgns.timing import measure, no_sync, time_call

TAG = "INVERSE_GNS_MEMORY_RESULT "


def log(msg: str) -> None:
    protocol.worker_run("inverse_gns_memory").print(msg, file=sys.stderr)


def loss_fn(n_steps: int, block: int | None, aspect_ratio: float, model: str):
    """(loss(phi) = soft-runout misfit of a GNS rollout of ``n_steps`` frames, nodes). The
    one place this benchmark calls the simulator."""
    from diffgns.inverse import objectives
    from diffgns.inverse.simulators import Column, ColumnCase, gns_simulator, model_info

    col = Column(ColumnCase.from_model(model_info(model), aspect_ratio))
    observed = col.observation({"friction_angle": 30.0})
    sim = gns_simulator(col, model, observed=observed, checkpoint_block=block, n_steps=n_steps)
    obj = objectives.runout_loss(observed[:sim.C + 1 + n_steps], method="softmax")

    def loss(phi):
        pos, overflow = sim.simulate({"friction_angle": phi})
        return obj(pos)

    return loss, col.n_nodes


def run_case(n_steps: int, block: int | None, repeats: int, aspect_ratio: float,
             model: str) -> dict:
    import jax
    import jax.numpy as jnp

    warm_up_jax()
    loss, nodes = loss_fn(n_steps, block, aspect_ratio, model)
    phi = jnp.asarray(45.0, jnp.float32)
    res = {"n_steps": n_steps, "block": block, "checkpoint": bool(block), "nodes": nodes,
           "loadavg_start": list(os.getloadavg())}
    exes = {}
    for name, fn in (("forward", loss), ("gradient", jax.value_and_grad(loss))):
        exes[name], res[name] = compile_ahead(jax.jit(fn), phi)
        lw, cw = res[name]["lower_s"], res[name]["compile_s"]
        log(f"[{n_steps} steps, block {block}] {name}: compile {lw + cw:.1f} s, XLA temp "
            f"{res[name]['memory']['temp_mb']:.1f} MB")
    res["peak_rss_after_compile_mb"] = peak_rss_mb()
    for name, exe in exes.items():
        t, out = time_call(lambda exe=exe: exe(phi), repeats)
        t.pop("compile_s")  # the executables are compiled: the first call is a warm-up
        res[name].update(t)
        if name == "gradient":
            res["loss"], res["dloss_dphi"] = float(out[0]), float(out[1])
        log(f"[{n_steps} steps, block {block}] {name}: first {t['first_call_s']:.2f} s, "
            f"median {t['median_s']:.2f} s (CPU {t['cpu_median_s']:.2f} s)")
    res["grad_over_forward"] = res["gradient"]["median_s"] / res["forward"]["median_s"]
    res["peak_rss_mb"] = peak_rss_mb()
    res["loadavg_end"] = list(os.getloadavg())
    return res


def spawn(run: protocol.Run, n_steps: int, block: int | None, args) -> dict:
    cmd = [str(Path(__file__).resolve()), "--case", str(n_steps), str(block or 0),
           "--repeats", str(args.repeats), "--aspect-ratio", str(args.aspect_ratio),
           "--model", args.model]
    case, (res, code) = measure(lambda: protocol.run_worker(run, cmd, TAG), sync=no_sync)
    if res is None:
        res = {"n_steps": n_steps, "block": block, "checkpoint": bool(block),
               "error": f"worker exited with code {code}"}
    res["case_wall_s"], res["case_cpu_s"] = case.wall_s, case.cpu_s
    return res


def table(rows) -> str:
    head = (f"{'frames':>6} {'ckpt':>5} {'grad temp MB':>12} {'fwd temp MB':>11} "
            f"{'compile g s':>11} {'grad s':>7} {'fwd s':>6} {'g/f':>5} {'RSS MB':>7}")
    lines = [head, "-" * len(head)]
    for r in rows:
        if "error" in r:
            lines.append(f"{r['n_steps']:>6} {r['block'] or '-':>5}  ERROR {r['error']}")
            continue
        g, f = r["gradient"], r["forward"]
        lines.append(f"{r['n_steps']:>6} {r['block'] or '-':>5} {g['memory']['temp_mb']:>12.1f} "
                     f"{f['memory']['temp_mb']:>11.1f} {g['lower_s'] + g['compile_s']:>11.1f} "
                     f"{g['median_s']:>7.2f} {f['median_s']:>6.2f} "
                     f"{r['grad_over_forward']:>5.2f} {r['peak_rss_mb']:>7.0f}")
    lines.append("frames = predicted GNS frames (5 ms) after 6 given; ckpt = jax.checkpoint block "
                 "(frames); temp = XLA temp allocation; times: median steady call; RSS = peak "
                 "RSS of the case's own process (MB = 1e6 bytes)")
    return "\n".join(lines)


def plot(rows, path: Path) -> None:
    plt = protocol.use_agg()
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(10, 4))
    blocks = sorted({r["block"] or 0 for r in rows if "error" not in r})
    for i, b in enumerate(blocks):
        rs = sorted((r for r in rows if "error" not in r and (r["block"] or 0) == b),
                    key=lambda r: r["n_steps"])
        lab = f"checkpoint block {b}" if b else "no checkpoint"
        n = [r["n_steps"] for r in rs]
        a0.plot(n, [r["gradient"]["memory"]["temp_mb"] for r in rs], "o-", color=f"C{i}",
                label=f"XLA temp, {lab}")
        a0.plot(n, [r["peak_rss_mb"] for r in rs], "x:", color=f"C{i}", label=f"peak RSS, {lab}")
        a1.plot(n, [r["gradient"]["median_s"] for r in rs], "o-", color=f"C{i}", label=lab)
    a0.set_yscale("log")
    a0.set_xlabel("GNS frames")
    a0.set_ylabel("MB")
    a0.set_title("memory of d loss / d phi (112-node column)")
    a0.legend(fontsize=7)
    a1.set_xlabel("GNS frames")
    a1.set_ylabel("s per gradient (median)")
    a1.set_title("time per gradient")
    a1.legend(fontsize=8)
    for a in (a0, a1):
        a.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[30, 100, 120])
    ap.add_argument("--blocks", type=int, nargs="+", default=[10, 2],
                    help="frames per jax.checkpoint block (each also run without)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--aspect-ratio", type=float, default=1.75)
    ap.add_argument("--model", default="gns_columns",
                    help="GNS model (folder or shipped name); the column is built at its "
                         "resolution")
    ap.add_argument("--note", default=None)
    ap.add_argument("--out", default="inverse_gns_memory.json")
    ap.add_argument("--case", nargs=2, type=int, help=argparse.SUPPRESS)
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    if args.case:  # worker process (the parent checked the load)
        res = run_case(args.case[0], args.case[1] or None, args.repeats, args.aspect_ratio,
                       args.model)
        print(TAG + json.dumps(res), flush=True)
        return
    run = protocol.start(args, "inverse_gns_memory")
    t0 = time.time()
    rows = [spawn(run, n, b, args) for n in sorted(args.frames) for b in (None, *args.blocks)]
    text = table(rows)
    run.print(text)
    payload = {
        "note": args.note,
        "description": f"d/dphi of the soft-runout misfit through GNS rollouts of {args.model}"
                       ", with and without jax.checkpoint blocks; AOT-compiled "
                       "programs, XLA memory_analysis, median steady calls (wall and CPU), "
                       "one process per case",
        "settings": {k: v for k, v in vars(args).items() if k != "case"},
        "total_wall_s": time.time() - t0, "table": text, "results": rows}
    path = run.finish(args.out, payload, lambda p: plot(rows, p.with_suffix(".png")))
    run.print(f"wrote {path} (and the plot beside it)")


if __name__ == "__main__":
    main()
