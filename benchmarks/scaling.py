"""Scaling table (issue 22): MPM and GNS cost per simulated second and peak memory from ~1k to
~256k particles (2D, float32), fitted cost laws ``cost = a N^b``, and the crossover where the
GNS starts to pay on the same physical column.

    .venv/bin/python benchmarks/scaling.py [--sizes 1024 4096 ...] [--quick] [--repeats 5]

What is measured. Both simulators run the sand column collapse of the shipped GNS
``gns_cg16_pfn`` (aspect ratio 1, friction angle 30 deg), the column made wider and taller to
reach N:

* **MPM**: ``column_collapse`` at the resolution that model emulates (dx = 0.1 m / 16 =
  6.25 mm, 4 particles per cell, so N = 4 c^2 for c cells across), 2.5 ms frames at the
  scene's stable substep (``scene.substep_dt``; it shrinks a little with the domain, whose
  diagonal bounds the free-fall speed of the CFL condition). Cost per simulated second =
  seconds per substep / substep_dt.
* **GNS**: the model's network (latent 64, 5 message-passing steps, radius 0.032 m, capacity
  multiplier 1.1, shipped weights) on a lattice of nodes at the model's node spacing (one node
  per 16 MPM particles: a 4 x 4 block, 12.5 mm), in the domain of the same column scene
  (``GNSConfig.bounds`` enlarged to it; the cost does not depend on the weights' values). One
  step = one 5 ms frame (frame stride 2 of the 2.5 ms data). Cost per simulated second =
  seconds per step / frame_dt. The nodes start at rest; the neighbour list is rebuilt every
  step (no skin), so the cost does not depend on how far they move. Up to 1,024 nodes the list
  is all-pairs, above a cell list (the library's choice).

Same physical column: a column that the MPM resolves with N particles is N / 16 GNS nodes, so
the ratio at a physical size is MPM cost(N) / GNS cost(N / 16) (both measured: the GNS is also
run at the sizes N / 16); the crossover solves MPM law(N) = GNS law(N / 16), the GNS law
fitted there on the node counts of the MPM's columns (N / 16). The GNS is only
accurate on the columns it was trained on (0.1 m wide): above that the figures are costs, not
validated simulations.

**3D** (``--dim 3``, issue 24: the MPM's cost law and memory in 3D, up to the largest
scene that fits): the MPM alone (there is no 3D GNS model yet) on the axisymmetric sand
column of the 3D data (``column_scene(1, dim=3)``: radius ``c dx``, height = radius, 8
particles per cell, so N ~ 8 pi c^3) at a fixed dx = :data:`DX_3D` (the column grows with
N, the substep stays near the same CFL limit), 2.5 ms frames, as ``MPM(scene)`` runs it
by default (one device below ``AUTO_MIN_PARTICLES_3D``, two above).

Each (simulator, size) runs in its own worker process (clean peak RSS; one that runs out of
memory loses only its case): the rollout is compiled ahead of time (``diffgns.memory``: compile
time and XLA's memory analysis), a case whose XLA estimate exceeds 80% of the memory available
is not run, then the first call and ``--repeats`` steady calls are timed (``diffgns.timing``,
block_until_ready; 3 steady calls when one call is expected to exceed ~3 s); frames per call
are chosen so that a call lasts ~1 s on a quiet machine. RSS delta = peak RSS of the worker -
its RSS before building the case (after imports and loading the model; compiling included).
Workers run size by size, MPM and GNS alternating first. Measured under
``benchmarks/protocol.py``; writes ``benchmarks/results/scaling.json`` and ``scaling.png``.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import protocol

SIZES = (1024, 4096, 16384, 65536, 262144)
QUICK_SIZES = (1024, 4096)
MODEL = "gns_cg16_pfn"
TAG = "SCALING_RESULT "
ASPECT, FRICTION = 1.0, 30.0
TARGET_CALL_S = 1.0
LONG_CALL_S = 3.0  # above this expected call time, 3 steady calls
MEMORY_FRACTION = 0.8
# rough cost models (seconds) that choose frames per call; a wrong guess only makes a call
# longer or shorter than TARGET_CALL_S (CPU time of --quick runs at ~1k and ~4k on a loaded
# machine, over the ~1.7 cores a quiet machine gives)
MPM_S_PER_SUBSTEP = (2.0e-4, 2.5e-7)  # overhead, per particle
MPM3D_S_PER_SUBSTEP = (5.0e-4, 1.0e-6)  # overhead, per particle (3D sand, 27-node stencil)
DX_3D = 0.01  # m: the 3D column's cell size (the 3D training data's resolution)
SIZES_3D = (4096, 16384, 65536, 262144, 1048576)
GNS_S_PER_STEP = (2.0e-3, 6.0e-5)  # overhead, per node


# ------------------------------------------------------------------ pure helpers
def model_geometry(info: dict) -> dict[str, float]:
    """The resolution a GNS model emulates, from its ``config.json`` ``info``: MPM cell
    ``dx`` (m), MPM ``particle_spacing`` (4 per cell), the coarse-graining ``factor`` (MPM
    particles per node) and the ``node_spacing`` (m) of the GNS nodes."""
    src = info.get("source") or {}
    if "width" not in src or "cells_across" not in src:
        raise ValueError("model config.json: source.width and source.cells_across are needed "
                         "to know the MPM resolution the model emulates")
    dx = float(src["width"]) / int(src["cells_across"])
    factor = int(info.get("factor", 1))
    spacing = dx / 2.0
    return {"dx": dx, "particle_spacing": spacing, "factor": factor,
            "node_spacing": spacing * math.sqrt(factor)}


def mpm_cells(n_target: int, particles_per_cell: int = 4) -> int:
    """Cells across a square column holding ~``n_target`` MPM particles (>= 1)."""
    return max(1, round(math.sqrt(n_target / particles_per_cell)))


def gns_nodes_across(n_target: int) -> int:
    """Nodes across a square lattice of ~``n_target`` GNS nodes (>= 1)."""
    return max(1, round(math.sqrt(n_target)))


def lattice(m: int, spacing: float) -> np.ndarray:
    """(m^2, 2) float32 node positions (m) of an m x m column at ``spacing`` whose lower left
    corner is the origin: node centres at (i + 1/2) * spacing (cluster means of the MPM
    particles of each 4 x 4 block)."""
    c = (np.arange(m) + 0.5) * spacing
    xx, yy = np.meshgrid(c, c, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel()], axis=1).astype(np.float32)


def gns_sizes(sizes, factor: int, smallest: int = 16) -> list[int]:
    """The GNS node counts to measure: ``sizes`` and the node counts of the columns that the
    MPM runs at ``sizes`` (MPM particles / ``factor``, those of at least ``smallest`` nodes),
    sorted, without duplicates."""
    same_column = {4 * mpm_cells(n) ** 2 // factor for n in sizes}
    return sorted(set(sizes) | {n for n in same_column if n >= smallest})


def frames_per_call(s_per_step: float, steps_per_frame: int, target_s: float = TARGET_CALL_S,
                    max_frames: int = 400) -> int:
    """Frames so that a call lasts ~``target_s`` (at least 1, at most ``max_frames``)."""
    per_frame = max(s_per_step * steps_per_frame, 1e-12)
    return int(min(max_frames, max(1, round(target_s / per_frame))))


def fit_power_law(n, cost) -> dict[str, float] | None:
    """Least-squares fit of ``log cost = log a + b log n``: ``{"a", "b", "r2", "n_min",
    "n_max", "points"}``; None with fewer than two distinct sizes."""
    n = np.asarray(n, float)
    cost = np.asarray(cost, float)
    ok = np.isfinite(n) & np.isfinite(cost) & (n > 0) & (cost > 0)
    n, cost = n[ok], cost[ok]
    if len(np.unique(n)) < 2:
        return None
    x, y = np.log(n), np.log(cost)
    b, log_a = np.polyfit(x, y, 1)
    resid = y - (log_a + b * x)
    ss = float(((y - y.mean()) ** 2).sum())
    r2 = 1.0 - float((resid ** 2).sum()) / ss if ss > 0 else 1.0
    return {"a": float(np.exp(log_a)), "b": float(b), "r2": r2, "n_min": float(n.min()),
            "n_max": float(n.max()), "points": int(len(n))}


def law(fit: dict[str, float], n) -> np.ndarray:
    """``a n^b`` of a :func:`fit_power_law` result."""
    return fit["a"] * np.asarray(n, float) ** fit["b"]


def crossover(mpm: dict[str, float], gns: dict[str, float], factor: int) -> dict[str, Any]:
    """Where MPM law(N) = GNS law(N / factor) (N = MPM particles of the column).

    Returns ``{"n_mpm", "n_gns", "gns_cheaper": "above" | "below" | "everywhere" | "nowhere",
    "in_measured_range"}``; ``n_mpm`` is None when the exponents are equal (the ratio is then
    the same at every size). ``gns_cheaper`` says on which side of the crossover
    MPM cost / GNS cost exceeds 1.
    """
    lr0 = math.log(mpm["a"] / gns["a"]) + gns["b"] * math.log(factor)  # log ratio at N = 1
    db = mpm["b"] - gns["b"]  # ratio = exp(lr0) N^db
    if abs(db) < 1e-12:
        return {"n_mpm": None, "n_gns": None, "in_measured_range": False,
                "gns_cheaper": "everywhere" if lr0 > 0 else "nowhere"}
    n = math.exp(-lr0 / db)
    lo = max(mpm["n_min"], gns["n_min"] * factor)
    hi = min(mpm["n_max"], gns["n_max"] * factor)
    return {"n_mpm": n, "n_gns": n / factor, "gns_cheaper": "above" if db > 0 else "below",
            "in_measured_range": bool(lo <= n <= hi)}


def physical_pairs(mpm_rows: list[dict], gns_rows: list[dict], factor: int) -> list[dict]:
    """For every MPM row, the GNS row of the same column (``n_particles == N / factor``):
    MPM and GNS cost per simulated second and their ratio (MPM / GNS; > 1: the GNS is
    cheaper). MPM rows without their GNS row (or without a cost) are left out."""
    by_n = {r["n_particles"]: r for r in gns_rows if r.get("s_per_sim_s")}
    out = []
    for m in mpm_rows:
        g = by_n.get(m["n_particles"] // factor)
        if g is None or not m.get("s_per_sim_s") or m["n_particles"] % factor:
            continue
        out.append({"mpm_particles": m["n_particles"], "gns_nodes": g["n_particles"],
                    "mpm_s_per_sim_s": m["s_per_sim_s"], "gns_s_per_sim_s": g["s_per_sim_s"],
                    "mpm_over_gns": m["s_per_sim_s"] / g["s_per_sim_s"]})
    return out


# ------------------------------------------------------------------ worker: one case
def _available_mb() -> float | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024 / 1e6
    except OSError:
        pass
    return None


def _mpm_case(n_target: int, geo: dict, model=None):
    from diffgns import MPM
    from diffgns.scene.builders import column_collapse

    c = mpm_cells(n_target)
    scene = column_collapse(width=c * geo["dx"], aspect_ratio=ASPECT, friction_angle=FRICTION,
                            cells_across=c, frame_dt=2.5e-3)
    sim = MPM(scene)
    n, sub = scene.n_particles, scene.substeps
    est = MPM_S_PER_SUBSTEP[0] + MPM_S_PER_SUBSTEP[1] * n
    info = {"n_particles": n, "cells_across": c, "width_m": c * geo["dx"], "dx_m": scene.dx,
            "grid_shape": list(scene.grid_shape), "domain_m": [list(d) for d in scene.domain],
            "frame_dt_s": scene.frame_dt, "substeps_per_frame": sub,
            "dt_s": scene.substep_dt}
    return sim, sim.params(), sim.init(), sub, est, info


def _mpm3d_case(n_target: int, geo: dict, model=None):
    from diffgns import MPM
    from diffgns.scene.recipes import column_scene

    c = max(2, round((n_target / (8 * math.pi)) ** (1 / 3)))
    scene = column_scene(ASPECT, width=c * DX_3D, cells_across=c, dim=3,
                         friction_angle=FRICTION, frame_dt=2.5e-3)
    sim = MPM(scene)
    n, sub = scene.n_particles, scene.substeps
    est = MPM3D_S_PER_SUBSTEP[0] + MPM3D_S_PER_SUBSTEP[1] * n
    info = {"n_particles": n, "cells_across_radius": c, "radius_m": c * DX_3D,
            "dx_m": scene.dx, "grid_shape": list(scene.grid_shape),
            "domain_m": [list(d) for d in scene.domain], "frame_dt_s": scene.frame_dt,
            "substeps_per_frame": sub, "dt_s": scene.substep_dt,
            "devices": len(sim.devices or [None])}
    return sim, sim.params(), sim.init(), sub, est, info


def _gns_case(n_target: int, geo: dict, model):
    import dataclasses

    import jax.numpy as jnp

    from diffgns.graph.gns import GNS, GNSParams
    from diffgns.scene.builders import column_collapse
    from diffgns.trajectory import SAND

    shipped, network, _ = model
    m = gns_nodes_across(n_target)
    width = m * geo["node_spacing"]
    domain = column_collapse(width=width, aspect_ratio=ASPECT, friction_angle=FRICTION,
                             cells_across=round(width / geo["dx"])).domain
    cfg = dataclasses.replace(shipped.config, bounds=domain)
    gns = GNS(cfg, shipped.normalizer, frame_dt=shipped.frame_dt)
    x = jnp.asarray(lattice(m, geo["node_spacing"]))
    history = jnp.repeat(x[:, None], cfg.history + 1, axis=1)  # at rest
    params = GNSParams(network, jnp.asarray(math.tan(math.radians(FRICTION)), jnp.float32))
    state = gns.init(history, jnp.full(m * m, SAND, jnp.int32))  # allocates the list
    cap = int(state.nbrs.idx.shape[-1])
    pairs = int(jnp.sum(state.nbrs.idx[0] < m * m))
    est = GNS_S_PER_STEP[0] + GNS_S_PER_STEP[1] * m * m
    info = {"n_particles": m * m, "nodes_across": m, "width_m": width,
            "node_spacing_m": geo["node_spacing"], "bounds_m": [list(d) for d in domain],
            "radius_m": cfg.radius, "latent": cfg.latent, "mp_steps": cfg.mp_steps,
            "capacity_multiplier": cfg.capacity_multiplier, "edge_capacity": cap,
            "neighbours_per_node": pairs / (m * m),
            "neighbour_list": "all-pairs" if m * m <= gns.neighbors.all_pairs_max
            else "cell list", "frame_dt_s": gns.frame_dt, "dt_s": gns.frame_dt}
    return gns, params, state, 1, est, info


class _TooBig(Exception):
    """The compiled program would not fit in the memory available."""


def measure_case(kind: str, n_target: int, repeats: int) -> dict[str, Any]:
    """Build, compile (ahead of time) and time one case; the worker's result."""
    from functools import partial

    import jax

    from diffgns.graph.train_loop import load_model
    from diffgns.interface import overflow_flags, retry_on_overflow, rollout
    from diffgns.memory import MB, compile_ahead, current_rss_mb, peak_rss_mb
    from diffgns.models import model_path
    from diffgns.timing import measure, time_call

    protocol.warm_up_jax()
    geo = model_geometry(json.loads((model_path(MODEL) / "config.json").read_text()))
    model = load_model(MODEL) if kind == "gns" else None
    rss0 = current_rss_mb()  # after imports and loading the model
    case = {"mpm": _mpm_case, "mpm3d": _mpm3d_case, "gns": _gns_case}[kind]
    sim, params, state, steps_per_frame, est, res = case(n_target, geo, model)
    frames = frames_per_call(est, steps_per_frame)
    steps = frames * steps_per_frame
    reps = repeats if est * steps <= LONG_CALL_S else min(repeats, 3)
    res.update(sim=kind, n_target=n_target, frames_per_call=frames, steps_per_call=steps,
               repeats=reps, dtype=str(jax.numpy.asarray(0.0).dtype))
    prog = jax.jit(partial(rollout, sim, n_frames=frames))

    def first_call(s):
        """Compile ahead, refuse a program that does not fit in memory, run it once."""
        exe, comp = compile_ahead(prog, params, s)
        need = comp["memory"].get("total_bytes", 0) / MB
        avail = _available_mb()
        if avail is not None and need > MEMORY_FRACTION * avail:
            raise _TooBig(f"XLA needs {need:.0f} MB > {MEMORY_FRACTION:.0%} of the "
                          f"{avail:.0f} MB available")
        first, out = measure(lambda: exe(params, s))
        return exe, comp, first, out, need

    def realloc(s, r, attempt):  # GNS neighbour list too small: re-allocate, recompile
        flags = overflow_flags(r[3][0])
        return sim.reallocate(s, r[3][0], int(np.argmax(flags)), attempt)

    try:
        (exe, comp, first, out0, need), state = retry_on_overflow(
            first_call, state, lambda r: bool(overflow_flags(r[3][0]).any()), realloc)
    except _TooBig as e:
        res["skipped"] = str(e)
        return res
    del out0
    res["compile"] = comp
    t, (frames_out, _) = time_call(lambda: exe(params, state), reps, first=first)
    t.pop("compile_s")  # compiled ahead: the first call is a warm-up
    n = res["n_particles"]
    res.update(timing=t, s_per_step=t["median_s"] / steps,
               s_per_sim_s=t["median_s"] / steps / res["dt_s"],
               particle_steps_per_s=n * steps / t["median_s"],
               finite=bool(jax.numpy.all(jax.numpy.isfinite(frames_out.positions))),
               overflow=bool(overflow_flags(frames_out).any()),
               rss_before_mb=rss0, peak_rss_mb=peak_rss_mb(),
               peak_rss_delta_mb=peak_rss_mb() - rss0, xla_total_mb=need)
    return res



