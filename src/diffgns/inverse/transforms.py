"""Parameter transforms: the optimiser works on an unconstrained ``u``, the simulator sees
the physical ``theta = forward(u)``.

:class:`Bounded` keeps a parameter inside its physical range, ``theta = lo + (hi - lo)
sigmoid(u)``, which no optimiser step can leave; :class:`Identity` leaves it free.
:data:`DEFAULT_TRANSFORMS` names the transform of the usual parameters and :func:`setup`
turns a physical start ``theta0`` into ``u`` (validating it).
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar, Protocol

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

__all__ = ["DEFAULT_TRANSFORMS", "FRICTION_ANGLE", "Bounded", "Identity", "Transform", "setup"]


class Transform(Protocol):
    """``forward``: optimiser value u -> physical value (differentiable); ``inverse``:
    physical -> u, raising ValueError naming ``name`` outside ``(lo, hi)``."""

    @property
    def lo(self) -> float: ...

    @property
    def hi(self) -> float: ...

    def forward(self, u: ArrayLike) -> jax.Array: ...

    def inverse(self, x: float, name: str = "parameter") -> float: ...


@dataclass(frozen=True)
class Bounded:
    """Physical parameter in the open interval ``(lo, hi)``: ``x = lo + (hi - lo) sigmoid(u)``.

    ``FRICTION_ANGLE = Bounded(0, 90)`` (degrees). ``u`` is clipped to +-15 first, so even in
    float32 every ``u`` maps strictly inside (within ~3e-7 of the range of either bound).
    """

    lo: float
    hi: float

    def forward(self, u: ArrayLike) -> jax.Array:
        return self.lo + (self.hi - self.lo) * jax.nn.sigmoid(jnp.clip(u, -15.0, 15.0))

    def inverse(self, x: float, name: str = "parameter") -> float:
        x = float(x)
        if not (self.lo < x < self.hi) or not math.isfinite(x):
            raise ValueError(f"{name} = {x:g} is outside its physical range ({self.lo:g}, "
                             f"{self.hi:g}); start from a value strictly inside it")
        p = (x - self.lo) / (self.hi - self.lo)
        return math.log(p / (1.0 - p))


@dataclass(frozen=True)
class Identity:
    """Unbounded parameter (optimised as it is)."""

    lo: ClassVar[float] = -math.inf
    hi: ClassVar[float] = math.inf

    def forward(self, u: ArrayLike) -> jax.Array:
        return jnp.asarray(u)

    def inverse(self, x: float, name: str = "parameter") -> float:
        if not math.isfinite(float(x)):
            raise ValueError(f"{name} = {x} is not finite")
        return float(x)


#: the friction angle, degrees
FRICTION_ANGLE = Bounded(0.0, 90.0)
#: transforms used when a parameter's name is given without one
DEFAULT_TRANSFORMS: dict[str, Transform] = {
    "friction_angle": FRICTION_ANGLE, "floor_mu": Bounded(0.0, 2.0), "wall_mu": Bounded(0.0, 2.0),
    "aspect_ratio": Bounded(0.25, 4.0)}


def setup(theta0: dict, transforms: dict | None
          ) -> tuple[dict[str, Transform], dict[str, jax.Array], Callable[[dict], dict]]:
    """(transforms by name, initial u, u -> theta) for physical ``theta0``; validates it."""
    tf: dict[str, Transform] = {
        k: (transforms or {}).get(k, DEFAULT_TRANSFORMS.get(k, Identity())) for k in theta0}
    dtype = jnp.result_type(float)
    u = {k: jnp.asarray(tf[k].inverse(v, k), dtype) for k, v in theta0.items()}
    return tf, u, lambda u: {k: tf[k].forward(v) for k, v in u.items()}
