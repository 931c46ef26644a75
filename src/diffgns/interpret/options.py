"""Options of ``diffgns symbolic`` (and ``examples/symbolic_regression.py``), kept light.

No JAX, flax or pyoperon import here, so that ``diffgns symbolic --help`` and its argument
errors print at once; :mod:`diffgns.interpret.pipeline` (heavy) checks that the laws and
variants named here are the ones it defines.
"""
from __future__ import annotations

from diffgns.models import models_root

LAWS = ("spring", "inverse_square")
"""Force laws of the n-body systems (:data:`diffgns.interpret.pipeline.SYSTEMS`)."""
VARIANT_NAMES = ("l1", "bottleneck")
"""Message-network variants (:data:`diffgns.interpret.pipeline.VARIANTS`)."""
SR_GENERATIONS = 200
SR_POPULATION = 1000
SR_MAX_SECONDS = 3600.0


def add_arguments(parser) -> None:
    """Command-line options of ``diffgns symbolic`` / ``examples/symbolic_regression.py``."""
    parser.add_argument("--law", choices=[*LAWS, "both"], default="both",
                        help="force law to recover (default: both)")
    parser.add_argument("--out", default="results/symbolic",
                        help="output folder: <out>/<law>/fronts.md, front.png, results.json")
    parser.add_argument("--data-dir", default="data/nbody",
                        help="n-body datasets, generated (seeded) if missing")
    parser.add_argument("--variant", choices=sorted(VARIANT_NAMES), default="l1",
                        help="message network: L1-penalised, dimension 100 (models/"
                             "message_net_<law>_l1), or bottleneck, dimension 2 "
                             "(models/message_net_<law>)")
    parser.add_argument("--models", default=str(models_root()),
                        help="folder holding the shipped message networks")
    parser.add_argument("--train", action="store_true",
                        help="train a new message network instead of loading the shipped one "
                             "(its recipe: 100,000 steps for l1, 8,000 for bottleneck)")
    parser.add_argument("--train-steps", type=int, default=None,
                        help="train this many steps in one stage instead of the recipe")
    parser.add_argument("--sr-samples", type=int, default=5000,
                        help="test edges given to each symbolic regression (default 5000)")
    parser.add_argument("--sr-generations", type=int, default=SR_GENERATIONS,
                        help=f"generations per search (default {SR_GENERATIONS}); the search "
                             "budget is a count, so the answer does not depend on the machine")
    parser.add_argument("--sr-population", type=int, default=SR_POPULATION,
                        help=f"expressions per generation (default {SR_POPULATION})")
    parser.add_argument("--sr-max-seconds", type=float, default=SR_MAX_SECONDS,
                        help=f"safety cap per search in s (default {SR_MAX_SECONDS:g}): a "
                             "search reaching it stops the command with an error instead of "
                             "returning a machine-dependent answer")
    parser.add_argument("--threads", type=int, default=1,
                        help="pyoperon threads (default 1; results are reproducible with 1 "
                             "and depend on the count, as on --seed)")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of every random choice: edge sampling and the searches")
