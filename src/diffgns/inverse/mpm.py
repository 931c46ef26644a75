"""The length of an MPM rollout that comes to rest (:func:`frames_to_rest`). Named physical
parameters are written into ``MPMParams`` by :func:`diffgns.inverse.parameters.set_params`.
"""
from __future__ import annotations

import numpy as np

__all__ = ["frames_to_rest"]

def frames_to_rest(speed, threshold: float = 0.02, margin: int = 10, multiple: int = 25) -> int:
    """Frames until the per-frame max speed (m/s) stays below ``threshold``, plus a margin,
    rounded up to a multiple of ``multiple``."""
    speed = np.asarray(speed)
    moving = np.flatnonzero(speed >= threshold)
    n = (moving[-1] + 1 if len(moving) else 0) + margin
    return int(-(-n // multiple) * multiple)
