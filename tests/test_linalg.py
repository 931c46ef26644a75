"""2x2 SVD and polar decomposition: exact forward, correct and finite derivatives."""
import jax
import jax.numpy as jnp
import numpy as np
from jax.test_util import check_grads

from diffgns.mpm import linalg as la


def _random_F(n=7, seed=0, scale=0.3):
    rng = np.random.default_rng(seed)
    return jnp.asarray(np.eye(2)[:, :, None] + scale * rng.normal(size=(2, 2, n)))


def test_svd_reconstructs_and_orders(x64):
    F = _random_F()
    U, s, V = la.svd(F)
    rec = la.matmul(la.matmul(U, la.diag(s[0], s[1])), la.transpose(V))
    np.testing.assert_allclose(np.asarray(rec), np.asarray(F), atol=1e-13)
    np.testing.assert_allclose(np.asarray(la.det(U)), 1.0, atol=1e-13)
    np.testing.assert_allclose(np.asarray(la.det(V)), 1.0, atol=1e-13)
    assert np.all(np.asarray(s[0]) >= np.abs(np.asarray(s[1])))
    np.testing.assert_allclose(np.sort(np.asarray(s), 0)[::-1],
                               np.sort(np.linalg.svd(np.moveaxis(np.asarray(F), -1, 0),
                                                     compute_uv=False).T, 0)[::-1], atol=1e-12)


def test_svd_jvp_matches_finite_differences(x64):
    F = _random_F(seed=1)
    check_grads(la.svd, (F,), order=1, modes=("fwd", "rev"), atol=1e-5, rtol=1e-5, eps=1e-6)


def test_svd_gradient_finite_at_identity_and_repeated_values(x64):
    def loss(F):  # an isotropic function that uses U and V
        U, s, V = la.svd(F)
        return jnp.sum(la.matmul(la.matmul(U, la.diag(jnp.log(s[0]), jnp.log(s[1]))),
                                 la.transpose(V)) ** 2)

    for F in [la.eye(3, jnp.float64), 1.2 * la.eye(3, jnp.float64)]:
        g = jax.grad(loss)(F)
        assert np.isfinite(np.asarray(g)).all()
    # at F = 1.2 I: d/dF sum(log(F)^2) = 2 log(1.2)/1.2 I
    g = np.asarray(jax.grad(loss)(1.2 * la.eye(1, jnp.float64)))[:, :, 0]
    np.testing.assert_allclose(g, 2 * np.log(1.2) / 1.2 * np.eye(2), atol=1e-6)


def test_polar_rotation(x64):
    F = _random_F(seed=2, scale=0.2)
    R = la.polar_rotation(F)
    S = la.matmul(la.transpose(R), F)
    np.testing.assert_allclose(np.asarray(S[0, 1]), np.asarray(S[1, 0]), atol=1e-13)
    assert np.isfinite(np.asarray(jax.grad(lambda F: la.polar_rotation(F).sum())(
        la.eye(2, jnp.float64)))).all()


def test_polar_rotation_is_a_rotation_and_finite_where_undefined():
    """float32: R^T R = I, det R = 1 for det F > 0; at F = 0 and at a reflection
    (x = F00 + F11 = 0, y = F10 - F01 = 0, det F < 0) value and gradient stay finite."""
    F = _random_F(n=200, seed=3, scale=0.6).astype(jnp.float32)
    F = F[:, :, np.asarray(la.det(F)) > 0]  # large rotations and stretches, det F > 0
    n = F.shape[-1]
    assert n > 100
    R = la.polar_rotation(F)
    np.testing.assert_allclose(np.asarray(la.det(R)), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(la.matmul(la.transpose(R), R)),
                               np.asarray(la.eye(n, jnp.float32)), atol=1e-6)
    S = la.matmul(la.transpose(R), F)
    assert (np.asarray(S[0, 0] + S[1, 1]) > 0).all()  # the symmetric factor is positive
    odd = jnp.stack([jnp.zeros((2, 2)), jnp.asarray([[1.0, 0.0], [0.0, -1.0]])], -1)
    R = la.polar_rotation(odd)
    assert np.isfinite(np.asarray(R)).all()
    np.testing.assert_array_equal(np.asarray(R), 0.0)
    g = jax.grad(lambda F: la.polar_rotation(F).sum())(odd)
    assert np.isfinite(np.asarray(g)).all()


def test_safe_norm_and_div_gradients_at_zero(x64):
    g = jax.grad(lambda x: la.safe_norm(x).sum())(jnp.zeros((2, 3)))
    assert np.isfinite(np.asarray(g)).all()
    g = jax.grad(lambda d: la.safe_div(1.0, d))(0.0)
    assert np.isfinite(g)


def test_sum0_weighted_first_axis_sum_matches_numpy(x64):
    """sum0 sums over the first axis with constant weights (zeros skipped), as jnp would."""
    a = jnp.asarray(np.random.default_rng(0).normal(size=(27, 5)))
    np.testing.assert_allclose(np.asarray(la.sum0(a)), np.asarray(a).sum(0), rtol=1e-13)
    coef = np.random.default_rng(1).integers(0, 3, 27)
    np.testing.assert_allclose(np.asarray(la.sum0(a, coef)), coef @ np.asarray(a),
                               rtol=1e-12, atol=1e-14)
