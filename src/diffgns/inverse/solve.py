"""The inverse-problem loop: gradient-based parameter identification through any rollout.

An inverse problem is ``optax`` on ``jax.grad(loss(simulator(theta)))``. ``theta`` is a dict
of named physical scalars (e.g. ``{"friction_angle": 45.0}``); a simulator is any function
``theta -> positions (T, N, 2)`` (see :mod:`diffgns.inverse.simulators`) and an objective
any function ``positions -> scalar`` (see :mod:`diffgns.inverse.objectives`).
:func:`optimize` is the optax loop: ahead-of-time compiled gradient (exact, AD, or finite
differences, :mod:`diffgns.inverse.gradients`), XLA memory analysis, stopping rules, a
progress callback and a history record per iteration (parameters, loss, gradient, time,
memory), on the transformed parameters of :mod:`diffgns.inverse.transforms`. Optimisers
are in :mod:`diffgns.inverse.optimizers`; Levenberg-Marquardt on residual vectors in
:mod:`diffgns.inverse.lsq`, which shares :func:`evaluate_redo` and :func:`record`.
"""
from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
import optax

from diffgns.inverse.gradients import central_difference, fd_step
from diffgns.inverse.transforms import setup
from diffgns.memory import compile_ahead, current_rss_mb, peak_rss_mb

__all__ = ["InverseResult", "evaluate_redo", "optimize", "record"]


@dataclass
class InverseResult:
    """Outcome of :func:`optimize`: final parameters and one record per iteration.

    ``compile_s`` is the ahead-of-time compile time of the gradient program and ``xla_memory``
    its XLA memory analysis (bytes: temp, argument, output); ``aux`` the auxiliary output of
    the last evaluation (e.g. the fitted positions) when the loss has one; ``scan`` the
    (theta, loss) pairs of the ``scan`` option and ``scan_s`` its seconds; ``starts`` one
    summary per local run (start, theta, loss, iterations, converged, stop_reason), the
    chosen one's history being ``history``.
    """

    theta: dict
    history: list = field(default_factory=list)
    converged: bool = False
    stop_reason: str = ""
    wall_time_s: float = 0.0
    compile_s: float = 0.0
    xla_memory: dict = field(default_factory=dict)
    aux: object = None
    scan: list = field(default_factory=list)
    scan_s: float = 0.0
    starts: list = field(default_factory=list)

    def series(self, key: str, name: str | None = None) -> np.ndarray:
        """History of ``key`` ("loss", "time_s", ...) or of parameter ``name`` under "theta"."""
        if name is None:
            return np.array([h[key] for h in self.history])
        return np.array([h[key][name] for h in self.history])


def evaluate_redo(evaluate: Callable, rebuild: Callable, on_overflow, to_theta, u, it: int):
    """``evaluate(u) -> (loss, aux, ...)``; on aux["overflow"], ``on_overflow(theta)``,
    ``rebuild()`` and redo (twice at most)."""
    for attempt in range(3):
        out = evaluate(u)
        aux = out[1]
        if not (isinstance(aux, dict) and bool(aux.get("overflow", False))):
            return out
        if on_overflow is None or attempt == 2:
            raise RuntimeError(f"neighbour list overflow at iteration {it} persists; raise "
                               "the simulator's neighbour capacity")
        on_overflow(to_theta(u))
        rebuild()
    raise AssertionError("unreachable")  # pragma: no cover


def record(it: int, tf: dict, u: dict, loss, g_u: dict | None, aux, t0: float,
           t_start: float) -> dict:
    """One history record (physical theta and gradient, time, memory, scalar aux); with
    ``g_u`` None (a point rejected on its loss alone) the gradient entries are nan."""
    loss = float(jax.block_until_ready(loss))
    theta = {k: float(tf[k].forward(v)) for k, v in u.items()}
    dth = {k: float(jax.grad(tf[k].forward)(u[k])) for k in u}
    g = {k: math.nan for k in u} if g_u is None else {k: float(v) for k, v in g_u.items()}
    rec = dict(iteration=it, theta=theta, loss=loss,
               grad={k: g[k] / dth[k] if dth[k] else math.nan for k in u},
               grad_u=g,
               time_s=time.perf_counter() - t0, elapsed_s=time.perf_counter() - t_start,
               rss_mb=current_rss_mb(), peak_rss_mb=peak_rss_mb(),
               aux={k: float(v) for k, v in (aux or {}).items() if np.ndim(v) == 0})
    if not np.isfinite(loss) or (g_u is not None
                                 and not all(np.isfinite(v) for v in g.values())):
        raise FloatingPointError(f"non-finite loss or gradient at iteration {it}: {rec}")
    return rec


