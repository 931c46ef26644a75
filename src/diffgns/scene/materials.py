"""Declarative material descriptions (static, validated, hashable).

These are *descriptions*: the numbers here become pytree leaves of
:class:`diffgns.mpm.state.MPMParams` when a scene is turned into a simulation, so
they can be differentiated. The constitutive laws themselves live in
:mod:`diffgns.mpm.constitutive`.

Units are SI throughout: Pa for moduli and cohesion, kg/m^3 for density,
degrees for friction angles, Pa*s for viscosity.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from diffgns.errors import SceneError

if TYPE_CHECKING:  # jax is imported where it is used: scene checks stay light (fast CLI)
    import jax
    from jax.typing import ArrayLike


def _positive(value: float, field: str, owner: str, hint: str) -> None:
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise SceneError(f"{owner}.{field} = {value!r} must be a positive finite number; {hint}")


def _poisson(nu: float, owner: str) -> None:
    if not (isinstance(nu, (int, float)) and 0.0 <= nu < 0.5):
        raise SceneError(
            f"{owner}.nu = {nu!r} is outside [0, 0.5); Poisson's ratio of a stable isotropic "
            "solid must satisfy 0 <= nu < 0.5 (use e.g. 0.3)"
        )


def lame(E: float, nu: float) -> tuple[float, float]:
    """Lamé parameters (lambda, mu) in Pa from Young's modulus E (Pa) and Poisson's ratio nu."""
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return lam, mu


def friction_feature(phi_deg: ArrayLike) -> jax.Array:
    """The learned simulators' material feature of a friction angle: ``tan(phi)``.

    ``phi_deg``: friction angle(s) in degrees, any shape (a Python float, an MPMParams leaf,
    a traced parameter); returns ``tan(phi)`` of the same shape and float dtype (the default
    float for Python numbers and integers; dimensionless, the Mohr-Coulomb friction
    coefficient), differentiable:
    ``d tan(phi) / d phi_deg = (pi / 180) / cos(phi)^2``. The only place diffgns computes it.
    """
    import jax.numpy as jnp

    return jnp.tan(jnp.deg2rad(phi_deg))


def friction_angle_of_feature(feature) -> float:
    """The inverse of :func:`friction_feature` on the host: degrees of ``arctan(feature)``
    (a float; e.g. the friction angles of a dataset's stored ``material_property``)."""
    return math.degrees(math.atan(float(feature)))


@dataclass(frozen=True)
class Elastic:
    """Hyperelastic solid.

    Args:
        E: Young's modulus, Pa.
        nu: Poisson's ratio, in [0, 0.5).
        rho: density, kg/m^3.
        model: "corotated" (fixed-corotated, large rotations) or "linear" (small strain).
    """

    E: float = 1.0e6
    nu: float = 0.3
    rho: float = 1000.0
    model: str = "corotated"

    kind = "elastic"

    def __post_init__(self):
        _positive(self.E, "E", "Elastic", "stiffness must be > 0 Pa (e.g. E = 1e6)")
        _poisson(self.nu, "Elastic")
        _positive(self.rho, "rho", "Elastic", "density must be > 0 kg/m^3 (e.g. rho = 1000)")
        if self.model not in ("corotated", "linear"):
            raise SceneError(
                f"Elastic.model = {self.model!r} is unknown; use 'corotated' or 'linear'"
            )

    @property
    def effect(self) -> str:
        return f"elastic_{self.model}"

    def wave_speed(self) -> float:
        """P-wave speed sqrt((lambda + 2 mu)/rho), m/s."""
        lam, mu = lame(self.E, self.nu)
        return math.sqrt((lam + 2.0 * mu) / self.rho)


@dataclass(frozen=True)
class Sand:
    """Drucker–Prager granular material (Klar et al. 2016 return map on Hencky strain).

    The cone is matched to Mohr–Coulomb in plane strain for the in-plane stresses:
    alpha = sin(phi)/sqrt(2), so that the 2D yield surface |s| <= -alpha tr(tau) is
    exactly (sigma_1 - sigma_2)/2 <= -sin(phi)(sigma_1 + sigma_2)/2 + c cos(phi).

    Args:
        friction_angle: internal friction angle phi, degrees, in (0, 90).
        E: Young's modulus, Pa.
        nu: Poisson's ratio, in [0, 0.5).
        rho: density, kg/m^3.
        cohesion: Mohr–Coulomb cohesion c, Pa (>= 0).
    """

    friction_angle: float = 30.0
    E: float = 2.0e6
    nu: float = 0.3
    rho: float = 1800.0
    cohesion: float = 0.0

    kind = "sand"
    effect = "sand"

    def __post_init__(self):
        phi = self.friction_angle
        if not (isinstance(phi, (int, float)) and 0.0 < phi < 90.0):
            raise SceneError(
                f"Sand.friction_angle = {phi!r} is outside (0, 90); give the internal friction "
                "angle in degrees, e.g. 30"
            )
        _positive(self.E, "E", "Sand", "stiffness must be > 0 Pa (e.g. E = 2e6)")
        _poisson(self.nu, "Sand")
        _positive(self.rho, "rho", "Sand", "density must be > 0 kg/m^3 (e.g. rho = 1800)")
        if not (isinstance(self.cohesion, (int, float)) and self.cohesion >= 0):
            raise SceneError(f"Sand.cohesion = {self.cohesion!r} must be >= 0 Pa")

    def wave_speed(self) -> float:
        lam, mu = lame(self.E, self.nu)
        return math.sqrt((lam + 2.0 * mu) / self.rho)


@dataclass(frozen=True)
class Fluid:
    """Weakly compressible Newtonian fluid, Tait equation of state.

    p = K/gamma * (J^-gamma - 1), sigma = -p I + viscosity (grad v + grad v^T).

    Args:
        bulk_modulus: K, Pa (sets the sound speed sqrt(K/rho); choose c >> flow speed).
        rho: density, kg/m^3.
        viscosity: dynamic viscosity, Pa*s (>= 0).
        gamma: Tait exponent (7 for water).
    """

    bulk_modulus: float = 2.0e5
    rho: float = 1000.0
    viscosity: float = 1.0e-3
    gamma: float = 7.0

    kind = "fluid"
    effect = "fluid"

    def __post_init__(self):
        _positive(self.bulk_modulus, "bulk_modulus", "Fluid", "stiffness must be > 0 Pa")
        _positive(self.rho, "rho", "Fluid", "density must be > 0 kg/m^3 (e.g. rho = 1000)")
        _positive(self.gamma, "gamma", "Fluid", "use 7 for water")
        if not (isinstance(self.viscosity, (int, float)) and self.viscosity >= 0):
            raise SceneError(f"Fluid.viscosity = {self.viscosity!r} must be >= 0 Pa*s")

    def wave_speed(self) -> float:
        return math.sqrt(self.bulk_modulus / self.rho)


Material = Elastic | Sand | Fluid

MATERIALS = {"elastic": Elastic, "sand": Sand, "fluid": Fluid}


def material_from_dict(d: dict, where: str) -> Material:
    """Build a material from a TOML/dict description ``{"type": "sand", ...}``."""
    d = dict(d)
    kind = d.pop("type", None)
    if kind not in MATERIALS:
        raise SceneError(
            f"{where}.material.type = {kind!r} is unknown; use one of {sorted(MATERIALS)}"
        )
    cls = MATERIALS[kind]
    allowed = set(cls.__dataclass_fields__)
    extra = set(d) - allowed
    if extra:
        raise SceneError(
            f"{where}.material has unknown field(s) {sorted(extra)} for type {kind!r}; "
            f"allowed: {sorted(allowed)}"
        )
    return cls(**d)


def material_to_dict(m: Material) -> dict:
    out = {"type": m.kind}
    out.update({k: getattr(m, k) for k in m.__dataclass_fields__})
    return out
