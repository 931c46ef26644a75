"""Position clamps that are counted, never silent: one mechanism for every simulator.

A simulator may keep positions inside its domain (the MPM to stay on its grid, a GNS so that a
wrong prediction cannot leave the box, the hybrid's particle map), but a clamp hides an
escape: a particle that should have stopped at a wall and one that the network threw through
it look the same afterwards. So every clamp goes through :func:`clamp_positions`, which
returns the clamped positions *and* a :class:`ClampCount` (how many positions it moved, and
by how much at most). The count travels in the simulator's state (a pytree leaf, traceable
under ``jit``/``grad``/``vmap``/``lax.scan``, not a Python side effect), each frame's
observation carries the count of that frame (``ParticleFrame.clamp``,
``HybridFrame.clamp``), :class:`~diffgns.trajectory.Trajectory` records it per frame
(``clamped``, ``clamp_shift``), and the command line reports it (:func:`clamp_summary`,
:func:`clamp_warning`)::

    x, c = clamp_positions(x, lo, hi, axis=-1)     # x (N, d); c.moved, c.shift
    state = state._replace(clamp=state.clamp.merge(c))

Counts are *clamp events*: a particle moved in k substeps of a frame counts k times.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["ClampCount", "clamp_positions", "clamp_summary", "clamp_warning"]


class ClampCount(NamedTuple):
    """Clamp events of a frame (or of one clamp).

    Attributes:
        moved: int32 scalar (or (T,) stacked over frames): positions moved by a clamp.
        shift: float scalar (or (T,)): largest distance a clamp moved a position, m.
    """

    moved: jax.Array
    shift: jax.Array

    @staticmethod
    def zero(dtype: Any = None) -> ClampCount:
        """No clamp (``dtype``: float dtype of ``shift``; default JAX's default float)."""
        return ClampCount(jnp.zeros((), jnp.int32), jnp.zeros((), dtype))

    @staticmethod
    def between(x: jax.Array, y: jax.Array, axis: int = -1,
                valid: jax.Array | None = None) -> ClampCount:
        """The count of a correction that moved positions ``x`` to ``y`` (coordinates along
        ``axis``): positions that moved, and the largest distance moved, m. No gradient.
        ``valid``: optional (N,) bool, the positions to count."""
        d = jax.lax.stop_gradient(y - x)
        moved = jnp.any(d != 0, axis=axis)
        d2 = jnp.sum(d * d, axis=axis)
        if valid is not None:
            moved, d2 = moved & valid, jnp.where(valid, d2, 0.0)
        shift = jnp.sqrt(jnp.max(d2, initial=0.0))
        return ClampCount(jnp.sum(moved, dtype=jnp.int32), shift.astype(x.dtype))

    def merge(self, other: ClampCount) -> ClampCount:
        """Both clamps' events: counts added, the larger shift."""
        return ClampCount(self.moved + other.moved,
                          jnp.maximum(self.shift, other.shift.astype(self.shift.dtype)))


def clamp_positions(x: jax.Array, lo: jax.Array, hi: jax.Array, axis: int = -1,
                    valid: jax.Array | None = None) -> tuple[jax.Array, ClampCount]:
    """``clip(x, lo, hi)`` and the count of positions it moved.

    Args:
        x: positions, m, with the coordinates along ``axis``: (N, d) with ``axis=-1`` or
            (d, N) with ``axis=0``.
        lo, hi: bounds broadcastable against ``x`` (e.g. (d,) or (d, 1)), m.
        axis: the coordinate axis of ``x``.
        valid: optional (N,) bool: positions to count (padding is clamped, not counted).

    Returns:
        ``(x_clamped, ClampCount)``; the count has no gradient (the clamped positions have
        the gradient of ``jnp.clip``).
    """
    y = jnp.clip(x, lo, hi)
    return y, ClampCount.between(x, y, axis, valid)


def clamp_summary(count: Any, shift: Any) -> dict:
    """JSON-ready summary of per-frame clamp counts ``count`` (T,) and shifts ``shift`` (T,)
    (m): total positions moved, frames with a clamp, the first such frame (None if none) and
    the largest shift in m."""
    c = np.asarray(count, np.int64).reshape(-1)
    s = np.asarray(shift, np.float64).reshape(-1)
    hit = np.flatnonzero(c > 0)
    return dict(clamped_positions=int(c.sum()), clamped_frames=int(hit.size),
                first_clamped_frame=int(hit[0]) if hit.size else None,
                max_clamp_shift_m=float(s.max()) if s.size else 0.0)


def clamp_warning(summary: dict, what: str = "the rollout") -> str | None:
    """The warning line for a :func:`clamp_summary` with clamps, None without."""
    if not summary["clamped_positions"]:
        return None
    return (f"warning: {what} clamped {summary['clamped_positions']} particle positions to the "
            f"domain in {summary['clamped_frames']} frames (first at frame "
            f"{summary['first_clamped_frame']}, moved by up to "
            f"{1e3 * summary['max_clamp_shift_m']:.3g} mm): particles crossed the domain "
            "boundary and were put back on it")
