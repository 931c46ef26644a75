"""How reproducible is the truth? The MPM against itself under perturbations far below any
modelling error (and one that is not: ``stiff``), scored exactly as a GNS is scored (issue
21's per-case targets).

    .venv/bin/python benchmarks/granular_truth_spread.py --families squares columns \
        obstacles collision --n 24 --seed 1 [--factor 16 --frame-stride 2] \
        [--perturb dt phi stiff jitter] [--jitter 0.25] [--young-modulus 2e6] [--flip 0] \
        [--out granular_truth_spread.json]

For every scene of ``diffgns dataset --kind granular --seed SEED --n N`` (the validation set
is seed 1, n 24; ``--young-modulus`` as the dataset's, default 2 MPa), or of a stored
family dataset (``--data PATH [--cases I ...]``: its scenes redrawn with its own ranges and
boxes, checked against its particle counts, as ``granular_heldout.py --timed`` does), the
MPM runs twice:
as generated, and perturbed by

- ``dt``: substeps 20% shorter (``--dt-factor``, default 0.8; the same model at another
  stable time step; a numerical perturbation of the kind any two correct solvers differ by;
  smaller fractions show how far the answer depends on the substep: with APIC alone it
  does not converge as the substep shrinks, docs/validation.md), or
- ``phi``: the friction angle 0.1 degrees higher (a tenth of the inversion tolerance), or
- ``stiff``: Young's modulus 10x higher, at that material's own stable time step (not a
  small perturbation: how much of the truth is set by the scenes' elastic stiffness, e.g.
  masses that rebound from an impact), or
- ``stiff_dt``: the substep of ``stiff`` at the scene's own E (the same number of substeps
  without the stiffer sand: what of ``stiff``'s spread is the substep count, not E).
- ``jitter``: every particle moved at frame 0 by a uniform random offset of up to
  ``--jitter`` particle spacings per axis (default 0.25), less its node's mean offset, so
  every node starts at exactly the same position and velocity: the same state for a GNS
  on these nodes, another arrangement of the particles within them. Its spread is the part
  of the truth a node-level model cannot know from its input (the nodes are scored with
  the unperturbed run's clusters).

Both trajectories are reduced to the GNS's nodes (``coarse_grain``: cluster means of
``factor`` particles fixed at frame 0, every ``frame_stride``-th frame) and the perturbed one
is scored against the unperturbed one with :func:`diffgns.graph.evaluate.score`, the very
function behind ``granular_heldout.py``'s tables. Also recorded per scene: the RMS and 99th
percentile distance of a particle from its node (cluster mean) at the last frame, m, i.e.
how far the particles one node stands for have scattered.

Reading: a target below the truth's own spread under ``dt`` cannot be met by any surrogate,
because it is below the disagreement of two equally valid MPM runs. Accuracy only (no
timing): the protocol records the load and never refuses.
"""
from __future__ import annotations

import argparse

import protocol

PERTURBATIONS = ("dt", "phi", "stiff", "stiff_dt", "jitter")


def node_spread(positions, factor: int) -> tuple[float, float]:
    """(RMS, 99th percentile) distance, m, of the particles of the last frame of
    ``positions`` (T, N, d) from their cluster means (clusters of frame 0)."""
    import numpy as np

    from diffgns.graph.data import cluster_means, coarse_grain_map

    cid = coarse_grain_map(positions[0], factor)
    last = np.asarray(positions[-1], np.float64)
    r = np.sqrt(((last - cluster_means(last, cid)[cid]) ** 2).sum(-1))
    return float(np.sqrt((r ** 2).mean())), float(np.percentile(r, 99))


def perturbed_scene(scene, how: str, dt_factor: float = 0.8):
    """``scene`` with the ``dt``, ``stiff`` or ``stiff_dt`` perturbation (``phi`` is a
    parameter, not a scene change: the scene itself is returned)."""
    from dataclasses import replace

    if how == "dt":
        return scene.replace(dt=dt_factor * scene.substep_dt)
    if how == "stiff":
        bodies = tuple(replace(b, material=replace(b.material, E=10 * b.material.E))
                       for b in scene.bodies)
        return scene.replace(bodies=bodies, dt=None)  # that material's own stable dt
    if how == "stiff_dt":
        return scene.replace(dt=perturbed_scene(scene, "stiff").substep_dt)
    return scene


def jittered(state, cid, amplitude: float, seed: int = 0):
    """``state`` (an ``MPMState``, x of shape (d, N) in m) with every particle moved by a
    uniform random offset in ``[-amplitude, amplitude]`` m per axis, less the mean offset of
    its cluster ``cid`` (N,): every cluster mean is unchanged (to float rounding)."""
    import jax.numpy as jnp
    import numpy as np

    from diffgns.graph.data import cluster_means

    x = np.asarray(state.x, np.float64).T
    off = np.random.default_rng(seed).uniform(-amplitude, amplitude, x.shape)
    off -= cluster_means(off, cid)[cid]
    return state.replace(x=jnp.asarray((x + off).T, state.x.dtype))


def perturbed_run(scene, how: str, n_frames: int, dt_factor: float = 0.8, cid=None,
                  jitter: float = 0.25):
    """MPM trajectory of ``scene`` perturbed by ``how`` (one of :data:`PERTURBATIONS`);
    ``jitter`` needs the clusters ``cid`` (N,) and takes ``jitter`` particle spacings."""
    from diffgns.mpm import MPM

    sim = MPM(perturbed_scene(scene, how, dt_factor))
    params, state = sim.params(), sim.init()
    if how == "phi":
        params = params.replace(friction_angle=params.friction_angle + 0.1)
    if how == "jitter":
        if cid is None:
            raise ValueError("perturbed_run: 'jitter' needs the clusters (cid)")
        side = round(scene.bodies[0].particles_per_cell ** (1.0 / state.x.shape[0]))
        state = jittered(state, cid, jitter * scene.dx / side)
    traj, _ = sim.run(params, state, n_frames)
    return traj


