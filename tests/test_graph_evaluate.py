"""graph.evaluate.rollout_reference: the rollout from a reference's first frames, timed with
diffgns.timing on the program the sizing run compiled."""
from __future__ import annotations

import jax
import numpy as np
import pytest

from diffgns.graph.evaluate import rollout_reference
from diffgns.graph.train_loop import load_model
from diffgns.interface import rollout_jit
from diffgns.models import model_path
from diffgns.trajectory import Trajectory

N_PREDICTED = 4


@pytest.fixture(scope="module")
def case():
    gns, params, info = load_model(model_path("gns_columns"))
    C = gns.config.history
    (x0, x1), (y0, y1) = info["gns"]["bounds"]
    g = np.stack(np.meshgrid(np.linspace(0.05, 0.15, 8), np.linspace(0.01, 0.1, 8)), -1)
    x = g.reshape(-1, 2).astype(np.float32)
    pos = np.repeat(x[None], C + 1 + N_PREDICTED, axis=0)  # a column at rest
    ref = Trajectory(positions=pos, velocities=np.zeros_like(pos),
                     particle_type=np.zeros(len(x), np.int32),
                     material=np.full(len(x), np.tan(np.radians(30.0)), np.float32),
                     frame_dt=float(info.get("frame_dt", 2.5e-3)), bounds=((x0, x1), (y0, y1)))
    return gns, params, ref


def test_rollout_reference_keeps_the_given_frames_and_times_without_recompiling(case):
    gns, params, ref = case
    C = gns.config.history
    untimed, none = rollout_reference(gns, params, ref, timed=False)
    compiled = rollout_jit._cache_size()
    timed, seconds = rollout_reference(gns, params, ref)
    assert none is None and isinstance(seconds, float) and seconds > 0
    assert rollout_jit._cache_size() == compiled  # the timed call reused the sizing program
    assert timed.positions.shape == ref.positions.shape
    np.testing.assert_array_equal(np.asarray(timed.positions[: C + 1]), ref.positions[: C + 1])
    np.testing.assert_allclose(np.asarray(timed.positions), np.asarray(untimed.positions))
    v = np.asarray(timed.velocities)
    np.testing.assert_allclose(v[1:], np.diff(np.asarray(timed.positions), axis=0) / ref.frame_dt,
                               rtol=1e-5, atol=1e-6)


def test_teacher_forced_is_one_step_from_each_reference_history_even_after_an_overflow(case):
    """teacher_forced's prediction of frame t equals GNS.step from ref's frames t-C-1..t-1
    with a list allocated there; the histories here compact the column 2x after frame C, so
    the one list allocated at frame C (no head-room) overflows and is re-allocated."""
    from diffgns.graph.evaluate import reference_inputs, teacher_forced

    gns, params, ref = case
    C = gns.config.history
    x0 = np.asarray(ref.positions[0])
    centre = x0.mean(0)
    T = C + 1 + N_PREDICTED
    scale = np.concatenate([np.ones(C + 1), np.linspace(0.8, 0.5, N_PREDICTED)])
    drop = 0.5 * 9.81 * (2.5e-3 * np.arange(T)) ** 2
    pos = np.stack([centre + s * (x0 - centre) - [0.0, d] for s, d in zip(scale, drop)])
    ref = ref.replace(positions=pos.astype(np.float32),
                      velocities=np.zeros_like(pos, dtype=np.float32))
    frames, x = teacher_forced(gns, params, ref, extra_capacity=0)
    np.testing.assert_array_equal(frames, np.arange(C + 1, T))
    g = gns.for_box(ref.bounds)
    for t, xt in zip(frames, x):
        sub = ref.replace(positions=ref.positions[t - C - 1:t],
                          velocities=ref.velocities[t - C - 1:t])
        prm, state, _ = reference_inputs(g, params, sub)
        want = np.asarray(g.step(prm, state).history[:, -1])
        np.testing.assert_allclose(xt, want, rtol=1e-5, atol=1e-7)
    _, x1 = teacher_forced(gns, params, ref, [T - 1])
    np.testing.assert_allclose(x1[0], x[-1], rtol=1e-5, atol=1e-7)
    # other weights, same shapes: the compiled program is reused (weights are arguments)
    from diffgns.graph.evaluate import _teacher_forced_compiled

    compiled = _teacher_forced_compiled._cache_size()
    assert compiled >= 1  # the calls above went through it
    _, x2 = teacher_forced(gns, jax.tree.map(lambda a: 1.01 * a, params), ref, [T - 1])
    assert _teacher_forced_compiled._cache_size() == compiled
    assert not np.allclose(x2, x1)
    with pytest.raises(ValueError, match="frames must be indices"):
        teacher_forced(gns, params, ref, [C])
