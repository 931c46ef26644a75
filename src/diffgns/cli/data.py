"""``diffgns simulate`` (the MPM on a 2D or 3D scene, with animation, plots, VTK and HDF5;
:func:`diffgns.io.outputs.write_outputs` draws each dimension's figures) and
``diffgns dataset`` (HDF5 training sets from the MPM or the cylinder-flow CFD)."""
from __future__ import annotations

import json
from pathlib import Path

from diffgns.cli.checks import (
    box_size,
    check_dataset,
    check_simulate,
    count,
    finite,
    frames,
    granular_kw,
    positive,
    probability,
    squares_kw,
)


def _simulate(args) -> int:
    scene, L0 = check_simulate(args)  # before JAX is imported: a refusal comes at once
    from diffgns.io.outputs import run_mpm, write_outputs

    print(f"scene: {scene.n_particles} particles, grid {scene.grid_shape}, "
          f"{scene.substeps} substeps/frame (dt = {scene.substep_dt:.2e} s), "
          f"effects: {', '.join(sorted(scene.effects))}")
    traj, timing = run_mpm(scene, args.frames, dtype=args.dtype)
    summary = write_outputs(traj, scene, args.out, vtk_every=args.vtk_every, L0=L0,
                            extra=dict(timing=timing))
    print(json.dumps({k: v for k, v in summary.items() if k != "files"}, indent=2))
    from diffgns.clamp import clamp_warning

    if warn := clamp_warning(summary, "the MPM"):
        print(warn)
    print(f"outputs written to {args.out}")
    return 0


def shard_arg(text: str):
    """argparse type of ``--shard``: ``i/n`` with n >= 1 and 0 <= i < n."""
    import argparse

    from diffgns.errors import InputError
    from diffgns.shard import Shard

    try:
        return Shard.parse(text)
    except InputError as e:
        raise argparse.ArgumentTypeError(f"{e.problem}; {e.fix}") from None


def _dataset(args) -> int:
    from diffgns.errors import InputError

    if args.merge:
        return _merge(args)
    from diffgns.cli.train import join_if_asked

    joined = join_if_asked(args)
    from diffgns.shard import Shard

    shard = args.shard or (Shard.of_process() if joined else Shard())
    if shard.count > 1 and args.kind not in ("column", "squares", "granular"):
        raise InputError("--shard", f"--kind {args.kind} is generated in one process",
                         "shard --kind column, squares or granular, or drop "
                         "--shard/--distributed")
    check_dataset(args)
    from diffgns.io.shards import shard_path

    try:
        _generate(args, shard)
    except InputError as e:  # the writer's refusal of the --out file (e.g. another recipe)
        if e.field.startswith(str(args.out)) or e.field.startswith(str(shard_path(args.out,
                                                                                  shard))):
            raise InputError(f"--out {e.field}", e.problem, e.fix) from None
        raise
    except BaseException as e:
        if not isinstance(e, Exception):  # KeyboardInterrupt or Interrupted: say what is kept
            e.detail = _kept(shard_path(args.out, shard))  # type: ignore[attr-defined]
        raise
    if joined and args.shard is None and shard.count > 1:  # every process done: merge once
        from diffgns.distributed import barrier, is_main
        from diffgns.io.shards import merge_shards, shards_of

        barrier("diffgns-dataset-shards-written")
        if is_main():
            print(f"dataset written to {merge_shards(shards_of(args.out, shard.count), args.out)}")
        barrier("diffgns-dataset-merged")
    return 0


def _merge(args) -> int:
    from diffgns.io.shards import merge_shards

    print(f"dataset written to {merge_shards(args.merge, args.out)}")
    return 0


def _kept(out: Path) -> str:
    """What an interrupted ``diffgns dataset`` left: the file and its trajectory count."""
    from diffgns.io.files import partial_path, trajectory_count

    for path in (out, partial_path(out)):
        if path.exists():
            n = trajectory_count(path)
            noun = "trajectory" if n == 1 else "trajectories"
            return f"{n} finished {noun} kept in {path}; run the same command to resume"
    return "no trajectory was finished; nothing written"


def _generate(args, shard) -> int:
    if args.kind == "cylinder":
        return _dataset_cylinder(args)
    if args.kind == "granular":  # issue 21: random scenes of every family
        from diffgns.io.families_data import generate_families

        path = generate_families(args.out, args.families, args.n, args.frames, seed=args.seed,
                                 shard=shard, **granular_kw(args))
        print(f"dataset written to {path}")
        return 0
    from diffgns.io.datagen import generate_columns, generate_squares

    if args.kind == "column":
        path = generate_columns(args.out, args.aspect_ratios, args.friction_angles, args.frames,
                                width=args.width, cells_across=args.cells_across,
                                batch=args.batch, domain_length=args.domain_length,
                                domain_height=args.domain_height, shard=shard,
                                dim=getattr(args, "dim", 2))
    else:
        path = generate_squares(args.out, args.n, args.frames, seed=args.seed, shard=shard,
                                **squares_kw(args))
    print(f"dataset written to {path}")
    return 0


