"""The static geometry a particle GNS sees: box walls and box obstacles, as traced inputs.

A GNS's node features include the clipped distances to the walls of the box and, when
``GNSConfig.use_obstacles``, to the nearest box obstacle (:mod:`diffgns.graph.features`).
Both are *inputs* here, not configuration: one compiled step serves every box and every
obstacle layout of the same shapes, so one model trains on trajectories in boxes of several
sizes and with different obstacles in one run, and runs in a box it was not trained in
(the features see a wall only within the connectivity radius R, and the other inputs are
relative positions, so a longer box changes no input the network was not trained on).

:class:`Geometry` is a pytree: ``walls`` (d, 2) ``[[xmin, xmax], [ymin, ymax]]`` m and
``obstacles`` (K, 2d) boxes ``[x0, y0, x1, y1]`` m. Batches of windows with different
obstacle counts are padded to one K with :data:`PARKED` boxes far outside any domain, whose
features are exactly those of no obstacle (distance beyond R).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["PARKED", "Geometry", "obstacle_array", "walls_array"]

#: a padding obstacle, m: a unit box 1 km away from every domain (features = no obstacle)
PARKED = (1.0e3, 1.0e3, 1.0e3 + 1.0, 1.0e3 + 1.0)


class Geometry(NamedTuple):
    """Walls and obstacles of one scene (or, with a leading axis, of a batch of windows).

    Attributes:
        walls: (d, 2) ``[lo, hi]`` of the box along each axis, m.
        obstacles: (K, 2d) ``[lo..., hi...]`` of each box obstacle, m; K >= 0. Ignored by
            a GNS whose config has ``use_obstacles = False``.
    """

    walls: jax.Array
    obstacles: jax.Array

    @classmethod
    def of(cls, bounds, obstacles: Sequence = (), pad_to: int = 0,
           dtype=jnp.float32) -> Geometry:
        """From ``bounds`` ``((xmin, xmax), (ymin, ymax))`` and box ``obstacles`` ``[x0, y0,
        x1, y1]`` (m), the obstacles padded with :data:`PARKED` to ``pad_to`` rows."""
        return cls(jnp.asarray(walls_array(bounds), dtype),
                   jnp.asarray(obstacle_array(obstacles, pad_to), dtype))


def walls_array(bounds) -> np.ndarray:
    """(d, 2) float64 array of ``bounds``; ValueError unless every ``lo < hi``."""
    w = np.asarray(bounds, float)
    if w.ndim != 2 or w.shape[1] != 2 or w.shape[0] not in (2, 3) or not np.all(w[:, 0] < w[:, 1]):
        raise ValueError(f"bounds must be ((xmin, xmax), (ymin, ymax)) with min < max, got "
                         f"{bounds!r}")
    return w


def obstacle_array(obstacles: Sequence, pad_to: int = 0) -> np.ndarray:
    """(max(K, pad_to), 4) float64 array of the box obstacles ``[x0, y0, x1, y1]`` (m),
    padded with :data:`PARKED`; ValueError for a box with ``x0 >= x1`` or ``y0 >= y1``."""
    obs = np.asarray(obstacles, float).reshape(-1, 4)
    if np.any(obs[:, :2] >= obs[:, 2:]):
        raise ValueError(f"obstacles must be [x0, y0, x1, y1] with x0 < x1 and y0 < y1, got "
                         f"{obs.tolist()}")
    if len(obs) < pad_to:
        obs = np.concatenate([obs, np.tile(np.asarray(PARKED), (pad_to - len(obs), 1))])
    return obs
