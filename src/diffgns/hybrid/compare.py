"""Accuracy and cost of MPM, GNS and hybrid runs of one scene, side by side.

Used by ``diffgns hybrid`` and ``benchmarks/hybrid_pareto.py``. Any scene a GNS model
supports (:func:`diffgns.graph.support.check_scene`: its training box, sand, the MPM
resolution and frame it emulates) runs; the column collapse of the model's training data is
built from the model folder (:func:`column_scene`). Every simulator is scored against one
reference trajectory (normally a finer MPM) on the same GNS frames:

* runout error ``|L - L_ref| / L_ref`` at the last frame (farthest particle from the box's
  left wall);
* material-point position error over time: each particle is compared with the mean of the
  reference particles that started nearest to it (resolutions may differ), averaged over
  particles; reported at the last frame and as the mean over all frames.

Timings are steady-state seconds of the jitted rollout (:func:`diffgns.timing.time_call`:
compile separated, median of ``repeats``, ``block_until_ready``).
"""
from __future__ import annotations

import numpy as np

from diffgns import MPM
from diffgns.clamp import clamp_summary
from diffgns.graph.support import check_scene
from diffgns.graph.support import node_factor as _node_factor
from diffgns.hybrid.simulator import Hybrid, HybridParams, Schedule
from diffgns.interface import rollout_jit
from diffgns.memory import check_mappings
from diffgns.scene.builders import column_collapse
from diffgns.timing import measure, time_call


