"""How much does the MPM's answer depend on its substep at a fixed cell size? Three cases
with analytic or substep-free answers, each at substeps that are fractions of the stable
one (the question behind ``granular_truth_spread.py --perturb stiff`` and
``collapse_resolution.py --dt-factors``).

    .venv/bin/python benchmarks/mpm_substep_dissipation.py [--dt-factors 1 0.25 0.0625] \
        [--flips 0 0.95 0.99] [--out mpm_substep_dissipation.json]

- ``slide``: an elastic block (E = 2 MPa, 0.1 x 0.04 m, dx = 10 mm) launched at 1 m/s
  along a Coulomb floor (mu = 0.5) under gravity. Rigid Coulomb sliding stops after
  v0^2 / (2 mu g) = 0.1019 m: the frictional wall's impulse, substep by substep.
- ``collision``: two elastic blocks (E = 0.1 MPa, 0.15 m squares, dx = 20 mm) meeting
  head-on at +-0.5 m/s in free space (no gravity, no wall). The kinetic energy kept after
  the rebound (0.3 s) is the transfers' and the contact's dissipation alone; an elastic
  continuum keeps most of it whatever the substep.
- ``bounce``: an elastic block (E = 0.1 MPa, 0.2 x 0.2 m, dx = 20 mm) released
  stress-free on a sticky floor under gravity; the peak-to-peak amplitude of its centre of
  mass over frames 0-40 and 160-200 (2.5 ms frames): how fast its elastic oscillation is
  damped.

``--flips``: each case with ``Scene.flip`` = each of them (0: APIC alone, the default).

Reading: a dissipation that comes with every particle-grid round trip, rather than with
time, grows with the number of substeps per second, so it does not vanish as the substep
shrinks at a fixed cell size. Accuracy only (the protocol records the load, never refuses),
unless ``--timed ROUNDS``: then also the cost of a FLIP update, one frame of the a = 1 sand
column at ``--cells`` against APIC alone, and the protocol refuses a loaded machine.
"""
from __future__ import annotations

import argparse

import numpy as np
import protocol

G = 9.81


def _run(scene, dt_factor: float, frames: int, flip: float):
    from diffgns import MPM

    scene = scene.replace(flip=flip)
    if dt_factor != 1.0:
        scene = scene.replace(dt=dt_factor * scene.substep_dt)
    sim = MPM(scene)
    traj = sim.run(sim.params(), sim.init(), frames, check=False)[0]
    return np.asarray(traj.positions), np.asarray(traj.velocities), int(scene.substeps)


def slide(dt_factor: float, flip: float = 0.0) -> dict:
    from diffgns import Body, Elastic, Rectangle, Scene, Wall, Walls

    mu, v0 = 0.5, 1.0
    body = Body(Rectangle(0.1, 0.0, 0.2, 0.04), Elastic(E=2e6, nu=0.3, rho=1000.0),
                velocity=(v0, 0.0))
    scene = Scene(domain=((0.0, 1.0), (0.0, 0.2)), dx=0.01, bodies=(body,),
                  walls=Walls(bottom=Wall("friction", mu)))
    x, _, sub = _run(scene, dt_factor, 100, flip)
    travel = float(x[-1, :, 0].mean() - x[0, :, 0].mean())
    exact = v0 ** 2 / (2 * mu * G)
    return dict(substeps_per_frame=sub, travel_m=travel, exact_m=exact,
                rel_error=travel / exact - 1.0)


def collision(dt_factor: float, flip: float = 0.0) -> dict:
    from diffgns import Body, Elastic, Rectangle, Scene

    m = Elastic(E=1e5, nu=0.3, rho=1000.0)
    bodies = (Body(Rectangle(0.3, 0.4, 0.45, 0.55), m, velocity=(0.5, 0.0)),
              Body(Rectangle(0.55, 0.4, 0.7, 0.55), m, velocity=(-0.5, 0.0)))
    scene = Scene(domain=((0.0, 1.0), (0.0, 1.0)), dx=0.02, bodies=bodies,
                  gravity=(0.0, 0.0))
    _, v, sub = _run(scene, dt_factor, 120, flip)
    ke = 0.5 * (v ** 2).sum(-1).mean(-1)
    half = v.shape[1] // 2
    return dict(substeps_per_frame=sub, kinetic_energy_kept=float(ke[-1] / ke[0]),
                left_block_vx_after=float(v[-1, :half, 0].mean()))


