"""The ``diffgns`` command.

    diffgns simulate --scene scenes/column_collapse.toml --frames 200 --out results/sim
    diffgns simulate --column --aspect-ratio 2 --friction-angle 30 --out results/col
    diffgns simulate --scene scenes/axisymmetric_column_3d.toml --frames 120 --out results/axi3d
    diffgns dataset --kind column --aspect-ratios 0.5 1 2 --friction-angles 25 35 45 \\
        --frames 320 --out data/columns.h5
    diffgns dataset --kind squares --n 20 --frames 320 --out data/squares.h5
    diffgns dataset --kind cylinder --n 16 --seed 0 --frames 300 --out data/cylinder_train.h5
    diffgns train --data data/columns.h5 --coarse-grain 4 --frame-stride 2 --out runs/gns
    diffgns train --kind mesh --data data/cylinder_train.h5 --latent 64 --mp-steps 8 \\
        --out runs/meshnet
    diffgns average runs/a/model runs/b/model --out runs/avg
    diffgns rollout --model gns_columns --data data/columns_test.h5 --out results/gns
    diffgns rollout --model runs/meshnet/model --data data/cylinder_test.h5 --out results/mgn
    diffgns hybrid --model gns_columns --aspect-ratio 1.75 --out results/hybrid
    diffgns invert scenes/sand_into_obstacle.toml --fit friction_angle=40:0:90 \\
        --observation results/obstacle/trajectory.h5 --simulator mpm --out results/invert
    diffgns symbolic --law spring

One module per group of subcommands (:mod:`.data`, :mod:`.train`, :mod:`.evaluate`,
:mod:`.invert`); each registers its parsers and imports the library only when its command
runs, so ``diffgns --help`` imports no JAX. :mod:`.checks` is the validation layer: invalid
arguments, recipes, scenes and input files print one line ``diffgns: error: <field>: <what
is wrong>; <fix>`` and exit with status 2 before anything is written; a failed command
removes the output folders it created if they are empty; SIGINT/SIGTERM print one line and
exit with 130/143 (``diffgns dataset`` keeps its finished trajectories, resumable).
"""
from __future__ import annotations

import argparse
import os
import sys
from contextlib import nullcontext

from diffgns.cli import data, evaluate, invert, train
from diffgns.cli.checks import Parser, report_interrupt, signals_as_exceptions

GROUPS = (data, train, evaluate, invert)

DESCRIPTION = """Differentiable MPM, GNS, hybrid and inverse problems. Commands:
  simulate  run the MPM on a 2D or 3D scene (animation, plots, VTK, HDF5)
  dataset   generate an HDF5 training set (MPM columns or squares, cylinder-flow CFD)
  train     train a particle GNS or a MeshGraphNet
  average   average the weights of fine-tuned GNS models
  rollout   roll a trained model out against a reference trajectory
  hybrid    hybrid GNS/MPM run against the MPM and the GNS
  invert    fit scene parameters to an observation
  symbolic  recover n-body force laws by symbolic regression
Run `diffgns <command> --help` for the options (SI units: m, s, kg, Pa, degrees)."""

#: commands that handle SIGTERM themselves (a checkpoint at the current step)
_OWN_SIGTERM = ("train", "symbolic")


def _symbolic(args) -> int:
    from diffgns.interpret.pipeline import main as run_symbolic

    return run_symbolic(args)


def build_parser(argv=None) -> Parser:
    """The ``diffgns`` parser. ``argv`` is accepted for compatibility and unused: every
    subcommand's options, the symbolic command's too (:mod:`diffgns.interpret.options`),
    are defined without importing JAX."""
    p = Parser(prog="diffgns", description=DESCRIPTION,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True, metavar="<command>")
    for group in GROUPS:
        group.register(sub)
    y = sub.add_parser("symbolic", help="recover n-body force laws from a message network "
                       "by symbolic regression")
    from diffgns.interpret.options import add_arguments

    add_arguments(y)
    y.set_defaults(func=_symbolic)
    return p


def main(argv=None) -> int:
    """Run ``diffgns`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status
    (0, 2 for invalid input, 130/143 when interrupted) instead of raising SystemExit."""
    from diffgns.errors import InputError, Interrupted, SceneError, UnstableError
    from diffgns.io.files import new_dirs, remove_empty_dirs

    try:
        args = build_parser(argv).parse_args(argv)
    except SystemExit as e:  # --help (0) or a usage error (2, already printed)
        return e.code if isinstance(e.code, int) else int(e.code is not None)
    out = getattr(args, "out", None)
    created = new_dirs(out) if out else []
    rc = 1
    guard = nullcontext() if args.command in _OWN_SIGTERM else signals_as_exceptions()
    try:
        with guard:
            rc = args.func(args)
        return rc
    except (SceneError, UnstableError, InputError) as e:
        print(f"diffgns: error: {e}", file=sys.stderr)
        rc = 2
        return rc
    except (KeyboardInterrupt, Interrupted) as e:
        rc = report_interrupt(e, getattr(e, "detail", ""))
        if argv is None:  # the `diffgns` process: files are closed; skip the interpreter's
            remove_empty_dirs(created)  # finalisation, which can crash (SIGSEGV) while
            sys.stdout.flush()  # XLA computations interrupted mid-flight are torn down
            sys.stderr.flush()
            os._exit(rc)
        return rc
    finally:
        if rc != 0:
            remove_empty_dirs(created)


if __name__ == "__main__":
    sys.exit(main())
