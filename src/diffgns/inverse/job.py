"""An inverse job end to end: simulator, objective, optimiser, progress, summary, figures.

Used by ``diffgns invert`` and ``examples/column_collapse_inverse.py``::

    obs = SceneObservation.for_model(scene, info, n_frames)          # or SceneObservation(...)
    sim = make_simulator("gns", obs, loaded=loaded, observed=nodes)
    objective = make_objective("runout", obs, observed=nodes)
    summary = solve(sim, objective, {"friction_angle": 45.0}, obs, out="results/inverse",
                    observed=nodes, truth={"friction_angle": 30.0})

:func:`solve` prints one line per iteration and writes ``summary.json``,
``convergence.png`` (parameters and loss per iteration) and ``deposits.png`` (observed and
fitted final deposits); its last printed line states the recovered parameters.
"""
from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from diffgns import inverse
from diffgns.inverse import objectives
from diffgns.inverse.observation import SceneObservation
from diffgns.inverse.simulators import (
    DEFAULT_MODEL,
    check_fit,
    gns_simulator,
    hybrid_simulator,
    mpm_simulator,
)
from diffgns.memory import check_mappings
from diffgns.metrics import runout
from diffgns.scene.builders3d import cylinder_axis

__all__ = ["OBJECTIVES", "SIMULATORS", "default_center", "make_objective", "make_simulator",
           "solve"]

SIMULATORS = ("mpm", "gns", "hybrid")
OBJECTIVES = ("runout", "runout-max", "runout-frame", "deposit")
#: default jax.checkpoint blocks (frames) of each simulator
DEFAULT_BLOCK = {"mpm": 25, "gns": 10, "hybrid": 10}


def make_simulator(kind: str, obs: SceneObservation, model=DEFAULT_MODEL, loaded=None,
                   observed=None, history: str = "observed", block: int | None = None,
                   theta0: dict | None = None, schedule=None):
    """The ``kind`` ("mpm", "gns" or "hybrid") adapter of ``obs`` (GNS ``history``:
    "observed" needs ``observed`` nodes; "mpm" is allocated at ``theta0``). ``block``:
    frames per ``jax.checkpoint`` block (None: :data:`DEFAULT_BLOCK`, 0: none);
    ``schedule``: the hybrid's :class:`~diffgns.hybrid.simulator.Schedule` (None: the
    :class:`~diffgns.inverse.simulators.HybridSimulator` default). Refuses to fit (the names
    of ``theta0``) what the simulator has no input for."""
    if kind not in SIMULATORS:
        raise ValueError(f"simulator {kind!r} is unknown; use one of {SIMULATORS}")
    obs.check_names(list(theta0 or {}))
    check_fit(list(theta0 or {}), kind, history)
    block = DEFAULT_BLOCK[kind] if block is None else (block or None)
    if kind == "mpm":
        return mpm_simulator(obs, block=block)
    if kind == "hybrid":
        return hybrid_simulator(obs, model, loaded=loaded, checkpoint_block=block,
                                schedule=schedule)
    sim = gns_simulator(obs, model, history=history, observed=observed,
                        checkpoint_block=block, loaded=loaded)
    if history == "mpm":
        sim.allocate(theta0 or {})
    return sim


def runout_value_loss(value: float, n_obs: int, frame: int = -1, method: str = "max",
                      origin: float = 0.0, center=None) -> Callable:
    """``positions -> (runout(positions[frame]) - value)^2`` (m^2) for a measured runout
    ``value`` (m from ``origin``, or the radius about the vertical axis ``center`` (cx, cz)
    in 3D) at observed frame ``frame`` of ``n_obs``."""
    if not -n_obs <= frame < n_obs:
        raise ValueError(f"frame {frame} is outside the {n_obs} observed frames")
    if not np.isfinite(value):
        raise ValueError(f"the observed runout {value} is not finite")
    t = frame % n_obs

    def loss(positions):
        return (runout(positions[t], origin=origin, method=method, center=center) - value) ** 2

    return loss


def default_center(scene) -> tuple[float, float] | None:
    """The vertical axis (cx, cz), m, about which a 3D scene's runout is a radius: the common
    axis of its bodies when they are all upright cylinders on one axis, else None (the
    runout is then measured along x, as in 2D)."""
    axis = cylinder_axis(scene)
    return None if axis is None else axis[0]