def bounce(dt_factor: float, flip: float = 0.0) -> dict:
    from diffgns import Body, Elastic, Rectangle, Scene, Wall, Walls

    body = Body(Rectangle(0.4, 0.0, 0.6, 0.2), Elastic(E=1e5, nu=0.3, rho=1000.0))
    scene = Scene(domain=((0.0, 1.0), (0.0, 1.0)), dx=0.02, bodies=(body,),
                  walls=Walls(bottom=Wall("sticky")))
    x, _, sub = _run(scene, dt_factor, 200, flip)
    y = x[:, :, 1].mean(1)
    first, last = float(np.ptp(y[:40])), float(np.ptp(y[160:]))
    return dict(substeps_per_frame=sub, amplitude_first_m=first, amplitude_last_m=last,
                amplitude_kept=last / first)


CASES = {"slide": slide, "collision": collision, "bounce": bounce}


def frame_cost(cells: int, flip: float, rounds: int) -> dict:
    """Seconds per frame of the a = 1 sand column (``cells`` across its 0.1 m width, state
    after 4 frames of collapse), APIC alone against ``Scene.flip = flip``, in interleaved
    rounds (compile apart, ``block_until_ready``); the ratio is the median of the per-round
    ratios."""
    import jax

    from diffgns import MPM, timing
    from diffgns.scene.builders import column_collapse

    base = column_collapse(width=0.1, aspect_ratio=1, friction_angle=30.0,
                           cells_across=cells)
    sims = {"apic": MPM(base), "flip": MPM(base.replace(flip=flip))}
    p = sims["apic"].params()
    state = sims["apic"].run(p, sims["apic"].init(), 4)[1]
    steps = {k: jax.jit(sim.step) for k, sim in sims.items()}
    res = timing.interleave({k: (lambda f=f: f(p, state)) for k, f in steps.items()}, rounds)
    return dict(cells=cells, particles=base.n_particles, substeps=base.substeps, flip=flip,
                flip_over_apic=res.ratio("flip", "apic"), **{
                    f"{k}_s_per_frame": res.summary(k)["median_s"] for k in steps},
                rounds=res.to_json()["rounds"])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dt-factors", type=float, nargs="+", default=[1.0, 0.25, 0.0625],
                    help="substeps as fractions of the stable one")
    ap.add_argument("--cases", nargs="+", choices=tuple(CASES), default=list(CASES))
    ap.add_argument("--flips", type=float, nargs="+", default=[0.0],
                    help="Scene.flip of every case (default 0: APIC alone)")
    ap.add_argument("--timed", type=int, default=0, metavar="ROUNDS",
                    help="also time one frame of the a = 1 column, APIC against the largest "
                    "--flips, ROUNDS interleaved rounds at --cells (needs a quiet machine)")
    ap.add_argument("--cells", type=int, nargs="+", default=[16, 45])
    ap.add_argument("--out", default="mpm_substep_dissipation.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "mpm_substep_dissipation", timed=args.timed > 0)
    rows, costs = [], []
    for cells in (args.cells if args.timed else []):
        c = frame_cost(cells, max(args.flips), args.timed)
        costs.append(c)
        run.print(f"column {cells} cells ({c['particles']} particles, {c['substeps']} "
                  f"substeps): APIC {c['apic_s_per_frame'] * 1e3:.2f} ms, flip {c['flip']:g} "
                  f"{c['flip_s_per_frame'] * 1e3:.2f} ms per frame, ratio "
                  f"{c['flip_over_apic']:.3f}")
    for name in args.cases:
        for flip in args.flips:
            for f in args.dt_factors:
                r = dict(case=name, flip=flip, dt_factor=f, **CASES[name](f, flip))
                rows.append(r)
                run.print(f"{name:<9} flip {flip:<5g} dt x {f:<7g} " + " ".join(
                    f"{k} {v:.4g}" for k, v in r.items()
                    if k not in ("case", "flip", "dt_factor")))
    path = run.finish(args.out, dict(dt_factors=args.dt_factors, flips=args.flips, rows=rows,
                                     costs=costs))
    run.print(f"wrote {path}")


if __name__ == "__main__":
    main()
