"""The MPM sharded over two host devices (diffgns.hostdevices) against the one-device MPM,
and the shuffled particle order of a frame against the scene's order.

The sharded frame splits every material group over the devices (padding with massless
copies), sums the grids with a psum and unpermutes: it must give the one-device frame up to
the grid's summation order, its gradients, its clamp counts (padding never counted), under
jit, grad and vmap; the device choice rejects what cannot work with a message. A frame
that runs its particles shuffled within blocks (``particle_order``, the CPU default in 2D)
must give the frame of the scene's order up to the same round-off.
"""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns import MPM, Body, Elastic, Fluid, Rectangle, Sand, Scene, Walls, hostdevices
from diffgns.errors import InputError
from diffgns.interface import rollout_jit
from diffgns.mpm import solver
from diffgns.mpm.solver import block_permutation
from diffgns.scene.recipes import column_scene


def two_devices():
    assert len(jax.local_devices()) >= 2, (
        "tests/conftest.py asks for two host devices before JAX starts (DIFFGNS_HOST_DEVICES)")


def mixed_scene(v_right=0.0, flip=0.0) -> Scene:
    """Three groups with odd particle counts (padding on every device): two sand bodies of
    different friction angles (one group, several bodies: per-particle parameters gathered),
    an elastic block and a fluid body."""
    bodies = (
        Body(Rectangle(0.05, 0.0, 0.25, 0.17), Sand(friction_angle=25.0, E=2e5)),
        Body(Rectangle(0.27, 0.0, 0.41, 0.13), Sand(friction_angle=40.0, E=2e5)),
        Body(Rectangle(0.50, 0.0, 0.61, 0.09), Elastic(E=1e5, nu=0.3, rho=1000.0),
             velocity=(v_right, 0.0)),
        Body(Rectangle(0.70, 0.0, 0.83, 0.11), Fluid(bulk_modulus=2e4, viscosity=1e-3)),
    )
    return Scene(domain=((0.0, 0.9), (0.0, 0.4)), dx=0.02, bodies=bodies,
                 walls=Walls.all("friction", mu=0.3), frame_dt=5e-3, flip=flip)


def frames(sim, p, s, n=3):
    return jax.jit(lambda p, s: rollout_jit(sim, p, s, n_frames=n))(p, s)


@pytest.mark.parametrize("flip", [0.0, 0.99])
def test_sharded_frames_equal_one_device_frames_with_padding_and_several_groups(x64, flip):
    """Also with a FLIP update: its extra grid channels are summed over the devices too."""
    two_devices()
    scene = mixed_scene(flip=flip)
    one, two = MPM(scene, devices=1), MPM(scene, devices=2)
    groups = scene.material_groups()
    assert len(groups) == 3 and any((g.stop - g.start) % 2 for g in groups.values())
    assert two.devices is not None and one.devices is None
    p, s = one.params(), one.init()
    (fa, sa), (fb, sb) = frames(one, p, s), frames(two, p, s)
    assert float(jnp.abs(sa.x - s.x).max()) > 1e-3  # the bodies moved
    for a, b in ((fa.positions, fb.positions), (fa.velocities, fb.velocities),
                 (sa.C, sb.C), (sa.F, sb.F)):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(np.asarray(sb.vol), np.asarray(s.vol))  # padding dropped


def test_sharded_clamp_counts_equal_and_padding_never_counted(x64):
    """Particles put 4 mm past the right wall, among them the first particle of every group
    (whose massless copies pad the groups), are clamped back: the sharded count equals the
    one-device count; the padding copies are clamped too but never counted."""
    two_devices()
    scene = mixed_scene()
    one, two = MPM(scene, devices=1), MPM(scene, devices=2)
    p, s = one.params(), one.init()
    firsts = [g.start for g in scene.material_groups().values()]
    out = np.array(sorted(set(firsts) | {5, 17, 40}))
    s = s.replace(x=s.x.at[0, out].set(scene.domain[0][1] + 0.004))
    (fa, _), (fb, _) = frames(one, p, s, 2), frames(two, p, s, 2)
    ca, cb = np.asarray(fa.clamp.moved), np.asarray(fb.clamp.moved)
    assert ca[1] >= len(out)  # every displaced particle clamped in the first substep
    np.testing.assert_array_equal(cb, ca)
    np.testing.assert_allclose(np.asarray(fb.clamp.shift), np.asarray(fa.clamp.shift),
                               atol=1e-9)
    assert float(fa.clamp.shift[1]) == pytest.approx(0.004, abs=1e-6)


