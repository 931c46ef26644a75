"""A/B of commit 6920902 (before the simulator interface, old API) against the working tree
(the one interface): steady time of the same MPM rollout and the same GNS rollout, each round
in fresh processes, old/new alternating.

    python benchmarks/interface_ab.py [--rounds 3] [--repeats 3] [--threads both]
        [--wait-quiet 600]

The old tree is unpacked once (``git archive <--old-commit> src models``, read-only, into
``--old-tree``; done by the script when the folder is missing). A round runs one worker
process of each tree (the order alternating round by round: old new, new old, ...); each
worker builds the same 16-cell column collapse (a = 1.75, phi = 30 deg) and times, with the
one timing helper ``src/diffgns/timing.py`` of the working tree (loaded by file in both
workers, so both are measured by the same code): the first call apart (compile), then
``--repeats`` steady calls (median; ``block_until_ready``; wall and CPU time) of an
``--mpm-frames`` MPM rollout and of a ``--gns-frames`` ``gns_cg16_pfn`` rollout from the
same 6 coarse-grained MPM frames (the GNS's neighbour-list sizing call, which compiles, is
timed before and recorded as ``sizing_call_s``). A ratio new/old is the median of the
per-round ratios of the two workers' medians. Both GNS rollouts must end at the same place
(checked).

Workers inherit the protocol's thread setting (``--threads 1`` pins this process and so its
workers; ``--threads both`` repeats the rounds pinned). Writes
``benchmarks/results/interface_ab_rounds.json`` under ``benchmarks/protocol.py``.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import protocol

from diffgns.timing import measure, no_sync

OLD_COMMIT = "6920902"
OLD_TREE = "/tmp/old"
TAG = "INTERFACE_AB_RESULT "
TIMING = protocol.REPO_DIR / "src" / "diffgns" / "timing.py"
WORKER = r'''
import importlib.util, json, sys
which, timing_py, old_tree = sys.argv[1], sys.argv[2], sys.argv[3]
mpm_frames, gns_frames, repeats = (int(v) for v in sys.argv[4:7])
spec = importlib.util.spec_from_file_location("bench_timing", timing_py)
timing = sys.modules["bench_timing"] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(timing)  # the working tree's timing helper, in both workers
import jax, jax.numpy as jnp, numpy as np
import diffgns
old = which == "old"
from diffgns.mpm import MPM
from diffgns.graph.train_loop import load_model
from diffgns.graph.data import coarse_grain
if old:
    from diffgns.scene_builders import column_collapse
else:
    from diffgns.scene.builders import column_collapse
    from diffgns import rollout_jit, rollout_safe
    from diffgns.graph.gns import GNSParams
jax.block_until_ready(jnp.arange(8.0).sum() + 1.0)  # backend up before the first timing
sc = column_collapse(width=0.1, aspect_ratio=1.75, friction_angle=30.0, cells_across=16,
                     domain_length=0.8, domain_height=0.35)
sim = MPM(sc)
p = sim.params()
if old:
    s = sim.init_state()
    mpm = lambda: sim.rollout_full(p, s, n_frames=mpm_frames)[0]
else:
    s = sim.init()
    mpm = lambda: rollout_jit(sim, p, s, n_frames=mpm_frames)[0].positions
t_mpm, _ = timing.time_call(mpm, repeats)
model = old_tree + "/models/gns_cg16_pfn" if old else "gns_cg16_pfn"
gns, params, info = load_model(model)
ref = (sim.rollout(p, s, 10) if old else sim.run(p, s, 10)[0])
nodes = coarse_grain(ref, info["factor"], info["frame_stride"])
hist = jnp.swapaxes(jnp.asarray(nodes.positions[:6]), 0, 1)
pt, mat = jnp.asarray(nodes.particle_type), jnp.asarray(nodes.material)
if old:
    first, (xs, nbrs) = timing.measure(lambda: gns.rollout_safe(params, hist, pt, mat,
                                                                 gns_frames))
    g = lambda: gns.rollout_safe(params, hist, pt, mat, gns_frames, nbrs)[0]
else:
    st = gns.init(hist, pt)
    first, (fr, _, start) = timing.measure(
        lambda: rollout_safe(gns, GNSParams(params, mat), st, gns_frames))
    g = lambda: rollout_jit(gns, GNSParams(params, mat), start, gns_frames)[0].positions
t_gns, out = timing.time_call(g, repeats)  # its own first call: any compile left
t_gns["sizing_call_s"], t_gns["sizing_call_cpu_s"] = first.wall_s, first.cpu_s  # + compile
print("INTERFACE_AB_RESULT " + json.dumps(dict(
    which=which, diffgns_file=diffgns.__file__, mpm=t_mpm, gns=t_gns,
    mpm_frames=mpm_frames, gns_frames=gns_frames, n_particles=int(sc.n_particles),
    gns_final_max_x=float(np.asarray(out)[-1][..., 0].max()))), flush=True)
'''


def old_tree(path: Path, commit: str) -> Path:
    """The old ``src`` and ``models`` unpacked from ``commit`` into ``path`` (``git archive``,
    read-only for the repository), unless already there."""
    if (path / "src" / "diffgns").is_dir() and (path / "models").is_dir():
        return path
    path.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "-C", str(protocol.REPO_DIR), "archive", commit, "src",
                              "models"], capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(path)], input=archive.stdout, check=True)
    return path


def worker(run: protocol.Run, which: str, tree: Path, args) -> dict:
    """One worker process of ``which`` tree; its JSON result."""
    env = run.worker_env()
    if which == "old":
        env["PYTHONPATH"] = str(tree / "src")
    cmd = [sys.executable, "-c", WORKER, which, str(TIMING), str(tree),
           str(args.mpm_frames), str(args.gns_frames), str(args.repeats)]
    took, p = measure(lambda: subprocess.run(cmd, capture_output=True, text=True, env=env,
                                             cwd="/tmp"), sync=no_sync)
    if p.returncode:
        raise SystemExit(f"{which} worker failed:\n{p.stderr[-3000:]}")
    line = next(x for x in p.stdout.splitlines() if x.startswith(TAG))
    row = json.loads(line[len(TAG):])
    want = str(tree / "src") if which == "old" else str(protocol.REPO_DIR / "src")
    if not row["diffgns_file"].startswith(want):
        raise SystemExit(f"{which} worker imported {row['diffgns_file']}, not from {want}")
    row["worker_wall_s"], row["worker_cpu_s"] = took.wall_s, took.cpu_s
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rounds_pos", type=int, nargs="?", default=None, metavar="ROUNDS",
                    help="A/B rounds (same as --rounds)")
    ap.add_argument("--rounds", type=int, default=3, help="A/B rounds (pairs of workers)")
    ap.add_argument("--repeats", type=int, default=3, help="steady calls per worker")
    ap.add_argument("--mpm-frames", type=int, default=50)
    ap.add_argument("--gns-frames", type=int, default=120)
    ap.add_argument("--old-commit", default=OLD_COMMIT)
    ap.add_argument("--old-tree", default=OLD_TREE)
    ap.add_argument("--out", default="interface_ab_rounds.json",
                    help="results file (the 2026-12-02 record interface_ab.json is kept)")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    rounds = args.rounds_pos or args.rounds
    run = protocol.start(args, "interface_ab")
    tree = old_tree(Path(args.old_tree), args.old_commit)
    out: dict = dict(old_commit=args.old_commit, old_tree=str(tree), rounds=rounds,
                     repeats=args.repeats, mpm_frames=args.mpm_frames,
                     gns_frames=args.gns_frames, rows=[])
    for r in range(rounds):
        for w in (("old", "new") if r % 2 == 0 else ("new", "old")):
            row = worker(run, w, tree, args)
            row["round"] = r
            out["rows"].append(row)
            run.print(f"round {r} {w}: MPM {row['mpm']['median_s']:.3f} s (CPU "
                      f"{row['mpm']['cpu_median_s']:.2f}, compile {row['mpm']['compile_s']:.1f})"
                      f", GNS {row['gns']['median_s']:.3f} s (CPU {row['gns']['cpu_median_s']:.2f},"
                      f" sizing call {row['gns']['sizing_call_s']:.1f}); worker "
                      f"{row['worker_wall_s']:.0f} s")
    ends = {x["gns_final_max_x"] for x in out["rows"]}
    out["gns_same_output"] = len(ends) == 1
    if len(ends) != 1:
        run.print(f"WARNING: the GNS rollouts differ (final max x {sorted(ends)})")

    def pick(w: str, r: int) -> dict:
        return next(x for x in out["rows"] if x["which"] == w and x["round"] == r)

    for k in ("mpm", "gns"):
        for clock in ("median_s", "cpu_median_s"):
            ratios = [pick("new", r)[k][clock] / pick("old", r)[k][clock] for r in range(rounds)]
            name = f"{k}_new_over_old" + ("_cpu" if clock.startswith("cpu") else "")
            out[name] = dict(per_round=ratios, median=float(np.median(ratios)))
        m = out[f"{k}_new_over_old"]
        run.print(f"{k} new/old per round", [f"{x:.3f}" for x in m["per_round"]],
                  "median", f"{m['median']:.3f}", "(CPU time",
                  f"{out[f'{k}_new_over_old_cpu']['median']:.3f})")
    if run.mode == "both" and not run.pinned:
        out["one_thread_pinned"] = child = run.pinned_child()
        for k in ("mpm", "gns"):
            one = (child.get(f"{k}_new_over_old") or {}).get("median")
            run.print(f"{k} new/old: " + protocol.both_ratios(
                out[f"{k}_new_over_old"]["median"], one, child))
    path = run.finish(args.out, out)
    run.print(f"wrote {path}")


if __name__ == "__main__":
    main()