def make_objective(name: str, obs: SceneObservation, observed=None, frame: int = -1,
                   observed_runout: float | None = None, origin: float | None = None,
                   center=None) -> Callable:
    """``positions (n_obs, n, d) -> loss``: ``name`` in :data:`OBJECTIVES`.

    runout: soft maximum (temperature 2 mm) of x at the last observed frame, squared misfit
    (m^2); runout-max: the farthest node; runout-frame: the soft runout at ``frame``;
    deposit: deposit height profile at ``frame`` in 40 bins across the box (dimensionless,
    2D only). The target is the observed nodes ``observed`` (n_obs, n', d), or a measured
    runout ``observed_runout`` (m from ``origin``, default the box's left wall; compared
    with the farthest node unless ``name`` is "runout" or "runout-frame"). In 3D the runout
    is the radius about the vertical axis ``center`` (cx, cz), m, by default
    :func:`default_center` (a cylinder's axis); x from ``origin`` when there is none.
    """
    if name not in OBJECTIVES:
        raise ValueError(f"objective {name!r} is unknown; use one of {OBJECTIVES}")
    if (observed is None) == (observed_runout is None):
        raise ValueError("give exactly one observation: an observed trajectory or a runout")
    if center is not None and obs.scene.dim != 3:
        raise ValueError("a runout centre (radial runout) is for 3D scenes; this scene is 2D: "
                         "use the origin")
    if center is not None and origin is not None:
        raise ValueError("give a runout origin (x) or a centre (radius), not both")
    if center is None and origin is None:
        center = default_center(obs.scene)
    origin = float(obs.bounds[0][0]) if origin is None else float(origin)
    method = "max" if name == "runout-max" else "softmax"
    fr = frame if name in ("runout-frame", "deposit") else -1
    if name == "deposit" and obs.scene.dim != 2:
        raise ValueError("the deposit objective is a 2D height profile along x; for a 3D scene "
                         "use runout, runout-max or runout-frame")
    if observed_runout is not None:
        if name == "deposit":
            raise ValueError("the deposit objective needs an observed trajectory, not a runout")
        return runout_value_loss(observed_runout, obs.n_obs, fr, method, origin, center)
    if name == "deposit":
        edges = np.linspace(obs.bounds[0][0], obs.bounds[0][1], 41)
        return objectives.deposit_loss(observed, edges, 4 / obs.scene.dx, frame=fr)
    return objectives.runout_loss(observed, frame=fr, method=method, origin=origin,
                                  center=center)


def gradient_text(g: float) -> str:
    """A gradient entry of a progress line; nan marks a trial point rejected on its loss
    alone (:func:`diffgns.inverse.solve.record`: its gradient was never computed), not a NaN."""
    return "(not computed: point rejected on its loss)" if math.isnan(g) else f"{g:+.3e}"


def history_for_json(history: list[dict]) -> list[dict]:
    """The iteration records for ``summary.json``: without ``aux``, and with the gradients of
    a trial point rejected on its loss (nan: never computed) as null, so the file is standard
    JSON (json.dumps would write ``NaN``, which strict parsers refuse)."""
    def grads(g: dict) -> dict:
        return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in g.items()}

    return [{k: grads(v) if k in ("grad", "grad_u") else v for k, v in h.items() if k != "aux"}
            for h in history]


def format_record(rec: dict) -> str:
    """One progress line of an iteration record of :func:`diffgns.inverse.optimize`."""
    parts = []
    for k, v in rec["theta"].items():
        if k == "friction_angle":
            parts.append(f"phi={v:7.3f} deg  loss={rec['loss']:.3e}  "
                         f"dloss/dphi={gradient_text(rec['grad'][k])}")
        else:
            parts.append(f"{k}={v:.4g}  dloss/d{k}={gradient_text(rec['grad'][k])}")
    if "friction_angle" not in rec["theta"]:
        parts.append(f"loss={rec['loss']:.3e}")
    return (f"iter {rec['iteration']:2d}  " + "  ".join(parts)
            + f"  t={rec['time_s']:.1f}s  rss={rec['rss_mb']:.0f}MB")


def recovered_line(theta: dict, truth: dict | None, label: str) -> str:
    """The last line of a job: the recovered parameters (and their targets, if known)."""
    truth = truth or {}

    def tgt(k):
        return f"target {truth[k]:g}, " if k in truth else ""

    if list(theta) == ["friction_angle"]:
        return (f"recovered friction angle: {theta['friction_angle']:.2f} deg "
                f"({tgt('friction_angle')}{label})")
    return "recovered: " + ", ".join(f"{k} = {v:.4g} ({tgt(k)}{label})"
                                     for k, v in theta.items())


