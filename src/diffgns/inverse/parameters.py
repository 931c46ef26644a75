"""Named scalar parameters of a scene for inverse problems: any ``MPMParams`` leaf.

A parameter name is a leaf of :class:`~diffgns.mpm.state.MPMParams`, optionally indexed:

=====================================  ============================================  =======
name                                   sets                                          unit
=====================================  ============================================  =======
``friction_angle``, ``E``, ``nu``,     that field of every body (``name[b]``: of     deg, Pa,
``rho``, ``cohesion``,                 body ``b``, given by name or index)           -, kg/m^3,
``bulk_modulus``, ``viscosity``,                                                     Pa, Pa,
``gamma``                                                                            Pa s, -
``wall_mu``                            all four walls (``wall_mu[left]``, ... one)   -
``floor_mu``                           the bottom wall (= ``wall_mu[bottom]``)       -
``obstacle_mu``                        every obstacle (``obstacle_mu[k]``: one)      -
``gravity[x]``, ``gravity[y]``         a gravity component                           m/s^2
``damping``                            the grid velocity damping rate                1/s
=====================================  ============================================  =======

plus the initial-state quantities a :class:`~diffgns.inverse.simulators.SceneObservation`
defines (``aspect_ratio`` of a scene of one rectangular body). :func:`set_params` writes
a ``theta`` dict into an ``MPMParams`` differentiably; :func:`parse_fit` reads the CLI's
``name=start:lo:hi``.
"""
from __future__ import annotations

import math
import re
from typing import Any

import jax.numpy as jnp

from diffgns.inverse.transforms import Bounded
from diffgns.scene.elements import WALL_NAMES

__all__ = ["BODY_FIELDS", "STATE_PARAMS", "check_names", "parse_fit", "set_params"]

#: per-body fields of MPMParams (shape (B,), scene body order)
BODY_FIELDS = ("friction_angle", "E", "nu", "rho", "cohesion", "bulk_modulus", "viscosity",
               "gamma")
#: initial-state quantities (handled by the scene observation, not MPMParams)
STATE_PARAMS = ("aspect_ratio",)
_NAME = re.compile(r"^([A-Za-z_]+)(?:\[([^\]]+)\])?$")


def _split(name: str) -> tuple[str, str | None]:
    m = _NAME.match(name.strip())
    if not m:
        raise ValueError(f"parameter name {name!r} is malformed; use e.g. friction_angle, "
                         "friction_angle[column] or wall_mu[bottom]")
    return m.group(1), m.group(2)


def _index(key: str | None, labels: list[str], what: str, name: str) -> int | None:
    """Index of ``key`` (a label or an integer) among ``labels``; None for no key."""
    if key is None:
        return None
    if key in labels:
        return labels.index(key)
    if key.lstrip("-").isdigit() and -len(labels) <= int(key) < len(labels):
        return int(key) % len(labels)
    plural = "bodies" if what == "body" else what + "s"
    raise ValueError(f"{name}: no {what} {key!r}; this scene has {plural} "
                     f"{[lab for lab in labels if lab] or list(range(len(labels)))} "
                     f"(or indices 0..{len(labels) - 1})")


def _target(bodies: list[str], n_obstacles: int, name: str) -> tuple[str, int | None]:
    """(MPMParams field, index or None for all) of a parameter name in a scene with bodies
    named ``bodies`` and ``n_obstacles`` obstacles."""
    base, key = _split(name)
    if base in BODY_FIELDS:
        return base, _index(key, bodies, "body", name)
    if base == "floor_mu" and key is None:
        return "wall_mu", WALL_NAMES.index("bottom")
    if base == "wall_mu":
        return "wall_mu", _index(key, list(WALL_NAMES), "wall", name)
    if base == "obstacle_mu":
        if not n_obstacles:
            raise ValueError(f"{name}: the scene has no obstacles")
        return "obstacle_mu", _index(key, [""] * n_obstacles, "obstacle", name)
    if base == "gravity":
        if key not in ("x", "y", "0", "1"):
            raise ValueError(f"{name}: fit a gravity component, gravity[x] or gravity[y]")
        return "gravity", {"x": 0, "y": 1, "0": 0, "1": 1}[key]
    if base == "damping" and key is None:
        return "damping", None
    raise ValueError(f"unknown parameter {name!r}; use one of {', '.join(BODY_FIELDS)} "
                     "(optionally [body]), wall_mu[wall], floor_mu, obstacle_mu[k], "
                     "gravity[x|y], damping, or " + ", ".join(STATE_PARAMS))


