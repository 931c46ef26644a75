"""The shipped message networks: the premise on held-out edges, and the whole pipeline (slow)."""
from pathlib import Path

import numpy as np
import pytest

from diffgns.interpret import message_net, messages, nbody_data, pipeline

MODELS = Path(__file__).resolve().parents[1] / "models"


@pytest.fixture(scope="module", params=["spring", "inverse_square"])
def shipped(request, tmp_path_factory):
    law = request.param
    net, norm, params, info = message_net.load(MODELS / f"message_net_{law}" / "model")
    cfg = pipeline.SYSTEMS[law]
    folder = tmp_path_factory.mktemp(law)
    # held-out systems: seeds the training set (seed 0) never used
    test = nbody_data.generate(folder / "t.h5", cfg, 2, pipeline.FRAMES[law], seed=7,
                               progress=False)
    train = nbody_data.generate(folder / "c.h5", cfg, 2, pipeline.FRAMES[law], seed=0,
                                progress=False)
    return law, net, norm, params, nbody_data.edge_samples(*nbody_data.load(test)), \
        nbody_data.edge_samples(*nbody_data.load(train))


# issue target 0.95; measured on the shipped networks 0.989 (spring) and 0.998 (inverse square,
# acceleration gauge) with the full test set
R2_MIN = {"spring": 0.95, "inverse_square": 0.95}
R2_FORCE_MIN = R2_MIN  # the force (or acceleration) recovered from both components


def test_top_messages_are_linear_in_the_true_force(shipped):
    """On 10,000 held-out edges the two top components are linear in the force."""
    law, net, norm, params, test, train = shipped
    contact = law == "spring"
    te = messages.edge_messages(net, norm, params, test, 10000, seed=1)
    assert len(te["messages"]) == 10000
    tr = messages.edge_messages(net, norm, params, train, 20000, seed=0, contact_only=contact)
    s = messages.summarise(tr, te)
    assert min(s["r2_top"]) >= R2_MIN[law], s
    assert s["r2_force_from_top"] >= R2_FORCE_MIN[law], s  # and together they determine it


@pytest.mark.slow
def test_pipeline_recovers_spring_law(tmp_path):
    res = pipeline.run("spring", tmp_path, tmp_path / "data",
                       model=str(MODELS / "message_net_spring" / "model"), sr_seconds=120,
                       progress=False)
    assert res["check"]["equivalent"], res["check"]
    assert abs(res["check"]["k"] - 100) < 1.0
    assert res["sr_force"]["selected"]["consistent"]
    assert (tmp_path / "front.png").exists() and (tmp_path / "fronts.md").exists()
    assert np.isfinite(res["premise_all_edges"]["r2_force_from_top"])


@pytest.mark.parametrize("text, gauge, equivalent", [
    ("-0.995*m_j/d**2 - 0.001", "acceleration", True),   # bias 0.1% of the mean |a|
    ("-0.995*m_i*m_j/d**2", "force", True),
    ("-0.995*m_j/d**2 - 0.05", "acceleration", False),   # bias of 5%
    ("-0.97*m_j/d**2", "acceleration", False),           # G 3% off
    ("-0.995*m_j/d**1.9", "acceleration", False),        # wrong exponent: ratio spreads
    ("-0.995*m_i/d**2", "acceleration", False),          # the wrong mass
])
def test_inverse_square_law_check(text, gauge, equivalent):
    import sympy

    rng = np.random.default_rng(0)
    n = 2000
    X = np.stack([rng.uniform(0.3, 2.0, n), rng.uniform(0.5, 2, n), rng.uniform(0.5, 2, n),
                  rng.uniform(0.1, 0.2, n), rng.uniform(0.1, 0.2, n)], axis=1)
    syms = {s: sympy.Symbol(s, real=True) for s in pipeline.FORCE_FEATURES}
    expr = sympy.sympify(text, locals=syms)
    out = pipeline.check_law("inverse_square", expr, pipeline.SYSTEMS["inverse_square"], X,
                             gauge)
    assert out["equivalent"] is equivalent, out
