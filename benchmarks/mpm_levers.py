"""MPM levers not yet measured on a quiet machine: two host devices, XLA CPU options, cell order.

    .venv/bin/python benchmarks/mpm_levers.py [--cells 45 90] [--shard-cells 16 23 32 45 90]
        [--repeats 7] [--frame-rounds 5] [--substeps 20] [--levers shard options order]
        [--threads 2|1|both] [--out mpm_levers.json] [--wait-quiet 600]

(~5 min on a quiet 2-core machine with the defaults, 2 threads; ``--threads both`` adds the
pinned 1-thread run, ~10 min in all.)

Scene: ``column_collapse(width=0.1, aspect_ratio=1, friction_angle=30, cells_across=c)``
(sand, 4 particles per cell, N = 4 c^2), on the state after 4 frames of the collapse (a
moving, yielding column), as in ``benchmarks/mpm_profile.py``. Three levers, each against the
current solver on the same state, in interleaved rounds (median wall and CPU time, the
compile timed apart, ``block_until_ready`` before the clock stops), outputs compared:

1. **Two host devices (the library's sharded MPM) and the particle order.** In a worker
   process with two CPU devices (``jax_num_cpu_devices=2``, set before the backend starts):
   one frame of ``MPM(scene, devices=2)`` (particles split over the devices with
   ``jax.shard_map``, each device scattering its share into a full grid, one ``psum`` of the
   grids per substep; :mod:`diffgns.mpm.solver`) against one frame of ``MPM(scene,
   devices=1)``, each also with ``particle_order="given"`` (the scene's order) against the
   default (shuffled within blocks in 2D on the CPU), at
   the sizes of ``--shard-cells`` (1,024 to 32,400 particles: where the sharded frame
   starts to pay sets :data:`diffgns.hostdevices.AUTO_MIN_PARTICLES`). The ``psum`` adds
   in another order than the one scatter: max |x| and |v| differences after the frame are
   reported (float32 round-off expected).
2. **XLA CPU compiler options.** One whole frame (``jax.jit(MPM.step)``: ``scene.substeps``
   substeps in a ``lax.scan``) compiled with each ``compiler_options`` set of
   :data:`XLA_OPTIONS` (XNNPACK off, XNNPACK graph fusion, oneDNN, fast math, 512-bit
   vectors, the fusion code generator without the fusion emitters, the FAST_RUNTIME preset)
   against the default options, interleaved. An option the installed XLA does not know is
   recorded as rejected (with XLA's message), not timed: in jaxlib 0.10.2 the thunk-runtime
   toggle ``xla_cpu_use_thunk_runtime`` is one (the thunk runtime is the only one left).
   Also recorded: whether the optimised HLO differs from the default's, and max |x|
   difference after the frame.
3. **Cell-sorted particles.** ``--substeps`` chained one-device substeps on the particles in the
   order the scene builds them (lattice order, x-major like the grid), sorted by base cell
   once (a sort per frame, its cost timed apart), randomly shuffled (the worst order), and
   with a sort by base cell before every substep: does XLA's scatter get faster with sorted
   indices? Results are unpermuted and compared.

Item 1 runs in a worker (XLA fixes the host device count at start-up); items 2-3 in this
process (one device). Writes ``benchmarks/results/mpm_levers.json`` (``--out``).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import protocol
from protocol import warm_up_jax

from diffgns import MPM, rollout_jit
from diffgns.clamp import ClampCount
from diffgns.scene.builders import column_collapse
from diffgns.timing import interleave, time_call

NAME = "mpm_levers"
TAG = "MPM_LEVERS_SHARD_RESULT "
SETTLE_FRAMES = 4  # frames of collapse before the measured state

#: compiler_options sets timed against the default in item 2 (names -> options). Checked
#: against jaxlib 0.10.2 (``XLA_FLAGS=--help``); an option XLA rejects is recorded, not timed.
XLA_OPTIONS: dict[str, dict[str, object]] = {
    "no_xnnpack": {"xla_cpu_use_xnnpack": False},
    "xnn_graph_greedy": {
        "xla_cpu_experimental_xnn_graph_fusion_mode": "XNN_GRAPH_FUSION_MODE_GREEDY"},
    "onednn": {"xla_cpu_use_onednn": True},
    "fast_math": {"xla_cpu_enable_fast_math": True},
    "vector_512": {"xla_cpu_prefer_vector_width": 512},
    "legacy_emitters": {"xla_cpu_use_fusion_emitters": False},
    "fast_runtime": {"xla_cpu_opt_preset": "CPU_OPT_PRESET_FAST_RUNTIME"},
    # deprecated in XLA_FLAGS (a warning, no effect), no longer a compile option: rejected
    "thunk_runtime_off": {"xla_cpu_use_thunk_runtime": False},
}


# ------------------------------------------------------------------ scene and helpers
def collapsed(cells: int, state_dir: str | None = None):
    """(scene, sim, params, state after SETTLE_FRAMES frames) of the sand column. With
    ``state_dir``, the settled state is read from (or first written to) a file there, so the
    parent and its worker settle the column once."""
    scene = column_collapse(width=0.1, aspect_ratio=1, friction_angle=30, cells_across=cells)
    sim = MPM(scene)
    if len(sim.groups) != 1 or len(np.unique(sim.body)) != 1:
        raise SystemExit("mpm_levers: the levers assume one body of one material")
    params, state = sim.params(), sim.init()
    path = Path(state_dir) / f"state_{cells}.npz" if state_dir else None
    if path is not None and path.exists():
        z = np.load(path)
        return scene, sim, params, state.replace(
            **{k: jnp.asarray(z[k]) for k in ("x", "v", "C", "F", "vol")},
            clamp=ClampCount(jnp.asarray(z["moved"]), jnp.asarray(z["shift"])))
    state = jax.block_until_ready(rollout_jit(sim, params, state, n_frames=SETTLE_FRAMES)[1])
    if path is not None:
        np.savez(path, **{k: np.asarray(getattr(state, k)) for k in ("x", "v", "C", "F", "vol")},
                 moved=np.asarray(state.clamp.moved), shift=np.asarray(state.clamp.shift))
    return scene, sim, params, state


def chain(sub, k: int):
    """``(params, state) -> k chained sub(params, state)`` in one ``lax.scan``."""
    def f(params, state):
        return jax.lax.scan(lambda s, _: (sub(params, s), None), state, None, length=k)[0]

    return f


def aot(fn, *args, **compile_kw):
    """(compiled ``jax.jit(fn)`` for ``args``, seconds to lower and compile)."""
    t = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile(**compile_kw)
    return compiled, time.perf_counter() - t


def max_diff(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))))


def timing_row(res, name: str, per: int) -> dict:
    """Median wall / CPU microseconds per substep (``per`` substeps per call)."""
    s = res.summary(name)
    return {"us_per_substep": 1e6 * s["median_s"] / per,
            "cpu_us_per_substep": 1e6 * s["cpu_median_s"] / per,
            "median_s": s["median_s"], "cpu_median_s": s["cpu_median_s"],
            "min_s": s["min_s"], "max_s": s["max_s"], "first_call_s": s["first_call_s"]}


# ------------------------------------------------------------------ 1. two devices
def shard_size(cells: int, repeats: int, state_dir: str | None) -> dict:
    """Item 1 at one size (in the two-device worker): one frame of ``MPM(scene,
    devices=1)`` against ``MPM(scene, devices=2)`` (the library's sharded frame)."""
    devices = jax.local_devices()
    if len(devices) < 2:
        raise SystemExit(f"mpm_levers worker: 2 host devices needed, got {len(devices)}")
    scene, _, params, state = collapsed(cells, state_dir)
    sims = {"one_device": MPM(scene, devices=1), "two_devices": MPM(scene, devices=2),
            "one_device_given_order": MPM(scene, devices=1, particle_order="given"),
            "two_devices_given_order": MPM(scene, devices=2, particle_order="given")}
    compiled = {k: aot(sim.step, params, state) for k, sim in sims.items()}
    res = interleave({k: (lambda f=f: f(params, state)) for k, (f, _) in compiled.items()},
                     repeats)
    a, b = res.outputs["one_device"], res.outputs["two_devices"]
    n_sub = int(scene.substeps)
    rows = {k: timing_row(res, k, n_sub) for k in res.names}
    for k, (_, c) in compiled.items():
        rows[k]["compile_s"] = c
        rows[k]["max_abs_diff_x_m"] = max_diff(res.outputs[k].x, a.x)
    return {
        "cells_across": cells, "n_particles": scene.n_particles,
        "grid_shape": list(scene.grid_shape), "substeps_per_call": n_sub,
        "devices": [str(d) for d in devices], "timing": rows,
        "shuffled_order_default": bool(sims["one_device"].shuffled),
        "speedup_two_over_one": 1.0 / res.ratio("two_devices", "one_device"),
        "cpu_ratio_two_over_one": res.ratio("two_devices", "one_device", cpu=True),
        "speedup_shuffled_over_given_one_device":
            1.0 / res.ratio("one_device", "one_device_given_order"),
        "speedup_shuffled_over_given_two_devices":
            1.0 / res.ratio("two_devices", "two_devices_given_order"),
        "max_abs_diff_frame": {"x_m": max_diff(a.x, b.x), "v_m_s": max_diff(a.v, b.v)},
        "clamp_moved_equal": int(a.clamp.moved) == int(b.clamp.moved),
        "rounds": res.to_json()["rounds"],
    }


def shard_worker(args) -> None:
    # two host devices, set before JAX starts its CPU backend. Not through XLA_FLAGS: in the
    # pinned 1-thread run XLA_FLAGS holds protocol.ONE_THREAD_XLA_FLAGS, whose bare token
    # "intra_op_parallelism_threads=1" ends XLA's flag parsing, so a flag appended after it
    # (run_worker's xla_flags) is silently ignored (seen: 1 device)
    jax.config.update("jax_num_cpu_devices", 2)
    run = protocol.worker_run(NAME)
    warm_up_jax()
    sizes = []
    for c in args.cells:
        sizes.append(shard_size(c, args.repeats, args.state_dir))
        run.print(f"  [worker] {c} cells done", file=sys.stderr)
    print(TAG + json.dumps({"sizes": sizes, "xla_flags": os.environ.get("XLA_FLAGS"),
                            "jax_num_cpu_devices": jax.config.jax_num_cpu_devices}),
          flush=True)


def report_shard(run: protocol.Run, r: dict) -> None:
    t = r["timing"]
    o, w = t["one_device"], t["two_devices"]
    d = r["max_abs_diff_frame"]
    run.print(f"  N = {r['n_particles']}: one device {o['us_per_substep']:.0f} us/substep "
              f"(CPU {o['cpu_us_per_substep']:.0f}), two {w['us_per_substep']:.0f} us "
              f"(CPU {w['cpu_us_per_substep']:.0f}): speed-up {r['speedup_two_over_one']:.2f}x; "
              f"compile {o['compile_s']:.1f} / {w['compile_s']:.1f} s; max |dx| "
              f"{d['x_m']:.1e} m, |dv| {d['v_m_s']:.1e} m/s after a frame")
    run.print("    shuffled order / scene order: "
              f"x{r['speedup_shuffled_over_given_one_device']:.2f}"
              f" on one device ({t['one_device_given_order']['us_per_substep']:.0f} us in the "
              f"scene's order), x{r['speedup_shuffled_over_given_two_devices']:.2f} on two "
              f"({t['two_devices_given_order']['us_per_substep']:.0f} us)")


# ------------------------------------------------------------------ 2. XLA options
def option_size(run: protocol.Run, cells: int, rounds: int, state_dir: str) -> dict:
    scene, sim, params, state = collapsed(cells, state_dir)
    n_sub = sim.n_sub
    compiled, compile_s, hlo, rejected = {}, {}, {}, {}
    for name, opts in {"default": {}, **XLA_OPTIONS}.items():
        try:
            compiled[name], compile_s[name] = aot(
                sim.step, params, state, **({"compiler_options": opts} if opts else {}))
        except Exception as e:  # an option this XLA does not know (INVALID_ARGUMENT)
            rejected[name] = {"options": opts, "error": str(e).splitlines()[0][:300]}
            continue
        hlo[name] = compiled[name].as_text()
    res = interleave({k: (lambda c=c: c(params, state)) for k, c in compiled.items()}, rounds)
    ref = res.outputs["default"]
    rows = {}
    for k in compiled:
        row = timing_row(res, k, n_sub)
        row.update(options={"default": {}, **XLA_OPTIONS}[k], compile_s=compile_s[k],
                   hlo_differs_from_default=hlo[k] != hlo["default"],
                   max_abs_diff_x_m=max_diff(res.outputs[k].x, ref.x),
                   max_abs_diff_v_m_s=max_diff(res.outputs[k].v, ref.v))
        if k != "default":
            row["speedup_over_default"] = 1.0 / res.ratio(k, "default")
        rows[k] = row
    d = rows["default"]
    run.print(f"  XLA options, one frame ({n_sub} substeps): default "
              f"{1e3 * d['median_s']:.0f} ms (CPU {1e3 * d['cpu_median_s']:.0f} ms, compile "
              f"{d['compile_s']:.1f} s)")
    for k, r in rows.items():
        if k == "default":
            continue
        run.print(f"    {k:>17}: {1e3 * r['median_s']:6.0f} ms  x{r['speedup_over_default']:.3f} "
                  f"(CPU {1e3 * r['cpu_median_s']:.0f} ms, compile {r['compile_s']:.1f} s, HLO "
                  f"{'changed' if r['hlo_differs_from_default'] else 'same'}, max |dx| "
                  f"{r['max_abs_diff_x_m']:.1e} m)")
    for k, r in rejected.items():
        run.print(f"    {k:>17}: rejected by XLA ({r['error'][:100]})")
    return {"cells_across": cells, "n_particles": scene.n_particles,
            "substeps_per_frame": n_sub, "options": rows, "rejected": rejected,
            "rounds": res.to_json()["rounds"]}


# ------------------------------------------------------------------ 3. cell order
def cell_key(sim: MPM, x):
    """Flat index of each particle's base node (the stencil's first node), as in
    :func:`diffgns.mpm.shape.stencil`."""
    X = (x - jnp.asarray(sim.origin, x.dtype)[:, None]) / sim.dx
    base = jnp.floor(X - 0.5).astype(jnp.int32)
    return base[0] * sim.grid_shape[1] + base[1]


def permute(state, perm):
    """The state's particles in the order ``perm`` (the clamp count is not per particle)."""
    return state.replace(x=state.x[:, perm], v=state.v[:, perm], C=state.C[..., perm],
                         F=state.F[..., perm], vol=state.vol[perm])


def sort_by_cell(sim: MPM, state, ids):
    perm = jnp.argsort(cell_key(sim, state.x), stable=True)
    return permute(state, perm), ids[perm]


def order_size(run: protocol.Run, cells: int, repeats: int, k: int, state_dir: str
               ) -> dict:
    scene, sim, params, state = collapsed(cells, state_dir)
    n = scene.n_particles
    ids0 = jnp.arange(n, dtype=jnp.int32)
    fn, compile_s = aot(chain(sim.substep, k), params, state)
    sorter, sort_compile_s = aot(lambda s, i: sort_by_cell(sim, s, i), state, ids0)
    s_sorted, ids_sorted = sorter(state, ids0)
    shuffle = jnp.asarray(np.random.default_rng(0).permutation(n), jnp.int32)
    s_shuffled, ids_shuffled = permute(state, shuffle), shuffle

    def sorted_each(params, carry):
        s, ids = sort_by_cell(sim, *carry)
        return sim.substep(params, s), ids

    each, each_compile_s = aot(chain(sorted_each, k), params, (state, ids0))
    res = interleave({"as_built": lambda: fn(params, state),
                      "sorted_once": lambda: fn(params, s_sorted),
                      "shuffled": lambda: fn(params, s_shuffled),
                      "sorted_each_substep": lambda: each(params, (state, ids0))}, repeats)
    sort_t = time_call(lambda: sorter(state, ids0), repeats)[0]
    sort_s = sort_t["median_s"]
    ref = res.outputs["as_built"]

    def unpermuted(out, ids):
        inv = jnp.zeros(n, jnp.int32).at[ids].set(jnp.arange(n, dtype=jnp.int32))
        return permute(out, inv)

    outs = {"as_built": ref, "sorted_once": unpermuted(res.outputs["sorted_once"], ids_sorted),
            "shuffled": unpermuted(res.outputs["shuffled"], ids_shuffled),
            "sorted_each_substep": unpermuted(*res.outputs["sorted_each_substep"])}
    rows = {}
    for name in res.names:
        row = timing_row(res, name, k)
        row.update(max_abs_diff_x_m=max_diff(outs[name].x, ref.x),
                   max_abs_diff_v_m_s=max_diff(outs[name].v, ref.v),
                   compile_s=each_compile_s if name == "sorted_each_substep" else compile_s)
        if name != "as_built":
            row["speedup_over_as_built"] = 1.0 / res.ratio(name, "as_built")
        rows[name] = row
    frame_s = rows["as_built"]["median_s"] / k * sim.n_sub
    keys = np.asarray(cell_key(sim, state.x))
    run.print(f"  particle order ({k} substeps, one device): as built "
              f"{rows['as_built']['us_per_substep']:.0f} us/substep; sort by cell "
              f"{1e3 * sort_s:.2f} ms = {100 * sort_s / frame_s:.2f}% of a frame")
    for name, r in rows.items():
        if name == "as_built":
            continue
        run.print(f"    {name:>19}: {r['us_per_substep']:7.0f} us  "
                  f"x{r['speedup_over_as_built']:.3f} (CPU {r['cpu_us_per_substep']:.0f} us; "
                  f"max |dx| {r['max_abs_diff_x_m']:.1e} m)")
    return {"cells_across": cells, "n_particles": n, "substeps_per_call": k,
            "as_built_cells_sorted_fraction": float(np.mean(np.diff(keys) >= 0)),
            "sort_s": sort_s, "sort_cpu_s": sort_t["cpu_median_s"],
            "sort_compile_s": sort_compile_s,
            "sort_share_of_frame": sort_s / frame_s, "timing": rows,
            "rounds": res.to_json()["rounds"]}


# ------------------------------------------------------------------ main
def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, nargs="+", default=[45, 90],
                    help="cells across the column (N = 4 cells^2 particles)")
    ap.add_argument("--shard-cells", type=int, nargs="+", default=[16, 23, 32, 45, 90],
                    help="sizes of item 1 (cells across; N = 1,024 ... 32,400 particles)")
    ap.add_argument("--repeats", type=int, default=7,
                    help="interleaved rounds of items 1 and 3 (>= 3)")
    ap.add_argument("--frame-rounds", type=int, default=5,
                    help="interleaved rounds of item 2 (whole frames; >= 3)")
    ap.add_argument("--substeps", type=int, default=20,
                    help="chained substeps per timed call in items 1 and 3")
    ap.add_argument("--levers", nargs="+", default=["shard", "options", "order"],
                    choices=["shard", "options", "order"])
    ap.add_argument("--out", default="mpm_levers.json")
    ap.add_argument("--shard-worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--state-dir", default=None, help=argparse.SUPPRESS)
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    args.repeats, args.frame_rounds = max(3, args.repeats), max(3, args.frame_rounds)
    if args.shard_worker:  # the parent checked the load
        shard_worker(args)
        return
    run = protocol.start(args, NAME)
    warm_up_jax()
    t0 = time.perf_counter()
    payload = {"description": __doc__.splitlines()[0], "jax": jax.__version__,
               "dtype": str(np.dtype(jnp.asarray(0.0).dtype)), "settle_frames": SETTLE_FRAMES,
               "substeps_per_call": args.substeps}
    with tempfile.TemporaryDirectory(prefix="mpm_levers_") as state_dir:
        shard_cells = args.shard_cells if "shard" in args.levers else []
        for c in sorted(set(args.cells) | set(shard_cells)):  # settle each column once,
            collapsed(c, state_dir)                            # for this process and worker
        shard = None
        if "shard" in args.levers:
            cmd = [str(Path(__file__).resolve()), "--shard-worker", "--cells",
                   *map(str, shard_cells), "--repeats", str(args.repeats),
                   "--state-dir", state_dir]
            shard, code = protocol.run_worker(run, cmd, TAG)  # 2 devices: shard_worker
            if shard is None:
                raise SystemExit(f"mpm_levers: two-device worker failed (exit {code})")
            payload["two_devices"] = shard
            run.print("two host devices (the library's sharded frame against one device):")
            for r in shard["sizes"]:
                report_shard(run, r)
        payload["xla_options"], payload["cell_order"] = [], []
        for c in args.cells:
            run.print(f"N = {4 * c * c} ({c} cells across):")
            if "options" in args.levers:
                payload["xla_options"].append(option_size(run, c, args.frame_rounds,
                                                          state_dir))
            if "order" in args.levers:
                payload["cell_order"].append(order_size(run, c, args.repeats, args.substeps,
                                                        state_dir))
    payload["duration_s"] = time.perf_counter() - t0
    path = run.finish(args.out, payload)
    run.print(f"wrote {path} ({payload['duration_s']:.0f} s)")


if __name__ == "__main__":
    main()
