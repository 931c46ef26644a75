"""Dimensional analysis, complexity, front and selection, and a seeded pyoperon recovery."""
import numpy as np
import pytest
import sympy

from diffgns.interpret import symbolic, units

U = {"d": "m", "r_i": "m", "r_j": "m", "m_i": "kg", "m_j": "kg", "dx": "m", "dy": "m"}
S = {n: sympy.Symbol(n, real=True) for n in U}


@pytest.mark.parametrize("text, target, ok", [
    ("100.0*(d - r_i - r_j)", "N", True),       # the constant carries N/m
    ("d - r_i - r_j", "N", False),              # metres are not newtons
    ("d + m_i", None, False),                   # adding kg to m
    ("exp(d)", None, False),                    # exp of a length
    ("exp(2.5*d)", None, True),                 # the constant makes it dimensionless
    ("d**1.37", None, False),                   # non-integer power of a length
    ("3.0*m_i*m_j/d**2", "N", True),
    ("m_i*m_j/d**2", "N", False),               # kg^2/m^2 without a constant
    ("Max(d, r_i) - r_j", "m", True),
    ("Max(d, m_i)", None, False),
    ("sqrt(d*r_i)", "m", True),
    ("log(d/r_i)", "1", True),
])
def test_dimensional_check(text, target, ok):
    expr = sympy.sympify(text, locals=S)
    assert units.check(expr, U, target)[0] is ok


def test_unit_parsing():
    np.testing.assert_allclose(units.parse_unit("N"), [1, 1, -2])
    np.testing.assert_allclose(units.parse_unit("kg m/s^2"), [1, 1, -2])
    np.testing.assert_allclose(units.parse_unit("m/s"), [0, 1, -1])
    with pytest.raises(ValueError, match="unknown unit"):
        units.parse_unit("furlong")


def _cand(c, mae, ok=True):
    return symbolic.Candidate(f"e{c}", sympy.Symbol("d"), c, mae, ok, "")


def test_pareto_and_selection_rule():
    cands = [_cand(3, 5.0), _cand(5, 4.0), _cand(6, 6.0), _cand(9, 0.1), _cand(12, 0.09),
             _cand(7, 0.5, ok=False)]
    front = symbolic.pareto(cands)
    assert [c.complexity for c in front] == [3, 5, 7, 9, 12]  # 6 is dominated
    best = symbolic.select(front)
    # consistent-only front 3, 5, 9, 12: the drop 4.0 -> 0.1 over 4 is the largest per unit
    assert best.complexity == 9 and best.selected
    np.testing.assert_allclose(best.score, np.log(4.0 / 0.1) / 4)
    anyway = symbolic.select(front, prefer_consistent=False)
    assert anyway.complexity == 7  # 4.0 -> 0.5 over 2 beats 0.5 -> 0.1 over 2


def test_linear_coefficients():
    e = sympy.sympify("99.5*d - 100.2*r_i - 100.1*r_j + 0.01", locals=S)
    c = symbolic.linear_coefficients(e, list(U))
    assert c == pytest.approx({"d": 99.5, "r_i": -100.2, "r_j": -100.1, "1": 0.01})
    assert symbolic.linear_coefficients(sympy.sympify("d*r_i", locals=S), list(U)) is None
    assert symbolic.linear_coefficients(sympy.sympify("2*r_i/d + 1", locals=S), list(U)) is None


def test_operon_recovers_spring_law_seeded():
    """Fixed seed, one thread and a generation budget (not a time limit, which would make the
    search depend on the machine): the selected expression is k (d - r_i - r_j), k = 100."""
    rng = np.random.default_rng(0)
    n = 3000
    ri, rj = rng.uniform(0.25, 0.5, n), rng.uniform(0.25, 0.5, n)
    d = (ri + rj) * rng.uniform(0.75, 1.0, n)
    mi, mj = rng.uniform(0.5, 2, n), rng.uniform(0.5, 2, n)
    X = np.stack([d, mi, mj, ri, rj], 1)
    y = 100 * (d - ri - rj) + rng.normal(0, 0.05, n)
    names = ["d", "m_i", "m_j", "r_i", "r_j"]
    front, best, info = symbolic.regress(X, y, names, U, "N", seed=1, n_threads=1,
                                         generations=40, population=300)
    assert best.consistent and best.selected
    coef = symbolic.linear_coefficients(best.expr, names)
    assert coef is not None and set(coef) == {"d", "r_i", "r_j", "1"}
    assert coef["d"] == pytest.approx(100, rel=0.01)
    assert coef["r_i"] == pytest.approx(-100, rel=0.01)
    assert coef["r_j"] == pytest.approx(-100, rel=0.01)
    assert [c.complexity for c in front] == sorted(c.complexity for c in front)
    assert best.mae < 0.06


def test_regress_rejects_bad_input():
    with pytest.raises(ValueError, match="must be"):
        symbolic.regress(np.zeros((5, 2)), np.zeros(5), ["d"], U, None)
    with pytest.raises(ValueError, match="finite"):
        symbolic.regress(np.full((5, 1), np.nan), np.zeros(5), ["d"], U, None)


def _tree(nodes):
    import pyoperon as op

    return op.Tree(nodes).UpdateNodes()