def scenes(args):
    """``(case index, family, scene seed, Scene)`` of ``--data`` (``--cases`` of it), or of
    the generator's draw ``--families --n --seed --young-modulus``."""
    if args.data is None:
        from diffgns.scene.recipes import family_scenes

        for i, (family, seed, scene, _) in enumerate(
                family_scenes(args.families, args.n, args.seed,
                              young_modulus=args.young_modulus)):
            yield i, family, seed, scene
        return
    from granular_heldout import samples, scene_of

    stored = samples(args.data)
    for i in (range(len(stored)) if args.cases is None else args.cases):
        if not 0 <= i < len(stored):
            raise SystemExit(f"--cases: {i} is not a trajectory of {args.data} "
                             f"({len(stored)} stored)")
        yield i, stored[i][0], stored[i][1], scene_of(stored[i])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--families", nargs="+",
                    default=["squares", "columns", "obstacles", "collision"])
    ap.add_argument("--n", type=int, default=24)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--frames", type=int, default=250)
    ap.add_argument("--factor", type=int, default=16, help="particles per node")
    ap.add_argument("--frame-stride", type=int, default=2)
    ap.add_argument("--perturb", nargs="+", choices=PERTURBATIONS, default=["dt", "phi"])
    ap.add_argument("--dt-factor", type=float, default=0.8,
                    help="the dt perturbation's substep, a fraction of the stable one (default "
                    "0.8; smaller values show how far the answer depends on the substep)")
    ap.add_argument("--jitter", type=float, default=0.25,
                    help="the jitter perturbation's largest offset per axis, in particle "
                    "spacings (default 0.25)")
    ap.add_argument("--flip", type=float, default=0.0,
                    help="Scene.flip of the unperturbed scenes (default 0: APIC alone, as the "
                    "datasets)")
    ap.add_argument("--young-modulus", type=float, default=2.0e6, metavar="PA",
                    help="the sand's E of the unperturbed scenes, as `diffgns dataset "
                    "--young-modulus` (default 2e6)")
    ap.add_argument("--data", default=None,
                    help="a stored family dataset (.h5): its scenes instead of --families/--n/"
                    "--seed/--young-modulus")
    ap.add_argument("--cases", nargs="+", type=int, default=None,
                    help="with --data: these trajectory indices only (default: all)")
    ap.add_argument("--out", default="granular_truth_spread.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "granular_truth_spread", timed=False)  # accuracy only

    import numpy as np

    from diffgns.graph.data import coarse_grain, coarse_grain_map
    from diffgns.graph.evaluate import TARGETS, per_family, score
    from diffgns.mpm import MPM

    rows: dict[str, list[dict]] = {p: [] for p in args.perturb}
    fams = []
    for i, family, seed, scene in scenes(args):
        scene = scene.replace(flip=args.flip)
        sim = MPM(scene)
        base, _ = sim.run(sim.params(), sim.init(), args.frames)
        cid = coarse_grain_map(np.asarray(base.positions[0]), args.factor)
        ref = coarse_grain(base, args.factor, args.frame_stride, cid=cid)
        rms, p99 = node_spread(np.asarray(base.positions), args.factor)
        fams.append(family)
        for how in args.perturb:
            other = coarse_grain(perturbed_run(scene, how, args.frames, args.dt_factor, cid,
                                               args.jitter),
                                 args.factor, args.frame_stride, cid=cid)
            row = score(other, ref)
            row.update(case=i, family=family, scene_seed=seed, perturbation=how,
                       node_spread_rms_m=rms, node_spread_p99_m=p99)
            rows[how].append(row)
            run.print(f"{i:3d} {family:<10} {how:<4} runout {row['flow_runout_rel_error']:.4f} "
                      f"position {row['final_position_error_rel_displacement']:.4f} "
                      f"node spread rms/p99 {rms * 1e3:.1f}/{p99 * 1e3:.1f} mm")
    tables = {how: per_family(r, fams) for how, r in rows.items()}
    for how, table in tables.items():
        run.print(f"\nMPM against itself, perturbation {how!r} "
                  f"(factor {args.factor}, frame stride {args.frame_stride}):")
        run.print(f"{'family':<12} {'cases':>5} {'runout mean/max':>16} "
                  f"{'pos err mean/max':>17} {'within targets':>15}")
        for fam, t in table.items():
            ok = sum(all(r[k] <= v for k, v in TARGETS.items())
                     for r, f in zip(rows[how], fams) if fam in (f, "all"))
            run.print(f"{fam:<12} {t['cases']:>5} "
                      f"{t['flow_runout_rel_error_mean']:>7.4f}/"
                      f"{t['flow_runout_rel_error_max']:<8.4f} "
                      f"{t['final_position_error_rel_displacement_mean']:>8.4f}/"
                      f"{t['final_position_error_rel_displacement_max']:<8.4f} "
                      f"{ok:>8}/{t['cases']}")
    path = run.finish(args.out, dict(families=args.families, n=args.n, seed=args.seed,
                                     data=args.data, cases=args.cases,
                                     young_modulus=args.young_modulus,
                                     dt_factor=args.dt_factor, flip=args.flip,
                                     jitter=args.jitter,
                                     factor=args.factor, frame_stride=args.frame_stride,
                                     targets=TARGETS, rows=rows, tables=tables))
    run.print(f"wrote {path}")


if __name__ == "__main__":
    main()
