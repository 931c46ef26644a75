"""The static geometry a particle GNS sees: box walls and box obstacles, as traced inputs.

A GNS's node features include the clipped distances to the walls of the box and, when
``GNSConfig.use_obstacles``, to the nearest box obstacle (:mod:`diffgns.graph.features`).
Both are *inputs* here, not configuration: one compiled step serves every box and every
obstacle layout of the same shapes, so one model trains on trajectories in boxes of several
sizes and with different obstacles in one run, and runs in a box it was not trained in
(the features see a wall only within the connectivity radius R, and the other inputs are
relative positions, so a longer box changes no input the network was not trained on).

:class:`Geometry` is a pytree: ``walls`` (d, 2) ``[[xmin, xmax], [ymin, ymax](, [zmin,
zmax])]`` m and ``obstacles`` (K, 2d) boxes ``[lo..., hi...]`` (2D ``[x0, y0, x1, y1]``, 3D
``[x0, y0, z0, x1, y1, z1]``) m; d = 2 or 3. Batches of windows with different obstacle
counts are padded to one K with :func:`parked` boxes far outside any domain, whose features
are exactly those of no obstacle (distance beyond R).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["PARKED", "Geometry", "obstacle_array", "parked", "walls_array"]

#: a 2D padding obstacle, m: a unit box 1 km away from every domain (features = no obstacle)
PARKED = (1.0e3, 1.0e3, 1.0e3 + 1.0, 1.0e3 + 1.0)


def parked(dim: int = 2) -> tuple[float, ...]:
    """The padding obstacle in ``dim`` dimensions: a unit cube 1 km away from every domain
    (:data:`PARKED` in 2D)."""
    return (1.0e3,) * dim + (1.0e3 + 1.0,) * dim


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
        """From ``bounds`` ``((xmin, xmax), (ymin, ymax)(, (zmin, zmax)))`` and box
        ``obstacles`` ``[lo..., hi...]`` (m, 2d numbers each), the obstacles padded with
        :func:`parked` to ``pad_to`` rows."""
        walls = walls_array(bounds)
        return cls(jnp.asarray(walls, dtype),
                   jnp.asarray(obstacle_array(obstacles, pad_to, len(walls)), dtype))


def walls_array(bounds) -> np.ndarray:
    """(d, 2) float64 array of ``bounds`` (d = 2 or 3); ValueError unless every ``lo < hi``."""
    w = np.asarray(bounds, float)
    if w.ndim != 2 or w.shape[1] != 2 or w.shape[0] not in (2, 3) or not np.all(w[:, 0] < w[:, 1]):
        raise ValueError(f"bounds must be ((xmin, xmax), (ymin, ymax)[, (zmin, zmax)]) with "
                         f"min < max, got {bounds!r}")
    return w


def obstacle_array(obstacles: Sequence, pad_to: int = 0, dim: int = 2) -> np.ndarray:
    """(max(K, pad_to), 2 dim) float64 array of the box obstacles ``[lo..., hi...]`` (m; 2D
    ``[x0, y0, x1, y1]``), padded with :func:`parked`; ValueError for a box of another
    length or with a ``lo >= hi``."""
    obs = np.asarray(obstacles, float)
    if obs.size and (obs.ndim > 2 or obs.size % (2 * dim)
                     or (obs.ndim == 2 and obs.shape[1] != 2 * dim)):
        raise ValueError(f"obstacles of a {dim}D geometry must be {2 * dim} numbers [lo..., "
                         f"hi...] each, got shape {obs.shape}")
    obs = obs.reshape(-1, 2 * dim)
    if np.any(obs[:, :dim] >= obs[:, dim:]):
        names = ("[x0, y0, x1, y1] with x0 < x1 and y0 < y1" if dim == 2 else
                 "[x0, y0, z0, x1, y1, z1] with x0 < x1, y0 < y1 and z0 < z1")
        raise ValueError(f"obstacles must be {names}, got {obs.tolist()}")
    if len(obs) < pad_to:
        obs = np.concatenate([obs, np.tile(np.asarray(parked(dim)), (pad_to - len(obs), 1))])
    return obs