@pytest.mark.slow  # the default suite checks a sharded gradient in the shuffled test, devices=2
def test_sharded_gradient_equals_one_device_gradient(x64):
    two_devices()
    scene = column_scene(1.0, cells_across=7)
    one, two = MPM(scene, devices=1), MPM(scene, devices=2)
    s = one.init()

    def runout(sim, phi):
        p = sim.params().replace(friction_angle=jnp.full((1,), phi))
        _, final = rollout_jit(sim, p, s, n_frames=4)
        return jnp.max(final.x[0])

    ga = jax.grad(lambda a: runout(one, a))(30.0)
    gb = jax.grad(lambda a: runout(two, a))(30.0)
    assert np.isfinite(float(ga)) and abs(float(ga)) > 0
    np.testing.assert_allclose(float(gb), float(ga), rtol=1e-7)
    ck = MPM(scene, devices=2, checkpoint_substeps=True)
    np.testing.assert_allclose(float(jax.grad(lambda a: runout(ck, a))(30.0)), float(ga),
                               rtol=1e-7)


def test_sharded_frame_vmaps_over_parameters(x64):
    two_devices()
    scene = column_scene(1.0, cells_across=7)
    one, two = MPM(scene, devices=1), MPM(scene, devices=2)
    s = one.init()
    phis = jnp.asarray([[25.0], [40.0]])

    def final_x(sim):
        def f(phi):
            return rollout_jit(sim, sim.params().replace(friction_angle=phi), s, 3)[1].x
        return jax.jit(jax.vmap(f))(phis)

    np.testing.assert_allclose(np.asarray(final_x(two)), np.asarray(final_x(one)), atol=1e-9)


def test_auto_devices_follow_the_particle_count(monkeypatch):
    two_devices()
    assert MPM(column_scene(1.0, cells_across=7)).devices is None  # 196 particles: one
    monkeypatch.setattr(hostdevices, "AUTO_MIN_PARTICLES", 100)
    sim = MPM(column_scene(1.0, cells_across=7))
    assert sim.devices == jax.local_devices()
    # 3D has its own, higher threshold (a 3D frame needs more particles to pay)
    sand3d = column_scene(1.0, cells_across=4, dim=3)  # 1,664 particles
    assert MPM(sand3d).devices is None
    monkeypatch.setattr(hostdevices, "AUTO_MIN_PARTICLES_3D", 1000)
    assert MPM(sand3d).devices == jax.local_devices()


def test_device_choices_rejected_with_a_message():
    scene = column_scene(1.0, cells_across=5)
    for bad, match in (("fast", "not a device choice"), (0, "not a device count"),
                       (1.5, "not a device count"), (True, "not a device count"),
                       ([], "an empty list")):
        with pytest.raises(InputError, match=match):
            MPM(scene, devices=bad)
    n = len(jax.local_devices())
    with pytest.raises(InputError, match=f"{n + 1} devices asked for, this process has {n}"):
        MPM(scene, devices=n + 1)


def test_host_device_setting_is_validated(monkeypatch):
    monkeypatch.setenv(hostdevices.ENV, "two")
    with pytest.raises(InputError, match="DIFFGNS_HOST_DEVICES: 'two' is not a positive"):
        hostdevices.wanted()
    monkeypatch.setenv(hostdevices.ENV, "3")
    assert hostdevices.wanted() == 3
    monkeypatch.delenv(hostdevices.ENV)
    for cores, want in (({0}, 1), ({0, 1}, 2), ({0, 1, 2, 3}, 2)):  # pinned, 2, 4 cores
        monkeypatch.setattr(hostdevices.os, "sched_getaffinity", lambda _, c=cores: c,
                            raising=False)
        assert hostdevices.wanted() == want
    assert hostdevices.request() is False  # JAX runs already: nothing changes


def test_3d_sand_shards_and_matches_one_device(monkeypatch):
    """3D sand's stress (the Jacobi SVD, no LAPACK call; LAPACK's batched SVD deadlocked
    the sharded frame at 2,352 particles) runs sharded above that size and agrees with one
    device; so do 3D corotated elastic bodies and fluids."""
    two_devices()
    monkeypatch.setattr(hostdevices, "AUTO_MIN_PARTICLES_3D", 100)
    sand = column_scene(1.0, cells_across=6, dim=3)  # 5,376 particles
    assert sand.n_particles > 2352
    from diffgns.scene.shapes import Box

    elastic = sand.replace(bodies=(dataclasses.replace(sand.bodies[0], material=Elastic(E=1e5)),))
    fluid = Scene(domain=((0, 0.2), (0, 0.2), (0, 0.2)), dx=0.02,
                  bodies=(Body(Box(0.03, 0, 0.03, 0.17, 0.12, 0.17), Fluid(bulk_modulus=2e4)),))
    for scene in (sand, elastic, fluid):
        one, auto = MPM(scene, devices=1), MPM(scene)
        assert auto.devices is not None and len(auto.devices) == 2
        p, s = one.params(), one.init()
        np.testing.assert_allclose(np.asarray(frames(auto, p, s, 2)[1].x),
                                   np.asarray(frames(one, p, s, 2)[1].x), atol=2e-6)