def _cylinder_refusal(msg: str):
    """An InputError naming the option of a CylinderSampling/CylinderRun message."""
    import re

    from diffgns.errors import InputError

    m = (re.search(r"Cylinder(?:Sampling|Run)\.(\w+)", msg)
         or re.search(r"\b(\w+_range)\b", msg))
    name = m.group(1) if m else ""
    option = "--frames" if name == "n_frames" else "--" + name.replace("_", "-")
    return InputError(option if m else "--kind cylinder", msg,
                      "see `diffgns dataset --help` for the units and defaults")


def _dataset_cylinder(args) -> int:
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
        raise _cylinder_refusal(str(e)) from None
    path = generate_cylinder(Path(args.out), args.n, seed=args.seed, sampling=sampling,
                             run=run, recipe=_cylinder_recipe(args), staged=True)
    print(f"dataset written to {path}")
    return 0


def _cylinder_recipe(args) -> dict:
    """The fingerprint of a cylinder-flow dataset: every option that shapes its trajectories
    (not ``--n``: trajectory i depends on the seed and i alone, so a resume may add more)."""
    names = ("seed", "frames", "re_range", "u_max_range", "radius_range", "cx_range",
             "cy_range", "frame_dt", "spinup", "size_cylinder", "size_far", "grading",
             "size_wake", "cfl")
    return dict(kind="cylinder", **{k: getattr(args, k) for k in names})


