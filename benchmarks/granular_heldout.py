"""Held-out accuracy of a particle GNS per scene family (issue 21's tables).

    .venv/bin/python benchmarks/granular_heldout.py --model runs/general/s8/model \
        --data data/granular_test.h5 [--n 24] [--families squares ...] [--out granular_heldout]

Rolls the model out from the first ``history + 1`` frames of every trajectory of ``--data``
(each in its own box, with its obstacles: :meth:`GNS.for_scene`-equivalent
``rollout_reference``) and scores it against the MPM (:func:`diffgns.graph.evaluate.score`):
runout from the back of the initial mass in the flow's direction (``flow_runout``), final
position error relative to the mean displacement (per node, and under the best one-to-one
matching of the final nodes: ``matched``, correspondence-free, reported beside), inside the
domain, finite, final kinetic energy (and "moving": cases still moving where the MPM has come
to rest, :data:`~diffgns.graph.evaluate.REST_KE_PER_KG`), and the positions the rollout
clamped into the box
(``clamped``: count, in how many cases; a clamped position left the domain, so the family
then misses the targets even when ``outside`` is 0).
:func:`~diffgns.graph.evaluate.per_family` gives the table per family (from the dataset's
``family`` attributes) against the targets of issue 21 (5% and 5% per case).
Accuracy alone by default: the protocol records the load but never refuses the run. With
``--timed ROUNDS`` each case's cost per simulated second is also measured against the MPM
at its stable dt on the case's own scene (redrawn from the stored family and scene seed and
checked against the stored particle count), in ``ROUNDS`` interleaved rounds
(``gns_accuracy_speed.py``'s calls and ratio: compile apart, block_until_ready, median of the
per-round ratios); then the protocol refuses a loaded machine. Draw the held-out set (``make
granular-test-data``) after the model is frozen.

Writes ``benchmarks/results/<out>.json`` (every row and the table) and prints the table.
"""
from __future__ import annotations

import argparse

import numpy as np
import protocol


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--model", required=True, help="model folder or shipped name")
    ap.add_argument("--data", required=True, help="held-out dataset (.h5 with families)")
    ap.add_argument("--n", type=int, default=None, help="first n trajectories only")
    ap.add_argument("--families", nargs="+", default=None, metavar="FAMILY",
                    help="only the trajectories of these families (after --n); rows keep "
                         "their case numbers in the file")
    ap.add_argument("--out", default="granular_heldout.json")
    ap.add_argument("--timed", type=int, default=0, metavar="ROUNDS",
                    help="also time GNS against the stable-dt MPM, ROUNDS interleaved rounds")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "granular_heldout", timed=args.timed > 0)

    from diffgns.graph.data import load_trajectories
    from diffgns.graph.evaluate import TARGETS, evaluate, per_family
    from diffgns.graph.train_loop import load_model
    from diffgns.io.families_data import read_families

    gns, params, info = load_model(args.model)
    trajs, _ = load_trajectories(args.data, int(info.get("factor", 1)),
                                 int(info.get("frame_stride", 1)))
    families = list(read_families(args.data).values())
    keep = select_cases(families, args.n, args.families)
    trajs, families = [trajs[i] for i in keep], [families[i] for i in keep]
    res = evaluate(gns, params, trajs)
    for row, fam, i in zip(res["rows"], families, keep):
        row.update(family=fam, case=i)
    if args.timed:
        drawn = samples(args.data)
        for row, ref, i in zip(res["rows"], trajs, keep):
            sample = drawn[i]
            row.update(speed_of_case(gns, params, ref, sample, args.timed))
            run.print(f"case {row['case']:>2} {row['family']:<10}: GNS "
                      f"{row['gns_s_per_sim_s']:.3f}, MPM {row['mpm_stable_s_per_sim_s']:.3f} "
                      f"s per simulated s ({row['mpm_substeps_stable']} substeps per frame); "
                      f"GNS {row['speedup_vs_mpm_stable']:.1f}x cheaper")
    table = per_family(res["rows"], families)
    run.print(f"{'family':<12} {'cases':>5} {'runout mean/max':>16} {'pos err mean/max':>17} "
              f"{'matched mean/max':>17} {'outside':>7} {'clamped':>12} {'NaN':>4} {'moving':>6} "
              f"{'met':>6}")
    m = "final_matched_error_rel_displacement"
    for fam, t in table.items():
        run.print(f"{fam:<12} {t['cases']:>5} "
                  f"{t['flow_runout_rel_error_mean']:>7.3f}/{t['flow_runout_rel_error_max']:<8.3f} "
                  f"{t['final_position_error_rel_displacement_mean']:>8.3f}/"
                  f"{t['final_position_error_rel_displacement_max']:<8.3f} "
                  f"{t.get(m + '_mean', np.nan):>8.3f}/{t.get(m + '_max', np.nan):<8.3f} "
                  f"{t['outside_domain']:>7} {t['clamped_positions']:>5} in "
                  f"{t['clamped_cases']:>3} "
                  f"{t['not_finite']:>4} {t['moving_when_ref_at_rest']:>6} "
                  f"{t['cases_met']:>3}/{t['cases']:<2}")
    run.print(f"targets per case: {TARGETS}; met: cases within them, inside, finite, never "
              f"clamped, at rest where the MPM is")
    if args.timed:
        for fam in dict.fromkeys(families):
            sp = [r["speedup_vs_mpm_stable"] for r in res["rows"] if r["family"] == fam]
            table[fam]["speedup_vs_mpm_stable_min"] = float(np.min(sp))
            table[fam]["speedup_vs_mpm_stable_median"] = float(np.median(sp))
            run.print(f"{fam:<12} GNS cheaper than the stable-dt MPM per simulated second: "
                      f"min {np.min(sp):.1f}x, median {np.median(sp):.1f}x")
    path = run.finish(args.out, dict(model=str(args.model), data=str(args.data),
                                     targets=TARGETS, rows=res["rows"], table=table))
    run.print(f"wrote {path}")


