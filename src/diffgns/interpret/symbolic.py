"""Symbolic regression with pyoperon: Pareto front, complexity, selection, dimensions.

pyoperon (a C++ genetic-programming library, installed as a wheel, offline) searches
expressions over the operators below with local constant fitting, minimising mean absolute
error and length (NSGA-II). We then

1. score every front expression with our own **complexity**: one per operator, constant and
   variable, three for ``pow``, ``exp`` and ``log``. pyoperon attaches a fitted weight to
   every variable (``w * x``); such a weighted variable counts 3 (constant, product,
   variable). ``<``/``>`` are searched as ``min``/``max`` (the piecewise selections they
   express); an inverse is a division.
2. keep the Pareto front of complexity against mean absolute error;
3. check every front expression for **dimensional consistency** (:mod:`.units`) on pyoperon's
   own tree, where the fitted weight of a variable is a pure number (so ``w * x`` keeps the
   unit of ``x``) and every free constant node is a wildcard that may carry any unit. Hence
   ``88 d - 91 r_i`` is a length (and times a free constant, a force), while ``88 d + 2 m_i``
   or ``exp(2.5 d)`` are rejected: a length scale inside ``exp`` must be a free constant
   (``exp(d / c)``), not a variable weight. (Were the weights wildcards too, every pyoperon
   expression would pass and the check would say nothing.)
4. **snap** exponents: in every front expression, a ``pow`` whose exponent is a fitted
   constant within ``snap_tol`` (0.1) of a multiple of 1/2 gets that multiple, frozen, and
   the remaining constants are refitted to the least absolute error (``d ** -1.977`` becomes
   ``d ** -2``). A fitted exponent is never exactly rational, so without this step no
   power law can pass the dimensional check; the snapped copy enters the pool beside the
   original, at the same complexity, and is judged like any other expression.
5. keep the union of the Pareto front of all candidates and that of the consistent ones
   (a consistent expression dominated only by inconsistent ones stays visible);
6. **select** the expression that maximises the fractional drop in error per unit of added
   complexity, ``-dlog(MAE)/dc`` between consecutive front members, among the dimensionally
   consistent ones when there are any.

Genetic programming is stochastic, but every source of randomness here is seeded: pyoperon's
generator by ``seed``, and the search is stopped by counts (``generations``, ``population``,
``max_evaluations``), never by time, so a given seed and thread count select the same
expression with the same constants on a fast or a slow, idle or loaded machine (tested with
one thread; with several, operon's threads share work in an order that is not guaranteed).
A wall-clock ``safety_seconds`` only caps a runaway search, and raises :class:`BudgetError`
rather than return a time-dependent front. Results do depend on the seed, the thread count
and the budget, which are all parameters.
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from diffgns._extras import require
from diffgns.interpret import units as _units

sympy = require("sympy", "symbolic")

OPERATORS = "add,sub,mul,div,fmin,fmax,pow,exp,log,constant,variable"
_HEAVY = ("Pow", "Exp", "Log")
MAX_EVALUATIONS = 10**7
"""Default cap on fitness evaluations per search (a count, like the generations)."""


@dataclasses.dataclass
class Candidate:
    """One expression of the front."""

    text: str
    expr: sympy.Expr
    complexity: int
    mae: float
    consistent: bool
    dim_note: str
    score: float = 0.0
    selected: bool = False
    snapped: bool = False
    constants: tuple[float, ...] = ()  # the tree's fitted coefficients, full precision

    def row(self) -> dict:
        return dict(expression=str(self.expr.evalf(5)), model=self.text,
                    constants=list(self.constants), complexity=self.complexity,
                    mae=self.mae, score=self.score, consistent=self.consistent,
                    dimensions=self.dim_note, selected=self.selected, snapped=self.snapped)


def complexity(tree) -> int:
    """Weighted size of a pyoperon tree (see the module docstring)."""
    total = 0
    for node in tree.Nodes:
        kind = str(node.Type).split(".")[-1]
        if kind == "Variable":
            total += 1 if node.Value == 1.0 else 3
        elif kind in _HEAVY:
            total += 3
        else:
            total += 1
    return total


_UNIT_OPS = {"Add": "add", "Sub": "add", "Fmin": "add", "Fmax": "add", "Mul": "mul",
             "Div": "div", "Aq": "div", "Abs": "abs", "Square": "square", "Sqrt": "sqrt",
             "Sqrtabs": "sqrt", "Cbrt": "cbrt", "Pow": "pow"}


def tree_units(tree, names_by_hash: dict, units: dict[str, str], target: str | None):
    """(consistent, note): dimensional verdict on a pyoperon tree (rules in the module doc)."""
    vec = _units.parse_units(units)
    stack: list = []
    try:
        for node in tree.Nodes:  # postfix; a node's first child is pushed last
            kind = str(node.Type).split(".")[-1]
            if kind == "Variable":
                stack.append(vec[names_by_hash[node.HashValue]])
                continue
            if kind == "Constant":
                stack.append((_units.WILD, float(node.Value)))
                continue
            args = [stack.pop() for _ in range(node.Arity)]
            vals = [a[1] if isinstance(a, tuple) else None for a in args]
            us = [a[0] if isinstance(a, tuple) else a for a in args]
            op = _UNIT_OPS.get(kind, "func")
            if node.Arity == 1 and kind == "Div":
                op = "inv"
            elif node.Arity == 1 and kind == "Sub":
                op = "abs"  # negation keeps the unit
            if op == "pow":
                out = _units.apply("pow", us[:1], kind, power=vals[1]) if vals[1] is not None \
                    else _units.apply("pow", us, kind)
            elif op in ("square", "sqrt", "cbrt"):
                out = _units.apply("pow", us, kind, power={"square": 2.0, "sqrt": 0.5,
                                                           "cbrt": 1 / 3}[op])
            else:
                out = us[0]
                for u in us[1:]:
                    out = _units.apply(op, [out, u], kind)
                if op != "add" and node.Arity == 1:
                    out = _units.apply(op, us, kind)
            stack.append(out)
    except _units.DimensionError as err:
        return False, str(err)
    (result,) = stack
    return _units.verdict(result[0] if isinstance(result, tuple) else result, target)


def snap_powers(tree, evaluate, y: np.ndarray, tol: float = 0.1):
    """Copy of a pyoperon ``tree`` with constant ``pow`` exponents within ``tol`` of a
    multiple of 1/2 set to it (and frozen), other constants refitted to the least absolute
    error of ``evaluate(tree) -> prediction (n,)`` against ``y`` (n,). None if nothing was
    snapped."""
    pyoperon = require("pyoperon", "symbolic")
    from scipy.optimize import least_squares

    nodes, changed = tree.Nodes, False
    for i, node in enumerate(nodes):
        if str(node.Type).split(".")[-1] != "Pow" or node.Arity != 2:
            continue
        e = nodes[i - 2 - nodes[i - 1].Length]  # postfix: base at i-1, exponent before it
        p = float(e.Value)
        q = round(2 * p) / 2
        if str(e.Type).split(".")[-1] == "Constant" and 0 < abs(p - q) <= tol:
            e.Value, e.Optimize, changed = q, False, True
    if not changed:
        return None
    out = pyoperon.Tree(nodes).UpdateNodes()
    c0 = np.asarray(out.GetCoefficients(), np.float64)
    if c0.size:
        def residual(c):
            out.SetCoefficients(c)
            r = evaluate(out) - y
            return np.where(np.isfinite(r), r, 1e6)

        # the search minimises the mean absolute error, so the refit does too: soft-L1 with a
        # scale well below the parent's typical residual is |r| for all but tiny residuals
        # (plain least squares let the heavy tail of 1/d^2 pull the constants: measured on
        # the inverse-square messages, G 0.74% off and a 1.45% offset, against 0.37% / 0.50%)
        scale = 0.1 * float(np.mean(np.abs(evaluate(tree) - y))) + 1e-12
        # node values are float32: finite-difference steps must be far above its epsilon
        out.SetCoefficients(least_squares(residual, c0, loss="soft_l1", f_scale=scale,
                                          diff_step=1e-3, max_nfev=400).x)
    return out


def to_sympy(text: str, names: list[str]) -> sympy.Expr:
    """pyoperon's infix string -> sympy expression over symbols ``names``."""
    local = {n: sympy.Symbol(n, real=True) for n in names}
    local.update(max=sympy.Max, min=sympy.Min, exp=sympy.exp, log=sympy.log)
    return sympy.sympify(text.replace("^", "**"), locals=local)


