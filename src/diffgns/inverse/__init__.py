"""Inverse problems: transforms, optimisers, objectives and simulator adapters.

``from diffgns import inverse; inverse.optimize(...)`` is the optax loop of
:mod:`diffgns.inverse.solve`; objectives are in :mod:`diffgns.inverse.objectives`,
Levenberg-Marquardt in :mod:`diffgns.inverse.lsq`.
"""
from diffgns.inverse.solve import (
    DEFAULT_TRANSFORMS,
    FRICTION_ANGLE,
    MPM_STATE_PARAMS,
    Bounded,
    Identity,
    InverseResult,
    apply_theta,
    current_rss_mb,
    evaluate_redo,
    finite_difference_grad,
    frames_to_rest,
    gauss_newton_step,
    gradient_check,
    make_optimizer,
    memory_stats,
    mpm_final_positions,
    optimize,
    peak_rss_mb,
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
    "current_rss_mb",
    "evaluate_redo",
    "finite_difference_grad",
    "frames_to_rest",
    "gauss_newton_step",
    "gradient_check",
    "make_optimizer",
    "memory_stats",
    "mpm_final_positions",
    "optimize",
    "peak_rss_mb",
    "record",
    "setup",
]