# ------------------------------------------------------------------ report
def _f(x: float | None, fmt: str = ".3g") -> str:
    return "-" if x is None else format(x, fmt)


def _cols(r: dict | None) -> list[str]:
    if r is None:
        return ["-"] * 4
    if "s_per_step" not in r:
        return ["skipped" if r.get("skipped") else "failed", "-", "-", "-"]
    return [_f(r["s_per_step"]), _f(r["s_per_sim_s"]), _f(r["xla_total_mb"], ".0f"),
            _f(r["peak_rss_delta_mb"], ".0f")]


def cost_table(mpm_rows: list[dict], gns_rows: list[dict]) -> str:
    """Table of both simulators by particle (node) count N."""
    mpm = {r["n_particles"]: r for r in mpm_rows}
    gns = {r["n_particles"]: r for r in gns_rows}
    head = ["N", "MPM s/substep", "MPM s/sim-s", "MPM XLA MB", "MPM RSS+ MB",
            "GNS s/step", "GNS s/sim-s", "GNS XLA MB", "GNS RSS+ MB"]
    lines = [" ".join(f"{h:>12}" for h in head)]
    for n in sorted(set(mpm) | set(gns)):
        cells = [str(n), *_cols(mpm.get(n)), *_cols(gns.get(n))]
        lines.append(" ".join(f"{c:>12}" for c in cells))
    lines.append("s/sim-s = wall seconds per simulated second (median steady call); XLA MB = "
                 "argument + output + temp - alias of the compiled rollout; RSS+ = peak RSS of "
                 "the case's process above its RSS before building the case (compiling "
                 "included); MB = 1e6 bytes")
    return "\n".join(lines)


