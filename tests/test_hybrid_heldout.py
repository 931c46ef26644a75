"""The hybrid on held-out tall, low-friction column collapses with the best shipped GNS.

Issue 21: with ``gns_cg16_pfn`` on a tall column at low friction (a = 2.5, phi = 24 deg) the
affine particle map carried particles through the walls, where a silent clamp put them on
the box, and the hybrid was less accurate than the GNS alone. The cases here are drawn from
a seeded generator over a in [2, 3], phi in [20, 26] deg (not the issue's case, and used for
no tuning: the particle map's limit has no tuned parameter, its margin is half the MPM
particle spacing). On each: the particle map clamps no position, in the GNS frames of the
GNS-alone run or of any hybrid (an MPM frame's clamps are the MPM's own, particles resting on
a wall moved back by micrometres; they are counted apart), and each hybrid's mean
material-point position error against the MPM is at most the GNS's alone. (Until 2026-12-04
it was not, on two of the three: the hand-off gave the MPM the GNS frame's mean velocity, half
a frame late; measured 2026-12-04 23:55 UTC with the end-of-frame velocity, hybrid / GNS:
2.79 / 4.46, 3.21 / 4.53, 3.27 / 5.41 mm.)
"""
from __future__ import annotations

import functools

import numpy as np
import pytest

from diffgns.graph.train_loop import load_model
from diffgns.hybrid.compare import (
    column_scene,
    model_cells,
    run_hybrid,
    run_mpm,
    score_against,
)
from diffgns.hybrid.simulator import DEFAULT_SCHEDULE, Schedule
from diffgns.models import model_path

N_FRAMES = 125  # GNS frames of 5 ms (0.625 s, the flows are at rest), as `diffgns hybrid`
#: the hybrid schedules checked: ``diffgns hybrid``'s default (the MPM until the flow settles,
#: then K = 2 MPM frames after every M = 8 GNS frames, since 2026-12-07) and its defaults
#: before: K = 8 after M = 2 (``Schedule()``) and, before that, K = 2 after M = 5
HYBRIDS = {"hybrid": DEFAULT_SCHEDULE, "hybrid_k8m2": Schedule(),
           "hybrid_k2m5": Schedule(warmup=5, gns_frames=5, mpm_frames=2)}
GNS_ALONE = Schedule(warmup=5, gns_frames=1, mpm_frames=0)


def heldout_cases(n: int = 3, seed: int = 2126) -> list[tuple[float, float]]:
    """``n`` (aspect ratio, phi deg) drawn over [2, 3] x [20, 26] by Latin hypercube (one
    case in each n-th of either range, so they spread); aspect ratios on the 1/16 grid of a
    16-cell column, phi to 0.1 deg."""
    rng = np.random.default_rng(seed)
    a = 2.0 + (np.arange(n) + rng.uniform(size=n)) / n
    phi = 20.0 + 6.0 * (rng.permutation(n) + rng.uniform(size=n)) / n
    a, phi = np.round(a * 16) / 16, np.round(phi, 1)
    return [(float(x), float(p)) for x, p in zip(a, phi)]


def evaluate(model, a: float, phi: float) -> dict:
    """Mean position errors (m) against the MPM and clamp counts of the GNS-alone particle map
    and the hybrid on the column (a, phi) of the model's training data."""
    gns, net, info = model
    scene = column_scene(a, phi, model_cells(info), info)
    stride = int(info.get("frame_stride", 1))
    ref, t_ref = run_mpm(scene, N_FRAMES, stride, repeats=1)
    out = dict(aspect_ratio=a, phi=phi, mpm_clamped=t_ref["clamped_positions"])
    for name, sched in (("gns", GNS_ALONE), *HYBRIDS.items()):
        res, t = run_hybrid(scene, gns, net, info, sched, N_FRAMES, repeats=1)
        s = score_against(np.asarray(res.positions), ref, float(scene.domain[0][0]))
        out[f"{name}_error_m"] = s["mean_position_error_m"]
        out[f"{name}_runout_error"] = s["runout_error"]
        # the particle map's clamps: those of the GNS frames (an MPM frame's are the MPM's
        # own, particles resting on a wall moved back by micrometres, and reported apart)
        out[f"{name}_clamped"] = t["clamped_positions_gns_frames"]
        out[f"{name}_mpm_frame_clamped"] = t["clamped_positions_mpm_frames"]
        out[f"{name}_finite"] = s["finite"]
    return out


def test_heldout_cases_are_tall_low_friction_columns_and_not_the_issue_case():
    cases = heldout_cases()
    assert len(set(cases)) == 3 and (2.5, 24.0) not in cases
    assert all(2.0 <= a <= 3.0 and 20.0 <= p <= 26.0 for a, p in cases)


@functools.cache
def _result(a: float, phi: float) -> dict:
    r = evaluate(load_model(model_path("gns_cg16_pfn")), a, phi)
    print(r)
    return r


@pytest.mark.slow  # three cases, each an MPM, a GNS and a hybrid rollout of 0.625 s
@pytest.mark.parametrize("case", heldout_cases())
def test_particle_map_never_clamps_on_heldout_flows(case):
    r = _result(*case)
    for name in ("gns", *HYBRIDS):
        assert r[f"{name}_finite"] and r[f"{name}_clamped"] == 0, name


@pytest.mark.slow
@pytest.mark.parametrize("case", heldout_cases())
def test_hybrid_is_no_worse_than_the_gns_alone_on_heldout_flows(case):
    r = _result(*case)
    for name in HYBRIDS:
        assert r[f"{name}_error_m"] <= r["gns_error_m"], name
