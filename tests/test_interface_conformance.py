"""The conformance battery every simulator passes (diffgns.interface).

For the MPM, the particle GNS, the hybrid and the MeshGraphNet alike: it is a Simulator;
``rollout`` gives ``n_frames + 1`` frames of the documented shapes; jit equals eager; new
parameter values do not recompile; ``jax.grad`` is finite and non-zero; a checkpointed
rollout equals the plain one; float64 runs in float64.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns.graph.features import Normalizer, ParticleStats
from diffgns.graph.gns import GNS, GNSConfig, GNSParams
from diffgns.hybrid import Hybrid, HybridParams, Schedule
from diffgns.interface import Simulator, rollout, rollout_jit, scan_frames
from diffgns.mesh.meshnet import (
    FLUID,
    INFLOW,
    OUTFLOW,
    WALL,
    MeshNet,
    MeshNetConfig,
    MeshStats,
    pad_mesh,
)
from diffgns.mpm import MPM
from diffgns.scene.builders import column_collapse

N_FRAMES = 5
META = {"vel_mean": [0.0, -1e-4], "vel_std": [1e-3, 1e-3],
        "acc_mean": [0.0, -2e-5], "acc_std": [5e-5, 5e-5]}


def _cast(tree, dtype):
    return jax.tree.map(lambda a: jnp.asarray(a).astype(dtype)
                        if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating) else a, tree)


def _scene():
    return column_collapse(width=0.1, aspect_ratio=0.5, friction_angle=30.0, cells_across=4,
                           domain_length=0.4, domain_height=0.2)


def _gns(bounds, history=2):
    cfg = GNSConfig(bounds=bounds, radius=0.06, latent=8, mp_steps=1, mlp_layers=1,
                    history=history)
    return GNS(cfg, ParticleStats.from_metadata(META, cfg.noise_std), frame_dt=2.5e-3)


def make_mpm(dtype):
    sim = MPM(_scene(), dtype=dtype)
    return sim, sim.params(), sim.init(), lambda p: p.friction_angle


def make_gns(dtype):
    gns = _gns(((0.0, 1.0), (0.0, 1.0)))
    rng = np.random.default_rng(0)
    x0 = rng.uniform(0.3, 0.7, (24, 1, 2))
    hist = np.concatenate([x0, x0 + np.cumsum(rng.normal(0, 1e-3, (24, 2, 2)), 1)], 1)
    hist = jnp.asarray(hist, dtype)
    ptype = np.full(24, 6, np.int32)
    net = gns.init_network(jax.random.key(0), (hist, ptype, np.zeros(24, np.float32)))
    params = GNSParams(_cast(net, dtype), jnp.asarray(0.6, dtype))
    return gns, params, gns.init(hist, ptype), lambda p: p.material


def make_hybrid(dtype):
    mpm = MPM(_scene(), dtype=dtype)
    gns = _gns(mpm.scene.domain)
    hyb = Hybrid(mpm, gns, frame_stride=1, factor=4,
                 schedule=Schedule(warmup=2, gns_frames=2, mpm_frames=1))
    x = hyb.nodes(mpm.init())
    hist = jnp.repeat(x[:, None], 3, axis=1)
    net = gns.init_network(jax.random.key(1), (hist, np.full(hyb.n_nodes, 6, np.int32),
                                               np.zeros(hyb.n_nodes, np.float32)))
    params = HybridParams(mpm.params(), _cast(net, dtype))
    return hyb, params, hyb.init(mpm.init()), lambda p: p.mpm.friction_angle


def make_meshnet(dtype):
    nx, ny = 5, 4
    xs, ys = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 0.5, ny), indexing="ij")
    pos = np.stack([xs.ravel(), ys.ravel()], 1)
    idx = np.arange(nx * ny).reshape(nx, ny)
    cells = [[idx[i, j], idx[i + 1, j], idx[i + 1, j + 1]] for i in range(nx - 1)
             for j in range(ny - 1)] + [[idx[i, j], idx[i + 1, j + 1], idx[i, j + 1]]
                                         for i in range(nx - 1) for j in range(ny - 1)]
    types = np.full(nx * ny, FLUID)
    types[idx[:, 0]] = types[idx[:, -1]] = WALL
    types[idx[0]], types[idx[-1]] = INFLOW, OUTFLOW
    nu = 1e-3
    graph = pad_mesh(pos, np.array(cells), types, 24, 96, nu)
    stats = MeshStats(Normalizer(jnp.zeros(2), jnp.ones(2)),
                      Normalizer(jnp.zeros(3), jnp.full(3, 0.1)), 0.25,
                      Normalizer(jnp.asarray(np.log(nu)), jnp.asarray(0.5)))
    model = MeshNet(MeshNetConfig(latent=8, mp_steps=1), stats)
    graph = _cast(graph, dtype)
    net = _cast(model.init_network(jax.random.key(2), graph), dtype)
    v0 = jnp.asarray(np.random.default_rng(3).normal(size=(24, 2)), dtype)
    first_leaf = lambda p: jax.tree.leaves(p)[0]  # noqa: E731
    return model, net, model.init(graph, v0), first_leaf


FACTORIES = {"mpm": make_mpm, "gns": make_gns, "hybrid": make_hybrid, "meshnet": make_meshnet}


@pytest.fixture(scope="module", params=list(FACTORIES))
def case(request):
    return request.param, FACTORIES[request.param](jnp.float32)


def _close(a, b, rtol=1e-5, atol=1e-6):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(np.asarray(x, np.float64), np.asarray(y, np.float64),
                                   rtol=rtol, atol=atol)


def _close_scaled(a, b, frac):
    """Leaves equal within ``frac`` of each leaf's largest magnitude (float32 round-off)."""
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        y = np.asarray(y, np.float64)
        np.testing.assert_allclose(np.asarray(x, np.float64), y, rtol=0,
                                   atol=frac * np.abs(y).max(initial=0.0) + 1e-12)


