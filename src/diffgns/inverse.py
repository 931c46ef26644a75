"""Inverse problems: gradient-based parameter identification through any rollout.

An inverse problem is ``optax`` on ``jax.grad(loss(rollout(params(theta))))``. ``theta`` is a
dict of physical parameters (e.g. ``{"friction_angle": 45.0}``); ``loss_fn(theta)`` runs the
simulator and scores it against the observation. This module supplies the optimisation loop
with a stopping rule, progress output and a history record, and finite-difference gradients
for comparison.
"""
from __future__ import annotations

import resource
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
import optax


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@dataclass
class InverseResult:
    """Outcome of :func:`optimize`: final parameters and one record per iteration."""

    theta: dict
    history: list = field(default_factory=list)
    converged: bool = False
    wall_time_s: float = 0.0

    def series(self, key: str, name: str | None = None) -> np.ndarray:
        """History of ``key`` ("loss", "time_s", ...) or of parameter ``name`` under "theta"."""
        if name is None:
            return np.array([h[key] for h in self.history])
        return np.array([h[key][name] for h in self.history])


def make_optimizer(name: str, learning_rate: float,
                   decay: float = 1.0) -> optax.GradientTransformation:
    """"adam" or "sgd" with an exponential learning-rate decay per iteration."""
    sched = optax.exponential_decay(learning_rate, transition_steps=1, decay_rate=decay)
    if name == "adam":
        return optax.adam(sched)
    if name == "sgd":
        return optax.sgd(sched)
    raise ValueError(f"optimizer {name!r} is unknown; use 'adam' or 'sgd'")


def optimize(loss_fn: Callable[[dict], jax.Array], theta0: dict,
             optimizer: optax.GradientTransformation, max_iter: int = 20,
             bounds: dict | None = None, loss_tol: float = 0.0, step_tol: float = 0.0,
             callback: Callable[[dict], None] | None = None) -> InverseResult:
    """Minimise ``loss_fn(theta)`` with ``optimizer`` and exact gradients.

    Args:
        loss_fn: theta (dict of scalars) -> scalar loss; jitted here with value_and_grad.
        theta0: initial parameters.
        bounds: {name: (lo, hi)}; parameters are projected into these after each step.
        loss_tol: stop when the loss falls below this.
        step_tol: stop when every parameter moved less than this in an iteration.
        callback: called with each history record (e.g. to print progress).
    Returns:
        InverseResult; its history holds per iteration: iteration, theta, loss, grad,
        time_s (of the iteration), elapsed_s, peak_rss_mb.
    """
    vg = jax.jit(jax.value_and_grad(loss_fn))
    theta = {k: jnp.asarray(v) for k, v in theta0.items()}
    state = optimizer.init(theta)
    result = InverseResult(theta=theta)
    t_start = time.perf_counter()
    for it in range(max_iter + 1):
        t0 = time.perf_counter()
        loss, grad = vg(theta)
        loss = float(jax.block_until_ready(loss))
        rec = dict(iteration=it, theta={k: float(v) for k, v in theta.items()}, loss=loss,
                   grad={k: float(v) for k, v in grad.items()},
                   time_s=time.perf_counter() - t0, elapsed_s=time.perf_counter() - t_start,
                   peak_rss_mb=peak_rss_mb())
        result.history.append(rec)
        if callback:
            callback(rec)
        if not np.isfinite(loss) or not all(np.isfinite(v) for v in rec["grad"].values()):
            raise FloatingPointError(f"non-finite loss or gradient at iteration {it}: {rec}")
        if loss <= loss_tol or it == max_iter:
            result.converged = loss <= loss_tol
            break
        updates, state = optimizer.update(grad, state, theta)
        new = optax.apply_updates(theta, updates)
        if bounds:
            new = {k: jnp.clip(v, *bounds[k]) if k in bounds else v for k, v in new.items()}
        moved = max(abs(float(new[k] - theta[k])) for k in theta)
        theta = new
        if moved < step_tol:
            result.converged = True
            loss = float(loss_fn(theta))
            result.history.append(dict(rec, iteration=it + 1, loss=loss,
                                       theta={k: float(v) for k, v in theta.items()}))
            break
    result.theta = {k: float(v) for k, v in theta.items()}
    result.wall_time_s = time.perf_counter() - t_start
    return result


def finite_difference_grad(loss_fn: Callable[[dict], jax.Array], theta: dict,
                           rel_step: float = 1e-4) -> dict:
    """Central finite-difference gradient of ``loss_fn`` at ``theta`` (one pair of runs per
    parameter), for comparison with the AD gradient."""
    f = jax.jit(loss_fn)
    out = {}
    for k, v in theta.items():
        h = rel_step * max(abs(float(v)), 1.0)
        up = dict(theta, **{k: jnp.asarray(float(v) + h)})
        dn = dict(theta, **{k: jnp.asarray(float(v) - h)})
        out[k] = float((f(up) - f(dn)) / (2 * h))
    return out


def apply_theta(params, theta: dict):
    """Write named physical parameters into an MPMParams pytree (differentiably).

    Names: friction_angle, E, nu, rho, cohesion (all bodies), floor_mu (bottom wall),
    wall_mu (all four walls).
    """
    rep = {}
    for k, v in theta.items():
        v = jnp.asarray(v, params.E.dtype)
        if k in ("friction_angle", "E", "nu", "rho", "cohesion"):
            rep[k] = jnp.broadcast_to(v, getattr(params, k).shape)
        elif k == "floor_mu":
            rep["wall_mu"] = rep.get("wall_mu", params.wall_mu).at[2].set(v)
        elif k == "wall_mu":
            rep["wall_mu"] = jnp.broadcast_to(v, (4,))
        else:
            raise ValueError(f"unknown parameter {k!r}; use friction_angle, E, nu, rho, "
                             "cohesion, floor_mu or wall_mu")
    return params.replace(**rep)


def mpm_final_positions(sim, state, n_frames: int, block: int = 25):
    """theta -> (N, 2) final positions of an MPM rollout, checkpointed for gradients."""
    base = sim.params()

    def final(theta):
        pos, _, _, _ = sim.rollout_full(apply_theta(base, theta), state, n_frames=n_frames,
                                        checkpoint=True, block=block)
        return pos[-1]

    return final


def frames_to_rest(speed, threshold: float = 0.02, margin: int = 10, multiple: int = 25) -> int:
    """Frames until the per-frame max speed (m/s) stays below ``threshold``, plus a margin,
    rounded up to a multiple of ``multiple``."""
    speed = np.asarray(speed)
    moving = np.flatnonzero(speed >= threshold)
    n = (moving[-1] + 1 if len(moving) else 0) + margin
    return int(-(-n // multiple) * multiple)
