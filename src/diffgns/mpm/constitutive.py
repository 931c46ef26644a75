"""Constitutive laws: Kirchhoff stress and plastic projection, per material effect.

Each law maps the elastic deformation gradient F (2, 2, N) and per-particle
parameters (N,) to (tau, F'), where tau (2, 2, N) is the Kirchhoff stress in Pa and
F' the (possibly projected) deformation gradient. Every law is wrapped in its own
``jax.jit`` so it appears as a named call in the jaxpr: tests check that a scene
traces exactly the laws it declares.
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
    e00, e11 = F[0, 0] - 1.0, F[1, 1] - 1.0
    e01 = 0.5 * (F[0, 1] + F[1, 0])
    tr = e00 + e11
    tau = jnp.stack([
        jnp.stack([lam * tr + 2 * mu * e00, 2 * mu * e01]),
        jnp.stack([2 * mu * e01, lam * tr + 2 * mu * e11]),
    ])
    return tau, F


@jax.jit
def elastic_corotated(F, E, nu):
    """Fixed-corotated elasticity: tau = 2 mu (F - R) F^T + lambda (J - 1) J I."""
    lam, mu = lame(E, nu)
    R = la.polar_rotation(F)
    J = la.det(F)
    tau = 2.0 * mu * la.matmul(F - R, la.transpose(F))
    p = lam * (J - 1.0) * J
    tau = tau + la.diag(p, p)
    return tau, F


def hencky_stress(U, eps, lam, mu):
    """Kirchhoff stress of Hencky elasticity: U diag(2 mu eps + lam tr eps) U^T."""
    tr = eps[0] + eps[1]
    d = la.diag(2 * mu * eps[0] + lam * tr, 2 * mu * eps[1] + lam * tr)
    return la.matmul(la.matmul(U, d), la.transpose(U))


@jax.jit
def drucker_prager(F, E, nu, friction_angle, cohesion):
    """Drucker–Prager return map on Hencky strain (Klar et al. 2016), 2D.

    The cone is alpha = sin(phi)/sqrt(2): in 2D this is exactly Mohr–Coulomb for the
    in-plane principal stresses. Cohesion c shifts the apex into tension by the
    volumetric strain 2 c cot(phi) / (2 lambda + 2 mu).

    Args:
        F: (2, 2, N) trial elastic deformation gradient.
        E, nu, friction_angle (degrees), cohesion (Pa): (N,) parameters.
    Returns:
        tau (2, 2, N) Pa, projected F (2, 2, N).
    """
    lam, mu = lame(E, nu)
    U, s, V = la.svd(F)
    s = jnp.maximum(s, 1e-4)
    eps = jnp.log(s)
    phi = jnp.deg2rad(friction_angle)
    alpha = jnp.sin(phi) / jnp.sqrt(2.0)
    k = 2.0 * lam + 2.0 * mu  # d lambda + 2 mu with d = 2
    apex = 2.0 * cohesion * jnp.cos(phi) / (jnp.sin(phi) * k)  # tensile trace at the apex
    tr = eps[0] + eps[1]
    tr_s = tr - apex
    hat = eps - 0.5 * tr
    hat_norm = la.safe_norm(hat)
    dgamma = hat_norm + k / (2.0 * mu) * tr_s * alpha
    to_apex = tr_s >= 0
    elastic = dgamma <= 0
    projected = eps - dgamma * hat / hat_norm
    eps_new = jnp.where(to_apex, 0.5 * apex, jnp.where(elastic, eps, projected))
    F_new = la.matmul(la.matmul(U, la.diag(jnp.exp(eps_new[0]), jnp.exp(eps_new[1]))),
                      la.transpose(V))
    return hencky_stress(U, eps_new, lam, mu), F_new


@jax.jit
def fluid(F, C, bulk_modulus, viscosity, gamma):
    """Weakly compressible fluid: tau = J(-p I + viscosity (C + C^T)), Tait pressure.

    F is reset to sqrt(J) I so no shear memory accumulates.
    """
    J = jnp.maximum(la.det(F), 1e-3)
    p = bulk_modulus / gamma * (J ** (-gamma) - 1.0)
    tau = la.diag(-p * J, -p * J) + viscosity * J * (C + la.transpose(C))
    r = jnp.sqrt(J)
    return tau, la.diag(r, r)
