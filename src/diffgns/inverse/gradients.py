"""Finite-difference gradients (the one helper of diffgns) and the AD-against-FD check.

The step rule, :func:`fd_step`, is the same everywhere (the ``gradient="fd"`` option of
:func:`diffgns.inverse.optimize`, :func:`finite_difference_grad`, :func:`gradient_check`)::

    h = rel_step * max(|x|, 1)          (x in the parameter's physical unit)

then shrunk, for a bounded parameter ``lo < x < hi``, to at most half the distance to the
nearer bound, so both ``x + h`` and ``x - h`` stay valid. The floor of 1 unit keeps ``h``
from vanishing at ``x = 0`` (e.g. zero cohesion), where a relative step would drown the
difference in float32 rounding; every physical parameter diffgns fits (degrees, friction
coefficients, aspect ratios, Pa) is of order 1 or larger in its unit.

:func:`central_difference` is ``(f(x + h) - f(x - h)) / (2 h)`` of a function of one scalar;
truncation error O(h^2 f'''), rounding error O(eps |f| / h).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.memory import compile_ahead
from diffgns.timing import time_call


def fd_step(x: float, rel_step: float, lo: float = -math.inf, hi: float = math.inf) -> float:
    """Central-difference step for a parameter at ``x`` (see the module docstring):
    ``rel_step * max(|x|, 1)``, at most half the distance from ``x`` to ``lo`` and to ``hi``."""
    x = float(x)
    h = rel_step * max(abs(x), 1.0)
    return min(h, 0.5 * (x - lo), 0.5 * (hi - x))


def central_difference(f: Callable[[float], Any], x: float, h: float) -> float:
    """``(f(x + h) - f(x - h)) / (2 h)`` for a scalar function ``f`` of one float."""
    x = float(x)
    return float((f(x + h) - f(x - h)) / (2.0 * h))


def finite_difference_grad(loss_fn: Callable[[dict], jax.Array], theta: dict,
                           rel_step: float = 1e-4) -> dict[str, float]:
    """Central finite-difference gradient of ``loss_fn`` at ``theta`` (one pair of runs per
    parameter, step :func:`fd_step`), for comparison with the AD gradient."""
    f = jax.jit(loss_fn)
    th = {k: jnp.asarray(v) for k, v in theta.items()}

    def along(k: str) -> Callable[[float], jax.Array]:
        return lambda x: f(dict(th, **{k: jnp.asarray(x)}))

    return {k: central_difference(along(k), v, fd_step(v, rel_step)) for k, v in theta.items()}


def gradient_check(loss_fn: Callable[[dict], jax.Array], theta: dict,
                   rel_steps: Sequence[float] = (1e-2, 1e-3, 1e-4), repeats: int = 3,
                   scan: int = 0) -> dict:
    """AD gradient against central finite differences at ``theta``: values and times.

    Both programs are compiled ahead of time (``compile_s``); times are medians of
    ``repeats`` steady calls (s). A finite-difference gradient costs 2 forward runs per
    parameter and step; ``rel_diff[step][k] = |fd - ad| / |ad|``, the step of each relative
    step given by :func:`fd_step`. With ``scan`` > 0 the loss is also evaluated at
    ``theta_k + j h`` (j = -scan..scan, h the step of the smallest relative step) and the
    one-sided slopes of the 2 scan intervals are summarised (``slopes[k]``: median, and the
    fraction within 2 % of AD): a piecewise-smooth loss (e.g. a rollout whose radius graph
    changes) shows as a few outlying slopes while most match AD.
    """
    th = {k: jnp.asarray(v, jnp.result_type(float)) for k, v in theta.items()}
    out: dict[str, Any] = {"theta": {k: float(v) for k, v in theta.items()}}
    progs = {}
    for name, fn in (("forward", loss_fn), ("gradient", jax.grad(loss_fn))):
        progs[name], info = compile_ahead(jax.jit(fn), th)
        out[f"{name}_compile_s"] = info["lower_s"] + info["compile_s"]
        out[f"{name}_xla_memory"] = info["memory"]

    def med(f):
        t, r = time_call(f, repeats)
        return r, t["median_s"]

    def along(k: str) -> Callable[[float], jax.Array]:
        return lambda x: progs["forward"](dict(th, **{k: jnp.asarray(x, th[k].dtype)}))

    g, out["ad_time_s"] = med(lambda: progs["gradient"](th))
    _, out["forward_time_s"] = med(lambda: progs["forward"](th))
    out["ad"] = {k: float(v) for k, v in g.items()}
    out["fd"], out["rel_diff"] = {}, {}
    for rel in rel_steps:
        fd = {k: central_difference(along(k), v, fd_step(v, rel)) for k, v in theta.items()}
        out["fd"][f"{rel:g}"] = fd
        out["rel_diff"][f"{rel:g}"] = {k: abs(fd[k] - out["ad"][k]) / max(abs(out["ad"][k]),
                                                                        1e-300) for k in fd}
    out["fd_time_s"] = 2 * len(theta) * out["forward_time_s"]
    if scan:
        out["slopes"] = {}
        for k, v in theta.items():
            h = fd_step(v, min(rel_steps))
            vals = np.array([float(along(k)(float(v) + j * h)) for j in range(-scan, scan + 1)])
            sl = np.diff(vals) / h
            ad = out["ad"][k]
            out["slopes"][k] = dict(step=h, median=float(np.median(sl)),
                                    median_rel_diff=float(abs(np.median(sl) - ad) / abs(ad)),
                                    within_2pct=float(np.mean(np.abs(sl - ad) <= 0.02 * abs(ad))),
                                    values=sl.tolist())
    return out