def pareto(cands: list[Candidate]) -> list[Candidate]:
    """Non-dominated candidates by (complexity, MAE), sorted by complexity."""
    front, best = [], np.inf
    cands = [c for c in cands if np.isfinite(c.mae)]
    for c in sorted(cands, key=lambda c: (c.complexity, c.mae)):
        if c.mae < best * (1 - 1e-9):
            front.append(c)
            best = c.mae
    return front


def merge_fronts(cands: list[Candidate]) -> list[Candidate]:
    """Union of the Pareto front of all candidates and that of the consistent ones, sorted
    by (complexity, MAE)."""
    both = pareto(cands) + pareto([c for c in cands if c.consistent])
    unique = {id(c): c for c in both}
    return sorted(unique.values(), key=lambda c: (c.complexity, c.mae))


def select(front: list[Candidate], prefer_consistent: bool = True) -> Candidate:
    """Mark and return the front member with the largest ``-dlog(MAE)/dc``.

    Scores are computed between consecutive members of the front restricted to consistent
    expressions (when ``prefer_consistent`` and any exist), else of the whole front.
    """
    pool = [c for c in front if c.consistent] if prefer_consistent else list(front)
    pool = pool or list(front)
    for c in front:
        c.score, c.selected = 0.0, False
    prev = None
    for c in pool:
        if prev is not None:
            c.score = float(-(np.log(max(c.mae, 1e-300)) - np.log(max(prev.mae, 1e-300)))
                            / max(c.complexity - prev.complexity, 1))
        prev = c
    best = max(pool, key=lambda c: c.score)
    best.selected = True
    return best