def select_cases(families: list[str], n: int | None, wanted: list[str] | None) -> list[int]:
    """Indices of the cases to score: the first ``n`` (all if None), then only those whose
    family is in ``wanted`` (all if None). An unknown family or an empty selection is refused."""
    idx = list(range(len(families) if n is None else min(n, len(families))))
    if wanted is None:
        return idx
    unknown = sorted(set(wanted) - set(families))
    if unknown:
        raise SystemExit(f"--families {unknown}: not in the dataset (it has "
                         f"{sorted(set(families))})")
    idx = [i for i in idx if families[i] in wanted]
    if not idx:
        raise SystemExit(f"--families {wanted}: no case among the first {n}")
    return idx


def samples(path) -> list[tuple]:
    """(family, scene seed, stored particle count, ranges) of every trajectory of ``path``."""
    import h5py

    from diffgns.io.families_data import read_families, read_ranges

    ranges = read_ranges(path)
    with h5py.File(path, "r") as f:
        return [(fam, int(f[k].attrs["scene_seed"]), int(f[k]["position"].shape[1]), ranges)
                for k, fam in read_families(path).items()]


def scene_of(sample: tuple):
    """The scene of ``sample = (family, scene seed, particles, ranges)`` (:func:`samples`),
    redrawn and checked against the stored particle count."""
    from diffgns.scene.families import random_scene

    family, seed, n_particles, ranges = sample
    scene = random_scene(family, seed, **ranges)
    if scene.n_particles != n_particles:
        raise SystemExit(f"{family}:{seed} redraws {scene.n_particles} particles, the data has "
                         f"{n_particles}: the dataset was drawn with other ranges")
    return scene


def speed_of_case(gns, params, ref, sample: tuple, rounds: int) -> dict:
    """``gns_accuracy_speed.stable_speed`` on the scene of ``sample`` (:func:`scene_of`)."""
    from gns_accuracy_speed import stable_speed

    return stable_speed(gns, params, ref, scene_of(sample), rounds)


if __name__ == "__main__":
    main()
