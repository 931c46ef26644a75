"""Recover pair-force laws from a graph network's messages by symbolic regression.

    python examples/symbolic_regression.py                     # both laws, shipped networks
    python examples/symbolic_regression.py --law spring --train --train-steps 12000

Simulates 10-body systems (contact springs k = 100 N/m; an inverse-square law), loads (or
trains) the L1-regularised message network, tests that its top message components are linear
in the true force, and fits them with pyoperon. Writes fronts.md, front.png and results.json
per law under --out. Same as ``diffgns symbolic``. Exit status 1 if a law was not recovered
(the check's relative tolerance, 1%, and its rule are printed).

Each search runs a fixed budget, --sr-generations (200) generations of --sr-population (1000),
with pyoperon seeded by --seed and one thread: the same expressions and constants on any
machine speed or load. --sr-max-seconds is a safety cap that stops with an error.
"""
import argparse
import sys

from diffgns.interpret.pipeline import add_arguments, main

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(parser)
    sys.exit(main(parser.parse_args()))