def pair_table(pairs: list[dict], factor: int) -> str:
    """Table of the same physical columns: MPM particles vs GNS nodes and the cost ratio."""
    head = ["MPM particles", "GNS nodes", "MPM s/sim-s", "GNS s/sim-s", "MPM/GNS"]
    lines = [" ".join(f"{h:>13}" for h in head)]
    for p in pairs:
        cells = [str(p["mpm_particles"]), str(p["gns_nodes"]), _f(p["mpm_s_per_sim_s"]),
                 _f(p["gns_s_per_sim_s"]), _f(p["mpm_over_gns"])]
        lines.append(" ".join(f"{c:>13}" for c in cells))
    lines.append(f"same column: 1 GNS node per {factor} MPM particles; MPM/GNS > 1: the GNS is "
                 "cheaper")
    return "\n".join(lines)


def summary_lines(laws: dict, cross: dict | None, factor: int, pairs=()) -> list[str]:
    """The fitted laws, the crossover and the measured same-column ratios, one line each."""
    out = []
    for k, name in (("mpm", "MPM (N particles)"), ("gns", "GNS (N nodes)"),
                    ("gns_same_column", "GNS on the MPM's columns (N nodes)")):
        f = laws.get(k)
        if k not in laws:
            continue
        out.append(f"{name}: no fit (fewer than 2 sizes)" if f is None else
                   f"{name}: s per simulated s = {f['a']:.3g} N^{f['b']:.3f} "
                   f"(r2 {f['r2']:.3f}, N {f['n_min']:.0f}-{f['n_max']:.0f})")
    if cross is None:
        out.append("crossover: needs both laws")
    elif cross["n_mpm"] is None:
        out.append(f"crossover: none (equal exponents); the GNS is cheaper {cross['gns_cheaper']}")
    else:
        where = "inside" if cross["in_measured_range"] else "OUTSIDE (extrapolated)"
        out.append(f"crossover: MPM law(N) = GNS same-column law(N/{factor}) at "
                   f"N = {cross['n_mpm']:.3g} MPM particles ({cross['n_gns']:.3g} GNS nodes), "
                   f"{where} the measured range; the GNS is cheaper {cross['gns_cheaper']} it")
    if pairs:
        r = [p["mpm_over_gns"] for p in pairs]
        cheaper = [p["mpm_particles"] for p in pairs if p["mpm_over_gns"] > 1]
        verdict = ("the GNS is cheaper on every measured column" if len(cheaper) == len(r) else
                   "the MPM is cheaper on every measured column" if not cheaper else
                   f"the GNS is cheaper on the columns of {', '.join(map(str, cheaper))} "
                   "MPM particles")
        out.append(f"measured MPM/GNS on the same columns: {min(r):.3g} to {max(r):.3g}; "
                   + verdict)
    return out