def check_names(scene, names, state_params=()) -> None:
    """Raise ValueError naming any parameter that ``scene`` does not have."""
    for k in names:
        if k not in state_params:
            _target([b.name for b in scene.bodies], len(scene.obstacles), k)


def set_params(params, scene, theta: dict):
    """``params`` (MPMParams) with the named scalars of ``theta`` written in (differentiable).

    ``scene`` (or None: bodies by index only) names the bodies. Names listed in
    :data:`STATE_PARAMS` are skipped (they set the initial state).
    """
    if scene is not None:
        bodies, n_obstacles = [b.name for b in scene.bodies], len(scene.obstacles)
    else:
        bodies, n_obstacles = [""] * len(params.E), len(params.obstacle_mu)
    rep: dict[str, Any] = {}
    for k, v in theta.items():
        if _split(k)[0] in STATE_PARAMS:
            continue
        field, i = _target(bodies, n_obstacles, k)
        cur = rep.get(field, getattr(params, field))
        v = jnp.asarray(v, cur.dtype)
        rep[field] = jnp.broadcast_to(v, cur.shape) if i is None else cur.at[i].set(v)
    return params.replace(**rep)


def parse_fit(spec: str) -> tuple[str, float, object]:
    """``"name=start[:lo:hi]"`` -> (name, start, transform): ``Bounded(lo, hi)`` when bounds
    are given (the start must lie strictly inside), otherwise None (the optimiser's default
    for that name, e.g. ``Bounded(0, 90)`` for ``friction_angle``, else unbounded)."""
    if "=" not in spec:
        raise ValueError(f"--fit {spec!r}: use name=start:lo:hi, e.g. friction_angle=40:0:90")
    name, _, rest = spec.partition("=")
    name = name.strip()
    _split(name)
    parts = rest.split(":")
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"--fit {spec!r}: start, lo and hi must be numbers") from None
    if len(vals) not in (1, 3) or not all(math.isfinite(v) for v in vals):
        raise ValueError(f"--fit {spec!r}: give start or start:lo:hi (finite numbers)")
    if len(vals) == 1:
        return name, vals[0], None
    start, lo, hi = vals
    if not lo < start < hi:
        raise ValueError(f"--fit {spec!r}: the start {start:g} must lie strictly inside "
                         f"({lo:g}, {hi:g})")
    return name, start, Bounded(lo, hi)


def parse_scan(spec: str) -> tuple[str, list[float]]:
    """``"name=lo:hi:n"`` -> (name, n values evenly spaced from lo to hi), for the ``scan``
    of :func:`diffgns.inverse.optimize` (``diffgns invert --scan``)."""
    name, _, rest = spec.partition("=")
    parts = rest.split(":")
    try:
        lo, hi, n = float(parts[0]), float(parts[1]), int(parts[2])
    except (ValueError, IndexError):
        raise ValueError(f"--scan {spec!r}: use name=lo:hi:n, e.g. "
                         "friction_angle=15:50:8") from None
    if len(parts) != 3 or not (math.isfinite(lo) and math.isfinite(hi) and lo < hi and n >= 2):
        raise ValueError(f"--scan {spec!r}: give finite lo < hi and n >= 2 points")
    _split(name.strip())
    return name.strip(), [lo + (hi - lo) * i / (n - 1) for i in range(n)]