def _revisits(history: list, theta: dict, tol: dict) -> int | None:
    """The first iteration of ``history`` whose parameters are within ``tol`` (physical
    units, by name; at least 1e-9 relative) of ``theta``, or None."""
    for h in history:
        if all(abs(h["theta"][k] - v) <= max(tol.get(k, 0.0), 1e-9 * abs(v))
               for k, v in theta.items()):
            return h["iteration"]
    return None


def _scan_points(loss_of, tf, u, scan: dict, dtype, result: InverseResult) -> list:
    """The points of ``scan`` (values by name, physical units) in u, from the lowest
    ``loss_of(u)`` up (non-finite losses left out); every point's (theta, loss) appended to
    ``result.scan``. ValueError for a name not fitted or a value outside its transform's
    range; FloatingPointError when no loss is finite."""
    unknown = sorted(set(scan) - set(u))
    if unknown:
        raise ValueError(f"scan names {unknown} are not fitted parameters {sorted(u)}")
    names = list(scan)
    for k in names:
        bad = [v for v in scan[k] if not (tf[k].lo < float(v) < tf[k].hi)]
        if bad or not len(scan[k]):
            raise ValueError(f"scan values of {k} must be a non-empty list inside "
                             f"({tf[k].lo}, {tf[k].hi}), got {list(scan[k])}")
    t0 = time.perf_counter()
    ranked = []
    for values in itertools.product(*(scan[k] for k in names)):
        uu = dict(u, **{k: jnp.asarray(tf[k].inverse(float(v), k), dtype)
                        for k, v in zip(names, values)})
        loss = float(loss_of(uu))
        result.scan.append(({k: float(tf[k].forward(uu[k])) for k in uu}, loss))
        if np.isfinite(loss):
            ranked.append((loss, len(ranked), uu))
    if not ranked:
        raise FloatingPointError(f"the loss is not finite at any scan point: {result.scan}")
    result.scan_s = time.perf_counter() - t0
    return [uu for _, _, uu in sorted(ranked, key=lambda r: r[:2])]