def plot(mpm_rows, gns_rows, laws, pairs, cross, factor, path) -> None:
    plt = protocol.use_agg()
    fig, (a0, a1, a2) = plt.subplots(1, 3, figsize=(15, 4.5))
    for rows, k, c, lab in ((mpm_rows, "mpm", "tab:blue", "MPM (particles)"),
                            (gns_rows, "gns", "tab:red", "GNS (nodes)")):
        ok = [r for r in rows if "s_per_sim_s" in r]
        n = np.array([r["n_particles"] for r in ok], float)
        a0.loglog(n, [r["s_per_sim_s"] for r in ok], "o", color=c, label=lab)
        if laws.get(k) and len(n):
            nn = np.geomspace(n.min(), n.max(), 50)
            f = laws[k]
            a0.loglog(nn, law(f, nn), "-", color=c, alpha=0.6,
                      label=f"{f['a']:.2g} N^{f['b']:.2f}")
        a2.loglog(n, [r["xla_total_mb"] for r in ok], "o-", color=c, label=f"{lab}: XLA")
        a2.loglog(n, [r["peak_rss_delta_mb"] for r in ok], "x:", color=c,
                  label=f"{lab}: peak RSS delta")
    a0.set_xlabel("N (MPM particles / GNS nodes)")
    a0.set_ylabel("wall s per simulated s")
    a0.set_title("cost per simulated second (2D, float32)")
    a0.legend(fontsize=7)
    if pairs:
        nm = np.array([p["mpm_particles"] for p in pairs], float)
        a1.loglog(nm, [p["mpm_over_gns"] for p in pairs], "o", color="k", label="measured")
        if laws.get("mpm") and laws.get("gns_same_column"):
            nn = np.geomspace(nm.min(), nm.max(), 50)
            a1.loglog(nn, law(laws["mpm"], nn) / law(laws["gns_same_column"], nn / factor), "-",
                      color="gray", label="fitted laws")
    a1.axhline(1.0, color="tab:green", lw=0.8)
    if cross and cross.get("n_mpm") and cross["in_measured_range"]:
        a1.axvline(cross["n_mpm"], color="tab:green", ls="--", label="crossover")
    a1.set_xlabel(f"MPM particles of the column (GNS nodes = N / {factor})")
    a1.set_ylabel("MPM cost / GNS cost")
    a1.set_title("same physical column")
    a1.legend(fontsize=7)
    a2.set_xlabel("N")
    a2.set_ylabel("MB")
    a2.set_title("memory")
    a2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ------------------------------------------------------------------ driver
