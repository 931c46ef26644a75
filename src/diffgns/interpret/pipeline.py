"""End to end: simulate an n-body system, train (or load) a message network, test the premise,
and recover the pair-force law by symbolic regression.

``run(law, out)`` writes to ``out``: ``results.json`` (premise figures, both regressions, the
checks against the true law), ``front_<target>.md`` tables and ``front.png``. Used by
``diffgns symbolic`` and ``examples/symbolic_regression.py``.

Two regressions are run on test edges:

* ``force``: the force read out of the top message components (linear gauge fixed on training
  edges, :func:`.messages.radial_force`), projected on the line of centres, in N, as a function
  of (d, m_i, m_j, r_i, r_j). This is the closed-form law, and the one checked against truth.
  The edge model sees the receiver's mass, so its messages may carry the force or the force
  over that mass (the receiver's acceleration due to the sender); the premise test scores both
  and the better one is used (``gauge``), in N or m/s^2.
* ``component``: the raw top message component, in the network's arbitrary units, as a
  function of (dx, dy, d, m_i, m_j, r_i, r_j): the paper's direct fit, whose direction factor
  the regression has to find too.

Only interacting edges enter the regressions: springs in contact, inverse-square pairs closer
than the cut-off (elsewhere the force is zero by definition; the messages there are reported as
``message_off_interaction``).

Two network variants of Cranmer et al. are shipped (:data:`VARIANTS`):

* ``l1`` (default): messages of dimension 100 with an L1 penalty (weight 1e-2) on them, so that
  only a few components stay active. Here it needs help and time: an L2 penalty on the node
  model's first layer (else the node model scales up and the messages shrink without going
  sparse), a warm-up of the L1 weight over 2,000 steps (else every message switches off,
  contacts being rare), and 100,000 steps in two stages (lr 3e-3 -> 3e-5 over 40,000 steps,
  then resumed with the decay spread over 100,000). At 7,600 steps 90 of 100 components were
  still active; at 40,000, 8; at 100,000, 6 (model cards). Folders ``message_net_<law>_l1``.
* ``bottleneck``: messages of dimension 2 (the dimension of the force), 8,000 steps; folders
  ``message_net_<law>``.

Hidden width 64 (reference 300): at equal steps the narrower MLPs fitted better here
(normalised MSE 0.0055 against 0.027 after 3,000 steps on the spring data) and train ~10x
faster on this CPU.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from diffgns.graph.training import TrainConfig
from diffgns.interpret import message_net, messages, nbody_data, symbolic
from diffgns.interpret.nbody import NBodyConfig
from diffgns.interpret.nbody_data import EDGE_UNITS
from diffgns.interpret.options import (  # noqa: F401  (re-exported)
    LAWS,
    SR_GENERATIONS,
    SR_MAX_SECONDS,
    SR_POPULATION,
    VARIANT_NAMES,
    add_arguments,
)
from diffgns.models import model_dir

SYSTEMS = {
    "spring": NBodyConfig(),
    "inverse_square": NBodyConfig(law="inverse_square", G=-1.0, speed=0.5,
                                  radius_range=(0.1, 0.2), periodic=True),
}
# variant -> (network, training stages: each trains to its step count with the learning rate
# decaying exponentially 3e-3 -> 3e-5 over that count, resuming the stage before)
VARIANTS = {
    "l1": (message_net.MessageNetConfig(msg_dim=100, hidden=64, l1_weight=1e-2, node_l2=1e-4,
                                        l1_warmup=2000), (40000, 100000)),
    "bottleneck": (message_net.MessageNetConfig(msg_dim=2, hidden=64, l1_weight=0.0,
                                                node_l2=0.0), (8000,)),
}
FRAMES = {"spring": 500, "inverse_square": 500}
# symbolic-regression budget per search: counts, never seconds, so that the selection does not
# depend on the machine (SR_MAX_SECONDS is only a safety cap that raises)
EQUIV_TOL = 0.01
"""Relative tolerance of :func:`check_law` (1%)."""
FORCE_FEATURES = ["d", "m_i", "m_j", "r_i", "r_j"]
COMPONENT_FEATURES = ["dx", "dy", "d", "m_i", "m_j", "r_i", "r_j"]
_COLUMNS = nbody_data.EDGE_FEATURES


def datasets(law: str, data_dir: str | Path, n_train: int = 30, n_test: int = 10,
             progress: bool = True) -> tuple[Path, Path]:
    """Generate (or resume) the training and held-out datasets of ``law``."""
    cfg, frames = SYSTEMS[law], FRAMES[law]
    data_dir = Path(data_dir)
    train = nbody_data.generate(data_dir / f"{law}_train.h5", cfg, n_train, frames, seed=0,
                                progress=progress)
    test = nbody_data.generate(data_dir / f"{law}_test.h5", cfg, n_test, frames, seed=1,
                               progress=progress)
    return train, test


def check_law(law: str, expr, cfg: NBodyConfig, X: np.ndarray, gauge: str = "force",
              tol: float = EQUIV_TOL) -> dict:
    """Compare a selected ``force`` expression with the true law on the samples X (n, 5).

    In the ``"acceleration"`` gauge the expression is F / m_i; it is multiplied by m_i first.
    Every test is relative, with tolerance ``tol`` (:data:`EQUIV_TOL`, 1%), recorded in the
    output with the rule. For either law an additive constant must stay below ``tol`` of the
    mean magnitude of the true law on X (``offset_rel``). Spring: the expression must be
    affine in d, r_i, r_j only, with the coefficients of r_i and r_j within ``tol`` of -k
    (k the coefficient of d) and k within ``tol`` of the truth. Inverse square: the
    expression minus its additive constant must be ``G' m_i m_j / d^2`` (relative spread of
    the ratio below ``tol``) with G' within ``tol`` of G.
    """
    import sympy

    rule = ("affine in d, r_i, r_j; coefficients of r_i, r_j within tol of -k; k within tol "
            "of the truth; constant below tol of the mean |F|" if law == "spring" else
            "G' m_i m_j / d^2 plus a constant; ratio spread, |G' - G| / |G| and constant "
            "below tol (constant relative to the mean |F|)")
    out = dict(expression=str(expr.evalf(6)), gauge=gauge, tolerance=tol, rule=rule)
    m_i = sympy.Symbol("m_i", real=True)
    offset, law_part = expr.as_coeff_Add()  # an additive constant, in the gauge's unit
    if gauge == "acceleration":
        expr, law_part = sympy.expand(expr * m_i), sympy.expand(law_part * m_i)
    if law == "spring":
        coef = symbolic.linear_coefficients(expr, FORCE_FEATURES)
        out["linear_coefficients"] = coef
        if coef is None or set(coef) != {"d", "r_i", "r_j", "1"}:
            out["equivalent"] = False
            return out
        k = coef["d"]
        out["k"] = k
        out["k_rel_error"] = abs(k - cfg.k) / cfg.k
        scale = float(np.mean(np.abs(cfg.k * (X[:, 0] - X[:, 3] - X[:, 4]))))
        out["offset_rel"] = abs(coef["1"]) / scale
        out["equivalent"] = bool(
            abs(coef["r_i"] / -k - 1) < tol and abs(coef["r_j"] / -k - 1) < tol
            and out["offset_rel"] < tol and out["k_rel_error"] < tol)
        return out
    sym = {n: sympy.Symbol(n, real=True) for n in FORCE_FEATURES}
    f = sympy.lambdify([sym[n] for n in FORCE_FEATURES], law_part, "numpy")
    vals = np.broadcast_to(f(*X.T), (len(X),))
    true = cfg.G * X[:, 1] * X[:, 2] / X[:, 0] ** 2
    scale = float(np.mean(np.abs(true / X[:, 1] if gauge == "acceleration" else true)))
    out["offset_rel"] = abs(float(offset)) / scale
    ratio = vals * X[:, 0] ** 2 / (X[:, 1] * X[:, 2])
    # attraction positive along the line of centres: F = G m_i m_j / d^2
    out["G"] = float(np.median(ratio))
    out["G_rel_error"] = abs(out["G"] - cfg.G) / abs(cfg.G)
    out["ratio_spread"] = float(np.std(ratio) / abs(np.mean(ratio)))
    out["uses"] = sorted(str(s) for s in law_part.free_symbols)
    out["equivalent"] = bool(out["ratio_spread"] < tol and out["G_rel_error"] < tol
                             and out["offset_rel"] < tol
                             and set(out["uses"]) == {"d", "m_i", "m_j"})
    return out


def _columns(edges: dict, names: list[str]) -> np.ndarray:
    return np.stack([edges["features"][:, _COLUMNS.index(n)] for n in names], axis=1)


def front_table(front, title: str) -> str:
    lines = [f"### {title}", "", "| | complexity | MAE | score | dimensions | expression |",
             "|---|---|---|---|---|---|"]
    for c in front:
        mark = "**>**" if c.selected else ""
        dims = ("ok" if c.consistent else "INCONSISTENT") + f" ({c.dim_note})"
        dims += ", exponents snapped" if c.snapped else ""
        lines.append(f"| {mark} | {c.complexity} | {c.mae:.4g} | {c.score:.3f} | {dims} | "
                     f"`{c.expr.evalf(5)}` |")
    return "\n".join(lines) + "\n"


def plot_fronts(fronts: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(fronts), figsize=(5 * len(fronts), 4), squeeze=False)
    for ax, (name, front) in zip(axes[0], fronts.items()):
        c = np.array([f.complexity for f in front])
        e = np.array([f.mae for f in front])
        ok = np.array([f.consistent for f in front])
        ax.semilogy(c, e, "-", color="0.7")
        ax.semilogy(c[ok], e[ok], "o", label="dimensionally consistent")
        ax.semilogy(c[~ok], e[~ok], "x", label="inconsistent")
        sel = [f for f in front if f.selected][0]
        ax.semilogy([sel.complexity], [sel.mae], "*", ms=16, label="selected")
        ax.set(xlabel="complexity", ylabel="mean absolute error", title=name)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def model_folder(models: str | Path, law: str, variant: str) -> Path:
    """The folder of the ``variant`` network of ``law`` under ``models``
    (``message_net_<law>[_l1]``, or its ``model/`` sub-folder in the earlier layout; see
    :func:`diffgns.models.model_dir`); raises ModelFolderError naming what is missing."""
    name = f"message_net_{law}" + ("_l1" if variant == "l1" else "")
    return model_dir(Path(models) / name, "model.json")


def train_network(samples: dict, out: str | Path, variant: str, train_steps: int | None = None,
                  seed: int = 0, progress: bool = True):
    """Train (or resume) the ``variant`` message network with its recipe; ``train_steps``
    replaces the recipe's stages by one stage of that length. Returns (net, norm, params)."""
    cfg, stages = VARIANTS[variant]
    for steps in (train_steps,) if train_steps else stages:
        tcfg = TrainConfig(steps=steps, batch_size=64, lr=3e-3, lr_final=3e-5,
                           lr_decay_steps=steps, log_every=200, checkpoint_every=1000,
                           seed=seed)
        net, norm, params = message_net.train(samples, out, cfg, tcfg, progress)
    return net, norm, params


