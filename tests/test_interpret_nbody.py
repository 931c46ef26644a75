"""n-body simulator and its datasets: conservation, the exact pair laws, round trips."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns.interpret import nbody_data
from diffgns.interpret.nbody import (
    NBodyConfig,
    accelerations,
    energy,
    initial_state,
    pair_forces,
    rollout,
)


@pytest.fixture(autouse=True)
def _double(x64):
    yield


def _bodies(x, m, r):
    x, m, r = (jnp.asarray(a, jnp.float64) for a in (x, m, r))
    return x, jnp.zeros_like(x), m, r


def test_spring_force_is_linear_contact_law_and_antisymmetric():
    cfg = NBodyConfig(n_bodies=3)
    x, v, m, r = _bodies([[1.0, 1.0], [1.7, 1.0], [3.0, 3.0]], [1.0, 2.0, 1.0], [0.4, 0.5, 0.3])
    F = np.asarray(pair_forces(cfg, x, v, m, r))
    # overlap 0.2 m -> |F| = k * 0.2 = 20 N, pushing body 0 in -x
    np.testing.assert_allclose(F[0, 1], [-20.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(F[1, 0], -F[0, 1], atol=1e-12)
    assert np.all(F[2] == 0) and np.all(F[:, 2] == 0)  # not in contact
    np.testing.assert_allclose(np.asarray(accelerations(cfg, x, v, m, r))[1], [10.0, 0.0])


def test_spring_contact_across_periodic_boundary():
    cfg = NBodyConfig(n_bodies=2, box=4.0)
    x, v, m, r = _bodies([[0.1, 2.0], [3.8, 2.0]], [1.0, 1.0], [0.3, 0.3])
    F = np.asarray(pair_forces(cfg, x, v, m, r))
    # minimum-image distance 0.3 m, overlap 0.3 m: body 0 pushed in +x
    np.testing.assert_allclose(F[0, 1], [30.0, 0.0], atol=1e-9)


def test_damping_opposes_approach():
    cfg = NBodyConfig(n_bodies=2, gamma=2.0)
    x = jnp.array([[1.0, 1.0], [1.5, 1.0]])
    v = jnp.array([[1.0, 0.0], [-1.0, 0.0]])  # approaching at 2 m/s
    F = np.asarray(pair_forces(cfg, x, v, jnp.ones(2), jnp.array([0.3, 0.3])))
    np.testing.assert_allclose(F[0, 1], [-(100 * 0.1 + 2.0 * 2.0), 0.0], atol=1e-9)


def test_inverse_square_magnitude_and_sign():
    for G in (2.0, -1.5):
        cfg = NBodyConfig(law="inverse_square", n_bodies=2, G=G)
        x, v, m, r = _bodies([[0.0, 0.0], [0.0, 2.0]], [1.5, 2.0], [0.1, 0.1])
        F = np.asarray(pair_forces(cfg, x, v, m, r))
        np.testing.assert_allclose(F[0, 1], [0.0, G * 1.5 * 2.0 / 4.0], atol=1e-12)


def test_periodic_inverse_square_uses_minimum_image_and_cutoff():
    cfg = NBodyConfig(law="inverse_square", n_bodies=3, G=-1.0, box=4.0, periodic=True)
    x, v, m, r = _bodies([[0.2, 1.0], [3.7, 1.0], [0.2, 3.1]], [1.0, 2.0, 1.0], [0.1] * 3)
    F = np.asarray(pair_forces(cfg, x, v, m, r))
    # 0-1: image distance 0.5 across x = 0, repelling body 0 towards +x: |F| = 2 / 0.25
    np.testing.assert_allclose(F[0, 1], [8.0, 0.0], atol=1e-9)
    # 0-2: image distance 1.9 < box/2 across y = 0, body 0 pushed towards +y
    np.testing.assert_allclose(F[0, 2], [0.0, 1.0 / 1.9**2], atol=1e-9)
    x = x.at[2].set(jnp.array([2.25, 3.0]))  # image distance sqrt(1.95^2 + 2^2) >= box/2
    F = np.asarray(pair_forces(cfg, x, v, m, r))
    assert np.all(F[0, 2] == 0) and np.all(F[2, 0] == 0)


@pytest.mark.parametrize("law", ["spring", "inverse_square"])
def test_rollout_conserves_energy_and_momentum(law):
    cfg = NBodyConfig(law=law, G=-1.0, speed=1.0 if law == "spring" else 0.3)
    x0, v0, m, r = initial_state(cfg, np.random.default_rng(3))
    xs, vs = rollout(cfg, x0, v0, m, r, 300)
    e = np.array([energy(cfg, xs[i], vs[i], m, r) for i in range(0, 300, 30)])
    p = np.einsum("n,tnd->td", m, np.asarray(vs))
    assert np.all(np.isfinite(np.asarray(xs)))
    assert np.ptp(e) / abs(e[0]) < 1e-4
    np.testing.assert_allclose(p, 0.0, atol=1e-10)  # initial momentum removed
    if law == "spring":  # contacts happened, so the test exercised the springs
        F = jax.vmap(lambda a, b: pair_forces(cfg, a, b, m, r))(xs, vs)
        assert np.count_nonzero(np.linalg.norm(np.asarray(F), axis=-1)) > 100


def test_invalid_configs_are_rejected():
    with pytest.raises(ValueError, match="law"):
        NBodyConfig(law="coulomb")
    with pytest.raises(ValueError, match="radius_range"):
        NBodyConfig(radius_range=(0.5, 2.0))
    with pytest.raises(ValueError, match="substeps"):
        NBodyConfig(k=1e5).check_stable()


def test_dataset_round_trip_resume_and_edges(tmp_path):
    cfg = NBodyConfig()
    path = tmp_path / "s.h5"
    nbody_data.generate(path, cfg, 2, 40, progress=False)
    nbody_data.generate(path, cfg, 3, 40, progress=False)  # resumes: one more trajectory
    cfg2, trajs = nbody_data.load(path)
    assert cfg2 == cfg and len(trajs) == 3
    x0, v0, m, r = initial_state(cfg, np.random.default_rng([0, 2, 0]))
    xs, _ = rollout(cfg, x0, v0, m, r, 40)
    np.testing.assert_allclose(trajs[2]["position"], np.asarray(xs), atol=1e-5)
    s = nbody_data.edge_samples(cfg2, trajs)
    assert s["edges"].shape == (120, 90, 9) and s["acc"].shape == (120, 10, 2)
    # accelerations are the summed pair forces over the receiver's mass
    acc = np.zeros_like(s["acc"])
    np.add.at(acc, (slice(None), s["receivers"]),
              s["force"] / s["node"][:, s["receivers"], :1])
    np.testing.assert_allclose(acc, s["acc"], atol=1e-6)
    d = s["edges"][..., 2]
    np.testing.assert_allclose(d, np.linalg.norm(s["edges"][..., :2], axis=-1), rtol=1e-6)
