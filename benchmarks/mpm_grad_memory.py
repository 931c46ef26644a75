"""Memory and time of reverse-mode gradients through whole MPM rollouts, with and without
checkpointing.

    .venv/bin/python benchmarks/mpm_grad_memory.py [--frames 100 400 1600]
        [--block 25] [--repeats 3] [--budget-s 600] [--mem-limit-gb 4] [--note TEXT]

Scene: ``column_collapse(width=0.1, aspect_ratio=2.0, friction_angle=30.0, cells_across=8)``
(512 sand particles, float32). Loss: ``runout(positions[-1], method="softmax")`` of the last
frame of ``diffgns.rollout(MPM(scene, checkpoint_substeps=c), params, state, n,
checkpoint_block=b)``; the gradient is ``jax.grad`` of that loss with respect to the whole
``MPMParams`` pytree.

For every n_frames and checkpoint in {False, True (block frames per checkpointed block)}:

* memory: the forward and the gradient programs are compiled ahead of time
  (``jax.jit(f).lower(params, state).compile()``) and XLA's ``memory_analysis()`` is stored
  (temp, argument, output, alias sizes; "total" = argument + output + temp - alias). MB and
  GB are decimal (1e6 / 1e9 bytes);
* time: the compiled executables are then called directly, so compile time (lower + compile)
  is measured on its own; one warm-up call, then up to ``--repeats`` steady calls of forward
  and gradient interleaved; every call ends with ``block_until_ready``. The gradient without
  checkpointing is only run where its analysed temp memory is below ``--mem-limit-gb``, and
  rollouts without checkpointing longer than ``--plain-time-max-frames`` are not timed at all.
  The whole script keeps to about ``--budget-s`` seconds: cases are run shortest first and
  the longest checkpointed case gets what is left (at least ``--reserve-s``); calls that would
  overrun the budget are skipped and the JSON says so;
* process peak RSS (``resource.getrusage(RUSAGE_SELF).ru_maxrss``): every case runs in its own
  fresh Python process, so the figure is that case's peak (after compiling both programs,
  and at the end of the case) rather than a running maximum over earlier cases.

Measured under ``benchmarks/protocol.py`` (the load check is made once, by the parent; the
workers inherit its thread setting), timed with ``benchmarks/timing.py`` (wall and CPU time).
Writes ``benchmarks/results/mpm_grad_memory.json`` and ``mpm_grad_memory.png``.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import protocol
from protocol import warm_up_jax

from diffgns.memory import compile_ahead, peak_rss_mb
from diffgns.timing import Sample, measure, no_sync, stats

SCENE_KW = dict(width=0.1, aspect_ratio=2.0, friction_angle=30.0, cells_across=8)
RESULT_TAG = "MPM_GRAD_MEMORY_RESULT "
GB = 1e9


def log(msg: str) -> None:
    protocol.worker_run("mpm_grad_memory").print(msg, file=sys.stderr)


# ------------------------------------------------------------------------ one case (worker)
def loss_fn(n_frames: int, ckpt: bool, block: int | None):
    """(scene, loss(params, state) = soft runout of the last frame, params, state). The one
    place this benchmark calls the simulator."""
    from diffgns import MPM, rollout
    from diffgns.metrics import runout
    from diffgns.scene.builders import column_collapse

    scene = column_collapse(**SCENE_KW)
    sim = MPM(scene, dtype="float32", checkpoint_substeps=ckpt)

    def loss(p, s):
        frames = rollout(sim, p, s, n_frames, checkpoint_block=block)[0]
        return runout(frames.positions[-1], method="softmax")

    return scene, loss, sim.params(), sim.init()


def run_case(n_frames: int, ckpt: bool, block: int, deadline: float, repeats: int,
             mem_limit_gb: float, time_it: bool) -> dict[str, Any]:
    """Compile, analyse and (budget permitting) time forward and gradient of one case.
    ``deadline`` is an absolute ``time.time()``."""
    import jax
    import jax.numpy as jnp

    warm_up_jax()
    blk = block if ckpt else None
    scene, loss, params, state = loss_fn(n_frames, ckpt, blk)
    tag = f"[{n_frames} frames, checkpoint={ckpt}]"

    res: dict[str, Any] = {
        "n_frames": n_frames, "checkpoint": ckpt, "block": blk,
        "n_particles": scene.n_particles, "grid_shape": list(scene.grid_shape),
        "substeps_per_frame": scene.substeps, "substeps": scene.substeps * n_frames,
        "loadavg_at_case_start": list(os.getloadavg()),
    }
    programs = {"forward": jax.jit(loss), "gradient": jax.jit(jax.grad(loss))}
    compiled = {}
    for name, fn in programs.items():
        compiled[name], res[name] = compile_ahead(fn, params, state)
        lw, cw = res[name]["lower_s"], res[name]["compile_s"]
        log(f"{tag} {name}: lower {lw:.1f} s, compile {cw:.1f} s, "
            f"XLA temp {res[name]['memory']['temp_mb']:.1f} MB, "
            f"total {res[name]['memory']['total_mb']:.1f} MB")
    res["peak_rss_after_compile_mb"] = peak_rss_mb()

    # which programs run
    run = {"forward": time_it, "gradient": time_it}
    grad_mem = res["gradient"]["memory"]
    if not time_it:
        for name in run:
            res[name]["note"] = "not timed (skipped by design: too long without checkpointing)"
    if grad_mem["temp_size_in_bytes"] >= mem_limit_gb * GB:
        run["gradient"] = False
        res["gradient"]["note"] = (f"not run: would need {grad_mem['total_bytes'] / GB:.1f} GB "
                                   f"(XLA temp {grad_mem['temp_size_in_bytes'] / GB:.1f} GB "
                                   f">= {mem_limit_gb:g} GB limit)")

    call = {name: (lambda exe=exe: exe(params, state)) for name, exe in compiled.items()}
    first: dict[str, float] = {}
    steady: dict[str, list] = {"forward": [], "gradient": []}
    outs: dict[str, Any] = {}

    def estimate(name: str) -> float:
        if name in first:
            return min([first[name]] + [x.wall_s for x in steady[name]])
        if name == "gradient" and "forward" in first:
            return 3.0 * first["forward"]  # a guess before the first gradient call
        return 0.0

    def fits(name: str) -> bool:
        return time.time() + estimate(name) <= deadline

    for name in ("forward", "gradient"):  # warm-up (first) calls
        if not run[name]:
            continue
        if not fits(name):
            res[name]["note"] = (f"not timed: would overrun the time budget "
                                 f"(estimated {estimate(name):.0f} s)")
            run[name] = False
            continue
        one, outs[name] = measure(call[name])
        first[name] = one.wall_s
        res[name]["first_call_s"], res[name]["first_call_cpu_s"] = one.wall_s, one.cpu_s
        log(f"{tag} {name}: first call {one.wall_s:.2f} s (cpu {one.cpu_s:.2f} s)")
    for _ in range(repeats):  # steady calls, forward and gradient interleaved
        for name in ("forward", "gradient"):
            if run[name] and len(steady[name]) < repeats and fits(name):
                one = measure(call[name])[0]
                steady[name].append(one)
                log(f"{tag} {name}: steady call {one.wall_s:.2f} s (cpu {one.cpu_s:.2f} s)")

    for name in ("forward", "gradient"):
        r = res[name]
        if name not in first:
            continue
        r.update(stats(steady[name] or [Sample(first[name], r["first_call_cpu_s"])]))
        r["n_steady"] = len(steady[name])
        if not steady[name]:
            r["note"] = "timed once only (time budget): median_s is the first call"
        elif len(steady[name]) < repeats:
            r["note"] = f"only {len(steady[name])} steady call(s) (time budget)"
    if "forward" in outs:
        res["loss_m"] = float(outs["forward"])
    if "gradient" in outs:
        g = outs["gradient"]
        res["grad"] = {"friction_angle_m_per_deg": float(g.friction_angle[0]),
                       "E_m_per_Pa": float(g.E[0]),
                       "all_finite": bool(all(bool(jnp.all(jnp.isfinite(x)))
                                              for x in jax.tree.leaves(g)))}
    if "median_s" in res["forward"] and "median_s" in res["gradient"]:
        res["grad_over_forward"] = res["gradient"]["median_s"] / res["forward"]["median_s"]
    res["peak_rss_mb"] = peak_rss_mb()
    res["loadavg_at_case_end"] = list(os.getloadavg())
    return res


# ----------------------------------------------------------------------------- driver
def spawn(run: protocol.Run, n_frames: int, ckpt: bool, args, deadline: float,
          time_it: bool) -> dict[str, Any]:
    """Run one case in a fresh Python process (clean peak RSS, isolated from OOM)."""
    cmd = [str(Path(__file__).resolve()), "--case", str(n_frames),
           str(int(ckpt)), "--deadline", repr(deadline), "--block", str(args.block),
           "--repeats", str(args.repeats), "--mem-limit-gb", str(args.mem_limit_gb)]
    if not time_it:
        cmd.append("--no-time")
    case, (res, code) = measure(lambda: protocol.run_worker(run, cmd, RESULT_TAG),
                                sync=no_sync)
    if res is None:
        res = {"n_frames": n_frames, "checkpoint": ckpt, "block": args.block if ckpt else None,
               "error": f"worker exited with code {code} and no result"}
    res["case_wall_s"], res["case_cpu_s"] = case.wall_s, case.cpu_s
    return res


def fmt_s(r: dict, name: str) -> str:
    x = r.get(name, {})
    if "median_s" not in x:
        return "-"
    return f"{x['median_s']:.2f}" + ("*" if x.get("n_steady", 0) < 3 else "")


def table(rows: list[dict]) -> str:
    head = (f"{'frames':>6} {'ckpt':>4} {'fwd MB':>8} {'grad MB':>9} {'grad tmp':>9} "
            f"{'comp f/g s':>10} {'fwd s':>7} {'grad s':>7} {'g/f':>6} {'RSS MB':>7}  note")
    lines = [head, "-" * len(head)]
    for r in rows:
        if "error" in r:
            lines.append(f"{r['n_frames']:>6} {'yes' if r['checkpoint'] else 'no':>4}  "
                         f"ERROR: {r['error']}")
            continue
        f, g = r["forward"], r["gradient"]
        ratio = f"{r['grad_over_forward']:.2f}" if "grad_over_forward" in r else "-"
        notes = [n for n in (f.get("note") and f"fwd {f['note']}",
                             g.get("note") and f"grad {g['note']}") if n]
        lines.append(
            f"{r['n_frames']:>6} {'yes' if r['checkpoint'] else 'no':>4} "
            f"{f['memory']['total_mb']:>8.1f} {g['memory']['total_mb']:>9.1f} "
            f"{g['memory']['temp_mb']:>9.1f} "
            f"{f['compile_s']:>4.1f}/{g['compile_s']:<5.1f} {fmt_s(r, 'forward'):>7} "
            f"{fmt_s(r, 'gradient'):>7} {ratio:>6} {r['peak_rss_mb']:>7.0f}  "
            + "; ".join(notes))
    lines.append("MB = 1e6 bytes; fwd/grad MB = XLA argument + output + temp - alias; grad tmp = "
                 "XLA temp; times = median steady call (* = fewer than 3 steady calls); "
                 "RSS = peak RSS of the case's own process")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path, block: int) -> None:
    plt = protocol.use_agg()
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(11, 4.2))
    ok = [r for r in rows if "error" not in r]
    for ckpt, color in ((False, "tab:red"), (True, "tab:blue")):
        rs = sorted((r for r in ok if r["checkpoint"] == ckpt), key=lambda r: r["n_frames"])
        if not rs:
            continue
        label = f"checkpoint (block {block})" if ckpt else "no checkpoint"
        n = [r["n_frames"] for r in rs]
        a0.plot(n, [r["gradient"]["memory"]["total_mb"] for r in rs], "o-", color=color,
                label=f"gradient, {label}")
        a0.plot(n, [r["forward"]["memory"]["total_mb"] for r in rs], "s--", color=color,
                alpha=0.6, label=f"forward, {label}")
        a0.plot(n, [r["peak_rss_mb"] for r in rs], "x:", color=color, alpha=0.5,
                label=f"process peak RSS, {label}")
        for r in rs:
            if "median_s" not in r["gradient"]:
                a0.annotate("grad not run", (r["n_frames"], r["gradient"]["memory"]["total_mb"]),
                            textcoords="offset points", xytext=(-30, 8), fontsize=8)
        rt = [r for r in rs if "grad_over_forward" in r]
        if rt:
            a1.plot([r["n_frames"] for r in rt], [r["grad_over_forward"] for r in rt], "o-",
                    color=color, label=label)
    a0.set_xscale("log")
    a0.set_yscale("log")
    a0.set_xlabel("frames (22 substeps each)")
    a0.set_ylabel("MB")
    a0.set_title("XLA memory analysis (arg + out + temp)\n512-particle sand column, float32")
    a0.legend(fontsize=7)
    a0.grid(True, which="both", alpha=0.3)
    a1.set_xscale("log")
    a1.set_xlabel("frames")
    a1.set_ylabel("gradient time / forward time")
    a1.set_title("cost of the gradient (median steady calls)")
    a1.set_ylim(bottom=0)
    a1.legend(fontsize=8)
    a1.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs="+", default=[100, 400, 1600])
    ap.add_argument("--block", type=int, default=25, help="frames per checkpointed block")
    ap.add_argument("--repeats", type=int, default=3, help="steady calls per program")
    ap.add_argument("--budget-s", type=float, default=600.0, help="target total wall time")
    ap.add_argument("--reserve-s", type=float, default=270.0,
                    help="time kept for the longest checkpointed case")
    ap.add_argument("--mem-limit-gb", type=float, default=4.0,
                    help="run the gradient without checkpointing only below this XLA temp size")
    ap.add_argument("--plain-time-max-frames", type=int, default=400,
                    help="do not time rollouts without checkpointing longer than this")
    ap.add_argument("--note", default=None, help="free-text note stored in the JSON")
    ap.add_argument("--out", default="mpm_grad_memory.json")
    ap.add_argument("--case", nargs=2, type=int, metavar=("FRAMES", "CKPT"), help=argparse.SUPPRESS)
    ap.add_argument("--deadline", type=float, default=math.inf, help=argparse.SUPPRESS)
    ap.add_argument("--no-time", action="store_true", help=argparse.SUPPRESS)
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)

    if args.case:  # worker process (the parent checked the load)
        res = run_case(args.case[0], bool(args.case[1]), args.block, args.deadline,
                       args.repeats, args.mem_limit_gb, not args.no_time)
        print(RESULT_TAG + json.dumps(res), flush=True)
        return

    run = protocol.start(args, "mpm_grad_memory")
    t_start = time.time()
    deadline = t_start + args.budget_s
    frames = sorted(args.frames)
    # shortest first; without checkpointing before with; the longest checkpointed case last
    cases = [(n, c) for n in frames for c in (False, True)]
    rows = []
    for i, (n, ckpt) in enumerate(cases):
        last = i == len(cases) - 1
        time_it = ckpt or n <= args.plain_time_max_frames
        case_deadline = deadline if last else deadline - args.reserve_s
        run.print(f"--- case {n} frames, checkpoint={ckpt} ({time.time() - t_start:.0f} s "
                  f"elapsed, load {os.getloadavg()[0]:.2f})", file=sys.stderr)
        rows.append(spawn(run, n, ckpt, args, case_deadline, time_it))
    total = time.time() - t_start

    text = table(rows)
    run.print(text)
    run.print(f"total benchmark time {total:.1f} s")
    payload = {
        "description": (
            "reverse-mode gradient of runout(pos[-1], method='softmax') w.r.t. MPMParams "
            "through the MPM rollout of column_collapse(" + ", ".join(
                f"{k}={v}" for k, v in SCENE_KW.items()) + "), float32; memory from XLA "
            "memory_analysis() of the AOT-compiled jax.jit programs (total = argument + "
            "output + temp - alias; MB = 1e6 bytes); times are medians of steady calls of the "
            "compiled executables (block_until_ready), wall and CPU; compile_s = lower + "
            "compile wall time; each case runs in a fresh process, peak_rss_mb is that "
            "process's ru_maxrss"),
        "note": args.note,
        "settings": {"frames": frames, "block": args.block, "repeats": args.repeats,
                     "budget_s": args.budget_s, "reserve_s": args.reserve_s,
                     "mem_limit_gb": args.mem_limit_gb,
                     "plain_time_max_frames": args.plain_time_max_frames},
        "total_wall_s": total, "table": text, "results": rows,
    }
    path = run.finish(args.out, payload,
                      lambda p: plot(rows, p.with_suffix(".png"), args.block))
    run.print(f"wrote {path} (and the plot beside it)")


if __name__ == "__main__":
    main()
