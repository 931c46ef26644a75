"""Levenberg-Marquardt for inverse problems with a few parameters and a few residuals.

When the misfit is a short vector of residuals ``r(theta)`` (e.g. the runout at two
frames) and theta has 2-3 entries, first-order optimisers crawl along the valleys of
``|r|^2``, while Gauss-Newton steps ``-(J^T J)^-1 J^T r`` jump to the solution. ``J`` is
computed in forward mode (one JVP per parameter through the whole rollout: no reverse-mode
memory), on the transformed parameters ``u`` of :mod:`diffgns.inverse.transforms`, so
physical bounds hold. The damping ``lam`` (relative to the mean diagonal of ``J^T J``) grows
10x when a step raises the misfit (the step is then retried from the previous point without
a new evaluation) and shrinks 3x after an accepted one.
"""
from __future__ import annotations

import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.inverse.solve import InverseResult, evaluate_redo, record
from diffgns.inverse.transforms import setup
from diffgns.memory import compile_ahead


def least_squares(residual_fn: Callable, theta0: dict, max_iter: int = 20,
                  transforms: dict | None = None, step_tol: float | dict = 0.0,
                  loss_tol: float = 0.0, damping: float = 1e-3, max_step: float = 1.0,
                  has_aux: bool = False, on_overflow: Callable | None = None,
                  callback: Callable[[dict], None] | None = None) -> InverseResult:
    """Minimise ``|r(theta)|^2`` by damped Gauss-Newton with forward-mode Jacobians.

    Args:
        residual_fn: theta (dict of physical scalars) -> (R,) residuals, or (residuals, aux)
            with ``has_aux`` (aux as in :func:`diffgns.inverse.solve`).
        damping: initial relative Levenberg-Marquardt damping.
        max_step: largest change of any transformed parameter ``u`` per iteration.
        Others as :func:`diffgns.inverse.solve`.
    Returns:
        InverseResult; each history record also holds ``residuals`` (R,), ``damping`` and
        ``accepted``; ``loss = |r|^2`` and ``grad = 2 J^T r`` (physical units).
    """
    if max_iter < 0:
        raise ValueError(f"max_iter must be >= 0, got {max_iter}")
    tf, u, to_theta = setup(theta0, transforms)
    names = list(theta0)
    full = residual_fn if has_aux else (lambda th: (residual_fn(th), {}))
    t_start = time.perf_counter()
    result = InverseResult(theta=dict(theta0))
    exe = None

    def f(uu):
        r, aux = full(to_theta(uu))
        r = jnp.atleast_1d(r)
        return r, (r, aux)

    def build():
        nonlocal exe
        exe, info = compile_ahead(jax.jit(jax.jacfwd(f, has_aux=True)), u)
        result.compile_s += info["lower_s"] + info["compile_s"]
        result.xla_memory = info["memory"]

    def evaluate(uu):
        J, (r, aux) = exe(uu)
        return r, aux, J

    build()
    tol = step_tol if isinstance(step_tol, dict) else {k: step_tol for k in names}
    lam, best = damping, None
    for it in range(max_iter + 1):
        t0 = time.perf_counter()
        r, aux, J = evaluate_redo(evaluate, build, on_overflow, to_theta, u, it)
        r = np.asarray(r, float)
        Jm = np.stack([np.asarray(J[k], float) for k in names], -1)  # (R, P)
        loss = float(r @ r)
        g_u = dict(zip(names, 2.0 * Jm.T @ r))
        accepted = best is None or loss <= best["loss"]
        rec = record(it, tf, u, loss, g_u, aux, t0, t_start)
        rec.update(residuals=r.tolist(), damping=lam, accepted=accepted)
        result.history.append(rec)
        if callback:
            callback(rec)
        if accepted:
            best = dict(u=u, loss=loss, r=r, J=Jm, theta=rec["theta"], aux=aux)
            lam = max(lam / 3.0, 1e-9)
        else:
            lam *= 10.0
        result.theta, result.aux = best["theta"], best["aux"]
        if best["loss"] <= loss_tol:
            result.converged, result.stop_reason = True, f"loss <= {loss_tol:g}"
            break
        if it == max_iter:
            result.stop_reason = f"max_iter = {max_iter}"
            break
        A = best["J"].T @ best["J"]
        A = A + lam * max(np.trace(A) / len(names), 1e-30) * np.eye(len(names))
        delta = np.clip(-np.linalg.solve(A, best["J"].T @ best["r"]), -max_step, max_step)
        new = {k: best["u"][k] + jnp.asarray(d, best["u"][k].dtype)
               for k, d in zip(names, delta)}
        step = {k: abs(float(tf[k].forward(new[k])) - best["theta"][k]) for k in names}
        if accepted and all(step[k] < tol.get(k, 0.0) for k in names):
            result.converged, result.stop_reason = True, "step < step_tol"
            break
        u = new
    result.wall_time_s = time.perf_counter() - t_start
    return result