def test_tree_units_on_pyoperon_trees():
    import pyoperon as op

    d, m, r = op.Node.Variable(88.0), op.Node.Variable(2.0), op.Node.Variable(-91.0)
    d.HashValue, m.HashValue, r.HashValue = 1, 2, 3
    names = {1: "d", 2: "m_i", 3: "r_i"}
    check = lambda nodes, target: symbolic.tree_units(_tree(nodes), names, U, target)[0]
    # weighted variables keep their units: 88 d - 91 r_i is a length, not a force ...
    assert check([r, d, op.Node.Sub()], "m")
    assert not check([r, d, op.Node.Sub()], "N")
    # ... until a free constant scales it
    assert check([op.Node.Constant(1.1), r, d, op.Node.Sub(), op.Node.Mul()], "N")
    assert not check([m, d, op.Node.Add()], None)          # 88 d + 2 m_i
    assert not check([d, op.Node.Exp()], None)             # exp(88 d)
    assert check([op.Node.Constant(0.3), d, op.Node.Div(), op.Node.Exp()], None)  # exp(d/c)
    two = op.Node.Constant(2.0)
    assert check([two, d, op.Node.Pow()], "m^2")           # (88 d)^2
    assert not check([op.Node.Constant(1.37), d, op.Node.Pow()], None)


def test_snapped_power_law_refits_and_passes_the_dimensional_check():
    """A fitted exponent is never exactly rational: -1.977 is snapped to -2, the remaining
    constants refitted, and the snapped law passes the check its parent fails."""
    import pyoperon as op

    rng = np.random.default_rng(0)
    d_val = rng.uniform(0.2, 2.0, 500)
    y = -1.3 / d_val**2 + 0.01
    tree = op.InfixParser.Parse("0.02 + (-1.2 * (d ^ -1.977))", {"d": 1})
    names = {1: "d"}

    def evaluate(t):
        text = op.InfixFormatter.Format(t, names, 12)
        return sympy.lambdify(S["d"], symbolic.to_sympy(text, ["d"]), "numpy")(d_val)

    assert not symbolic.tree_units(tree, names, U, "N")[0]
    snapped = symbolic.snap_powers(tree, evaluate, y, tol=0.1)
    assert symbolic.tree_units(snapped, names, U, "N")[0]
    np.testing.assert_allclose(evaluate(snapped), y, atol=1e-6)  # -1.3 / d^2 + 0.01 exactly
    assert [n.Value for n in tree.Nodes][0] == pytest.approx(-1.977)  # the parent unchanged
    # nothing within tolerance of a half-integer: no copy
    far = op.InfixParser.Parse("-1.2 * (d ^ -1.75)", {"d": 1})
    assert symbolic.snap_powers(far, evaluate, y, tol=0.1) is None


def test_merged_front_keeps_consistent_expressions_dominated_by_inconsistent_ones():
    cands = [_cand(3, 5.0), _cand(9, 0.10, ok=False), _cand(9, 0.12), _cand(12, 0.09, ok=False)]
    front = symbolic.merge_fronts(cands)
    assert [(c.complexity, c.mae) for c in front] == [(3, 5.0), (9, 0.10), (9, 0.12),
                                                      (12, 0.09)]
    assert symbolic.select(front).mae == 0.12  # the consistent 9 is chosen


def _spring_samples(n=1500, seed=0):
    rng = np.random.default_rng(seed)
    ri, rj = rng.uniform(0.25, 0.5, n), rng.uniform(0.25, 0.5, n)
    d = (ri + rj) * rng.uniform(0.75, 1.0, n)
    X = np.stack([d, rng.uniform(0.5, 2, n), rng.uniform(0.5, 2, n), ri, rj], 1)
    return X, 100 * (d - ri - rj) + rng.normal(0, 0.5, n)


def _front_signature(front):
    """Everything a reader sees of a front, constants at full precision."""
    return [(c.text, c.constants, c.complexity, c.mae, c.consistent, c.selected)
            for c in front]


def test_search_is_reproducible_and_ignores_machine_load():
    """Budgeted in generations with a fixed seed: two searches in a row, and one with a busy
    process competing for the CPU, give the same front to the last bit of every constant
    (a time budget would stop the loaded search at another generation)."""
    import subprocess
    import sys

    X, y = _spring_samples()
    names = ["d", "m_i", "m_j", "r_i", "r_j"]
    kw = dict(seed=3, n_threads=1, generations=12, population=200)
    runs = [symbolic.regress(X, y, names, U, "N", **kw) for _ in range(2)]
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    try:
        runs.append(symbolic.regress(X, y, names, U, "N", **kw))
    finally:
        for p in busy:
            p.kill()
            p.wait()
    first = _front_signature(runs[0][0])
    assert len(first) >= 3 and any(c[-1] for c in first)
    for front, best, info in runs[1:]:
        assert _front_signature(front) == first
        assert best.text == runs[0][1].text and best.constants == runs[0][1].constants
        assert info["generations_run"] == 12
    # another seed searches differently (the comparison above can fail)
    other = symbolic.regress(X, y, names, U, "N", **dict(kw, seed=4))[0]
    assert _front_signature(other) != first


def test_safety_cap_raises_instead_of_returning_a_shorter_search():
    X, y = _spring_samples(500)
    names = ["d", "m_i", "m_j", "r_i", "r_j"]
    with pytest.raises(symbolic.BudgetError, match="safety cap.*--sr-max-seconds"):
        symbolic.regress(X, y, names, U, "N", generations=10**6, population=200,
                         safety_seconds=1)
    with pytest.raises(ValueError, match="generations must be a positive count"):
        symbolic.regress(X, y, names, U, "N", generations=0)
