"""Batched small-matrix linear algebra (2x2 and 3x3) with gradients that stay finite.

Matrices are stored component-major, shape (d, d, N) with d = 2 or 3: ``A[i, j]`` is an (N,)
array. This layout keeps every operation a fused elementwise kernel on CPU. The 2D
expressions are written so that a 2D scene computes exactly (bitwise) what the 2D-only code
computed; 3D adds the 3x3 determinant and a 3x3 SVD (:func:`svd3`, Jacobi rotations, no
LAPACK call) whose derivative stays finite at repeated singular values.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def tiny(dtype) -> float:
    """A squared-length floor that is representable and harmless in ``dtype``."""
    return 1e-30 if jnp.finfo(dtype).bits <= 32 else 1e-60


def gap(dtype) -> float:
    """Floor of |s_i^2 - s_j^2| in the SVD derivative (clamped near repeated values)."""
    return 1e-6 if jnp.finfo(dtype).bits <= 32 else 1e-12


def safe_norm(x: jax.Array) -> jax.Array:
    """sqrt(sum x^2 + tiny) over the first axis ((d, ...) -> (...)): equal to the norm away
    from 0, finite gradient (0) at 0."""
    return jnp.sqrt(sum0(x * x) + tiny(x.dtype))


def sum0(a: jax.Array, coef=None) -> jax.Array:
    """``sum_i coef_i a_i`` over the first (short) axis, (K, ...) -> (...): ``coef`` K
    constants (default all 1; zero terms skipped), as left-to-right elementwise adds that XLA
    fuses into one pass. (``jnp.sum(a, 0)`` became a library reduction on the CPU that read
    the array across its rows: over the 27-node stencil it took 90% of a 3D sand substep at
    43k particles.)"""
    coef = [1] * a.shape[0] if coef is None else coef
    return _sum([a[i] if c == 1 else c * a[i] for i, c in enumerate(coef) if c != 0])


def safe_div(num: jax.Array, den: jax.Array, fallback: float = 0.0) -> jax.Array:
    """num/den where den != 0, else ``fallback``; the gradient is finite everywhere
    (double-where pattern)."""
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1), fallback)


def _sum(terms):
    """Left-to-right sum of a sequence of arrays (the summation order of the 2D code)."""
    out = terms[0]
    for t in terms[1:]:
        out = out + t
    return out


def matmul(A: jax.Array, B: jax.Array) -> jax.Array:
    """(d,d,N) @ (d,d,N) -> (d,d,N)."""
    d = A.shape[0]
    return jnp.stack([jnp.stack([_sum([A[i, k] * B[k, j] for k in range(d)])
                                 for j in range(d)]) for i in range(d)])


def transpose(A: jax.Array) -> jax.Array:
    """(d,d,N) -> (d,d,N) transposed."""
    d = A.shape[0]
    return jnp.stack([jnp.stack([A[j, i] for j in range(d)]) for i in range(d)])


def trace(A: jax.Array) -> jax.Array:
    """(N,) trace of (d,d,N)."""
    return _sum([A[i, i] for i in range(A.shape[0])])


def det(A: jax.Array) -> jax.Array:
    """(N,) determinant of (d,d,N), d = 2 or 3."""
    if A.shape[0] == 2:
        return A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    return (A[0, 0] * (A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1])
            - A[0, 1] * (A[1, 0] * A[2, 2] - A[1, 2] * A[2, 0])
            + A[0, 2] * (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]))


def rotation(c: jax.Array, s: jax.Array) -> jax.Array:
    """2D rotation matrices [[c, -s], [s, c]] from cosines and sines (N,)."""
    return jnp.stack([jnp.stack([c, -s]), jnp.stack([s, c])])


def diag(*ds: jax.Array) -> jax.Array:
    """(d,d,N) diagonal matrices from d diagonals (N,)."""
    z = jnp.zeros_like(ds[0])
    n = len(ds)
    return jnp.stack([jnp.stack([ds[i] if i == j else z for j in range(n)]) for i in range(n)])


def eye(n: int, dtype, d: int = 2) -> jax.Array:
    """(d,d,n) identity matrices."""
    return diag(*([jnp.ones(n, dtype)] * d))


def polar_rotation(F: jax.Array) -> jax.Array:
    """Rotation R of the polar decomposition F = R S, (d,d,N).

    2D: closed form (for det F > 0). R is the rotation by atan2(F10 - F01, F00 + F11),
    computed from the vector (x, y) = (F00 + F11, F10 - F01) normalised by
    r = sqrt(x^2 + y^2 + tiny) > 0, so the value and the gradient are finite everywhere. For
    det F > 0, x^2 + y^2 = |F|^2 + 2 det F > 0, so ``tiny`` only guards the gradient;
    (x, y) = 0 needs det F <= 0 (outside the domain), where R is the zero matrix.
    3D: R = U V^T from :func:`svd3` (rotations U, V), finite derivative everywhere.
    """
    if F.shape[0] == 3:
        U, _, V = svd3(F)
        return matmul(U, transpose(V))
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
def svd2(F: jax.Array):
    """2x2 SVD F = U diag(s) V^T of (2,2,N) matrices, closed form.

    U and V are rotations; s[0] >= |s[1]| and s[1] < 0 when det F < 0.
    The JVP uses the analytic SVD derivative with the near-degenerate denominators
    s_j^2 - s_i^2 clamped, so gradients are finite at repeated singular values
    (e.g. F = I, every particle's first step).
    """
    return _svd_fwd_closed(F)


@svd2.defjvp
def _svd2_jvp(primals, tangents):
    (F,), (dF,) = primals, tangents
    U, s, V = _svd_fwd_closed(F)
    dP = matmul(matmul(transpose(U), dF), V)
    ds = jnp.stack([dP[0, 0], dP[1, 1]])
    s0, s1 = s[0], s[1]
    den = s1 * s1 - s0 * s0  # for (i, j) = (0, 1)
    eps = gap(F.dtype)
    den = jnp.where(jnp.abs(den) < eps, jnp.where(den < 0, -eps, eps), den)
    wu = (s1 * dP[0, 1] + s0 * dP[1, 0]) / den
    wv = (s0 * dP[0, 1] + s1 * dP[1, 0]) / den
    z = jnp.zeros_like(wu)
    Wu = jnp.stack([jnp.stack([z, wu]), jnp.stack([-wu, z])])
    Wv = jnp.stack([jnp.stack([z, wv]), jnp.stack([-wv, z])])
    return (U, s, V), (matmul(U, Wu), ds, matmul(V, Wv))


#: cyclic Jacobi sweeps of :func:`_svd3_fwd` per dtype: each sweep squares the off-diagonal
#: norm once the rotations settle; 4 sweeps reach float32 round-off and 6 float64 round-off
#: on random and near-degenerate F (tests/test_mpm3d.py)
JACOBI_SWEEPS = {32: 4, 64: 6}


def _jacobi_rotation(S, V, p: int, q: int):
    """One Jacobi rotation J in the (p, q) plane zeroing S[p, q] of the symmetric (3,3,N)
    ``S``: returns (J^T S J, V J). The angle is the smaller root, t = tan = sign(h) 2 S_pq /
    (|h| + sqrt(h^2 + 4 S_pq^2)) with h = S_qq - S_pp; t = 0 where S_pq = 0 (the
    double-where keeps the value and derivative finite)."""
    apq = S[p, q]
    h = S[q, q] - S[p, p]
    den = jnp.abs(h) + jnp.sqrt(h * h + 4.0 * apq * apq)
    sgn = jnp.where(h < 0, -1.0, 1.0).astype(S.dtype)
    t = safe_div(sgn * 2.0 * apq, den)
    c = 1.0 / jnp.sqrt(1.0 + t * t)
    sn = t * c
    rows = [[S[i, j] for j in range(3)] for i in range(3)]
    r = 3 - p - q  # the third index
    # S' = J^T S J with J = identity except J_pp = J_qq = c, J_pq = sn, J_qp = -sn
    spp = rows[p][p] - t * apq
    sqq = rows[q][q] + t * apq
    srp = c * rows[r][p] - sn * rows[r][q]
    srq = sn * rows[r][p] + c * rows[r][q]
    z = jnp.zeros_like(apq)
    out: list[list[jax.Array]] = [[z] * 3 for _ in range(3)]
    out[p][p], out[q][q], out[r][r] = spp, sqq, rows[r][r]
    out[p][q] = out[q][p] = z
    out[r][p] = out[p][r] = srp
    out[r][q] = out[q][r] = srq
    Vn = [[V[i, j] for j in range(3)] for i in range(3)]
    for i in range(3):
        vp, vq = Vn[i][p], Vn[i][q]
        Vn[i][p], Vn[i][q] = c * vp - sn * vq, sn * vp + c * vq
    stack = lambda m: jnp.stack([jnp.stack(row) for row in m])  # noqa: E731
    return stack(out), stack(Vn)


def _swap(cond, a, b):
    """Elementwise (b, a) where ``cond`` else (a, b)."""
    return jnp.where(cond, b, a), jnp.where(cond, a, b)


def _svd3_fwd(F: jax.Array):
    """Rotation-preserving 3x3 SVD of (3,3,N), elementwise (no LAPACK call): U, V proper
    rotations (det +1), s (3,N) descending in magnitude with s[2] < 0 when det F < 0.

    V diagonalises F^T F by cyclic Jacobi rotations (:data:`JACOBI_SWEEPS`), its columns
    sorted by eigenvalue and the last one flipped if det V < 0; the columns b_i = F v_i
    are orthogonal with |b_i| = |s_i|; U by Gram-Schmidt on b_1, b_2 and u_3 = u_1 x u_2,
    s = (|b_1|, |b_2 - (u_1.b_2) u_1|, u_3.b_3). A zero b_1 or b_2 (rank-deficient F,
    outside the deformation gradients' domain) takes a fallback direction, never NaN. The
    same construction as the MPM literature's minimal-branching SVD (McAdams et al. 2011),
    with exact rotation angles; it fuses into elementwise kernels, and unlike LAPACK's
    batched SVD it runs on two host devices sharing one thread pool.
    """
    S = matmul(transpose(F), F)
    V = eye(F.shape[-1], F.dtype, 3)
    for _ in range(JACOBI_SWEEPS[32 if jnp.finfo(F.dtype).bits <= 32 else 64]):
        for p, q in ((0, 1), (0, 2), (1, 2)):
            S, V = _jacobi_rotation(S, V, p, q)
    lam = [S[0, 0], S[1, 1], S[2, 2]]
    cols = [V[:, 0], V[:, 1], V[:, 2]]
    for i, j in ((0, 1), (1, 2), (0, 1)):  # sorting network, descending eigenvalues
        sw = lam[i] < lam[j]
        lam[i], lam[j] = _swap(sw, lam[i], lam[j])
        cols[i], cols[j] = _swap(sw, cols[i], cols[j])
    V = jnp.stack(cols, axis=1)  # (3, 3, N), columns v_i
    flip = jnp.where(det(V) < 0, -1.0, 1.0).astype(F.dtype)
    V = V.at[:, 2].multiply(flip)
    B = matmul(F, V)
    b1, b2, b3 = B[:, 0], B[:, 1], B[:, 2]
    e = [jnp.zeros_like(b1[0]), jnp.ones_like(b1[0])]
    s1 = safe_norm(b1)
    u1 = jnp.where(s1 > jnp.sqrt(tiny(F.dtype)) * 10, b1 / s1,
                   jnp.stack([e[1], e[0], e[0]]))
    w = b2 - sum0(u1 * b2) * u1
    s2 = safe_norm(w)
    # fallback for a rank-one F: the coordinate axis least aligned with u1, orthogonalised
    ax = jnp.argmin(jnp.abs(u1), axis=0)
    a = jnp.stack([(ax == k).astype(F.dtype) for k in range(3)])
    a = a - sum0(u1 * a) * u1
    u2 = jnp.where(s2 > jnp.sqrt(tiny(F.dtype)) * 10, w / s2, a / safe_norm(a))
    u3 = jnp.stack([u1[1] * u2[2] - u1[2] * u2[1], u1[2] * u2[0] - u1[0] * u2[2],
                    u1[0] * u2[1] - u1[1] * u2[0]])
    s3 = sum0(u3 * b3)
    U = jnp.stack([u1, u2, u3], axis=1)
    return U, jnp.stack([s1, s2, s3]), V


@jax.custom_jvp
def svd3(F: jax.Array):
    """3x3 SVD F = U diag(s) V^T of (3,3,N) matrices; U, V rotations.

    The JVP is the analytic one, dP = U^T dF V, ds_i = dP_ii and dU = U W_U, dV = V W_V with
    W_U[i,j] = (s_j dP_ij + s_i dP_ji)/(s_j^2 - s_i^2), W_V[i,j] = (s_i dP_ij + s_j dP_ji)/
    (s_j^2 - s_i^2), the denominators clamped to +-:func:`gap` so that it stays finite at
    repeated singular values (F = I, uniaxial F = diag(a, 1, 1)). Where the loss is an
    isotropic function of F (Hencky stress, F - R), the clamped terms multiply
    differences of equal principal values and the derivative is exact.
    """
    return _svd3_fwd(F)


@svd3.defjvp
def _svd3_jvp(primals, tangents):
    (F,), (dF,) = primals, tangents
    U, s, V = _svd3_fwd(F)
    dP = matmul(matmul(transpose(U), dF), V)
    eps = gap(F.dtype)
    z = jnp.zeros_like(s[0])
    Wu = [[z] * 3 for _ in range(3)]
    Wv = [[z] * 3 for _ in range(3)]
    for i in range(3):
        for j in range(i + 1, 3):
            den = s[j] * s[j] - s[i] * s[i]
            den = jnp.where(jnp.abs(den) < eps, jnp.where(den < 0, -eps, eps), den)
            wu = (s[j] * dP[i, j] + s[i] * dP[j, i]) / den
            wv = (s[i] * dP[i, j] + s[j] * dP[j, i]) / den
            Wu[i][j], Wu[j][i] = wu, -wu
            Wv[i][j], Wv[j][i] = wv, -wv
    Wu_a = jnp.stack([jnp.stack(r) for r in Wu])
    Wv_a = jnp.stack([jnp.stack(r) for r in Wv])
    ds = jnp.stack([dP[0, 0], dP[1, 1], dP[2, 2]])
    return (U, s, V), (matmul(U, Wu_a), ds, matmul(V, Wv_a))


def svd(F: jax.Array):
    """SVD F = U diag(s) V^T of (d,d,N) matrices, d = 2 (:func:`svd2`) or 3 (:func:`svd3`):
    rotations U, V and signed singular values s (d, N), finite derivatives everywhere."""
    return svd2(F) if F.shape[0] == 2 else svd3(F)