def optimize(loss_fn: Callable, theta0: dict, optimizer: optax.GradientTransformation,
             max_iter: int = 20, transforms: dict | None = None, loss_tol: float = 0.0,
             step_tol: float | dict = 0.0, gradient: str = "ad", fd_rel_step: float = 1e-3,
             smooth_rel_step: float = 1e-2, has_aux: bool = False,
             on_overflow: Callable | None = None,
             callback: Callable[[dict], None] | None = None,
             scan: dict[str, Sequence[float]] | None = None,
             starts: int = 1) -> InverseResult:
    """Minimise ``loss_fn(theta)`` with ``optimizer`` over transformed parameters.

    Args:
        loss_fn: theta (dict of scalars, physical units) -> scalar loss, or (loss, aux) with
            ``has_aux``; aux is a dict whose scalar entries are recorded per iteration and
            whose ``"overflow"`` entry, if true, triggers ``on_overflow``.
        theta0: initial physical parameters; each must lie inside its transform's range.
        transforms: {name: Bounded/Identity}; default :data:`DEFAULT_TRANSFORMS` by name,
            Identity otherwise.
        loss_tol: stop when the loss is at or below this.
        step_tol: stop when every proposed step (physical units; a float or a dict by name)
            is smaller than this; the final theta is then the last evaluated one. A step
            back to an earlier iterate (within ``step_tol``) stops the loop unconverged with a
            "cycle" reason: the loop is deterministic, so the cycle would only repeat (seen
            with Gauss-Newton on the MPM's runout of a tall collapse, a loss that is rough
            on a 0.01 deg scale: its exact slope changes sign there, in float64 too). An
            unconverged loop (cycle, max_iter) returns the iterate of the lowest loss.
        gradient: "ad" (value_and_grad, compiled ahead of time), "fd" (central finite
            differences of the compiled loss in physical units, step
            :func:`~diffgns.inverse.gradients.fd_step` of ``fd_rel_step``) or "auto", a
            trust-region safeguard: "ad" until a step raises the loss above the lowest so
            far (or leads back to an earlier iterate); such a step is rejected, the optimiser
            restarts from the lowest-loss iterate with central differences of step
            ``smooth_rel_step`` (from then on) and each step in u is clipped to half the
            rejected one, halved again while it would land on an iterate already evaluated;
            an accepted step doubles that radius. It ends when a step is below
            ``step_tol`` or at ``max_iter`` (on a cycle only if ``step_tol`` is 0).
            Records: ``gradient`` says which; an iterate whose loss rose, or whose proposed
            step would revisit a point, has ``rejected`` (restart iteration, radius, the
            differences there). On a loss that never rises, "auto" takes exactly the steps
            of "ad". Why: the exact gradient of a loss that is rough on a scale far below
            the step (the MPM's runout of a tall collapse: its slope changes sign within
            0.01 deg) can point the wrong way, where a difference over ``smooth_rel_step``
            (0.45 deg at 45 deg) follows the trend; and Gauss-Newton's step overshoots a
            loss whose minimum is above zero (a deposit the model cannot match exactly).
        on_overflow: theta -> None, called when aux["overflow"] is true (e.g. to re-allocate
            a neighbour list); the iteration is then recompiled and redone (twice at most).
        callback: called with each history record (e.g. to print progress).
        scan: {name: values (physical units)}: before the loop, the loss (forward only) at
            every combination of the values, parameters not named keeping ``theta0``; the
            loop starts from the lowest (``theta0`` itself is not evaluated unless listed).
            For a loss with several minima (a deposit behind an obstacle: the flow over
            the obstacle or not), where a local method started far away ends in the
            nearest one. Recorded in ``result.scan`` as (theta, loss) pairs.
        starts: with a scan, run the local method from each of the ``starts`` lowest scan
            points (sharing the compiled programs) and return the run that ends at the
            lowest loss (ties: the lower-ranked start). A minimum's basin can be narrower
            than the grid's spacing, so its grid points may rank second or third: on the
            MPM's deposit behind an obstacle (true 30 deg, grid 17.5-52.5 by 5 deg) the
            truth's basin spans ~28.2-32.5 deg, 27.5 deg (0.0232) ranks just below 32.5 deg
            (0.0233) and leads to a minimum at 25.4 deg; 32.5 deg leads to the truth.
            ``result.starts`` summarises every run; history records carry ``start``.
    Returns:
        InverseResult; history records: iteration, theta, loss, grad (d loss / d theta,
        physical), grad_u (optimiser space), gradient ("ad" or "fd"; see "auto" for
        ``turn``), time_s, elapsed_s, rss_mb, peak_rss_mb, aux.
    Raises:
        ValueError for an invalid start or option; FloatingPointError on a non-finite loss.
    """
    if gradient not in ("ad", "fd", "auto"):
        raise ValueError(f"gradient must be 'ad', 'fd' or 'auto', got {gradient!r}")
    if not (fd_rel_step > 0 and smooth_rel_step > 0):
        raise ValueError(f"fd_rel_step and smooth_rel_step must be > 0, got {fd_rel_step} "
                         f"and {smooth_rel_step}")
    if max_iter < 0:
        raise ValueError(f"max_iter must be >= 0, got {max_iter}")
    if not (isinstance(starts, int) and starts >= 1) or (starts > 1 and not scan):
        raise ValueError(f"starts must be an int >= 1, and > 1 only with a scan to rank "
                         f"starts from; got starts={starts!r}, scan={scan!r}")
    tf, u, to_theta = setup(theta0, transforms)
    dtype = jnp.result_type(float)
    full = loss_fn if has_aux else (lambda th: (loss_fn(th), {}))
    t_start = time.perf_counter()
    result = InverseResult(theta=dict(theta0))

    mode = "ad" if gradient == "auto" else gradient  # "auto" turns to "fd" at a rejection
    rel_step = fd_rel_step if gradient == "fd" else smooth_rel_step
    f = lambda uu: full(to_theta(uu))
    programs: dict = {}  # "ad" (value and gradient) and "fwd" (loss, aux), compiled once

    def program(kind: str, fresh: bool = False):
        """The compiled program ``kind``, shared by every start (again after an overflow's
        reallocation, ``fresh``)."""
        if fresh:
            programs.clear()
        if kind not in programs:
            fn = jax.value_and_grad(f, has_aux=True) if kind == "ad" else f
            ex, info = compile_ahead(jax.jit(fn), u)
            result.compile_s += info["lower_s"] + info["compile_s"]
            if kind == "ad" or not result.xla_memory:
                result.xla_memory = info["memory"]
            programs[kind] = ex
        return programs[kind]

    exe = None

    def build(fresh: bool = False):
        nonlocal exe
        exe = program(mode, fresh)

    def differences(u, loss=None, aux=None):
        """Central differences of the loss (forward program) in physical units, chained
        to u; with the loss at u when it is not given."""
        if loss is None:
            loss, aux = exe(u)
        theta = to_theta(u)
        g_u = {}
        for k in u:
            along = lambda x, k=k: exe(dict(u, **{k: jnp.asarray(tf[k].inverse(x, k),
                                                                 dtype)}))[0]
            x = float(theta[k])
            g_theta = central_difference(along, x, fd_step(x, rel_step, tf[k].lo, tf[k].hi))
            g_u[k] = g_theta * jax.grad(tf[k].forward)(u[k])
        return loss, aux, g_u

    def evaluate(u):
        if mode == "ad":
            (loss, aux), g_u = exe(u)
            return loss, aux, g_u
        loss, aux = exe(u)
        if gradient == "auto" and best is not None and float(loss) > best["loss"]:
            return loss, aux, None  # rejected on its loss: no differences needed
        return differences(u, loss, aux)

    if scan:
        origins = _scan_points(lambda uu: program("fwd")(uu)[0], tf, u, scan, dtype,
                               result)[:starts]
    else:
        origins = [u]
    tol = step_tol if isinstance(step_tol, dict) else {k: step_tol for k in u}
    radius = math.inf

    def propose(g, st, uu, value):
        """The optimiser's step from ``uu``, each component clipped to ``radius``."""
        upd, st = optimizer.update(g, st, uu, value=jnp.asarray(value))
        if math.isfinite(radius):
            upd = jax.tree.map(lambda d: jnp.clip(d, -radius, radius), upd)
        return optax.apply_updates(uu, upd), st

    runs = []
    for start_index, u in enumerate(origins):
        mode = "ad" if gradient == "auto" else gradient
        build()
        best = None  # dict(loss, it, theta, aux, u, g_u, mode) of the lowest loss so far
        run = InverseResult(theta=to_theta(u))
        state = optimizer.init(u)
        radius = math.inf  # "auto": trust radius on each step in u, set by the first rejection
        for it in range(max_iter + 1):
            t0 = time.perf_counter()
            loss, aux, g_u = evaluate_redo(evaluate, lambda: build(fresh=True), on_overflow,
                                           to_theta, u, it)
            rec = record(it, tf, u, loss, g_u, aux, t0, t_start)
            rec["gradient"] = mode if g_u is not None else "none (rejected on its loss)"
            if len(origins) > 1:
                rec["start"] = start_index
            loss, theta = rec["loss"], rec["theta"]
            run.history.append(rec)
            run.theta, run.aux, returned = theta, aux, loss
            rose = best is not None and loss > best["loss"]
            if not rose:
                if best is not None and math.isfinite(radius):
                    radius *= 2.0  # an accepted step: widen the trust region again
                best = dict(loss=loss, it=it, theta=theta, aux=aux, u=u, g_u=g_u, mode=mode)
            if callback:
                callback(rec)
            if loss <= loss_tol:
                run.converged, run.stop_reason = True, f"loss <= {loss_tol:g}"
                break
            if it == max_iter:
                run.stop_reason = f"max_iter = {max_iter}"
                break
            new, back = u, None  # (a point rejected on its loss alone has no gradient)
            if g_u is not None:
                new, state = propose(g_u, state, u, loss)
                back = _revisits(run.history[:-1],
                                 {k: float(tf[k].forward(new[k])) for k in u}, tol)
            start = theta  # the point the step is taken from
            if gradient == "auto" and (rose or back is not None):
                # the step raised the loss (or leads back to a point no better): reject it.
                # From the lowest-loss iterate, with differences over smooth_rel_step (the
                # exact slope may be what misled: a loss rough below the step's scale) and a
                # trust radius of half the rejected step in u, halved again while the step
                # would land on an iterate already evaluated (its loss is known to be no
                # lower)
                if mode == "ad":
                    mode = "fd"
                    build()
                if best["mode"] != "fd":  # differences at the best point (its loss is known)
                    best["g_u"] = differences(best["u"], best["loss"], best["aux"])[2]
                    best["mode"] = "fd"
                start = best["theta"]
                taken = max(abs(float(u[k]) - float(best["u"][k])) for k in u)
                radius = min(radius, 0.5 * taken) if taken > 0 else radius
                for _ in range(60):  # 2^-60: with step_tol = 0 a cycle stop ends it
                    state = optimizer.init(best["u"])
                    new, state = propose(best["g_u"], state, best["u"], best["loss"])
                    back = _revisits(run.history,
                                     {k: float(tf[k].forward(new[k])) for k in u}, tol)
                    small = all(abs(float(tf[k].forward(new[k])) - start[k])
                                < tol.get(k, 0.0) for k in u)
                    if back is None or small:
                        break
                    radius = 0.5 * max(abs(float(new[k]) - float(best["u"][k])) for k in u)
                rec["rejected"] = dict(restart_iteration=best["it"], radius_u=radius,
                                       grad_u_fd={k: float(v) for k, v in best["g_u"].items()})
                run.theta, run.aux, returned = best["theta"], best["aux"], best["loss"]
            step = {k: abs(float(tf[k].forward(new[k])) - start[k]) for k in u}
            if all(step[k] < tol.get(k, 0.0) for k in u):
                run.converged = True
                run.stop_reason = "step < step_tol"
                break
            if back is not None:  # deterministic: the same points would follow again
                were = ", ".join(f"{k}={run.history[back]['theta'][k]:.4g}" for k in u)
                run.stop_reason = (
                    f"cycle: the next step returns to iteration {back}'s parameters ({were}) "
                    f"from {', '.join(f'{k}={v:.4g}' for k, v in start.items())}: the "
                    "gradient disagrees with the loss change (a noisy or non-smooth objective)")
                break
            u = new
        if not run.converged and best is not None and best["it"] != run.history[-1]["iteration"]:
            # unconverged: the lowest loss
            run.theta, run.aux, returned = best["theta"], best["aux"], best["loss"]
            run.stop_reason += f"; returned iteration {best['it']}, the lowest loss"
        runs.append((returned, start_index, run))
        result.starts.append(dict(start=run.history[0]["theta"], theta=run.theta, loss=returned,
                                  iterations=len(run.history) - 1, converged=run.converged,
                                  stop_reason=run.stop_reason))
    final, chosen, run = min(runs, key=lambda r: (r[0], r[1]))
    result.theta, result.aux, result.history = run.theta, run.aux, run.history
    result.converged, result.stop_reason = run.converged, run.stop_reason
    if len(runs) > 1:
        result.stop_reason += (f"; start {chosen} of {len(runs)} (lowest final loss "
                               f"{final:.4g})")
    result.wall_time_s = time.perf_counter() - t_start
    return result
