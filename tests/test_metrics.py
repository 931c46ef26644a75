"""diffgns.metrics: runout of any flow."""
import numpy as np
import pytest


def test_flow_runout_is_measured_from_the_back_of_the_mass_in_either_direction():
    from diffgns.metrics import flow_runout

    x0 = np.stack([np.linspace(0.3, 0.4, 11), np.zeros(11)], -1)
    right = x0 + np.array([[0.0, 0.0]] * 10 + [[0.25, 0.0]])  # front to 0.65
    assert flow_runout(x0, right) == (pytest.approx(0.35), 1)
    mirrored = np.stack([0.7 - x0[:, 0], x0[:, 1]], -1)
    left = np.stack([0.7 - right[:, 0], right[:, 1]], -1)
    assert flow_runout(mirrored, left) == (pytest.approx(0.35), -1)
    # a prediction scored in the reference's direction, even if it went the other way
    assert flow_runout(x0, x0 - [0.1, 0.0], 1)[0] == pytest.approx(0.0)
    with pytest.raises(ValueError, match="direction"):
        flow_runout(x0, right, 0)


def test_per_family_summary_flags_any_case_over_a_target():
    from diffgns.graph.evaluate import per_family

    def row(runout, pos, inside=True, finite=True):
        return dict(flow_runout_rel_error=runout, final_position_error_rel_displacement=pos,
                    inside_domain=inside, finite=finite, final_kinetic_energy_per_kg=1e-6)

    rows = [row(0.01, 0.02), row(0.04, 0.03), row(0.02, 0.06), row(0.01, 0.01, inside=False),
            dict(row(0.01, 0.01), clamped_positions=3), dict(row(0.01, 0.01), clamped_positions=0)]
    fams = ["squares", "squares", "columns", "obstacles", "collision", "collision"]
    t = per_family(rows, fams)
    assert t["squares"]["met"] and t["squares"]["cases"] == 2
    assert t["squares"]["clamped_positions"] == 0 and t["squares"]["clamped_cases"] == 0
    assert t["squares"]["flow_runout_rel_error_max"] == pytest.approx(0.04)
    assert not t["columns"]["met"]  # position error 6% > 5%
    assert not t["obstacles"]["met"] and t["obstacles"]["outside_domain"] == 1
    # inside the domain and within the targets, but only because 3 positions were clamped
    assert not t["collision"]["met"]
    assert t["collision"]["clamped_positions"] == 3 and t["collision"]["clamped_cases"] == 1
    assert t["all"]["cases"] == 6 and not t["all"]["met"] and t["all"]["clamped_cases"] == 1
    # per case: squares 2 of 2; the 6% column, the escaped and the clamped case fail
    assert [t[f]["cases_met"] for f in ("squares", "columns", "obstacles", "collision",
                                        "all")] == [2, 0, 0, 1, 3]
    moving = dict(row(0.01, 0.01), moving_when_ref_at_rest=True)
    nan = row(float("nan"), 0.01)
    assert per_family([moving, nan], ["squares"] * 2)["squares"]["cases_met"] == 0
    with pytest.raises(ValueError, match="6 rows for 5"):
        per_family(rows, fams[:5])


def test_matched_position_error_ignores_labels_and_measures_a_shift():
    from diffgns.metrics import MATCHED_MAX_POINTS, matched_position_error

    rng = np.random.default_rng(0)
    x = rng.uniform(0.0, 0.5, (60, 2))
    perm = rng.permutation(60)
    assert matched_position_error(x[perm], x) == pytest.approx(0.0, abs=1e-12)
    per_point = np.linalg.norm(x[perm] - x, axis=1).mean()
    assert per_point > 0.1  # the labelled error sees the relabelling
    # a rigid shift by d is matched to itself: the error is exactly d (no shorter matching)
    assert matched_position_error(x + [0.003, -0.004], x) == pytest.approx(0.005)
    # two points, each 1 m from the other's place: matching swaps them, error 0; a third
    # point 0.3 m off keeps its own error, averaged over 3
    a = np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 5.0]])
    b = np.array([[1.0, 0.0], [0.0, 0.0], [5.0, 5.3]])
    assert matched_position_error(b, a) == pytest.approx(0.1)
    # at most the per-point error, on random pairs
    y = x + rng.normal(0, 0.05, x.shape)
    assert matched_position_error(y, x) <= np.linalg.norm(y - x, axis=1).mean() + 1e-12
    with pytest.raises(ValueError, match="one shape"):
        matched_position_error(x, x[:-1])
    big = np.zeros((MATCHED_MAX_POINTS + 1, 2))
    with pytest.raises(ValueError, match="at most"):
        matched_position_error(big, big)


