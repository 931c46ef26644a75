"""pytest-benchmark micro-benchmarks of the MPM solver (small sizes).

    .venv/bin/python -m pytest benchmarks/ --benchmark-enable [--allow-loaded]

Not part of the default test run (``testpaths = ["tests"]``). Compilation happens in the
fixtures, outside the timed region; every timed call blocks until its result is ready. The
load check of ``protocol.py`` applies (``conftest.py``).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns import MPM, rollout_jit
from diffgns.scene import Body, Scene, Walls
from diffgns.scene.builders import column_collapse
from diffgns.scene.materials import Fluid
from diffgns.scene.shapes import Rectangle

ROUNDS = 5


def _compiled_frame(scene, n_frames=1):
    sim = MPM(scene)
    params, state = sim.params(), sim.init()
    fn = lambda: jax.block_until_ready(
        rollout_jit(sim, params, state, n_frames=n_frames)[0].positions)
    fn()  # compile
    return fn, scene


@pytest.fixture(scope="module")
def sand_2k():
    # 23 x 23 cells x 4 particles per cell = 2116 particles, friction floor
    return _compiled_frame(column_collapse(cells_across=23))


@pytest.fixture(scope="module")
def fluid_2k():
    body = Body(Rectangle(0.05, 0.05, 0.28, 0.28), Fluid(), particles_per_cell=4)
    scene = Scene(domain=((0.0, 1.0), (0.0, 0.5)), dx=0.01, bodies=(body,),
                  walls=Walls.all("slip"))
    return _compiled_frame(scene)


def _bench_frame(benchmark, compiled):
    fn, scene = compiled
    benchmark.extra_info.update(n_particles=scene.n_particles, substeps=scene.substeps,
                                grid_shape=list(scene.grid_shape))
    pos = benchmark.pedantic(fn, rounds=ROUNDS, iterations=1, warmup_rounds=1)
    assert bool(jnp.all(jnp.isfinite(pos)))
    return pos


def test_frame_sand_column_2k(benchmark, sand_2k):
    """One frame (all its substeps) of a ~2k-particle sand column collapse."""
    _bench_frame(benchmark, sand_2k)


def test_frame_fluid_2k(benchmark, fluid_2k):
    """One frame of a ~2k-particle weakly compressible fluid block."""
    _bench_frame(benchmark, fluid_2k)


def test_mpm88_kernels_50_substeps(benchmark):
    """50 substeps of the mpm88 problem built from diffgns' transfer kernels (8192
    particles, 128^2 grid), the diffgns side of ``mpm_vs_taichi.py``."""
    from mpm_vs_taichi import N_PARTICLES, SCAN_LEN, DiffgnsJFluid, initial_positions

    sim = DiffgnsJFluid()
    x0 = initial_positions(0)
    sim.reset(x0)
    sim.run(SCAN_LEN)  # compile
    benchmark.extra_info.update(n_particles=N_PARTICLES, substeps=SCAN_LEN)
    benchmark.pedantic(lambda: sim.run(SCAN_LEN), setup=lambda: sim.reset(x0),
                       rounds=ROUNDS, iterations=1, warmup_rounds=1)
    x = sim.positions()
    assert np.all(np.isfinite(x)) and x[:, 1].mean() < 0.4  # fell under gravity


def test_sand_taichi_transcription_agrees():
    """The Taichi transcription of the sand substep (``mpm_sand_vs_taichi.py``) follows
    diffgns' MPM: 216 substeps of a 400-particle column, mean height, runout, mean x and
    mean speed within 0.1% (no timing)."""
    ti = pytest.importorskip("taichi")
    from mpm_sand_vs_taichi import build, physics_check

    ti.init(arch=ti.cpu, default_fp=ti.f32, random_seed=0, cpu_max_num_threads=2)
    scene, sims = build(ti, cells=10, seg=2)
    check = physics_check(sims, (8,), tol=1e-3)["8"]
    assert 8 * scene.substeps == 216
    assert check["agree"], check
    assert check["taichi"]["mean_y"] < 0.05  # the column has started to slump
