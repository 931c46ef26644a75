"""How much does the MPM's answer depend on its substep at a fixed cell size? Three cases
with analytic or substep-free answers, each at substeps that are fractions of the stable
one (the question behind ``granular_truth_spread.py --perturb stiff`` and
``collapse_resolution.py --dt-factors``).

    .venv/bin/python benchmarks/mpm_substep_dissipation.py [--dt-factors 1 0.25 0.0625] \
        [--out mpm_substep_dissipation.json]

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

Reading: a dissipation that comes with every particle-grid round trip, rather than with
time, grows with the number of substeps per second, so it does not vanish as the substep
shrinks at a fixed cell size. Accuracy only (the protocol records the load, never refuses).
"""
from __future__ import annotations

import argparse

import numpy as np
import protocol

G = 9.81


def _run(scene, dt_factor: float, frames: int):
    from diffgns import MPM

    if dt_factor != 1.0:
        scene = scene.replace(dt=dt_factor * scene.substep_dt)
    sim = MPM(scene)
    traj = sim.run(sim.params(), sim.init(), frames, check=False)[0]
    return np.asarray(traj.positions), np.asarray(traj.velocities), int(scene.substeps)


def slide(dt_factor: float) -> dict:
    from diffgns import Body, Elastic, Rectangle, Scene, Wall, Walls

    mu, v0 = 0.5, 1.0
    body = Body(Rectangle(0.1, 0.0, 0.2, 0.04), Elastic(E=2e6, nu=0.3, rho=1000.0),
                velocity=(v0, 0.0))
    scene = Scene(domain=((0.0, 1.0), (0.0, 0.2)), dx=0.01, bodies=(body,),
                  walls=Walls(bottom=Wall("friction", mu)))
    x, _, sub = _run(scene, dt_factor, 100)
    travel = float(x[-1, :, 0].mean() - x[0, :, 0].mean())
    exact = v0 ** 2 / (2 * mu * G)
    return dict(substeps_per_frame=sub, travel_m=travel, exact_m=exact,
                rel_error=travel / exact - 1.0)


def collision(dt_factor: float) -> dict:
    from diffgns import Body, Elastic, Rectangle, Scene

    m = Elastic(E=1e5, nu=0.3, rho=1000.0)
    bodies = (Body(Rectangle(0.3, 0.4, 0.45, 0.55), m, velocity=(0.5, 0.0)),
              Body(Rectangle(0.55, 0.4, 0.7, 0.55), m, velocity=(-0.5, 0.0)))
    scene = Scene(domain=((0.0, 1.0), (0.0, 1.0)), dx=0.02, bodies=bodies,
                  gravity=(0.0, 0.0))
    _, v, sub = _run(scene, dt_factor, 120)
    ke = 0.5 * (v ** 2).sum(-1).mean(-1)
    half = v.shape[1] // 2
    return dict(substeps_per_frame=sub, kinetic_energy_kept=float(ke[-1] / ke[0]),
                left_block_vx_after=float(v[-1, :half, 0].mean()))


def bounce(dt_factor: float) -> dict:
    from diffgns import Body, Elastic, Rectangle, Scene, Wall, Walls

    body = Body(Rectangle(0.4, 0.0, 0.6, 0.2), Elastic(E=1e5, nu=0.3, rho=1000.0))
    scene = Scene(domain=((0.0, 1.0), (0.0, 1.0)), dx=0.02, bodies=(body,),
                  walls=Walls(bottom=Wall("sticky")))
    x, _, sub = _run(scene, dt_factor, 200)
    y = x[:, :, 1].mean(1)
    first, last = float(np.ptp(y[:40])), float(np.ptp(y[160:]))
    return dict(substeps_per_frame=sub, amplitude_first_m=first, amplitude_last_m=last,
                amplitude_kept=last / first)


CASES = {"slide": slide, "collision": collision, "bounce": bounce}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dt-factors", type=float, nargs="+", default=[1.0, 0.25, 0.0625],
                    help="substeps as fractions of the stable one")
    ap.add_argument("--cases", nargs="+", choices=tuple(CASES), default=list(CASES))
    ap.add_argument("--out", default="mpm_substep_dissipation.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "mpm_substep_dissipation", timed=False)  # accuracy only
    rows = []
    for name in args.cases:
        for f in args.dt_factors:
            r = dict(case=name, dt_factor=f, **CASES[name](f))
            rows.append(r)
            run.print(f"{name:<9} dt x {f:<7g} " + " ".join(
                f"{k} {v:.4g}" for k, v in r.items() if k not in ("case", "dt_factor")))
    path = run.finish(args.out, dict(dt_factors=args.dt_factors, rows=rows))
    run.print(f"wrote {path}")


if __name__ == "__main__":
    main()
