"""The ``diffgns`` command: simulate scenes and generate datasets.

    diffgns simulate --scene scenes/column_collapse.toml --frames 200 --out results/sim
    diffgns simulate --column --aspect-ratio 2 --friction-angle 30 --out results/col
    diffgns dataset --kind column --aspect-ratios 0.5 1 2 --friction-angles 25 35 45 \
        --frames 320 --out data/columns.h5
    diffgns dataset --kind squares --n 20 --frames 320 --out data/squares.h5
"""
from __future__ import annotations

import argparse
import json
import sys

from .errors import SceneError, UnstableError


def _simulate(args) -> int:
    from .scene_builders import column_collapse
    from .scene_io import load_scene
    from .simulate import run_mpm, write_outputs

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
    from .datagen import generate_columns, generate_squares

    if args.kind == "column":
        path = generate_columns(args.out, args.aspect_ratios, args.friction_angles, args.frames,
                                width=args.width, cells_across=args.cells_across,
                                batch=args.batch)
    else:
        path = generate_squares(args.out, args.n, args.frames, seed=args.seed, dx=args.dx)
    print(f"dataset written to {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="diffgns", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)

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

    d = sub.add_parser("dataset", help="generate an HDF5 training set with the MPM (resumable)")
    d.add_argument("--kind", choices=["column", "squares"], required=True)
    d.add_argument("--out", required=True, help="output .h5 file (resumes if it exists)")
    d.add_argument("--frames", type=int, default=320)
    d.add_argument("--aspect-ratios", type=float, nargs="+", default=[0.5, 1.0, 2.0, 3.0])
    d.add_argument("--friction-angles", type=float, nargs="+", default=[25.0, 35.0, 45.0])
    d.add_argument("--width", type=float, default=0.1)
    d.add_argument("--cells-across", type=int, default=10)
    d.add_argument("--batch", type=int, default=4, help="friction angles rolled out together")
    d.add_argument("--n", type=int, default=10, help="number of square-flow trajectories")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--dx", type=float, default=0.02)
    d.set_defaults(func=_dataset)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (SceneError, UnstableError) as e:
        print(f"diffgns: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
