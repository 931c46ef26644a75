"""Objectives for inverse problems over any rollout ``positions (T, N, d)`` in m (d = 2, 3).

Each constructor takes the observed (target) trajectory and returns a pure, differentiable
``loss(positions) -> scalar``; the simulator output and the target must have the same
particles (or nodes) and the same frames. Constructors validate their arguments (outside
``jit``) and say what to fix.

* :func:`runout_loss`: ``(runout(x_t) - runout(target_t))^2`` (m^2) at frame ``t`` (the last
  by default), with the hard ``"max"`` or the smooth ``"softmax"``/``"percentile"`` runout of
  :func:`diffgns.metrics.runout` (:func:`runout_residual`: the signed difference, m);
* :func:`deposit_loss`: mean squared difference of smoothed deposit height profiles at frame
  ``t``, normalised by the mean squared target height (dimensionless);
* :func:`tracks_loss`: mean squared distance (m^2) between selected particles and their
  observed positions over selected frames;
* :func:`weighted_sum` of several.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import jax.numpy as jnp
import numpy as np

from diffgns.metrics import deposit_profile, runout

RUNOUT_METHODS = ("max", "softmax", "percentile")


def _frame(target, frame: int) -> int:
    T = np.shape(target)[0]
    if not -T <= frame < T:
        raise ValueError(f"frame {frame} is outside the target trajectory of {T} frames; use "
                         f"-{T} <= frame < {T}")
    return frame % T


def _check_target(target) -> np.ndarray:
    target = np.asarray(target)
    if target.ndim != 3 or target.shape[-1] not in (2, 3):
        raise ValueError(f"target positions must be (T, N, 2) or (T, N, 3), got {target.shape}")
    if not np.isfinite(target).all():
        raise ValueError("target positions contain NaN or inf")
    return target


def runout_residual(target, frame: int = -1, method: str = "softmax", origin: float = 0.0,
                    temperature: float = 2e-3, center=None) -> Callable:
    """``positions (T, N, 2) -> runout - observed runout`` (m) at ``frame``.

    ``method="max"`` is the farthest particle (gradient through one particle); "softmax"
    a soft maximum of length scale ``temperature`` (m) that spreads the gradient over the
    front; "percentile" the 99th percentile. ``center`` (cx, cz), m: the runout radius about
    that vertical axis (3D) instead of x from ``origin``. The observed value is
    ``runout_value``.
    """
    target = _check_target(target)
    if method not in RUNOUT_METHODS:
        raise ValueError(f"runout method {method!r} is unknown; use one of {RUNOUT_METHODS}")
    t = _frame(target, frame)
    kw = dict(origin=origin, method=method, temperature=temperature, center=center)
    value = float(runout(jnp.asarray(target[t]), **kw))

    def residual(positions):
        return runout(positions[t], **kw) - value

    residual.runout_value, residual.frame = value, t
    return residual


def runout_loss(target, frame: int = -1, method: str = "softmax", origin: float = 0.0,
                temperature: float = 2e-3, center=None) -> Callable:
    """``positions -> (runout - observed runout)^2`` in m^2 (see :func:`runout_residual`)."""
    res = runout_residual(target, frame, method, origin, temperature, center)

    def loss(positions):
        return res(positions) ** 2

    loss.runout_value, loss.frame = res.runout_value, res.frame
    return loss


def deposit_loss(target, edges, sharpness: float, frame: int = -1) -> Callable:
    """``positions -> mean((h - h_obs)^2) / mean(h_obs^2)`` of deposit profiles (dimensionless).

    Args:
        edges: (B + 1,) bin edges along x, m.
        sharpness: inverse width (1/m) of the sigmoid bin membership (makes the profile
            differentiable in horizontal positions), e.g. 4 / dx.
    """
    target = _check_target(target)
    edges = np.asarray(edges, float)
    if edges.ndim != 1 or len(edges) < 2 or not np.all(np.diff(edges) > 0):
        raise ValueError("edges must be an increasing 1-D array of at least 2 bin edges")
    if not sharpness > 0:
        raise ValueError(f"sharpness must be > 0 (1/m), got {sharpness}")
    t = _frame(target, frame)
    e = jnp.asarray(edges)
    h_obs = deposit_profile(jnp.asarray(target[t]), e, sharpness)
    scale = float(jnp.mean(h_obs**2))
    if not scale > 0:
        raise ValueError("the target deposit profile is empty inside the given bin edges")

    def loss(positions):
        return jnp.mean((deposit_profile(positions[t], e, sharpness) - h_obs) ** 2) / scale

    loss.profile = np.asarray(h_obs)
    return loss


def tracks_loss(target, particles: Sequence[int], frames: Sequence[int] | None = None
                ) -> Callable:
    """``positions -> mean |x_p(t) - x_obs_p(t)|^2`` (m^2) over ``particles`` x ``frames``
    (all frames when ``frames`` is None)."""
    target = _check_target(target)
    T, N = target.shape[:2]
    p = np.asarray(particles, int)
    if p.ndim != 1 or len(p) == 0 or p.min() < 0 or p.max() >= N:
        raise ValueError(f"particles must be a non-empty list of indices in [0, {N})")
    f = np.arange(T) if frames is None else np.array([_frame(target, i) for i in frames])
    obs = jnp.asarray(target[f][:, p])

    def loss(positions):
        d = positions[f][:, p] - obs
        return jnp.mean(jnp.sum(d * d, -1))

    return loss


def weighted_sum(terms: Sequence[tuple[float, Callable]]) -> Callable:
    """``positions -> sum_i w_i loss_i(positions)``."""
    terms = list(terms)
    if not terms:
        raise ValueError("weighted_sum needs at least one (weight, loss) term")
    return lambda positions: sum(w * f(positions) for w, f in terms)
