"""Optimisers for :func:`diffgns.inverse.optimize`: optax's Adam and SGD with an exponential
learning-rate decay, and the Gauss-Newton step for one squared residual. All accept the loss
as the ``value=`` extra argument of ``update``. (Levenberg-Marquardt on residual vectors is
:mod:`diffgns.inverse.lsq`.)
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

__all__ = ["gauss_newton_step", "make_optimizer"]


def gauss_newton_step(scale: float = 1.0, max_step: float = 1.0
                      ) -> optax.GradientTransformationExtraArgs:
    """Update ``-scale * 2 L / |g|^2 * g`` (``value=L`` passed to ``update``), each component
    clipped to ``max_step``. For ``L = r^2`` with one residual this is the Newton step
    ``-r / r'`` on ``r``; for a sum of squares it is Polyak's step with ``f* = 0`` doubled."""

    def update(updates, state, params=None, *, value, **extra):
        del params, extra
        g2 = sum(jnp.sum(g * g) for g in jax.tree.leaves(updates))
        lr = jnp.where(g2 > 0, 2.0 * scale * value / jnp.where(g2 > 0, g2, 1.0), 0.0)
        return jax.tree.map(lambda g: jnp.clip(-lr * g, -max_step, max_step), updates), state

    return optax.GradientTransformationExtraArgs(lambda params: optax.EmptyState(), update)


def make_optimizer(name: str, learning_rate: float = 1.0, decay: float = 1.0,
                   max_step: float = 1.0) -> optax.GradientTransformationExtraArgs:
    """``"adam"``/``"sgd"`` (exponential learning-rate decay per iteration) or
    ``"gauss-newton"`` (:func:`gauss_newton_step` scaled by ``learning_rate``, updates
    clipped to ``max_step`` in optimiser units, e.g. the transformed ``u``). All accept the
    loss ``value=`` extra argument of :func:`optimize`."""
    if name == "gauss-newton":
        return gauss_newton_step(learning_rate, max_step)
    sched = optax.exponential_decay(learning_rate, transition_steps=1, decay_rate=decay)
    if name == "adam":
        return optax.with_extra_args_support(optax.adam(sched))
    if name == "sgd":
        return optax.with_extra_args_support(optax.sgd(sched))
    raise ValueError(f"optimizer {name!r} is unknown; use 'gauss-newton', 'adam' or 'sgd'")