def test_score_reports_the_matched_error_beside_the_per_node_one():
    from diffgns.graph.evaluate import per_family, score
    from diffgns.trajectory import Trajectory

    rng = np.random.default_rng(1)
    x0 = rng.uniform(0.1, 0.3, (40, 2))
    xT = x0 + [0.2, 0.0]
    ref = np.stack([x0, xT])
    perm = rng.permutation(40)
    pred = np.stack([x0, xT[perm]])  # right deposit, nodes relabelled

    def traj(p):
        return Trajectory(positions=p, velocities=np.zeros_like(p),
                          particle_type=np.zeros(40, int), material=np.full(40, 30.0),
                          frame_dt=0.01, bounds=((0.0, 0.8), (0.0, 0.35)))

    row = score(traj(pred), traj(ref))
    assert row["final_matched_error_rel_displacement"] == pytest.approx(0.0, abs=1e-9)
    assert row["final_position_error_rel_displacement"] > 0.2
    t = per_family([dict(row, family="squares")], ["squares"])
    assert t["squares"]["final_matched_error_rel_displacement_max"] == pytest.approx(0, abs=1e-9)
    assert not t["squares"]["met"]  # the target stays the per-node error
    # a family where one case lacks it (too many points to match) gets no partial summary
    bare = {k: v for k, v in row.items() if not k.startswith("final_matched")}
    t2 = per_family([row, bare], ["squares", "squares"])
    assert "final_matched_error_rel_displacement_mean" not in t2["squares"]


def test_score_flags_a_rollout_still_moving_where_the_reference_is_at_rest():
    """The reference's last-frame kinetic energy is reported; a prediction above the rest
    threshold where the reference is below it is flagged and fails the family's ``met``; a
    prediction at rest, or a reference still moving, is not flagged."""
    from diffgns.graph.evaluate import REST_KE_PER_KG, per_family, score
    from diffgns.trajectory import Trajectory

    x0 = np.stack(np.meshgrid(np.linspace(0.1, 0.2, 5), np.linspace(0.0, 0.1, 4)),
                  -1).reshape(-1, 2)
    dt = 0.01

    def traj(last_speed):  # three frames; the last step at ``last_speed`` m/s along x
        p = np.stack([x0, x0 + 0.05, x0 + 0.05 + [last_speed * dt, 0.0]])
        return Trajectory(positions=p, velocities=np.zeros_like(p),
                          particle_type=np.zeros(len(x0), int), material=np.full(len(x0), 0.5),
                          frame_dt=dt, bounds=((0.0, 0.8), (0.0, 0.35)))

    rest, slow, moving = 0.0, 0.5 * np.sqrt(2 * REST_KE_PER_KG), 3 * np.sqrt(2 * REST_KE_PER_KG)
    row = score(traj(moving), traj(rest))
    assert row["final_kinetic_energy_ref_per_kg"] == pytest.approx(0.0, abs=1e-12)
    assert row["final_kinetic_energy_per_kg"] == pytest.approx(9 * REST_KE_PER_KG, rel=1e-3)
    assert row["moving_when_ref_at_rest"]
    assert not score(traj(slow), traj(rest))["moving_when_ref_at_rest"]
    assert not score(traj(moving), traj(moving))["moving_when_ref_at_rest"]
    ok = dict(row, flow_runout_rel_error=0.0, final_position_error_rel_displacement=0.0)
    t = per_family([ok, dict(ok, moving_when_ref_at_rest=False)], ["squares", "columns"])
    assert t["squares"]["moving_when_ref_at_rest"] == 1 and not t["squares"]["met"]
    assert t["columns"]["met"] and t["all"]["moving_when_ref_at_rest"] == 1
