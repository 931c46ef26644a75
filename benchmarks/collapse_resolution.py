"""Granular column collapse runout against resolution, 2D (planar) and 3D (axisymmetric),
beside the experiments' scaling (issue 24's validation).

    .venv/bin/python benchmarks/collapse_resolution.py --dim 2 --aspect-ratios 1 \
        --cells 5 10 20 [--out collapse_resolution_2d]
    .venv/bin/python benchmarks/collapse_resolution.py --dim 3 --aspect-ratios 0.5 1 2 \
        --cells 5 8 [--out collapse_resolution_3d]
    .venv/bin/python benchmarks/collapse_resolution.py --dim 2 --aspect-ratios 1 \
        --cells 16 --dt-factors 1 0.5 0.25 0.125 [--floor sticky] \
        --out collapse_dt_convergence_2d.json

2D: :func:`diffgns.scene.builders.column_collapse` (width L0 = 0.1 m against a wall,
``cells`` cells across L0, 4 particles per cell), normalised runout (L - L0)/L0 against Lube
et al. (2005): 1.2 a (a < 1.8), 1.9 a^(2/3) (a > 2.8). 3D:
:func:`diffgns.scene.builders3d.axisymmetric_column` (R0 = 0.05 m, ``cells`` cells across
R0, 8 particles per cell), (R - R0)/R0 against Lube et al. (2004): 1.24 a (a <= 1.7), 1.6
a^(1/2) above. ``--dt-factors``: each case also at substeps that fraction of the stable one
(the time-step convergence at a fixed cell size); ``--floor``: a Coulomb floor of
coefficient ``--floor-mu`` (default), or a slip or sticky one; ``--flip``: the
``Scene.flip`` of every case. Sand phi = 30 deg, floor mu = 0.5, E = 2 MPa, rho = 1800
kg/m^3, in float32, run to ``--seconds`` (default 1 s) of flow. Three measures of the final
deposit: ``front`` (far edge of the farthest one-cell bin of x, or of r, holding at least
one cell of deposit height: :func:`diffgns.metrics.deposit_front`), ``p99`` (99th percentile
of x or r) and ``max`` (farthest particle); 3D adds the spread of the per-sector p99 radius
over eight 45-degree sectors (axisymmetry) and the final top height. Accuracy only (the
protocol records the load, never refuses); each case is written as soon as it is done and
skipped when ``--out`` already holds it (resumable). Wall time per case is recorded, not a
speed figure.
"""
from __future__ import annotations

import argparse
import itertools
import json
import time

import numpy as np
import protocol


def lube(dim: int, a: float) -> float:
    from diffgns.metrics import lube_runout
    from diffgns.scene.builders3d import axisymmetric_runout_estimate

    return float(lube_runout(a)) if dim == 2 else axisymmetric_runout_estimate(a)


