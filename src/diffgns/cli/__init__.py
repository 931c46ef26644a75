"""The ``diffgns`` command.

    diffgns simulate --scene scenes/column_collapse.toml --frames 200 --out results/sim
    diffgns simulate --column --aspect-ratio 2 --friction-angle 30 --out results/col
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
runs, so ``diffgns --help`` stays fast. Errors at the edge (invalid scene, unsupported
scene for a model, unstable run) print ``diffgns: error: ...`` and exit with status 2.
"""
from __future__ import annotations

import argparse
import sys

from diffgns.cli import data, evaluate, invert, train

GROUPS = (data, train, evaluate, invert)


def _symbolic(args) -> int:
    from diffgns.interpret.pipeline import main as run_symbolic

    return run_symbolic(args)


def build_parser(argv=None) -> argparse.ArgumentParser:
    """The ``diffgns`` parser (``argv``: the symbolic command's options are added only when
    it is the command, as they import the symbolic-regression code)."""
    p = argparse.ArgumentParser(prog="diffgns", description="Differentiable MPM, GNS, hybrid "
                                "and inverse problems (run `diffgns <command> --help`).")
    sub = p.add_subparsers(dest="command", required=True)
    for group in GROUPS:
        group.register(sub)
    y = sub.add_parser("symbolic", help="recover n-body force laws from a message network "
                       "by symbolic regression")
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["symbolic"]:
        from diffgns.interpret.pipeline import add_arguments

        add_arguments(y)
    y.set_defaults(func=_symbolic)
    return p


def main(argv=None) -> int:
    from diffgns.errors import SceneError, UnstableError

    args = build_parser(argv).parse_args(argv)
    try:
        return args.func(args)
    except (SceneError, UnstableError) as e:
        print(f"diffgns: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
