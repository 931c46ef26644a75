"""The shipped message networks: the premise on held-out edges, and the whole pipeline (slow)."""
import numpy as np
import pytest

from diffgns.interpret import message_net, messages, nbody_data, pipeline
from diffgns.models import models_root

MODELS = models_root()


@pytest.fixture(scope="module", params=[(law, variant) for law in pipeline.SYSTEMS
                                        for variant in pipeline.VARIANTS],
                ids="-".join)
def shipped(request, tmp_path_factory):
    law, variant = request.param
    net, norm, params, info = message_net.load(pipeline.model_folder(MODELS, law, variant))
    assert net.cfg == pipeline.VARIANTS[variant][0]  # the shipped network is the recipe's
    cfg = pipeline.SYSTEMS[law]
    folder = tmp_path_factory.mktemp(law)
    # held-out systems: seeds the training set (seed 0) never used
    test = nbody_data.generate(folder / "t.h5", cfg, 2, pipeline.FRAMES[law], seed=7,
                               progress=False)
    train = nbody_data.generate(folder / "c.h5", cfg, 2, pipeline.FRAMES[law], seed=0,
                                progress=False)
    return law, net, norm, params, nbody_data.edge_samples(*nbody_data.load(test)), \
        nbody_data.edge_samples(*nbody_data.load(train))


# issue target 0.95; measured on the shipped bottleneck networks 0.989 (spring) and 0.998
# (inverse square, acceleration gauge), on the L1 spring network 0.981 / 0.963
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


def test_l1_messages_are_sparse(tmp_path):
    """The L1 networks keep only a few of their 100 components active on held-out edges."""
    for law in pipeline.SYSTEMS:
        net, norm, params, _ = message_net.load(pipeline.model_folder(MODELS, law, "l1"))
        cfg = pipeline.SYSTEMS[law]
        samples = nbody_data.edge_samples(*nbody_data.load(nbody_data.generate(
            tmp_path / f"{law}.h5", cfg, 1,
            pipeline.FRAMES[law], seed=7, progress=False)))
        m = messages.edge_messages(net, norm, params, samples, 5000, seed=1)["messages"]
        _, std = messages.rank_components(m)
        assert m.shape[1] == 100
        assert int(np.sum(std > 0.1 * std[0])) <= 8, std[:10] / std[0]


def test_training_recipe_runs_its_stages_in_turn(tmp_path, monkeypatch):
    tiny = message_net.MessageNetConfig(msg_dim=4, hidden=8, layers=1, l1_weight=1e-2,
                                        l1_warmup=5)
    monkeypatch.setitem(pipeline.VARIANTS, "tiny", (tiny, (10, 30)))
    path = nbody_data.generate(tmp_path / "s.h5", pipeline.SYSTEMS["spring"], 1, 20, seed=0,
                               progress=False)
    samples = nbody_data.edge_samples(*nbody_data.load(path))
    net, _, _ = pipeline.train_network(samples, tmp_path / "run", "tiny", progress=False)
    assert net.cfg == tiny
    info = message_net.load(tmp_path / "run" / "model")[3]
    # the second stage resumed the first: 30 steps in all, its own schedule recorded, and
    # the log holds the end of both stages (a second stage started afresh would log only 30)
    assert info["steps"] == 30 and info["train"]["lr_decay_steps"] == 30
    log = np.loadtxt(tmp_path / "run" / "train_log.csv", delimiter=",", skiprows=1, ndmin=2)
    assert log[:, 0].tolist() == [10, 30]
    with pytest.raises(ValueError, match="variant"):
        pipeline.run("spring", tmp_path, tmp_path, variant="l2")


@pytest.mark.slow
@pytest.mark.parametrize("variant", list(pipeline.VARIANTS))
def test_pipeline_recovers_spring_law(tmp_path, variant):
    res = pipeline.run("spring", tmp_path, tmp_path / "data",
                       model=str(pipeline.model_folder(MODELS, "spring", variant)),
                       progress=False, variant=variant)  # the default budget
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


def _symbolic(tmp_path, name, law="both"):
    """``diffgns symbolic`` (shipped L1 networks) on a reduced budget; returns its printed
    output without the timing lines, and each law's fronts and check."""
    import io
    import json
    from contextlib import redirect_stdout

    from diffgns.cli import main

    out = tmp_path / name
    buf = io.StringIO()
    with redirect_stdout(buf):
        code = main(["symbolic", "--law", law, "--out", str(out),
                     "--data-dir", str(tmp_path / "data"),
                     "--sr-samples", "400", "--sr-generations", "4", "--sr-population", "60"])
    assert code in (0, 1)  # 1: a law not recovered on this tiny budget, not an error
    text = "\n".join(line for line in buf.getvalue().splitlines()
                     if not line.endswith(f"results in {out / line.split(':')[0]}"))
    fronts = {}
    for each in pipeline.SYSTEMS if law == "both" else [law]:
        res = json.loads((out / each / "results.json").read_text())
        fronts[each] = [(res[f"sr_{k}"]["front"], res[f"sr_{k}"]["selected"])
                        for k in ("force", "component")] + [res["check"]]
    return text, fronts


def _loaded(fn):
    """``fn()`` while a busy process competes for the CPU."""
    import subprocess
    import sys

    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        return fn()
    finally:
        busy.kill()
        busy.wait()


@pytest.mark.slow  # 23 s in the full suite beside a 2-process CFD job (2026-12-03)
def test_symbolic_command_spring_is_reproducible_under_load(tmp_path):
    """Fast variant: the spring law twice, the second time beside a busy process."""
    first = _symbolic(tmp_path, "a", "spring")
    assert _loaded(lambda: _symbolic(tmp_path, "b", "spring")) == first
    assert first[1]["spring"][0][1]["constants"]  # the selection carries its constants


@pytest.mark.slow
def test_symbolic_command_gives_the_same_answer_twice_and_under_load(tmp_path):
    """The whole command (both laws) twice in a row and once beside a busy process:
    identical fronts, selections, fitted constants (full precision), checks and output."""
    first = _symbolic(tmp_path, "a")
    assert _symbolic(tmp_path, "b") == first
    assert _loaded(lambda: _symbolic(tmp_path, "c")) == first
    text, fronts = first
    for law, (force, _component, check) in fronts.items():
        assert force[1]["selected"] and force[1]["constants"], law
        assert check["tolerance"] == pipeline.EQUIV_TOL
    assert text.count("relative tolerance 0.01") == 2 and "selected (spring, force)" in text


def test_symbolic_command_refuses_a_bad_budget(tmp_path, capsys):
    from diffgns.cli import main

    assert main(["symbolic", "--out", str(tmp_path), "--sr-generations", "0"]) == 2
    assert "--sr-generations must be at least 1" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing written


def test_light_cli_options_name_the_pipelines_laws_and_variants():
    """diffgns.interpret.options (no JAX, for a fast --help) repeats the pipeline's names."""
    from diffgns.interpret import options

    assert set(options.LAWS) == set(pipeline.SYSTEMS)
    assert set(options.VARIANT_NAMES) == set(pipeline.VARIANTS)
