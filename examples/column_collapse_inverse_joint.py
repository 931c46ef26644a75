"""Two parameters at once: friction angle and column aspect ratio (or floor friction).

    python examples/column_collapse_inverse_joint.py --out results/inverse_joint   # GNS
    python examples/column_collapse_inverse_joint.py --objective runout            # ill-posed
    python examples/column_collapse_inverse_joint.py --simulator mpm --second floor_mu

The observation is an MPM collapse (phi = 30 deg, aspect ratio 1.75) seen as GNS nodes. The
simulator knows neither parameter nor the true column: it starts from a column of aspect
ratio 2.0 (its own particle lattice) with phi = 40 deg and stretches that column vertically
(at a fixed particle count, volumes scaled) to the aspect ratio being tried. With the GNS,
the first 5 GNS frames (10 MPM frames) are a differentiable MPM start-up at theta (a column
at rest gives the GNS no velocity history; see the README), the remaining 120 frames a GNS
rollout; gradients flow through both. The objective is the deposit profile (default) or the
final runout only.

What the data can identify is printed at the end: the Jacobian J of the observed features
(runout; deposit heights in 40 bins) with respect to (phi, second parameter) at the recovered
point, its singular values in scaled units (phi per 5 deg, aspect ratio per 0.25, mu per 0.1)
and, for the runout, the direction along which it does not change. One number (the runout)
cannot fix two parameters: a taller, stronger column runs as far as a shorter, weaker one.
The deposit profile adds the deposit's area (set by the column's size, as the sand barely
changes volume) and its shape, so both parameters are locally identifiable from it.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffgns import inverse
from diffgns.inverse import objectives
from diffgns.inverse.job import gradient_text
from diffgns.inverse.lsq import least_squares
from diffgns.inverse.simulators import Column, ColumnCase, gns_simulator, mpm_simulator
from diffgns.io import figures as viz
from diffgns.metrics import deposit_profile, runout

SCALES = {"friction_angle": 5.0, "aspect_ratio": 0.25, "floor_mu": 0.1}
DEFAULTS = {"aspect_ratio": (1.75, 2.0), "floor_mu": (0.5, 0.3)}  # (target, start)


def parse(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="results/inverse_joint")
    ap.add_argument("--simulator", default="gns", choices=["gns", "mpm"])
    ap.add_argument("--second", default="aspect_ratio", choices=["aspect_ratio", "floor_mu"])
    ap.add_argument("--objective", default="front", choices=["front", "deposit", "runout"],
                    help="front: runout at --early-frame and at rest; deposit: deposit "
                         "profile at rest; runout: runout at rest only (ill-posed)")
    ap.add_argument("--early-frame", type=int, default=30, help="GNS frame (5 ms) of the "
                    "early front position")
    ap.add_argument("--early-weight", type=float, default=10.0,
                    help="weight of the early runout residual (it varies ~10x less)")
    ap.add_argument("--target-phi", type=float, default=30.0)
    ap.add_argument("--start-phi", type=float, default=40.0)
    ap.add_argument("--target-second", type=float, default=None)
    ap.add_argument("--start-second", type=float, default=None)
    ap.add_argument("--optimizer", default="lm", choices=["lm", "adam", "sgd", "gauss-newton"],
                    help="lm: Levenberg-Marquardt on the residuals (forward-mode Jacobian); "
                         "others: optax on |r|^2 with reverse-mode gradients")
    ap.add_argument("--lr", type=float, default=0.1, help="on u = logit-transformed params")
    ap.add_argument("--decay", type=float, default=0.9, help="learning-rate decay/iteration")
    ap.add_argument("--max-iter", type=int, default=20)
    args = ap.parse_args(argv)
    tgt, start = DEFAULTS[args.second]
    args.target_second = tgt if args.target_second is None else args.target_second
    args.start_second = start if args.start_second is None else args.start_second
    if args.simulator == "gns" and args.second == "floor_mu":
        ap.error("the GNS was trained at floor mu = 0.5 and has no input for it; use "
                 "--simulator mpm with --second floor_mu")
    for name, v in (("--target-phi", args.target_phi), ("--start-phi", args.start_phi)):
        if not 0 < v < 90:
            ap.error(f"{name} {v:g} deg is not a friction angle: use 0 < phi < 90")
    return args


def identifiability(simulate, theta: dict, second: str, early: int, edges,
                    sharpness: float) -> dict:
    """Jacobians (forward mode, 2 JVPs) of the observed features at ``theta``: final runout,
    runout at frame ``early`` and the deposit profile; singular values in scaled units."""
    names = ["friction_angle", second]

    def features(th):
        x = simulate(th)
        return (runout(x[-1], method="softmax"), runout(x[early], method="softmax"),
                deposit_profile(x[-1], edges, sharpness))

    th = {k: jnp.asarray(theta[k], jnp.float32) for k in names}
    J = jax.jit(jax.jacfwd(features))(th)
    s = np.array([SCALES[k] for k in names])
    jac = [np.atleast_2d(np.stack([np.asarray(Ji[k]) for k in names], -1)) for Ji in J]
    jr, je, jp = jac

    def sv(j):
        return np.linalg.svd(j * s, compute_uv=False).tolist()

    null = np.array([-jr[0, 1], jr[0, 0]])  # the final runout does not change along this
    front = np.concatenate([jr, je])
    return dict(params=names, scales=s.tolist(), runout_jacobian=jr[0].tolist(),
                early_runout_jacobian=je[0].tolist(),
                runout_null_direction=(null / np.linalg.norm(null)).tolist(),
                front_singular_values_scaled=sv(front),
                front_condition_number=float(np.divide(*sv(front))),
                profile_singular_values_scaled=sv(jp),
                profile_condition_number=float(np.divide(*sv(jp)[:2])))


def main(argv=None):
    args = parse(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    second = args.second
    truth = {"friction_angle": args.target_phi, second: args.target_second}
    start = {"friction_angle": args.start_phi, second: args.start_second}
    a_true = args.target_second if second == "aspect_ratio" else 1.75
    a_sim = args.start_second if second == "aspect_ratio" else 1.75
    mu_true = args.target_second if second == "floor_mu" else 0.5
    # the truth: its own column (lattice) and floor; the simulator: the start's column
    target_col = Column(ColumnCase(aspect_ratio=a_true, floor_mu=mu_true))
    observed = target_col.observation({"friction_angle": args.target_phi})
    col = Column(ColumnCase(aspect_ratio=a_sim))
    if args.simulator == "gns":
        sim = gns_simulator(col, history="mpm")
        sim.allocate(start)
        simulate, on_overflow = sim.simulate, sim.reallocate
    else:
        sim = mpm_simulator(col)
        simulate, on_overflow = sim.simulate, sim.reallocate
    print(f"observation: MPM phi={args.target_phi:g}, {second}={args.target_second:g} "
          f"({target_col.n_nodes} nodes); simulator {args.simulator} on a column of aspect "
          f"ratio {a_sim:g} ({col.n_nodes} nodes); {time.perf_counter() - t_start:.1f} s",
          flush=True)
    edges = jnp.linspace(*col.bounds[0], 41)
    sharp = 4 / col.scene.dx
    final = objectives.runout_residual(observed, method="softmax")
    if args.objective == "deposit":  # |r|^2 = mean((h - h_obs)^2) / mean(h_obs^2)
        h_obs = deposit_profile(jnp.asarray(observed[-1]), edges, sharp)
        norm = jnp.sqrt(jnp.sum(h_obs**2))

        def residual(pos):
            return (deposit_profile(pos[-1], edges, sharp) - h_obs) / norm
    elif args.objective == "front":
        early = objectives.runout_residual(observed, frame=args.early_frame, method="softmax")

        def residual(pos):
            return jnp.stack([final(pos), args.early_weight * early(pos)])
    else:
        def residual(pos):
            return final(pos)[None]

    def residuals(theta):
        pos, overflow = simulate(theta)
        return residual(pos), {"overflow": overflow, "positions": pos}

    def show(rec):
        th = "  ".join(f"{k}={rec['theta'][k]:.3f}" for k in start)
        gr = " ".join(f"d/d{k}={gradient_text(rec['grad'][k])}" for k in start)
        lm = "" if "accepted" not in rec else f"  lm={rec['damping']:.0e}" + (
            "" if rec["accepted"] else " (step rejected)")
        print(f"iter {rec['iteration']:2d}  {th}  loss={rec['loss']:.3e}  {gr}{lm}  "
              f"t={rec['time_s']:.1f}s", flush=True)

    tol = {"friction_angle": 0.01, second: 0.001}
    if args.optimizer == "lm":
        res = least_squares(residuals, start, max_iter=args.max_iter, step_tol=tol,
                            has_aux=True, on_overflow=on_overflow, callback=show)
    else:
        def loss(theta):
            r, aux = residuals(theta)
            return jnp.sum(r**2), aux
        opt = inverse.make_optimizer(args.optimizer, args.lr, args.decay)
        res = inverse.optimize(loss, start, opt, max_iter=args.max_iter, step_tol=tol,
                               has_aux=True, on_overflow=on_overflow, callback=show)
    ident = identifiability(lambda th: simulate(th)[0], res.theta, second, args.early_frame,
                            edges, sharp)
    fitted = np.asarray(res.aux["positions"])
    viz.plot_convergence(res, out / "convergence.png", truth=truth)
    viz.plot_deposits([(observed[0], "true initial column"),
                       (observed[-1], "target: MPM " + ", ".join(
                           f"{k}={v:g}" for k, v in truth.items())),
                       (fitted[-1], f"recovered: {args.simulator} " + ", ".join(
                           f"{k}={v:.3g}" for k, v in res.theta.items()))],
                      out / "deposits.png", col.bounds)
    wall = time.perf_counter() - t_start
    summary = dict(simulator=args.simulator, objective=args.objective, target=truth,
                   start=start, recovered=res.theta, iterations=len(res.history) - 1,
                   stop_reason=res.stop_reason, wall_time_s=wall, compile_s=res.compile_s,
                   peak_rss_mb=inverse.peak_rss_mb(), identifiability=ident,
                   history=[{k: v for k, v in h.items() if k != "aux"} for h in res.history])
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    jr, nd = ident["runout_jacobian"], ident["runout_null_direction"]
    print(f"identifiability at the recovered point (scales: phi {SCALES['friction_angle']:g} "
          f"deg, {second} {SCALES[second]:g}):")
    print(f"  final runout: d/d(phi, {second}) = ({jr[0]:+.4f} m/deg, {jr[1]:+.4f} m); "
          f"+1 deg of phi is undone by {nd[1] / nd[0]:+.3f} of {second}: one number cannot "
          "identify two parameters")
    print("  final + early runout: scaled singular values "
          + ", ".join(f"{v:.3g}" for v in ident["front_singular_values_scaled"])
          + f" (condition number {ident['front_condition_number']:.1f})")
    print("  deposit profile: scaled singular values "
          + ", ".join(f"{v:.3g}" for v in ident["profile_singular_values_scaled"])
          + f" (condition number {ident['profile_condition_number']:.1f})")
    print(f"wall time {wall:.1f} s (compile {res.compile_s:.1f} s), {summary['iterations']} "
          f"iterations ({res.stop_reason}); outputs in {out}")
    print("recovered: " + ", ".join(f"{k} = {res.theta[k]:.3f} (target {truth[k]:g})"
                                    for k in start))


if __name__ == "__main__":
    main()
