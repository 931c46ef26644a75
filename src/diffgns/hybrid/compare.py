"""Accuracy and cost of MPM, GNS and hybrid runs of one column collapse, side by side.

Used by ``diffgns hybrid`` and ``benchmarks/hybrid_pareto.py``. Every simulator is scored
against one reference trajectory (normally a finer MPM) on the same GNS frames:

* runout error ``|L - L_ref| / L_ref`` at the last frame (farthest particle from the wall);
* material-point position error over time: each particle is compared with the mean of the
  reference particles that started nearest to it (resolutions may differ), averaged over
  particles; reported at the last frame and as the mean over all frames.

Timings are steady-state seconds of the jitted rollout (compile separated, median of
``repeats``, ``block_until_ready``).
"""
from __future__ import annotations

import time

import jax
import numpy as np

from diffgns import MPM
from diffgns.hybrid.simulator import Hybrid, Schedule
from diffgns.scene.builders import column_collapse


def lagrangian_map(x0: np.ndarray, x0_ref: np.ndarray) -> np.ndarray:
    """(N, k) indices of the k reference particles nearest to each particle at t = 0, with
    k = round(N_ref / N) (at least 1): the reference material of each particle."""
    k = max(1, int(round(len(x0_ref) / len(x0))))
    d2 = ((x0[:, None] - x0_ref[None]) ** 2).sum(-1)
    return np.argsort(d2, axis=1)[:, :k]


def position_error(x: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
    """(T,) mean distance (m) between particles of ``x`` (T, N, 2) and their reference
    material in ``x_ref`` (T, N_ref, 2) (same frames)."""
    idx = lagrangian_map(x[0], x_ref[0])
    ref = x_ref[:, idx].mean(2)  # (T, N, 2)
    return np.sqrt(((x - ref) ** 2).sum(-1)).mean(-1)


def score_against(x: np.ndarray, x_ref: np.ndarray, wall_x: float = 0.0) -> dict:
    """Runout and material-point errors of positions ``x`` (T, N, 2) against ``x_ref``."""
    err = position_error(x, x_ref)
    L, Lr = x[-1, :, 0].max() - wall_x, x_ref[-1, :, 0].max() - wall_x
    return dict(runout_m=float(L), runout_ref_m=float(Lr),
                runout_error=float(abs(L - Lr) / Lr), final_position_error_m=float(err[-1]),
                mean_position_error_m=float(err.mean()), finite=bool(np.isfinite(x).all()))


def _steady(fn, repeats: int):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t0)
    med = float(np.median(ts))
    return out, dict(seconds=med, seconds_all=ts, compile_s=max(0.0, first - med))


def column_scene(aspect_ratio: float, friction_angle: float, cells_across: int = 8,
                 domain=(0.8, 0.35)):
    """The column collapse the shipped GNS was trained on (width 0.1 m)."""
    return column_collapse(width=0.1, aspect_ratio=aspect_ratio, friction_angle=friction_angle,
                           cells_across=cells_across, domain_length=domain[0],
                           domain_height=domain[1])


def model_cells(info: dict) -> int:
    """MPM resolution (cells across the column) of a GNS model's training data."""
    return int(info.get("source", {}).get("cells_across", 8))


def run_mpm(scene, n_frames: int, stride: int, repeats: int = 3):
    """(positions (n_frames+1, N, 2) on GNS frames, timing dict) of the MPM alone."""
    sim = MPM(scene)
    p, s = sim.params(), sim.init_state()
    out, t = _steady(lambda: sim.rollout_full(p, s, n_frames=n_frames * stride), repeats)
    t["substeps_per_frame"] = sim.n_sub
    return np.asarray(out[0])[::stride], t


def node_factor(info: dict, cells_across: int) -> int:
    """MPM particles per GNS node when a GNS model runs on the MPM at ``cells_across`` cells:
    its training factor scaled so that the nodes keep the spacing it was trained on."""
    f = info.get("factor", 1) * (cells_across / model_cells(info)) ** 2
    if abs(f - round(f)) > 1e-9 or round(f) < 1:
        raise ValueError(f"the GNS (factor {info.get('factor', 1)} at {model_cells(info)} cells)"
                         f" cannot run on {cells_across} cells: {f:g} particles per node")
    return int(round(f))


def run_hybrid(scene, gns, gns_params, info: dict, schedule: Schedule, n_frames: int,
               repeats: int = 3, cells_across: int | None = None):
    """(HybridResult, timing dict) of a hybrid (or GNS-only) run of ``n_frames`` frames;
    ``cells_across``: the resolution of ``scene`` when it is not the model's own."""
    sim = MPM(scene)
    p, s = sim.params(), sim.init_state()
    factor = node_factor(info, cells_across or model_cells(info))
    hyb = Hybrid(sim, gns, gns_params, info.get("frame_stride", 1), factor, schedule)
    t0 = time.perf_counter()
    _, nbrs = jax.block_until_ready(hyb.run(p, s, n_frames))  # allocate a list that fits
    first = time.perf_counter() - t0
    res, t = _steady(lambda: hyb.run(p, s, n_frames, nbrs)[0], repeats)
    t["compile_s"] = max(0.0, first - t["seconds"])
    t["mpm_fraction"] = res.mpm_fraction
    return res, t


def compare(model, aspect_ratio: float, friction_angle: float, schedule: Schedule,
            n_frames: int, reference_cells: int = 16, cells_across: int | None = None,
            repeats: int = 3) -> dict:
    """MPM (reference and at ``cells_across``), GNS alone and the hybrid on one column.

    ``model`` is ``(gns, params, info)`` from :func:`~diffgns.graph.train_loop.load_model`;
    the GNS and hybrid run on the MPM resolution of its training data unless ``cells_across``
    is given.
    Returns ``{"rows": [...], "positions": {label: (T+1, N, 2)}, "frame_dt": s}``; each row
    has the label, the scores of :func:`score_against` and the timing.
    """
    gns, gp, info = model
    stride = info.get("frame_stride", 1)
    cells_across = cells_across or model_cells(info)
    ref, t_ref = run_mpm(column_scene(aspect_ratio, friction_angle, reference_cells),
                         n_frames, stride, repeats=1)
    scene = column_scene(aspect_ratio, friction_angle, cells_across)
    x_mpm, t_mpm = run_mpm(scene, n_frames, stride, repeats)
    gns_only = Schedule(warmup=schedule.warmup, gns_frames=1, mpm_frames=0,
                        particle_map=schedule.particle_map)
    runs = {f"MPM {reference_cells} cells (reference)": (ref, t_ref),
            f"MPM {cells_across} cells": (x_mpm, t_mpm)}
    for sched in (gns_only, schedule):
        res, t = run_hybrid(scene, gns, gp, info, sched, n_frames, repeats, cells_across)
        runs[sched.label] = (np.asarray(res.positions), t)
    rows = []
    for label, (x, t) in runs.items():
        rows.append(dict(label=label, **score_against(x, ref), **t))
    return dict(rows=rows, positions={k: v[0] for k, v in runs.items()},
                frame_dt=float(scene.frame_dt) * stride, bounds=scene.domain)