def test_is_a_simulator_with_documented_frames(case):
    name, (sim, params, state, _) = case
    assert isinstance(sim, Simulator) and sim.frame_dt > 0
    frames, final = rollout_jit(sim, params, state, n_frames=N_FRAMES)
    first = sim.observe(state)
    for stacked, single in zip(jax.tree.leaves(frames), jax.tree.leaves(first)):
        assert stacked.shape == (N_FRAMES + 1,) + jnp.shape(single)
        assert np.isfinite(np.asarray(stacked, np.float64)).all()
    _close(jax.tree.map(lambda a: a[0], frames), first, 0, 0)  # frame 0 is the state
    _close(jax.tree.map(lambda a: a[-1], frames), sim.observe(final), 0, 0)
    assert not np.asarray(getattr(frames, "overflow", False)).any()
    moved = [np.abs(np.asarray(a[-1]) - np.asarray(a[0])).max()
             for a in jax.tree.leaves(frames) if jnp.issubdtype(a.dtype, jnp.floating)]
    assert max(moved) > 0  # the simulator does something


def test_jit_equals_eager_and_no_recompilation(case):
    name, (sim, params, state, _) = case
    jitted, _ = rollout_jit(sim, params, state, n_frames=N_FRAMES)
    with jax.disable_jit():
        eager, _ = rollout(sim, params, state, N_FRAMES)
    _close_scaled(jitted, eager, 5e-3)  # float32, fused against unfused: round-off
    size = rollout_jit._cache_size()
    other = jax.tree.map(lambda a: a * 1.01 if jnp.issubdtype(jnp.asarray(a).dtype,
                                                                jnp.floating) else a, params)
    rollout_jit(sim, other, state, n_frames=N_FRAMES)
    rollout_jit(sim, other, state, N_FRAMES, checkpoint_block=None)  # spelled differently
    assert rollout_jit._cache_size() == size  # new values, same program


def test_gradient_finite_and_checkpointed_equals_plain(case):
    name, (sim, params, state, leaf) = case

    def loss(p, block):
        frames, _ = rollout(sim, p, state, N_FRAMES, checkpoint_block=block)
        field = frames[0]  # positions (particles) or velocity (mesh)
        return jnp.sum(field[-1] ** 2), frames

    plain_g, plain = jax.jit(jax.grad(lambda p: loss(p, None), has_aux=True))(params)
    ckpt_g, ckpt = jax.jit(jax.grad(lambda p: loss(p, 2), has_aux=True))(params)
    # 5 frames = two blocks of 2 + 1. Equal to float32 round-off relative to each field's
    # scale: the sand return map amplifies round-off of a different fusion order (the same
    # check in float64 is exact to 1e-10: test_mpm_substep_checkpointing_...).
    _close_scaled(ckpt, plain, 5e-3)
    _close_scaled(ckpt_g, plain_g, 1e-2)
    g = np.asarray(leaf(plain_g))
    assert np.isfinite(g).all() and np.abs(g).sum() > 0
    for x in jax.tree.leaves(plain_g):
        assert np.isfinite(np.asarray(x)).all()


@pytest.mark.slow  # 32 s in the full suite beside a 2-process CFD job (2026-12-03)
def test_mpm_substep_checkpointing_changes_nothing_but_memory(x64):
    """float64, tight: in float32 the sand return map amplifies the recomputation's round-off
    (which is why the float32 battery compares checkpointed and plain per field scale)."""
    sim, params, state, leaf = make_mpm(jnp.float64)
    ck = MPM(sim.scene, dtype=jnp.float64, checkpoint_substeps=True)

    def loss(s, p, block=None):
        frames, _ = rollout(s, p, state, 3, checkpoint_block=block)
        return jnp.sum(frames.positions[-1] ** 2), frames

    g0, f0 = jax.jit(jax.grad(lambda p: loss(sim, p), has_aux=True))(params)
    # substep and block checkpointing together (blocks of 2 over 3 frames)
    g1, f1 = jax.jit(jax.grad(lambda p: loss(ck, p, 2), has_aux=True))(params)
    for x, y in zip(jax.tree.leaves(f1), jax.tree.leaves(f0)):  # round-off only
        y = np.asarray(y, np.float64)
        np.testing.assert_allclose(np.asarray(x, np.float64), y, rtol=0,
                                   atol=1e-10 * np.abs(y).max(initial=0.0) + 1e-14)
    np.testing.assert_allclose(np.asarray(leaf(g1)), np.asarray(leaf(g0)), rtol=1e-9)


@pytest.mark.parametrize("name", list(FACTORIES))
def test_float64(name, x64):
    sim, params, state, _ = FACTORIES[name](jnp.float64)
    frames, _ = rollout_jit(sim, params, state, n_frames=2)
    field = frames[0]
    assert field.dtype == jnp.float64 and np.isfinite(np.asarray(field)).all()


def test_scan_frames_blocks_and_rejects_empty():
    body = lambda c, x: (c + x, c * x)  # noqa: E731
    xs = jnp.arange(7.0)
    ref = jax.lax.scan(body, 1.0, xs)
    for block in (None, 1, 2, 3, 7, 9):
        _close(scan_frames(body, 1.0, xs, checkpoint_block=block), ref, 0, 0)
    with pytest.raises(ValueError, match="length"):
        scan_frames(body, 1.0, None, 0)
    with pytest.raises(ValueError, match="n_frames"):
        rollout(*make_mpm(jnp.float32)[:3], 0)
