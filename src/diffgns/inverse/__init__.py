"""Inverse problems: transforms, optimisers, objectives and simulator adapters.

``from diffgns import inverse; inverse.optimize(...)`` is the optax loop of
:mod:`diffgns.inverse.solve`; objectives are in :mod:`diffgns.inverse.objectives`,
Levenberg-Marquardt in :mod:`diffgns.inverse.lsq`.
"""
from diffgns.inverse.gradients import (
    central_difference,
    fd_step,
    finite_difference_grad,
    gradient_check,
)
from diffgns.inverse.memory import current_rss_mb, memory_stats, peak_rss_mb
from diffgns.inverse.solve import (
    DEFAULT_TRANSFORMS,
    FRICTION_ANGLE,
    MPM_STATE_PARAMS,
    Bounded,
    Identity,
    InverseResult,
    apply_theta,
    evaluate_redo,
    frames_to_rest,
    gauss_newton_step,
    make_optimizer,
    optimize,
    record,
    setup,
)

__all__ = [
    "Bounded",
    "DEFAULT_TRANSFORMS",
    "FRICTION_ANGLE",
    "Identity",
    "InverseResult",
    "MPM_STATE_PARAMS",
    "apply_theta",
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
    "setup",
]