def register(sub) -> None:
    """Add the ``simulate`` and ``dataset`` parsers to ``sub``."""
    s = sub.add_parser("simulate", help="run the MPM on a scene and write animation, plots, "
                       "VTK and HDF5")
    src = s.add_mutually_exclusive_group(required=True)
    src.add_argument("--scene", help="scene TOML file, 2D or 3D (a domain with three axes; "
                     "see scenes/); a 3D run writes a 3D animation and a top view and radial "
                     "profile of the deposit")
    src.add_argument("--column", action="store_true",
                     help="a granular column collapse set by the column options below")
    s.add_argument("--width", type=finite, default=0.1, help="column width, m (default 0.1)")
    s.add_argument("--aspect-ratio", type=finite, default=2.0,
                   help="column height / width, dimensionless (default 2)")
    s.add_argument("--friction-angle", type=finite, default=30.0,
                   help="friction angle of the sand, degrees in (0, 90) (default 30)")
    s.add_argument("--cells-across", type=count, default=10,
                   help="grid cells across the column width, count (default 10)")
    s.add_argument("--frames", type=frames, default=200,
                   help="frames to simulate, count >= 2 (frame dt from the scene, 2.5 ms for "
                   "--column) (default 200)")
    s.add_argument("--dtype", default=None, choices=["float32", "float64"],
                   help="floating-point precision (default: JAX's, float32 unless "
                   "JAX_ENABLE_X64 is set)")
    s.add_argument("--vtk-every", type=count, default=10,
                   help="write a VTK file every this many frames, count (default 10)")
    s.add_argument("--out", default="results/simulate",
                   help="output folder, created (default results/simulate)")
    s.set_defaults(func=_simulate)

    d = sub.add_parser("dataset", help="generate an HDF5 training set with the MPM or, for "
                       "--kind cylinder, the cylinder-flow CFD (resumable)")
    what = d.add_mutually_exclusive_group(required=True)
    what.add_argument("--merge", nargs="+", metavar="SHARD", default=None,
                      help="merge the shard files of --shard 0/n .. n-1/n (all of them, one "
                      "recipe) into --out, identical to a one-process run")
    what.add_argument("--kind", choices=["column", "squares", "granular", "cylinder"],
                   help="column collapses over (aspect ratio x friction angle), "
                   "random granular squares, random scenes of the granular --families, or "
                   "cylinder flows")
    d.add_argument("--families", nargs="+", default=["squares", "columns", "obstacles",
                   "collision"], help="granular: scene families, round-robin (repeat one to "
                   "weight it); the held-out compositions column_pair and column_hit are "
                   "for test sets (default squares columns obstacles collision)")
    d.add_argument("--boxes", type=box_size, nargs="+", default=None, metavar="LxH",
                   help="granular: boxes drawn from, LENGTHxHEIGHT in m, multiples of "
                   "0.0125 m (default 0.8x0.35 0.6x0.5; a held-out longer box: 1.4x0.35)")
    d.add_argument("--young-modulus", type=positive, default=None, metavar="PA",
                   help="granular: the sand's Young's modulus E in Pa, > 0 (default 2e6; the "
                   "MPM's substep shrinks as 1/sqrt(E), so 2e7 costs ~3.2x the substeps)")
    d.add_argument("--flip", type=probability, default=None, metavar="F",
                   help="granular: the MPM's FLIP fraction Scene.flip in [0, 1] (default 0: "
                   "APIC alone; 0.99 keeps the answer nearly independent of the substep)")
    d.add_argument("--out", required=True,
                   help="output .h5 file; built as <out>.partial and renamed when complete; "
                   "an existing file or .partial made by the same recipe is resumed")
    d.add_argument("--frames", type=frames, default=320,
                   help="frames per trajectory, count >= 2 (2.5 ms each for MPM kinds; "
                   "--frame-dt for cylinder) (default 320)")
    d.add_argument("--aspect-ratios", type=finite, nargs="+", default=[0.5, 1.0, 2.0, 3.0],
                   help="column: height / width ratios, dimensionless > 0 (default 0.5 1 2 3)")
    d.add_argument("--friction-angles", type=finite, nargs="+", default=[25.0, 35.0, 45.0],
                   help="friction angles, degrees in (0, 90); column: each one, squares: "
                   "uniform between their min and max (default 25 35 45)")
    d.add_argument("--dim", type=int, choices=[2, 3], default=2,
                   help="column: 2 (a column against a wall) or 3 (an axisymmetric cylinder "
                   "of radius --width; trajectories (T, N, 3)) (default 2)")
    d.add_argument("--width", type=finite, default=0.1,
                   help="column width L0, m; with --dim 3 the cylinder's radius R0 "
                   "(default 0.1)")
    d.add_argument("--cells-across", type=count, default=10,
                   help="column: grid cells across the width (3D: the radius), count "
                   "(default 10)")
    d.add_argument("--domain-length", type=finite, default=None,
                   help="fixed box length, m (default: from the runout of each column; "
                   "squares: with --domain-height, else a 1 m box)")
    d.add_argument("--domain-height", type=finite, default=None,
                   help="fixed box height, m (default: 1.1 x column height + 2 cells)")
    d.add_argument("--batch", type=count, default=4,
                   help="column: friction angles rolled out together, count (memory; "
                   "default 4)")
    d.add_argument("--n", type=count, default=10,
                   help="squares/cylinder: number of trajectories, count (default 10)")
    d.add_argument("--seed", type=int, default=0,
                   help="squares/cylinder: random seed, integer (default 0)")
    d.add_argument("--dx", type=finite, default=0.02,
                   help="squares: grid cell size, m (default 0.02)")
    d.add_argument("--size", type=finite, default=0.2,
                   help="squares: side of each square, m, a multiple of --dx (default 0.2)")
    c = d.add_argument_group("cylinder flow (--kind cylinder; ranges are MIN MAX, SI units)")
    c.add_argument("--re-range", type=finite, nargs=2, default=[80.0, 160.0],
                   help="Reynolds number Ubar D / nu, dimensionless (default 80 160)")
    c.add_argument("--u-max-range", type=finite, nargs=2, default=[1.0, 2.0],
                   help="peak inflow speed Um, m/s (nu follows from Re) (default 1 2)")
    c.add_argument("--radius-range", type=finite, nargs=2, default=[0.04, 0.06],
                   help="cylinder radius, m (default 0.04 0.06)")
    c.add_argument("--cx-range", type=finite, nargs=2, default=[0.15, 0.35],
                   help="cylinder centre x, m (default 0.15 0.35)")
    c.add_argument("--cy-range", type=finite, nargs=2, default=[0.16, 0.25],
                   help="cylinder centre y, m (default 0.16 0.25)")
    c.add_argument("--frame-dt", type=finite, default=0.01,
                   help="time between frames, s (default 0.01)")
    c.add_argument("--spinup", type=finite, default=35.0,
                   help="simulated time before the first stored frame, in units of D / Ubar "
                   "(default 35)")
    c.add_argument("--size-cylinder", type=finite, default=0.008,
                   help="mesh edge length at the cylinder, m (default 0.008)")
    c.add_argument("--size-far", type=finite, default=0.035,
                   help="largest mesh edge length, m (default 0.035)")
    c.add_argument("--grading", type=finite, default=0.25,
                   help="mesh size growth, m/m (default 0.25)")
    c.add_argument("--size-wake", type=finite, default=0.014,
                   help="mesh edge length along 1 m of wake behind the cylinder, m (0: none; "
                   "default 0.014)")
    c.add_argument("--cfl", type=finite, default=0.15,
                   help="largest Um dt / h_min, dimensionless (sets the CFD time step; "
                   "default 0.15)")
    d.add_argument("--shard", type=shard_arg, default=None, metavar="I/N",
                   help="column/squares/granular: make only shard I of N (every N-th unit of "
                   "work) into "
                   "<out stem>.shard-I-of-N.h5, resumable; merge with --merge (default: "
                   "all, or this process's share under --distributed/--coordinator)")
    from diffgns.cli.train import add_distributed_arguments

    add_distributed_arguments(d)
    d.set_defaults(func=_dataset)
