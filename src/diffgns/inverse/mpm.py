"""MPM parameter plumbing of inverse problems: named physical parameters into ``MPMParams``
(:func:`apply_theta`) and the length of a rollout that comes to rest (:func:`frames_to_rest`).
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = ["MPM_STATE_PARAMS", "apply_theta", "frames_to_rest"]

#: parameters that enter through the initial state rather than MPMParams
MPM_STATE_PARAMS = ("aspect_ratio",)


def apply_theta(params, theta: dict):
    """Write named physical parameters into an MPMParams pytree (differentiably).

    Names: friction_angle, E, nu, rho, cohesion (all bodies), floor_mu (bottom wall),
    wall_mu (all four walls). Other names (e.g. aspect_ratio, handled by the simulator's
    initial state) are ignored when listed in ``MPM_STATE_PARAMS``.
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
        elif k not in MPM_STATE_PARAMS:
            raise ValueError(f"unknown parameter {k!r}; use friction_angle, E, nu, rho, "
                             "cohesion, floor_mu, wall_mu or " + ", ".join(MPM_STATE_PARAMS))
    return params.replace(**rep)


def frames_to_rest(speed, threshold: float = 0.02, margin: int = 10, multiple: int = 25) -> int:
    """Frames until the per-frame max speed (m/s) stays below ``threshold``, plus a margin,
    rounded up to a multiple of ``multiple``."""
    speed = np.asarray(speed)
    moving = np.flatnonzero(speed >= threshold)
    n = (moving[-1] + 1 if len(moving) else 0) + margin
    return int(-(-n // multiple) * multiple)
