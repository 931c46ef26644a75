"""``diffgns simulate`` (the MPM on a scene, with animation, plots, VTK and HDF5) and
``diffgns dataset`` (HDF5 training sets from the MPM or the cylinder-flow CFD)."""
from __future__ import annotations

import json


def _simulate(args) -> int:
    from diffgns.io.outputs import run_mpm, write_outputs
    from diffgns.scene.builders import column_collapse
    from diffgns.scene.files import load_scene

    if args.scene:
        scene, L0 = load_scene(args.scene), None
    else:
        scene = column_collapse(width=args.width, aspect_ratio=args.aspect_ratio,
                                friction_angle=args.friction_angle,
                                cells_across=args.cells_across)
        L0 = args.width
    print(f"scene: {scene.n_particles} particles, grid {scene.grid_shape}, "
          f"{scene.substeps} substeps/frame (dt = {scene.substep_dt:.2e} s), "
          f"effects: {', '.join(sorted(scene.effects))}")
    traj, timing = run_mpm(scene, args.frames, dtype=args.dtype)
    summary = write_outputs(traj, scene, args.out, vtk_every=args.vtk_every, L0=L0,
                            extra=dict(timing=timing))
    print(json.dumps({k: v for k, v in summary.items() if k != "files"}, indent=2))
    print(f"outputs written to {args.out}")
    return 0


def _dataset(args) -> int:
    if args.kind == "cylinder":
        return _dataset_cylinder(args)
    from diffgns.io.datagen import generate_columns, generate_squares

    if args.kind == "column":
        path = generate_columns(args.out, args.aspect_ratios, args.friction_angles, args.frames,
                                width=args.width, cells_across=args.cells_across,
                                batch=args.batch, domain_length=args.domain_length,
                                domain_height=args.domain_height)
    else:
        kw = dict(dx=args.dx, size=args.size,
                  friction_angle=(min(args.friction_angles), max(args.friction_angles)))
        if args.domain_length and args.domain_height:
            kw["domain"] = ((0.0, args.domain_length), (0.0, args.domain_height))
        path = generate_squares(args.out, args.n, args.frames, seed=args.seed, **kw)
    print(f"dataset written to {path}")
    return 0


def _dataset_cylinder(args) -> int:
    from diffgns.errors import SceneError
    from diffgns.mesh.datagen import CylinderRun, CylinderSampling, generate_cylinder

    try:
        sampling = CylinderSampling(re_range=tuple(args.re_range),
                                    u_max_range=tuple(args.u_max_range),
                                    radius_range=tuple(args.radius_range),
                                    cx_range=tuple(args.cx_range), cy_range=tuple(args.cy_range))
        run = CylinderRun(n_frames=args.frames, frame_dt=args.frame_dt, spinup=args.spinup,
                          size_cylinder=args.size_cylinder, size_far=args.size_far,
                          grading=args.grading, size_wake=args.size_wake or None,
                          cfl=args.cfl)
    except ValueError as e:
        raise SceneError(str(e)) from e
    path = generate_cylinder(args.out, args.n, seed=args.seed, sampling=sampling, run=run)
    print(f"dataset written to {path}")
    return 0


def register(sub) -> None:
    """Add the ``simulate`` and ``dataset`` parsers to ``sub``."""
    s = sub.add_parser("simulate", help="run the MPM on a scene and write animation, plots, VTK")
    src = s.add_mutually_exclusive_group(required=True)
    src.add_argument("--scene", help="scene TOML file")
    src.add_argument("--column", action="store_true", help="a granular column collapse")
    s.add_argument("--width", type=float, default=0.1, help="column width, m")
    s.add_argument("--aspect-ratio", type=float, default=2.0)
    s.add_argument("--friction-angle", type=float, default=30.0, help="degrees")
    s.add_argument("--cells-across", type=int, default=10, help="grid cells across the column")
    s.add_argument("--frames", type=int, default=200)
    s.add_argument("--dtype", default=None, choices=[None, "float32", "float64"])
    s.add_argument("--vtk-every", type=int, default=10)
    s.add_argument("--out", default="results/simulate")
    s.set_defaults(func=_simulate)

    d = sub.add_parser("dataset", help="generate an HDF5 training set with the MPM or, for "
                       "--kind cylinder, the cylinder-flow CFD (resumable)")
    d.add_argument("--kind", choices=["column", "squares", "cylinder"], required=True)
    d.add_argument("--out", required=True, help="output .h5 file (resumes if it exists)")
    d.add_argument("--frames", type=int, default=320)
    d.add_argument("--aspect-ratios", type=float, nargs="+", default=[0.5, 1.0, 2.0, 3.0])
    d.add_argument("--friction-angles", type=float, nargs="+", default=[25.0, 35.0, 45.0])
    d.add_argument("--width", type=float, default=0.1)
    d.add_argument("--cells-across", type=int, default=10)
    d.add_argument("--domain-length", type=float, default=None, help="fixed box length, m")
    d.add_argument("--domain-height", type=float, default=None, help="fixed box height, m")
    d.add_argument("--batch", type=int, default=4, help="friction angles rolled out together")
    d.add_argument("--n", type=int, default=10,
                   help="number of square-flow / cylinder-flow trajectories")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--dx", type=float, default=0.02, help="cell size of square flows, m")
    d.add_argument("--size", type=float, default=0.2, help="side of the squares, m")
    c = d.add_argument_group("cylinder flow (--kind cylinder; ranges are MIN MAX, SI units)")
    c.add_argument("--re-range", type=float, nargs=2, default=[80.0, 160.0],
                   help="Reynolds number Ubar D / nu")
    c.add_argument("--u-max-range", type=float, nargs=2, default=[1.0, 2.0],
                   help="peak inflow speed Um, m/s (nu follows from Re)")
    c.add_argument("--radius-range", type=float, nargs=2, default=[0.04, 0.06])
    c.add_argument("--cx-range", type=float, nargs=2, default=[0.15, 0.35],
                   help="cylinder centre x, m")
    c.add_argument("--cy-range", type=float, nargs=2, default=[0.16, 0.25],
                   help="cylinder centre y, m")
    c.add_argument("--frame-dt", type=float, default=0.01, help="time between frames, s")
    c.add_argument("--spinup", type=float, default=35.0,
                   help="simulated time before the first stored frame, in units of D / Ubar")
    c.add_argument("--size-cylinder", type=float, default=0.008,
                   help="mesh edge length at the cylinder, m")
    c.add_argument("--size-far", type=float, default=0.035, help="largest mesh edge length, m")
    c.add_argument("--grading", type=float, default=0.25, help="mesh size growth, m/m")
    c.add_argument("--size-wake", type=float, default=0.014,
                   help="mesh edge length along 1 m of wake behind the cylinder, m (0: none)")
    c.add_argument("--cfl", type=float, default=0.15,
                   help="largest Um dt / h_min (sets the CFD time step)")
    d.set_defaults(func=_dataset)