def run_case(run: protocol.Run, kind: str, n: int, repeats: int) -> dict[str, Any]:
    """One case in a fresh worker process (see the module docstring)."""
    args = [str(Path(__file__).resolve()), "--case", kind, str(n), "--repeats", str(repeats)]
    from diffgns.timing import measure, no_sync

    took, (res, code) = measure(lambda: protocol.run_worker(run, args, TAG), sync=no_sync)
    if res is None:
        res = {"sim": kind, "n_target": n, "failed": f"worker exit code {code}",
               "n_particles": None}
    res["worker_wall_s"] = took.wall_s  # the whole case: start-up, building, compiling, timing
    line = (f"{kind} N={res['n_particles']}: " + (
        f"{res['s_per_step']:.3g} s/step, {res['s_per_sim_s']:.3g} s per simulated s, "
        f"XLA {res['xla_total_mb']:.0f} MB" if "s_per_step" in res else
        res.get("skipped") or res.get("failed", "?")))
    run.print(line)
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=None, metavar="N",
                    help=f"MPM particle counts, also GNS node counts (default {SIZES})")
    ap.add_argument("--quick", action="store_true", help=f"only {QUICK_SIZES}")
    ap.add_argument("--repeats", type=int, default=5,
                    help="steady calls per case (3 when one call exceeds ~3 s)")
    ap.add_argument("--dim", type=int, choices=(2, 3), default=2,
                    help=f"3: the 3D MPM alone (default sizes {SIZES_3D})")
    ap.add_argument("--out", default=None, help="default scaling.json (3D: scaling_3d.json)")
    ap.add_argument("--case", nargs=2, metavar=("SIM", "N"), help=argparse.SUPPRESS)
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    if args.case:  # worker: one case, its JSON on one tagged line of stdout
        res = measure_case(args.case[0], int(args.case[1]), max(1, args.repeats))
        print(TAG + json.dumps(res, default=protocol._json_default), flush=True)
        return
    run = protocol.start(args, "scaling")
    if args.dim == 3:
        return main_3d(run, args)
    args.out = args.out or "scaling.json"
    from diffgns.models import model_path

    info = json.loads((model_path(MODEL) / "config.json").read_text())
    geo = model_geometry(info)
    factor = geo["factor"]
    sizes = sorted(set(args.sizes or (QUICK_SIZES if args.quick else SIZES)))
    g_sizes = gns_sizes(sizes, factor)
    reps = max(3, args.repeats)
    cases = []
    for i, n in enumerate(sorted(set(sizes) | set(g_sizes))):
        kinds = [k for k, s in (("mpm", sizes), ("gns", g_sizes)) if n in s]
        cases += [(k, n) for k in (kinds if i % 2 == 0 else kinds[::-1])]
    rows = [run_case(run, k, n, reps) for k, n in cases]
    mpm_rows = [r for r in rows if r["sim"] == "mpm" and r["n_particles"]]
    gns_rows = [r for r in rows if r["sim"] == "gns" and r["n_particles"]]
    lo, hi = min(sizes), max(sizes)
    ranges = {"mpm": (mpm_rows, lo, hi), "gns": (gns_rows, lo, hi),
              "gns_same_column": (gns_rows, lo // factor, hi // factor)}
    laws = {}
    for k, (rs, a, b) in ranges.items():
        fit_rows = [r for r in rs if "s_per_sim_s" in r and a <= r["n_particles"] <= b]
        laws[k] = fit_power_law([r["n_particles"] for r in fit_rows],
                                [r["s_per_sim_s"] for r in fit_rows])
    cross = (crossover(laws["mpm"], laws["gns_same_column"], factor)
             if laws["mpm"] and laws["gns_same_column"] else None)
    pairs = physical_pairs(mpm_rows, gns_rows, factor)
    run.print(cost_table(mpm_rows, gns_rows))
    run.print(pair_table(pairs, factor))
    for line in summary_lines(laws, cross, factor, pairs):
        run.print(line)
    payload = {
        "description": __doc__.split("\n\n")[2].replace("\n", " "),
        "model": MODEL, "geometry": geo, "aspect_ratio": ASPECT, "friction_angle": FRICTION,
        "sizes": sizes, "gns_sizes": g_sizes, "repeats": reps,
        "fit_ranges_n": {k: [a, b] for k, (_, a, b) in ranges.items()}, "laws": laws,
        "crossover": cross, "same_column": pairs,
        "results": rows,
    }
    path = run.finish(args.out, payload, lambda p: plot(mpm_rows, gns_rows, laws, pairs,
                                                         cross, factor, p.with_suffix(".png")))
    run.print(f"wrote {path} (and the plot beside it)")


def main_3d(run: protocol.Run, args) -> None:
    """The 3D MPM's cost law and memory (see the module docstring)."""
    sizes = sorted(set(args.sizes or SIZES_3D))
    rows = [run_case(run, "mpm3d", n, max(3, args.repeats)) for n in sizes]
    ok = [r for r in rows if "s_per_sim_s" in r]
    law = fit_power_law([r["n_particles"] for r in ok], [r["s_per_sim_s"] for r in ok])
    law_substep = fit_power_law([r["n_particles"] for r in ok], [r["s_per_step"] for r in ok])
    head = ["N", "substeps/frame", "devices", "s/substep", "us/particle-substep", "s/sim-s",
            "XLA MB", "RSS+ MB"]
    lines = [" ".join(f"{h:>18}" for h in head)]
    for r in rows:
        if "s_per_step" not in r:
            lines.append(f"{r.get('n_particles')!s:>18} " + (r.get("skipped")
                                                              or r.get("failed", "?")))
            continue
        cells = [r["n_particles"], r["substeps_per_frame"], r["devices"], _f(r["s_per_step"]),
                 _f(1e6 * r["s_per_step"] / r["n_particles"]), _f(r["s_per_sim_s"]),
                 _f(r["xla_total_mb"], ".0f"), _f(r["peak_rss_delta_mb"], ".0f")]
        lines.append(" ".join(f"{c!s:>18}" for c in cells))
    run.print("\n".join(lines))
    if law:
        run.print(f"3D MPM cost law: {law['a']:.3g} N^{law['b']:.3f} s per simulated second "
                  f"(R^2 {law['r2']:.3f}); per substep {law_substep['a']:.3g} "
                  f"N^{law_substep['b']:.3f} s")
    payload = {"description": "3D MPM cost per simulated second and memory (issue 24)",
               "dx_m": DX_3D, "aspect_ratio": ASPECT, "friction_angle": FRICTION,
               "sizes": sizes, "law_s_per_sim_s": law, "law_s_per_substep": law_substep,
               "results": rows}
    path = run.finish(args.out or "scaling_3d.json", payload)
    run.print(f"wrote {path}")


if __name__ == "__main__":
    main()
