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

    rows = [row(0.01, 0.02), row(0.04, 0.03), row(0.02, 0.06), row(0.01, 0.01, inside=False)]
    fams = ["squares", "squares", "columns", "obstacles"]
    t = per_family(rows, fams)
    assert t["squares"]["met"] and t["squares"]["cases"] == 2
    assert t["squares"]["flow_runout_rel_error_max"] == pytest.approx(0.04)
    assert not t["columns"]["met"]  # position error 6% > 5%
    assert not t["obstacles"]["met"] and t["obstacles"]["outside_domain"] == 1
    assert t["all"]["cases"] == 4 and not t["all"]["met"]
    with pytest.raises(ValueError, match="4 rows for 3"):
        per_family(rows, fams[:3])
