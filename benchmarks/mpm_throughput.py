"""MPM throughput (particle-substeps per second) of a granular column collapse at ~2k,
~8k and ~32k particles.

    .venv/bin/python benchmarks/mpm_throughput.py [--repeats 5] [--quick | --cells 23 45 90]
        [--threads both]

Each size is ``column_collapse(cells_across=c)`` (sand, 4 particles per cell, friction
floor, slip walls) run with the jitted MPM rollout. ``frame_dt`` is scaled with dx so every
frame has ~60 substeps at every resolution, and the number of frames per call is chosen so
a steady call lasts about a second. For each size: the first call (compile + run) and
``--repeats`` steady calls are timed (``benchmarks/timing.py``); compile time = first call -
median steady call. Measured under ``benchmarks/protocol.py`` (quiet machine, load
recorded). Writes ``benchmarks/results/mpm_throughput.json`` and ``mpm_throughput.png``.
"""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import protocol
from protocol import fmt_rate, warm_up_jax

from diffgns import MPM, rollout_jit
from diffgns.scene.builders import column_collapse
from diffgns.timing import measure, time_call

# (cells across the column, frames per timed call); 4 particles per cell -> N = 4 c^2
SIZES = ((23, 10), (45, 4), (90, 2))
BASE_CELLS, BASE_FRAME_DT = 23, 2.5e-3


def frames_for(cells: int) -> int:
    """Frames per timed call at ``cells`` across: those of :data:`SIZES`, else about as many
    particle-substeps per call as at 23 cells (10 frames)."""
    return dict(SIZES).get(cells, max(1, round(10 * BASE_CELLS ** 2 / cells ** 2)))


def rollout_call(cells: int, n_frames: int):
    """(scene, zero-argument call returning the (T, N, 2) positions of an MPM rollout).
    The one place this benchmark calls the simulator."""
    scene = column_collapse(cells_across=cells, frame_dt=BASE_FRAME_DT * BASE_CELLS / cells)
    sim = MPM(scene)
    params, state = sim.params(), sim.init()
    return scene, lambda: rollout_jit(sim, params, state, n_frames=n_frames)[0].positions


def measure_size(cells: int, n_frames: int, repeats: int) -> dict:
    scene, call = rollout_call(cells, n_frames)
    t, pos = time_call(call, repeats=repeats)
    n, sub = scene.n_particles, scene.substeps
    work = n * sub * n_frames  # particle-substeps per call
    return {
        "n_particles": n, "cells_across": cells, "grid_shape": list(scene.grid_shape),
        "grid_nodes": scene.grid_shape[0] * scene.grid_shape[1], "dx_m": scene.dx,
        "substep_dt_s": scene.substep_dt, "substeps_per_frame": sub,
        "frames_per_call": n_frames, "substeps_per_call": sub * n_frames,
        "particle_substeps_per_call": work, "finite": bool(jnp.all(jnp.isfinite(pos))),
        **t,
        "steady_particle_substeps_per_s": work / t["median_s"],
        "steady_particle_substeps_per_s_best": work / t["min_s"],
        "time_per_substep_ms": 1e3 * t["median_s"] / (sub * n_frames),
    }


def plot(rows, path):
    plt = protocol.use_agg()
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(10, 4))
    labels = [f"{r['n_particles']}" for r in rows]
    rates = [r["steady_particle_substeps_per_s"] / 1e6 for r in rows]
    lo = [(r["steady_particle_substeps_per_s"] - r["particle_substeps_per_call"] / r["max_s"])
          / 1e6 for r in rows]
    hi = [(r["steady_particle_substeps_per_s_best"] - r["steady_particle_substeps_per_s"]) / 1e6
          for r in rows]
    a0.bar(labels, rates, yerr=[lo, hi], capsize=4, color="tab:blue")
    a0.set_xlabel("particles")
    a0.set_ylabel("M particle-substeps / s (median, min-max bars)")
    a0.set_title("MPM steady throughput (sand column, float32)")
    a1.bar(labels, [r["compile_s"] for r in rows], color="tab:orange")
    a1.set_xlabel("particles")
    a1.set_ylabel("s")
    a1.set_title("compile time (first call - median steady)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def measure_all(run: protocol.Run, sizes, repeats: int) -> list[dict]:
    run.print(f"{'particles':>9} {'grid':>9} {'sub/call':>8} {'first s':>8} {'compile s':>9} "
              f"{'steady s':>9} {'cpu s':>6} {'ms/substep':>10} {'particle-substeps/s':>20}")
    rows = []
    for cells, frames in sizes:
        r = measure_size(cells, frames, repeats)
        rows.append(r)
        run.print(f"{r['n_particles']:>9} {r['grid_shape'][0]:>4}x{r['grid_shape'][1]:<4} "
                  f"{r['substeps_per_call']:>8} {r['first_call_s']:>8.2f} "
                  f"{r['compile_s']:>9.2f} {r['median_s']:>9.3f} {r['cpu_median_s']:>6.2f} "
                  f"{r['time_per_substep_ms']:>10.3f} "
                  f"{fmt_rate(r['steady_particle_substeps_per_s']):>20}")
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5, help="steady calls per size (>= 3)")
    ap.add_argument("--quick", action="store_true", help="only the smallest size")
    ap.add_argument("--cells", type=int, nargs="+", default=None,
                    help="cells across the column (N = 4 cells^2; default "
                         f"{' '.join(str(c) for c, _ in SIZES)})")
    ap.add_argument("--out", default="mpm_throughput.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "mpm_throughput")
    warm_up_jax()
    sizes = SIZES[:1] if args.quick else SIZES
    if args.cells:
        sizes = tuple((c, frames_for(c)) for c in args.cells)
    total, rows = measure(lambda: measure_all(run, sizes, max(3, args.repeats)),
                          sync=lambda _: None)
    payload = {
        "description": "column_collapse sand scene (4 ppc, friction floor), jitted MPM "
                       "rollout; compile_s = first call - median steady call",
        "dtype": str(jnp.asarray(0.0).dtype), "jax": jax.__version__,
        "repeats": max(3, args.repeats), "total_wall_s": total.wall_s,
        "total_cpu_s": total.cpu_s, "results": rows,
    }
    path = run.finish(args.out, payload, lambda p: plot(rows, p.with_suffix(".png")))
    run.print(f"wrote {path} (and the plot beside it)")


if __name__ == "__main__":
    main()