def test_eager_frame_of_a_sharded_mpm_runs_on_one_device(x64):
    """Under jax.disable_jit a shard_map runs op by op per device (minutes for a frame); the
    sharded MPM then runs its one-device substeps: the same frame up to round-off."""
    two_devices()
    scene = column_scene(1.0, cells_across=5)
    two = MPM(scene, devices=2)
    p, s = two.params(), two.init()
    jitted = jax.jit(two.step)(p, s)
    with jax.disable_jit():
        eager = two.step(p, s)
    np.testing.assert_allclose(np.asarray(eager.x), np.asarray(jitted.x), rtol=0, atol=1e-12)
    assert "shard_map" in str(jax.make_jaxpr(two.step)(p, s))


def test_block_permutation_shuffles_within_blocks_only():
    perm = block_permutation(2500, 1000, np.random.default_rng(0))
    np.testing.assert_array_equal(np.sort(perm), np.arange(2500))  # a permutation
    for lo in (0, 1000, 2000):  # every block maps onto itself, and is shuffled
        blk = perm[lo:lo + 1000]
        np.testing.assert_array_equal(np.sort(blk), np.arange(lo, min(lo + 1000, 2500)))
        assert np.mean(blk != np.arange(lo, lo + len(blk))) > 0.9
    np.testing.assert_array_equal(block_permutation(5, 1, np.random.default_rng(0)),
                                  np.arange(5))


def test_particle_order_default_and_rejected_with_a_message():
    """2D on the CPU runs shuffled by default, 3D in the scene's order (no gain measured)."""
    assert jax.default_backend() == "cpu"
    assert MPM(column_scene(1.0, cells_across=5)).shuffled
    assert not MPM(column_scene(1.0, cells_across=5), particle_order="given").shuffled
    assert not MPM(column_scene(1.0, cells_across=3, dim=3)).shuffled
    assert MPM(column_scene(1.0, cells_across=3, dim=3), particle_order="shuffled").shuffled
    with pytest.raises(InputError, match="particle_order: 'sorted' is not an order"):
        MPM(column_scene(1.0, cells_across=5), particle_order="sorted")


@pytest.mark.parametrize("devices", [1, 2])
def test_shuffled_order_gives_the_frames_clamps_and_gradient_of_the_scene_order(
        x64, devices, monkeypatch):
    """Three material groups, several bodies in one group, particles pushed past a wall: the
    shuffled frame (one device, or two with padding) equals the scene-order frame to
    round-off, counts the same clamps, and differentiates to the same gradient. Blocks of
    200 particles (764 in the scene), so there are several, one spanning two groups."""
    two_devices()
    monkeypatch.setattr(solver, "ORDER_BLOCK", 200)
    scene = mixed_scene(v_right=0.5)
    given = MPM(scene, devices=1, particle_order="given")
    shuf = MPM(scene, devices=devices, particle_order="shuffled")
    assert shuf._layout is not None and not np.array_equal(
        shuf._layout["src"][shuf._layout["real"]], np.arange(scene.n_particles))
    p, s = given.params(), given.init()
    s = s.replace(x=s.x.at[0, np.array([3, 400, 700])].set(scene.domain[0][1] + 0.004))
    (fa, sa), (fb, sb) = frames(given, p, s), frames(shuf, p, s)
    assert float(jnp.abs(sa.x - s.x).max()) > 1e-3
    for a, b in ((fa.positions, fb.positions), (fa.velocities, fb.velocities),
                 (sa.C, sb.C), (sa.F, sb.F)):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=0, atol=1e-9)
    np.testing.assert_array_equal(np.asarray(fb.clamp.moved), np.asarray(fa.clamp.moved))
    assert int(fa.clamp.moved[1]) >= 3

    def runout(sim, phi):
        q = p.replace(friction_angle=p.friction_angle.at[0].set(phi))
        return jnp.max(rollout_jit(sim, q, s, n_frames=2)[1].x[0])

    ga = jax.grad(lambda a: runout(given, a))(25.0)
    gb = jax.grad(lambda a: runout(shuf, a))(25.0)
    assert np.isfinite(float(ga))
    np.testing.assert_allclose(float(gb), float(ga), rtol=1e-7, atol=1e-12)