def solve(sim, objective: Callable, theta0: dict, obs: SceneObservation, out,
          transforms: dict | None = None, optimizer: str = "gauss-newton",
          lr: float | None = None, max_iter: int = 20, step_tol: float | dict = 0.01,
          gradient: str = "auto", observed=None, truth: dict | None = None,
          label: str = "", fd_check: bool = False, extra: dict | None = None,
          scan: dict | None = None, starts: int = 1,
          t_start: float | None = None) -> dict:
    """Fit ``theta0`` with ``optimizer`` on ``objective(sim(theta))``; print, write, return.

    Args:
        sim: an adapter of :mod:`diffgns.inverse.simulators`.
        objective: ``positions -> scalar`` (from :func:`make_objective`).
        theta0: start (physical units); ``transforms``: {name: Bounded} where not default.
        optimizer: "gauss-newton", "adam" or "sgd"; ``lr`` (default 1 for Gauss-Newton,
            0.1 otherwise) acts on the transformed parameters.
        step_tol: stop when every step is below this (physical units, float or by name).
        gradient: "auto", "ad" or "fd" (:func:`diffgns.inverse.optimize`).
        scan: {name: values}: start from the lowest loss of a grid (``optimize``'s scan);
            ``starts``: refine that many of its lowest points, keep the lowest end.
        observed: observed nodes (n_obs, n', 2) for the deposit figure (None: a runout).
        truth: the true parameters when known (figures, ``error``).
        label: the simulator's name for messages; ``extra``: more summary entries.
        fd_check: also compare the AD gradient with finite differences at the start.
        t_start: ``time.perf_counter()`` at the job's start (default: now).
    Returns:
        the summary written to ``out/summary.json``.
    """
    t_start = time.perf_counter() if t_start is None else t_start
    check_mappings()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)

    def loss(theta):
        pos, overflow = sim.simulate(theta)
        return objective(pos), {"overflow": overflow, "positions": pos}

    opt = inverse.make_optimizer(optimizer, lr or (1.0 if optimizer == "gauss-newton"
                                                   else 0.1))
    res = inverse.optimize(loss, theta0, opt, max_iter=max_iter, transforms=transforms,
                           step_tol=step_tol, gradient=gradient, has_aux=True,
                           on_overflow=sim.reallocate, scan=scan, starts=starts,
                           callback=lambda rec: print(format_record(rec), flush=True))
    aux = res.aux
    assert isinstance(aux, dict)
    fitted = np.asarray(aux["positions"])
    truth = truth or {}
    extrap = sim.parameter_warnings(res.theta)  # a learned model outside its training data
    summary = dict(
        simulator=label, optimizer=optimizer, gradient=gradient, target=truth or None,
        start=dict(theta0), recovered=res.theta,
        error={k: res.theta[k] - v for k, v in truth.items() if k in res.theta},
        iterations=len(res.history) - 1, evaluations=len(res.history),
        converged=res.converged, stop_reason=res.stop_reason,
        scan=[dict(theta=t, loss=v) for t, v in res.scan], scan_s=res.scan_s,
        starts=res.starts,
        compile_s=res.compile_s, optimisation_time_s=res.wall_time_s,
        time_per_iteration_s=float(np.median([h["time_s"] for h in res.history[1:]]
                                             or [res.history[0]["time_s"]])),
        xla_gradient_memory=res.xla_memory, nodes=obs.n_nodes,
        particles=obs.scene.n_particles, frames=obs.n_obs, frame_dt=obs.frame_dt,
        coarse_grain=obs.coarse_grain, frame_stride=obs.frame_stride,
        warnings=list(obs.warnings) + extrap, parameter_warnings=extrap, **(extra or {}))
    if "friction_angle" in summary["error"]:
        summary["error_deg"] = summary["error"]["friction_angle"]
    summary["history"] = history_for_json(res.history)
    from diffgns.io import figures

    figures.plot_convergence(res, out / "convergence.png", truth=truth or None)
    fit = ", ".join(f"{k}={v:.3g}" for k, v in res.theta.items())
    deposits = [(fitted[0], "initial")] if observed is None else [
        (np.asarray(observed)[0], "initial"),
        (np.asarray(observed)[-1], "target" + (": " + ", ".join(
            f"{k}={v:g}" for k, v in truth.items()) if truth else ""))]
    deposits.append((fitted[-1], f"recovered: {label}, {fit}"))
    figures.plot_deposits(deposits, out / "deposits.png", obs.bounds)
    summary["wall_time_s"] = time.perf_counter() - t_start  # the whole job, with compiling
    summary["peak_rss_mb"] = inverse.peak_rss_mb()
    if fd_check:  # after the job's figures, so they exclude this extra work
        t0 = time.perf_counter()
        summary["gradient_check"] = inverse.gradient_check(lambda th: loss(th)[0], theta0,
                                                           scan=10)
        summary["gradient_check"]["seconds"] = time.perf_counter() - t0
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=_json))
    print(f"wall time {summary['wall_time_s']:.1f} s (compile {res.compile_s:.1f} s), "
          f"{summary['iterations']} iterations ({res.stop_reason}), peak RSS "
          f"{summary['peak_rss_mb']:.0f} MB, XLA gradient temp "
          f"{res.xla_memory.get('temp_size_in_bytes', 0) / 1e6:.0f} MB; outputs in {out}")
    for w in extrap:
        print(f"warning: {w}", flush=True)
    print(recovered_line(res.theta, truth, label), flush=True)
    return summary


def _json(v):
    if isinstance(v, (np.generic, jnp.ndarray)):
        return np.asarray(v).tolist()
    raise TypeError(f"{type(v).__name__} is not JSON serialisable")
