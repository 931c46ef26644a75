"""Inverse problems: transforms, optimisers, objectives and simulator adapters.

``from diffgns import inverse; inverse.optimize(...)`` is the optax loop of
:mod:`diffgns.inverse.solve`. The package re-exports the API of its single-purpose modules:
:mod:`~diffgns.inverse.transforms` (Bounded, Identity, DEFAULT_TRANSFORMS),
:mod:`~diffgns.inverse.optimizers` (make_optimizer, gauss_newton_step),
:mod:`~diffgns.inverse.gradients` (the finite-difference helper, gradient_check),
:mod:`~diffgns.memory` (RSS, XLA memory analysis) and :mod:`~diffgns.inverse.mpm`
(frames_to_rest), :mod:`~diffgns.inverse.parameters` (set_params: any MPMParams leaf by
name). Objectives are in :mod:`diffgns.inverse.objectives`,
Levenberg-Marquardt in :mod:`diffgns.inverse.lsq`.
"""
from diffgns.inverse.gradients import (
    central_difference,
    fd_step,
    finite_difference_grad,
    gradient_check,
)
from diffgns.inverse.mpm import frames_to_rest
from diffgns.inverse.optimizers import gauss_newton_step, make_optimizer
from diffgns.inverse.parameters import STATE_PARAMS, parse_fit, set_params
from diffgns.inverse.solve import InverseResult, evaluate_redo, optimize, record
from diffgns.inverse.transforms import (
    DEFAULT_TRANSFORMS,
    FRICTION_ANGLE,
    Bounded,
    Identity,
    Transform,
    setup,
)
from diffgns.memory import current_rss_mb, memory_stats, peak_rss_mb

__all__ = [
    "Bounded",
    "DEFAULT_TRANSFORMS",
    "FRICTION_ANGLE",
    "Identity",
    "InverseResult",
    "STATE_PARAMS",
    "Transform",
    "central_difference",
    "current_rss_mb",
    "evaluate_redo",
    "fd_step",
    "finite_difference_grad",
    "frames_to_rest",
    "gauss_newton_step",
    "gradient_check",
    "make_optimizer",
    "memory_stats",
    "optimize",
    "peak_rss_mb",
    "record",
    "set_params",
    "parse_fit",
    "setup",
]