def regression_targets(law: str, data_dir: str | Path = "data/nbody", model: str | None = None,
                       out: str | Path | None = None, train_steps: int | None = None,
                       sr_samples: int = 5000, seed: int = 0, progress: bool = True,
                       variant: str = "l1") -> tuple[dict, dict]:
    """Data, network and premise of ``law``: returns (results so far, targets), where targets
    maps ``force`` / ``component`` to (X (n, p), y (n,), feature names, unit of y or None).

    ``model``: a saved message network; None trains the ``variant`` network into
    ``out``/train first. Every random choice is seeded from ``seed``."""
    if law not in SYSTEMS:
        raise ValueError(f"law must be one of {sorted(SYSTEMS)}, got {law!r}")
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {sorted(VARIANTS)}, got {variant!r}")
    train_path, test_path = datasets(law, data_dir, progress=progress)
    train_samples = nbody_data.edge_samples(*nbody_data.load(train_path))
    test_samples = nbody_data.edge_samples(*nbody_data.load(test_path))
    if model is not None:
        net, norm, params, _ = message_net.load(model)
    else:
        net, norm, params = train_network(train_samples, Path(out or ".") / "train", variant,
                                          train_steps, seed, progress)
    tr = messages.edge_messages(net, norm, params, train_samples, 50000, seed, True)
    te_all = messages.edge_messages(net, norm, params, test_samples, 10000, seed + 1)
    te = messages.edge_messages(net, norm, params, test_samples, None, seed + 2, True)
    res = dict(law=law, model=model, msg_dim=net.cfg.msg_dim, system=dict(SYSTEMS[law].__dict__),
               premise_all_edges=messages.summarise(tr, te_all),
               premise_regression_edges=messages.summarise(tr, te))
    off = np.linalg.norm(te_all["force"], axis=-1) == 0
    top = res["premise_all_edges"]["top_components"][:2]
    res["message_off_interaction"] = dict(
        mean_abs_top=float(np.abs(te_all["messages"][off][:, top]).mean()) if off.any()
        else float("nan"),
        mean_abs_top_interacting=float(np.abs(te_all["messages"][~off][:, top]).mean()))
    W = np.asarray(res["premise_all_edges"]["calibration"])
    top = res["premise_all_edges"]["top_components"]
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(te["messages"]), min(sr_samples, len(te["messages"])), replace=False)
    sub = {k: v[pick] for k, v in te.items()}
    gauge = res["premise_all_edges"]["gauge"]
    targets = {
        "force": (_columns(sub, FORCE_FEATURES), messages.radial_force(
            sub["messages"][:, top[:2]], W, sub["features"]), FORCE_FEATURES,
            "N" if gauge == "force" else "m/s^2"),
        "component": (_columns(sub, COMPONENT_FEATURES), sub["messages"][:, top[0]],
                      COMPONENT_FEATURES, None),
    }
    return res, targets


