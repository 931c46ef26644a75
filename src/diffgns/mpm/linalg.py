"""Batched 2x2 linear algebra with gradients that stay finite.

Matrices are stored component-major, shape (2, 2, N): ``A[i, j]`` is an (N,) array.
This layout keeps every operation a fused elementwise kernel on CPU.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def tiny(dtype) -> float:
    """A squared-length floor that is representable and harmless in ``dtype``."""
    return 1e-30 if jnp.finfo(dtype).bits <= 32 else 1e-60


def safe_norm(x: jax.Array, axis: int = 0) -> jax.Array:
    """sqrt(sum x^2 + tiny): equal to the norm away from 0, finite gradient (0) at 0."""
    return jnp.sqrt(jnp.sum(x * x, axis=axis) + tiny(x.dtype))


def safe_div(num: jax.Array, den: jax.Array, fallback: float = 0.0) -> jax.Array:
    """num/den where den != 0, else ``fallback``; the gradient is finite everywhere
    (double-where pattern)."""
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1), fallback)


def matmul(A: jax.Array, B: jax.Array) -> jax.Array:
    """(2,2,N) @ (2,2,N) -> (2,2,N)."""
    return jnp.stack([
        jnp.stack([A[0, 0] * B[0, 0] + A[0, 1] * B[1, 0], A[0, 0] * B[0, 1] + A[0, 1] * B[1, 1]]),
        jnp.stack([A[1, 0] * B[0, 0] + A[1, 1] * B[1, 0], A[1, 0] * B[0, 1] + A[1, 1] * B[1, 1]]),
    ])


def transpose(A: jax.Array) -> jax.Array:
    return jnp.stack([jnp.stack([A[0, 0], A[1, 0]]), jnp.stack([A[0, 1], A[1, 1]])])


def det(A: jax.Array) -> jax.Array:
    return A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]


def rotation(c: jax.Array, s: jax.Array) -> jax.Array:
    """Rotation matrices [[c, -s], [s, c]] from cosines and sines (N,)."""
    return jnp.stack([jnp.stack([c, -s]), jnp.stack([s, c])])


def diag(d0: jax.Array, d1: jax.Array) -> jax.Array:
    z = jnp.zeros_like(d0)
    return jnp.stack([jnp.stack([d0, z]), jnp.stack([z, d1])])


def eye(n: int, dtype) -> jax.Array:
    o, z = jnp.ones(n, dtype), jnp.zeros(n, dtype)
    return jnp.stack([jnp.stack([o, z]), jnp.stack([z, o])])


def polar_rotation(F: jax.Array) -> jax.Array:
    """Rotation R of the polar decomposition F = R S (closed form for det F > 0).

    R is the rotation by atan2(F10 - F01, F00 + F11), computed from the vector (x, y) =
    (F00 + F11, F10 - F01) normalised by r = sqrt(x^2 + y^2 + tiny) > 0, so the value and
    the gradient are finite everywhere. For det F > 0, x^2 + y^2 = |F|^2 + 2 det F > 0, so
    ``tiny`` only guards the gradient; (x, y) = 0 needs det F <= 0 (outside the domain),
    where R is the zero matrix.
    """
    x = F[0, 0] + F[1, 1]
    y = F[1, 0] - F[0, 1]
    r = jnp.sqrt(x * x + y * y + tiny(F.dtype))
    return rotation(x / r, y / r)


def _svd_fwd_closed(F: jax.Array):
    a, b, c, d = F[0, 0], F[0, 1], F[1, 0], F[1, 1]
    E, Fm = (a + d) / 2, (a - d) / 2
    G, H = (c + b) / 2, (c - b) / 2
    Q = jnp.sqrt(E * E + H * H)
    R = jnp.sqrt(Fm * Fm + G * G)
    s = jnp.stack([Q + R, Q - R])
    a1 = jnp.arctan2(G, Fm)
    a2 = jnp.arctan2(H, E)
    theta = (a2 - a1) / 2
    phi = (a2 + a1) / 2
    U = rotation(jnp.cos(phi), jnp.sin(phi))
    V = rotation(jnp.cos(theta), -jnp.sin(theta))  # F = Rot(phi) diag(s) Rot(theta)
    return U, s, V


@jax.custom_jvp
def svd(F: jax.Array):
    """2x2 SVD F = U diag(s) V^T of (2,2,N) matrices, closed form.

    U and V are rotations; s[0] >= |s[1]| and s[1] < 0 when det F < 0.
    The JVP uses the analytic SVD derivative with the near-degenerate denominators
    s_j^2 - s_i^2 clamped, so gradients are finite at repeated singular values
    (e.g. F = I, every particle's first step).
    """
    return _svd_fwd_closed(F)


@svd.defjvp
def _svd_jvp(primals, tangents):
    (F,), (dF,) = primals, tangents
    U, s, V = _svd_fwd_closed(F)
    dP = matmul(matmul(transpose(U), dF), V)
    ds = jnp.stack([dP[0, 0], dP[1, 1]])
    s0, s1 = s[0], s[1]
    den = s1 * s1 - s0 * s0  # for (i, j) = (0, 1)
    eps = 1e-6 if jnp.finfo(F.dtype).bits <= 32 else 1e-12
    den = jnp.where(jnp.abs(den) < eps, jnp.where(den < 0, -eps, eps), den)
    wu = (s1 * dP[0, 1] + s0 * dP[1, 0]) / den
    wv = (s0 * dP[0, 1] + s1 * dP[1, 0]) / den
    z = jnp.zeros_like(wu)
    Wu = jnp.stack([jnp.stack([z, wu]), jnp.stack([-wu, z])])
    Wv = jnp.stack([jnp.stack([z, wv]), jnp.stack([-wv, z])])
    return (U, s, V), (matmul(U, Wu), ds, matmul(V, Wv))