def lagrangian_map(x0: np.ndarray, x0_ref: np.ndarray) -> np.ndarray:
    """(N, k) indices of the k reference particles nearest to each particle at t = 0, with
    k = round(N_ref / N) (at least 1): the reference material of each particle."""
    k = max(1, int(round(len(x0_ref) / len(x0))))
    rows = max(1, 2**26 // max(1, len(x0_ref)))  # blocks of ~0.5 GB of squared distances
    return np.concatenate([
        np.argsort(((x0[i:i + rows, None] - x0_ref[None]) ** 2).sum(-1), axis=1)[:, :k]
        for i in range(0, len(x0), rows)])


def position_error(x: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
    """(T,) mean distance (m) between particles of ``x`` (T, N, 2) and their reference
    material in ``x_ref`` (T, N_ref, 2) (same frames)."""
    idx = lagrangian_map(x[0], x_ref[0])
    ref = x_ref[:, idx].mean(2)  # (T, N, 2)
    return np.sqrt(((x - ref) ** 2).sum(-1)).mean(-1)


def score_against(x: np.ndarray, x_ref: np.ndarray, wall_x: float = 0.0) -> dict:
    """Runout (from ``wall_x``, m) and material-point errors of positions ``x`` (T, N, 2)
    against ``x_ref``."""
    err = position_error(x, x_ref)
    L, Lr = x[-1, :, 0].max() - wall_x, x_ref[-1, :, 0].max() - wall_x
    return dict(runout_m=float(L), runout_ref_m=float(Lr),
                runout_error=float(abs(L - Lr) / Lr), final_position_error_m=float(err[-1]),
                mean_position_error_m=float(err.mean()), finite=bool(np.isfinite(x).all()))


def _timing(t: dict) -> dict:
    """The timing keys of a row from :func:`~diffgns.timing.time_call`'s summary: steady
    ``seconds`` (median), ``seconds_all``, ``cpu_seconds`` (median) and ``compile_s``."""
    return dict(seconds=t["median_s"], seconds_all=t["samples_s"],
                cpu_seconds=t["cpu_median_s"], compile_s=t["compile_s"])


#: length (m) that a "cells" resolution counts cells over for random family scenes: the
#: column width of every shipped column model (and FamilyRanges.dx = REFERENCE_LENGTH / 16)
REFERENCE_LENGTH = 0.1


def model_cells(info: dict) -> int:
    """MPM resolution of a GNS model's training data: cells across the training column, or,
    for a model of random family scenes (``source.dx`` only), cells per
    :data:`REFERENCE_LENGTH` (0.1 m: 16 for dx = 6.25 mm)."""
    src = info.get("source") or {}
    if "cells_across" in src:
        return int(src["cells_across"])
    if "dx" in src:
        cells = REFERENCE_LENGTH / float(src["dx"])
        if abs(cells - round(cells)) > 1e-6:
            raise ValueError(f"the model's MPM cell size {src['dx']} m is not "
                             f"{REFERENCE_LENGTH} m over a whole number of cells")
        return int(round(cells))
    raise ValueError("the model folder records neither source.cells_across nor source.dx "
                     "(the MPM resolution of its training data)")


def family_scene(family: str, seed: int, cells: int):
    """The random scene ``family``:``seed`` (:func:`diffgns.scene.families.random_scene`,
    default ranges: drawn on its own 6.25 mm lattice, so the same bodies, obstacles and box at
    every resolution) with the MPM at ``cells`` cells per :data:`REFERENCE_LENGTH` (0.1 m)."""
    from diffgns.scene.families import random_scene

    if not (isinstance(cells, (int, np.integer)) and cells >= 1):
        raise ValueError(f"family_scene: cells = {cells!r} must be an integer >= 1 (cells per "
                         f"{REFERENCE_LENGTH} m)")
    scene = random_scene(family, seed)
    return scene.replace(dx=REFERENCE_LENGTH / cells)  # the Scene refuses a box not in cells


def column_scene(aspect_ratio: float, friction_angle: float, cells_across: int, info: dict):
    """The column collapse of a model's training data (``info["source"]``: column width and
    box) at ``cells_across`` cells across the column."""
    src = info.get("source") or {}
    bounds = src.get("bounds") or info["gns"]["bounds"]
    (x0, x1), (y0, y1) = bounds
    if src.get("kind", "column") != "column" or "width" not in src or (x0, y0) != (0, 0):
        raise ValueError(f"the model was not trained on column collapses from the origin "
                         f"(source {src}); give a scene instead")
    return column_collapse(width=float(src["width"]), aspect_ratio=aspect_ratio,
                           friction_angle=friction_angle, cells_across=cells_across,
                           domain_length=x1 - x0, domain_height=y1 - y0)


def run_mpm(scene, n_frames: int, stride: int, repeats: int = 3):
    """(positions (n_frames+1, N, 2) on GNS frames, timing dict with the run's clamp summary
    (:func:`diffgns.clamp.clamp_summary`, over all MPM frames)) of the MPM alone."""
    sim = MPM(scene)
    p, s = sim.params(), sim.init()
    t, frames = time_call(lambda: rollout_jit(sim, p, s, n_frames=n_frames * stride)[0],
                          repeats)
    return np.asarray(frames.positions)[::stride], dict(
        _timing(t), substeps_per_frame=sim.n_sub,
        **clamp_summary(frames.clamp.moved, frames.clamp.shift))


def node_factor(info: dict, cells_across: int) -> int:
    """MPM particles per GNS node when a GNS model runs on the MPM at ``cells_across`` cells:
    its training factor scaled so that the nodes keep the spacing it was trained on."""
    return _node_factor(int(info.get("factor", 1)), 1.0 / model_cells(info), 1.0 / cells_across)


def make_hybrid(scene, gns, info: dict, schedule: Schedule, resolution: str = "exact",
                model: str = "the model") -> Hybrid:
    """The :class:`Hybrid` of ``scene`` and a trained GNS (``info``: its ``config.json``);
    refuses a scene the model does not support, naming why (``resolution``: see
    :func:`~diffgns.graph.support.check_scene`)."""
    sup = check_scene(scene, info, resolution, model)
    gns, geometry = gns.for_scene(scene)  # the scene's walls and obstacles
    return Hybrid(MPM(scene), gns, sup.frame_stride, sup.factor, schedule, geometry=geometry)


def run_hybrid(scene, gns, network, info: dict, schedule: Schedule, n_frames: int,
               repeats: int = 3, cells_across: int | None = None):
    """(HybridResult, timing dict) of a hybrid (or GNS-only) run of ``n_frames`` frames;
    ``cells_across``: the resolution of ``scene`` when it is not the model's own (nodes then
    keep the trained spacing)."""
    check_mappings()
    own = cells_across is None or cells_across == model_cells(info)
    hyb = make_hybrid(scene, gns, info, schedule, "exact" if own else "node-spacing")
    params = HybridParams(hyb.mpm.params(), network)
    s = hyb.mpm.init()
    first, (_, state) = measure(lambda: hyb.run(params, s, n_frames))  # allocates a list
    t, res = time_call(lambda: hyb.run(params, s, n_frames, state=state)[0], repeats,
                       first=first)
    return res, dict(_timing(t), mpm_fraction=res.mpm_fraction,
                     warmup_frames=res.warmup_frames, **res.clamp_summary())


def compare_scene(model, scene, reference, schedule: Schedule, n_frames: int,
                  repeats: int = 3, labels: tuple[str, str] | None = None,
                  cells_across: int | None = None) -> dict:
    """MPM (``reference`` scene and ``scene``), GNS alone and the hybrid on ``scene``.

    ``model`` is ``(gns, params, info)`` from :func:`~diffgns.graph.train_loop.load_model`;
    ``labels``: names of the reference and the MPM rows (default: their cell sizes).
    Returns ``{"rows": [...], "positions": {label: (T+1, N, 2)}, "frame_dt": s, "bounds",
    "warnings"}`` (``warnings``: what the scene has that the model was not trained on,
    :func:`~diffgns.graph.support.check_scene`);
    each row has the label, the scores of :func:`score_against`, the timing and the run's
    position clamps (``clamped_positions``, ... of :func:`diffgns.clamp.clamp_summary`).
    """
    gns, gp, info = model
    stride = int(info.get("frame_stride", 1))
    labels = labels or (f"MPM dx={reference.dx:g} m (reference)", f"MPM dx={scene.dx:g} m")
    wall = float(scene.domain[0][0])
    gns_only = Schedule(warmup=schedule.warmup, gns_frames=1, mpm_frames=0,
                        particle_map=schedule.particle_map)
    # refuse an unsupported scene before any run; keep what it was not trained on
    sup = check_scene(scene, info, "exact" if cells_across is None else "node-spacing")
    ref, t_ref = run_mpm(reference, n_frames, stride, repeats=1)
    x_mpm, t_mpm = run_mpm(scene, n_frames, stride, repeats)
    runs = {labels[0]: (ref, t_ref), labels[1]: (x_mpm, t_mpm)}
    for sched in (gns_only, schedule):
        res, t = run_hybrid(scene, gns, gp, info, sched, n_frames, repeats, cells_across)
        runs[sched.label] = (np.asarray(res.positions), t)
    rows = [dict(label=label, **score_against(x, ref, wall), **t)
            for label, (x, t) in runs.items()]
    return dict(rows=rows, positions={k: v[0] for k, v in runs.items()},
                frame_dt=float(scene.frame_dt) * stride, bounds=scene.domain,
                warnings=list(sup.warnings))


def compare(model, aspect_ratio: float, friction_angle: float, schedule: Schedule,
            n_frames: int, reference_cells: int | None = None, cells_across: int | None = None,
            repeats: int = 3) -> dict:
    """:func:`compare_scene` on the column collapse of the model's training data (its box and
    column width), at the MPM resolution it emulates unless ``cells_across`` is given; the
    reference is that column at ``reference_cells`` cells across (default: twice the cells
    the GNS and hybrid runs use)."""
    info = model[2]
    own = model_cells(info)
    cells = cells_across or own
    reference_cells = reference_cells or 2 * cells
    scene = column_scene(aspect_ratio, friction_angle, cells, info)
    reference = column_scene(aspect_ratio, friction_angle, reference_cells, info)
    return compare_scene(model, scene, reference, schedule, n_frames, repeats,
                         (f"MPM {reference_cells} cells (reference)", f"MPM {cells} cells"),
                         None if cells == own else cells)