def run(law: str, out: str | Path, data_dir: str | Path = "data/nbody", model: str | None = None,
        train_steps: int | None = None, sr_samples: int = 5000,
        sr_generations: int = SR_GENERATIONS, sr_population: int = SR_POPULATION,
        sr_max_seconds: float | None = SR_MAX_SECONDS, seed: int = 0, n_threads: int = 1,
        progress: bool = True, variant: str = "l1") -> dict:
    """The whole pipeline for ``law`` ("spring" or "inverse_square"); returns the results.

    ``model``: a saved message network; None trains the ``variant`` network first. Each of
    the two searches runs ``sr_generations`` generations of ``sr_population`` expressions
    with pyoperon seeded by ``seed``; ``sr_max_seconds`` is a safety cap per search that
    raises :class:`.symbolic.BudgetError` (it never shortens a search silently)."""
    out = Path(out)
    res, targets = regression_targets(law, data_dir, model, out, train_steps, sr_samples, seed,
                                      progress, variant)
    out.mkdir(parents=True, exist_ok=True)
    gauge = res["premise_all_edges"]["gauge"]
    fronts, tables = {}, []
    for name, (X, y, names, unit) in targets.items():
        front, best, info = symbolic.regress(
            X, y, names, {n: EDGE_UNITS[n] for n in names}, unit, seed=seed,
            n_threads=n_threads, generations=sr_generations, population=sr_population,
            safety_seconds=sr_max_seconds)
        fronts[name] = front
        res[f"sr_{name}"] = dict(info, front=[c.row() for c in front], selected=best.row())
        tables.append(front_table(front, f"{law}: {name} ({info['samples']} test edges, "
                                         f"{info['generations']} generations of "
                                         f"{info['population']}, seed {seed})"))
        if name == "force":
            res["check"] = check_law(law, best.expr, SYSTEMS[law], X, gauge)
    (out / "fronts.md").write_text("\n".join(tables))
    plot_fronts(fronts, out / "front.png")
    (out / "results.json").write_text(json.dumps(res, indent=2, default=str))
    return res


