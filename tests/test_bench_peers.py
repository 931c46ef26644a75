"""The diffgns side of the peer benchmarks still traces against the library: a change of a
kernel's signature (as when the MPM became dimension-generic and ``wall_slip`` took tuples)
must fail here, not in the next quiet-machine run. Tracing only (``jax.eval_shape``): no
compilation, no timing."""
import sys
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


def test_mpm88_transcription_traces_with_the_library_kernels():
    from mpm_vs_taichi import N_PARTICLES, DiffgnsJFluid, initial_positions

    sim = DiffgnsJFluid()
    sim.reset(initial_positions(0))
    out = jax.eval_shape(sim._run_scan, sim.state)
    assert out[0].shape[-1] == N_PARTICLES or out[0].shape[0] == N_PARTICLES
    assert all(np.issubdtype(o.dtype, np.floating) for o in jax.tree.leaves(out))
