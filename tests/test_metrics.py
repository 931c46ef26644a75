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
