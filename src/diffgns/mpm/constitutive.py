"""Constitutive laws: Kirchhoff stress and plastic projection, per material effect, 2D or 3D.

Each law maps the elastic deformation gradient F (d, d, N) and per-particle
parameters (N,) to (tau, F'), where tau (d, d, N) is the Kirchhoff stress in Pa and
F' the (possibly projected) deformation gradient; d = 2 or 3 is read from F. Every law
is wrapped in its own ``jax.jit`` so it appears as a named call in the jaxpr: tests check
that a scene traces exactly the laws it declares.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from diffgns.mpm import linalg as la


def lame(E, nu):
    """Lamé (lambda, mu) in Pa from E (Pa) and nu, elementwise."""
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return lam, mu


@jax.jit
def elastic_linear(F, E, nu):
    """Small-strain linear elasticity: tau ~ sigma = lambda tr(eps) I + 2 mu eps."""
    lam, mu = lame(E, nu)
    d = F.shape[0]
    e = [[F[i, i] - 1.0 if i == j else None for j in range(d)] for i in range(d)]
    for i in range(d):
        for j in range(i + 1, d):
            e[i][j] = e[j][i] = 0.5 * (F[i, j] + F[j, i])  # one node: 2D bitwise as before
    tr = la._sum([e[i][i] for i in range(d)])
    tau = jnp.stack([jnp.stack([lam * tr + 2 * mu * e[i][i] if i == j else 2 * mu * e[i][j]
                                for j in range(d)]) for i in range(d)])
    return tau, F


@jax.jit
def elastic_corotated(F, E, nu):
    """Fixed-corotated elasticity: tau = 2 mu (F - R) F^T + lambda (J - 1) J I."""
    lam, mu = lame(E, nu)
    R = la.polar_rotation(F)
    J = la.det(F)
    tau = 2.0 * mu * la.matmul(F - R, la.transpose(F))
    p = lam * (J - 1.0) * J
    tau = tau + la.diag(*([p] * F.shape[0]))
    return tau, F


def hencky_stress(U, eps, lam, mu):
    """Kirchhoff stress of Hencky elasticity: U diag(2 mu eps + lam tr eps) U^T."""
    d = eps.shape[0]
    tr = la._sum([eps[i] for i in range(d)])
    dg = la.diag(*[2 * mu * eps[i] + lam * tr for i in range(d)])
    return la.matmul(la.matmul(U, dg), la.transpose(U))


def cone_slope(friction_angle, d: int):
    """Drucker–Prager slope alpha of the cone |dev tau| <= -alpha (tr tau - tr tau_apex).

    alpha = sqrt(2) sin(phi) / d: the cone passes through the Mohr–Coulomb surface of angle
    phi (degrees) on its *shear meridian* (Lode angle 0, the intermediate principal stress
    the mean of the other two). That is the state of non-dilatant plane-strain flow, so
    phi is the plane-strain Mohr–Coulomb angle in 2D and in 3D alike: a 3D slab between
    frictionless walls yields where the 2D scene does. In 2D this is exactly Mohr–Coulomb
    for the in-plane stresses. In 3D triaxial compression the cone is weaker than
    Mohr–Coulomb of angle phi (it matches MC of angle phi_c with sin phi_c =
    sqrt(3) sin(phi) / (2 + sin(phi)/sqrt(3)); phi = 30 deg gives phi_c = 22.2 deg), and
    stronger in triaxial extension. Klar et al. (2016) use the compression meridian
    instead, alpha = sqrt(2/3) 2 sin(phi)/(3 - sin(phi)).
    """
    phi = jnp.deg2rad(friction_angle)
    if d == 2:
        return jnp.sin(phi) / jnp.sqrt(2.0)
    return jnp.sqrt(2.0) * jnp.sin(phi) / d


@jax.jit
def drucker_prager(F, E, nu, friction_angle, cohesion):
    """Drucker–Prager return map on Hencky strain (Klar et al. 2016), 2D or 3D.

    The cone is :func:`cone_slope` (shear-meridian Mohr–Coulomb match; in 2D exactly
    Mohr–Coulomb for the in-plane principal stresses). Cohesion c shifts the apex into
    tension by the volumetric strain d c cot(phi) / (d lambda + 2 mu). Plastic flow is
    non-dilatant (radial return in the deviatoric plane at fixed volume); a trial state in
    volumetric tension beyond the apex goes to the apex.

    Args:
        F: (d, d, N) trial elastic deformation gradient.
        E, nu, friction_angle (degrees), cohesion (Pa): (N,) parameters.
    Returns:
        tau (d, d, N) Pa, projected F (d, d, N).
    """
    lam, mu = lame(E, nu)
    d = F.shape[0]
    U, s, V = la.svd(F)
    s = jnp.maximum(s, 1e-4)
    eps = jnp.log(s)
    phi = jnp.deg2rad(friction_angle)
    alpha = cone_slope(friction_angle, d)
    k = float(d) * lam + 2.0 * mu  # d lambda + 2 mu
    apex = float(d) * cohesion * jnp.cos(phi) / (jnp.sin(phi) * k)  # tensile trace at the apex
    tr = la._sum([eps[i] for i in range(d)])
    tr_s = tr - apex
    hat = eps - (1.0 / d) * tr
    hat_norm = la.safe_norm(hat)
    dgamma = hat_norm + k / (2.0 * mu) * tr_s * alpha
    to_apex = tr_s >= 0
    elastic = dgamma <= 0
    projected = eps - dgamma * hat / hat_norm
    eps_new = jnp.where(to_apex, (1.0 / d) * apex, jnp.where(elastic, eps, projected))
    F_new = la.matmul(la.matmul(U, la.diag(*[jnp.exp(eps_new[i]) for i in range(d)])),
                      la.transpose(V))
    return hencky_stress(U, eps_new, lam, mu), F_new


@jax.jit
def fluid(F, C, bulk_modulus, viscosity, gamma):
    """Weakly compressible fluid: tau = J(-p I + viscosity (C + C^T)), Tait pressure.

    F is reset to J^(1/d) I so no shear memory accumulates.
    """
    d = F.shape[0]
    J = jnp.maximum(la.det(F), 1e-3)
    p = bulk_modulus / gamma * (J ** (-gamma) - 1.0)
    tau = la.diag(*([-p * J] * d)) + viscosity * J * (C + la.transpose(C))
    r = jnp.sqrt(J) if d == 2 else jnp.cbrt(J)
    return tau, la.diag(*([r] * d))