def case(dim: int, a: float, cells: int, seconds: float, dt_factor: float = 1.0,
         floor_mu: float = 0.5, floor: str = "friction", flip: float = 0.0) -> dict:
    from diffgns import MPM, metrics
    from diffgns.scene.builders import column_collapse
    from diffgns.scene.builders3d import axisymmetric_column, cylinder_axis

    if dim == 2:
        sc = column_collapse(width=0.1, aspect_ratio=a, friction_angle=30.0, cells_across=cells,
                             floor_mu=floor_mu)
        L0 = 0.1
    else:
        sc = axisymmetric_column(radius=0.05, aspect_ratio=a, friction_angle=30.0,
                                 cells_across=cells, floor_mu=floor_mu)
        L0 = 0.05
    if floor != "friction":  # slip or sticky instead of the Coulomb floor
        from dataclasses import replace

        from diffgns.scene.elements import Wall

        sc = sc.replace(walls=replace(sc.walls, bottom=Wall(floor)))
    if flip:
        sc = sc.replace(flip=flip)
    if dt_factor != 1.0:  # a fraction of the stable substep: the time-step convergence
        sc = sc.replace(dt=dt_factor * sc.substep_dt)
    frames = int(np.ceil(seconds / sc.frame_dt))
    sim = MPM(sc)
    t0 = time.perf_counter()
    traj = sim.run(sim.params(), sim.init(), frames)[0]
    wall = time.perf_counter() - t0
    x = np.asarray(traj.positions[-1])
    speed = np.linalg.norm(np.asarray(traj.velocities), axis=-1).max(-1)  # (T,)
    floor = sc.domain[1][0]
    if dim == 2:
        origin = sc.domain[0][0]
        dist = x[:, 0] - origin
        front = float(metrics.deposit_front(traj.positions[-1], sc.dx, sc.dx, origin=origin))
        extra = {}
    else:
        centre = cylinder_axis(sc)[0]
        dist = np.asarray(metrics.radial_distance(x, centre))
        rh = np.stack([dist, x[:, 1] - floor], 1)
        front = float(metrics.deposit_front(rh, sc.dx, sc.dx))
        d = x[:, [0, 2]] - np.asarray(centre)
        th = np.arctan2(d[:, 1], d[:, 0])
        sectors = [float(np.percentile(dist[(th >= lo) & (th < lo + np.pi / 4)], 99))
                   for lo in np.arange(-np.pi, np.pi - 1e-9, np.pi / 4)]
        extra = {"sector_p99_spread": (max(sectors) - min(sectors)) / float(np.mean(sectors))}
    norm = {k: (v - L0) / L0 for k, v in (("front", front), ("p99", np.percentile(dist, 99)),
                                        ("max", dist.max()))}
    return dict(dim=dim, aspect_ratio=a, cells=cells, dt_factor=dt_factor, flip=flip,
                floor=floor,
                floor_mu=floor_mu if floor == "friction" else None, dx=sc.dx,
                substep_dt=float(sc.substep_dt), particles=int(x.shape[0]),
                substeps_per_frame=int(sc.substeps), frames=frames,
                runout_front=float(norm["front"]), runout_p99=float(norm["p99"]),
                runout_max=float(norm["max"]), lube=lube(dim, a),
                front_vs_lube=float(norm["front"] / lube(dim, a) - 1.0),
                final_height_over_L0=float((x[:, 1].max() - floor) / L0),
                final_max_speed=float(speed[-1]),
                frame_of_rest=int(np.flatnonzero(speed >= 0.02).max(initial=-1) + 1),
                finite=bool(np.isfinite(x).all()), wall_s=wall, **extra)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dim", type=int, choices=(2, 3), required=True)
    ap.add_argument("--aspect-ratios", type=float, nargs="+", default=[1.0])
    ap.add_argument("--cells", type=int, nargs="+", default=[5, 10],
                    help="cells across L0 (2D) or R0 (3D)")
    ap.add_argument("--seconds", type=float, default=1.0, help="simulated time, s")
    ap.add_argument("--dt-factors", type=float, nargs="+", default=[1.0],
                    help="substeps as fractions of the stable one (default 1; e.g. 1 0.5 0.25 "
                    "0.125: the time-step convergence at each resolution)")
    ap.add_argument("--flip", type=float, default=0.0,
                    help="Scene.flip, the FLIP fraction of the velocity update (default 0)")
    ap.add_argument("--floor", choices=("friction", "slip", "sticky"), default="friction",
                    help="the floor's condition (default friction, Coulomb with --floor-mu)")
    ap.add_argument("--floor-mu", type=float, default=0.5,
                    help="Coulomb friction coefficient of a friction floor (default 0.5)")
    ap.add_argument("--out", default=None, help="results JSON (default "
                    "collapse_resolution_<dim>d.json)")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    out = args.out or f"collapse_resolution_{args.dim}d.json"
    from diffgns.errors import SceneError

    run = protocol.start(args, "collapse_resolution", timed=False)  # accuracy only
    path = protocol.results_path(out)
    rows = json.loads(path.read_text()).get("rows", []) if path.exists() else []
    done = {(r["dim"], r["aspect_ratio"], r["cells"], r.get("dt_factor", 1.0),
             r.get("floor", "friction"), r.get("floor_mu", 0.5), r.get("flip", 0.0))
            for r in rows}
    mu = args.floor_mu if args.floor == "friction" else None
    run.print(f"{'a':>4} {'cells':>5} {'dt':>6} {'N':>7} {'front':>6} {'p99':>6} {'max':>6} "
              f"{'law':>5} {'front/law-1':>11} {'H/L0':>5} {'rest@':>5}")
    for a, c, f in itertools.product(args.aspect_ratios, args.cells, args.dt_factors):
        if (args.dim, a, c, f, args.floor, mu, args.flip) in done:
            continue
        try:
            r = case(args.dim, a, c, args.seconds, f, args.floor_mu, args.floor, args.flip)
        except SceneError as e:  # a height that is not a whole number of cells
            run.print(f"{a:>4g} {c:>5}  skipped: {e}")
            continue
        rows.append(r)
        run.print(f"{a:>4g} {c:>5} {f:>6g} {r['particles']:>7} {r['runout_front']:>6.2f} "
                  f"{r['runout_p99']:>6.2f} {r['runout_max']:>6.2f} {r['lube']:>5.2f} "
                  f"{r['front_vs_lube']:>+11.0%} {r['final_height_over_L0']:>5.2f} "
                  f"{r['frame_of_rest']:>5}"
                  + (f"  sectors {r['sector_p99_spread']:.1%}" if args.dim == 3 else ""))
        run.write(out, dict(rows=rows))
    run.print(f"wrote {path}")


if __name__ == "__main__":
    main()