class BudgetError(RuntimeError):
    """A search hit its wall-clock safety cap before its generation or evaluation budget."""


def regress(X: np.ndarray, y: np.ndarray, names: list[str], units: dict[str, str],
            target_unit: str | None, seed: int = 0, n_threads: int = 1,
            generations: int = 300, population: int = 1000, max_length: int = 30,
            max_evaluations: int = MAX_EVALUATIONS, safety_seconds: float | None = 3600.0,
            snap_tol: float = 0.1) -> tuple[list[Candidate], Candidate, dict]:
    """Run pyoperon on (X (n, p), y (n,)); returns (front, selected, run info).

    ``names`` label the columns of X, ``units`` give each name's unit (:mod:`.units` syntax)
    and ``target_unit`` the unit y must have (None: y's unit is arbitrary). ``snap_tol``:
    exponent snapping tolerance (0 disables it).

    The search stops after ``generations`` generations of ``population`` or
    ``max_evaluations`` fitness evaluations, whichever comes first: both are counts, so
    with a fixed ``seed`` and ``n_threads`` the result does not depend on the machine's
    speed or load. ``safety_seconds`` (None: no cap) only guards against a runaway search:
    a search that reaches it raises :class:`BudgetError` instead of returning a front that
    would depend on how fast the machine was.
    """
    SymbolicRegressor = require("pyoperon.sklearn", "symbolic").SymbolicRegressor

    X, y = np.asarray(X, np.float64), np.asarray(y, np.float64)
    if X.ndim != 2 or X.shape[1] != len(names) or len(y) != len(X):
        raise ValueError(f"X must be (n, {len(names)}) and y (n,), got {X.shape}, {y.shape}")
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(y))):
        raise ValueError("X and y must be finite")
    for name, value in (("generations", generations), ("population", population),
                        ("max_evaluations", max_evaluations)):
        if int(value) < 1:
            raise ValueError(f"{name} must be a positive count, got {value}")
    if safety_seconds is not None and safety_seconds <= 0:
        raise ValueError(f"safety_seconds must be positive or None, got {safety_seconds}")
    # pyoperon checks its time limit once per generation (whole seconds)
    cap = None if safety_seconds is None else max(1, int(np.ceil(safety_seconds)))
    reg = SymbolicRegressor(
        allowed_symbols=OPERATORS, objectives=["mae", "length"], max_length=max_length,
        generations=generations, population_size=population, n_threads=n_threads,
        random_state=seed, max_evaluations=max_evaluations, max_time=cap,
        optimizer_iterations=5)
    t0 = time.perf_counter()
    reg.fit(X, y)
    seconds = time.perf_counter() - t0
    stats = reg.stats_
    if cap is not None and seconds >= cap and stats["generations"] < generations:
        raise BudgetError(
            f"symbolic regression reached its {cap} s safety cap after {stats['generations']} "
            f"of {generations} generations; its "
            f"front would depend on the machine's speed, so none is returned: raise the cap "
            f"(--sr-max-seconds) or lower --sr-generations / --sr-population")
    hashes = {k: names[i] for i, k in enumerate(reg.variables_)}
    evaluate = lambda tree: reg.evaluate_model(tree, X)  # noqa: E731
    cands = []
    for sol in reg.pareto_front_:
        trees = [(sol["tree"], False)]
        if snap_tol > 0:
            snapped = snap_powers(sol["tree"], evaluate, y, snap_tol)
            trees += [(snapped, True)] if snapped is not None else []
        for tree, was_snapped in trees:
            pred = evaluate(tree)
            if not np.all(np.isfinite(pred)):
                continue
            text = reg.get_model_string(tree, 6, names)
            ok, note = tree_units(tree, hashes, units, target_unit)
            cands.append(Candidate(text, to_sympy(text, names), complexity(tree),
                                   float(np.mean(np.abs(pred - y))), ok, note,
                                   snapped=was_snapped,
                                   constants=tuple(float(c) for c in tree.GetCoefficients())))
    front = merge_fronts(cands)
    best = select(front)
    return front, best, dict(seconds=seconds, samples=len(y), seed=seed, n_threads=n_threads,
                             generations=generations, population=population,
                             max_evaluations=max_evaluations,
                             generations_run=int(stats["generations"]))


def linear_coefficients(expr: sympy.Expr, names: list[str]) -> dict[str, float] | None:
    """Coefficients of ``expr`` if it is affine in its variables (else None); key "1" is the
    constant term."""
    syms = sorted(expr.free_symbols, key=str)
    expr = sympy.expand(expr)
    if syms and not expr.is_polynomial(*syms):  # 1/d, exp(d), min(...): not affine
        return None
    poly = sympy.Poly(expr, *syms) if syms else None
    if poly is None or poly.total_degree() > 1:
        return None
    out = {str(s): float(poly.coeff_monomial(s)) for s in syms}
    out["1"] = float(poly.coeff_monomial(1))
    return out