def _positive(args) -> str | None:
    for flag in ("sr_samples", "sr_generations", "sr_population", "threads"):
        if getattr(args, flag) < 1:
            return (f"--{flag.replace('_', '-')} must be at least 1, got "
                    f"{getattr(args, flag)}")
    if args.sr_max_seconds <= 0:
        return f"--sr-max-seconds must be positive, got {args.sr_max_seconds:g}"
    return None


def main(args) -> int:
    """Run the pipeline for the chosen law(s) and print the fronts and checks."""
    import sys
    import time

    problem = _positive(args)
    if problem:
        print(f"diffgns: error: {problem}", file=sys.stderr)
        return 2
    laws = list(SYSTEMS) if args.law == "both" else [args.law]
    summary = {}
    for law in laws:
        t0 = time.perf_counter()
        model = None if args.train else str(model_folder(args.models, law, args.variant))
        try:
            res = run(law, Path(args.out) / law, args.data_dir, model, args.train_steps,
                      args.sr_samples, args.sr_generations, args.sr_population,
                      args.sr_max_seconds, args.seed, args.threads, variant=args.variant)
        except symbolic.BudgetError as err:
            print(f"diffgns: error: {law}: {err}", file=sys.stderr)
            return 2
        seconds = time.perf_counter() - t0
        print((Path(args.out) / law / "fronts.md").read_text())
        p = res["premise_all_edges"]
        print(f"premise ({p['n_test_edges']} test edges): R^2 of the top components on the "
              f"true force {[round(r, 4) for r in p['r2_top']]}")
        check = res["check"]
        print(f"selected ({law}, force): {res['sr_force']['selected']['expression']}")
        print(f"check against the true law (relative tolerance {check['tolerance']:g}: "
              f"{check['rule']}): {json.dumps(check)}")
        print(f"{law}: {seconds:.0f} s; results in {Path(args.out) / law}")
        summary[law] = dict(seconds=seconds, check=check, r2_top=p["r2_top"],
                            selected={k: res[f"sr_{k}"]["selected"]["expression"]
                                      for k in ("force", "component")})
    (Path(args.out) / "summary.json").write_text(json.dumps(summary, indent=2))
    ok = all(s["check"].get("equivalent") for s in summary.values())
    return 0 if ok else 1
