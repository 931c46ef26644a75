"""The inversion table: friction angle recovered from an observed MPM runout, over scenes.

    .venv/bin/python benchmarks/inverse_sweep.py [--model gns_cg16_pfn]
        [--aspect-ratios 0.5 1 1.5 2 2.5 3] [--scenes squares:5 obstacles:2 ...]
        [--frames 250] [--phis 20 25 30 35 40 45] [--simulators gns mpm] [--start-phi 45]
        [--max-iter 20] [--out inverse_sweep]

The scenes are columns (aspect ratio ``a``; the column of the model's training data:
``ColumnCase.from_model``, its box, width, MPM resolution, nodes and frame stride) and, with
``--scenes FAMILY:SEED``, random scenes of the generator
(:func:`diffgns.scene.families.random_scene`, ``--frames`` frames, the model's nodes and frame
stride; ``--aspect-ratios`` with no value for none). For every scene and every
true friction angle ``phi``, the observation is the MPM run at ``phi`` seen as the GNS
sees it (nodes, frames); ``phi`` is then recovered from the observed final runout (soft
maximum of the nodes' x, objective "runout"; ``--objective deposit``: the final deposit
profile) by the one inverse path of the package
(:func:`diffgns.inverse.job.make_simulator`, :func:`~diffgns.inverse.job.make_objective`,
:func:`~diffgns.inverse.job.solve`: Gauss-Newton on logit(phi / 90), exact gradients through
the checkpointed rollout), through each simulator of ``--simulators``.

Writes ``benchmarks/results/<out>.json`` (every row, with the load average and commit) and
``<out>.md`` (aspect ratio, true phi, recovered phi, error, iterations, seconds) after every
case, so an interrupted sweep keeps its rows, and a re-run with the same ``--out`` skips the
cases already done. The seconds are wall times of the whole job (observation excluded,
compiling included) on whatever machine state there was: indicative only, the load average
is recorded next to them.
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import protocol

RESULTS = Path(__file__).resolve().parent / "results"
TARGET_DEG = {"gns": 1.0, "mpm": 0.5, "hybrid": 1.0}  # issue 21's tolerances


def scene_label(row: dict) -> str:
    """"column a=1.5" or the ``FAMILY:SEED`` of a random scene, with the objective when it
    is not the runout."""
    label = row.get("scene") or f"column a={float(row['aspect_ratio']):g}"
    obj = row.get("objective", "runout")
    return label if obj == "runout" else f"{label} ({obj})"


def key(row: dict) -> tuple:
    return (row["simulator"], scene_label(row), float(row["true_phi"]))


def markdown(rows: list[dict], model: str) -> str:
    """The table of ``rows`` (one line per simulator, aspect ratio and true phi)."""
    lines = [f"Friction angle recovered from an observed MPM run: its runout, or the "
             f"objective named beside the scene (model `{model}`; "
             "seconds: whole job incl. compile, indicative only, load average in brackets)",
             "", "| simulator | scene | true φ (°) | recovered φ (°) | error (°) | "
             "within target | iterations | seconds (load) |", "|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=key):
        if "failed" in r:
            lines.append(f"| {r['simulator']} | {scene_label(r)} | {r['true_phi']:g} | "
                         f"failed: {r['failed']} |||||")
            continue
        ok = abs(r["error_deg"]) <= TARGET_DEG[r["simulator"]]
        mark = " †" if extrapolated(r) else ""
        lines.append(
            f"| {r['simulator']} | {scene_label(r)} | {r['true_phi']:g} | "
            f"{r['recovered_phi']:.2f}{mark} | {r['error_deg']:+.2f} | "
            f"{'yes' if ok else 'no'} (±{TARGET_DEG[r['simulator']]:g}) | {r['iterations']} | "
            f"{r['seconds']:.0f} ({r['load_1min']:.1f}) |")
    done = [r for r in rows if "failed" not in r]
    for sim in sorted({r["simulator"] for r in done}):
        errs = [abs(r["error_deg"]) for r in done if r["simulator"] == sim]
        n_ok = sum(e <= TARGET_DEG[sim] for e in errs)
        lines += ["", f"{sim}: {n_ok}/{len(errs)} cases within ±{TARGET_DEG[sim]:g}°; "
                  f"mean |error| {sum(errs) / len(errs):.2f}°, max {max(errs):.2f}°"]
    if any(extrapolated(r) for r in done):
        lines += ["", "† outside the friction angles of the model's training data (the run's "
                  "warning): the network's material input was extrapolated"]
    return "\n".join(lines) + "\n"


def extrapolated(row: dict) -> bool:
    """Whether a row's recovered angle lies outside its model's training range (the warning
    of :meth:`~diffgns.inverse.simulators.GNSSimulator.parameter_warnings`)."""
    return bool(row.get("parameter_warnings"))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default=None, help="GNS model (default: the inverse default)")
    ap.add_argument("--aspect-ratios", type=float, nargs="*",
                    default=[0.5, 1.0, 1.5, 2.0, 2.5, 3.0])
    ap.add_argument("--scenes", nargs="*", default=[], metavar="FAMILY:SEED",
                    help="random scenes of diffgns.scene.families (e.g. squares:5)")
    ap.add_argument("--frames", type=int, default=250, help="MPM frames of a random scene")
    ap.add_argument("--objective", default="runout",
                    help="diffgns.inverse.job objective (runout, deposit, ...)")
    ap.add_argument("--phis", type=float, nargs="+", default=[20, 25, 30, 35, 40, 45])
    ap.add_argument("--simulators", nargs="+", default=["gns"],
                    choices=["gns", "mpm", "hybrid"])
    ap.add_argument("--start-phi", type=float, default=45.0,
                    help="start of every inversion, deg (a true phi equal to it starts at "
                         "35 deg instead)")
    ap.add_argument("--max-iter", type=int, default=20)
    ap.add_argument("--step-tol", type=float, default=0.01, help="deg")
    ap.add_argument("--gradient", default="auto", choices=["auto", "ad", "fd"],
                    help="diffgns.inverse.optimize's gradient (auto: AD, then differences "
                         "over 1%% of phi from the best point once a step raises the loss)")
    ap.add_argument("--scan", type=float, nargs=3, default=None, metavar=("LO", "HI", "N"),
                    help="start each inversion from the lowest loss of N friction angles "
                         "from LO to HI deg (forward runs) instead of --start-phi alone")
    ap.add_argument("--starts", type=int, default=1,
                    help="with --scan: refine this many of the lowest scan points, keep the "
                         "lowest end")
    ap.add_argument("--schedule", default=None,
                    help="the hybrid's schedule, a name of hybrid_pareto.py (K2M8:S0.1, "
                         "K2M10:W5, ...; default: the inversion's own, HybridSimulator's)")
    ap.add_argument("--out", default="inverse_sweep", help="results/<out>.json and .md")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "inverse_sweep")  # load, steal, commit; refuses if loaded

    from diffgns.inverse.job import make_objective, make_simulator, solve
    from diffgns.inverse.observation import SceneObservation
    from diffgns.inverse.simulators import (
        DEFAULT_MODEL,
        Column,
        ColumnCase,
        load_gns,
        model_info,
    )
    from diffgns.scene.families import random_scene

    scan = None
    if args.scan:
        lo, hi, n = args.scan
        from diffgns.inverse.parameters import parse_scan

        scan = dict([parse_scan(f"friction_angle={lo}:{hi}:{int(n)}")])
    model = args.model or DEFAULT_MODEL
    loaded = load_gns(model) if set(args.simulators) - {"mpm"} else None
    if args.schedule is not None:
        from hybrid_pareto import parse_schedule

        schedule = parse_schedule(args.schedule)
    else:
        schedule = None
    info = loaded[2] if loaded else model_info(model)
    RESULTS.mkdir(exist_ok=True)
    jpath, mpath = RESULTS / f"{args.out}.json", RESULTS / f"{args.out}.md"
    rows: list[dict] = json.loads(jpath.read_text())["rows"] if jpath.exists() else []
    done = {key(r) for r in rows}
    work = Path(os.environ.get("TMPDIR", "/tmp")) / f"diffgns_{args.out}"
    cases = [(f"column a={a:g}", dict(aspect_ratio=a), lambda a=a: Column(
        ColumnCase.from_model(info, a))) for a in args.aspect_ratios]
    for spec in args.scenes:
        family, _, seed = spec.partition(":")
        if not seed.isdigit():
            ap.error(f"--scenes {spec!r}: use FAMILY:SEED, e.g. squares:5")
        cases.append((spec, dict(scene=spec), lambda f=family, n=int(seed): (
            SceneObservation.for_model(random_scene(f, n), info, args.frames, model=model))))
    import jax

    for label, fields, build in cases:
        jax.clear_caches()  # free the last scene's compiled programs (memory mappings)
        col = None
        for phi in args.phis:
            todo = [s for s in args.simulators
                    if key(dict(simulator=s, **fields, objective=args.objective,
                                true_phi=phi)) not in done]
            if not todo:
                continue
            col = col or build()
            truth = {"friction_angle": float(phi)}
            t0 = time.perf_counter()
            observed = col.observation(truth)
            t_obs = time.perf_counter() - t0
            start = args.start_phi if abs(args.start_phi - phi) > 1e-6 else 35.0
            for sim_kind in todo:
                theta0 = {"friction_angle": start}
                print(f"--- {sim_kind}: {label}, phi = {phi:g} (start {start:g}); "
                      f"observation {t_obs:.0f} s", flush=True)
                row = dict(simulator=sim_kind, **fields, objective=args.objective,
                           gradient=args.gradient, scan=args.scan, starts=args.starts,
                           schedule=args.schedule if sim_kind == "hybrid" else None,
                           true_phi=phi,
                           start_phi=start,
                           nodes=col.n_nodes, particles=col.scene.n_particles,
                           observation_s=t_obs)
                t1 = time.perf_counter()
                try:
                    sim = make_simulator(sim_kind, col, model, loaded=loaded,
                                         observed=observed, theta0=theta0,
                                         schedule=schedule)
                    objective = make_objective(args.objective, col, observed=observed)
                    tag = label.replace(" ", "_").replace(":", "_").replace("=", "")
                    s = solve(sim, objective, theta0, col, work / f"{sim_kind}_{tag}_{phi:g}",
                              max_iter=args.max_iter, step_tol=args.step_tol,
                              gradient=args.gradient, observed=observed, truth=truth,
                              label=sim_kind, t_start=t1, scan=scan,
                              starts=args.starts)
                    row.update(recovered_phi=s["recovered"]["friction_angle"],
                               error_deg=s["error_deg"], iterations=s["iterations"],
                               converged=s["converged"], stop_reason=s["stop_reason"],
                               seconds=s["wall_time_s"], compile_s=s["compile_s"],
                               warnings=s["warnings"], scan_losses=s["scan"],
                               parameter_warnings=s["parameter_warnings"],
                               starts=s["starts"])
                except Exception as e:  # noqa: BLE001 - a failed case is a row of the table
                    row["failed"] = f"{type(e).__name__}: {e}"[:200]
                    row["seconds"] = time.perf_counter() - t1
                row["load_1min"] = os.getloadavg()[0]
                rows.append(row)
                done.add(key(row))
                jpath.write_text(json.dumps(dict(
                    model=model, settings=vars(args), commit=_commit(), rows=rows,
                    protocol=run.metadata()),
                    indent=2))
                mpath.write_text(markdown(rows, model))
    mpath.write_text(markdown(rows, model))  # also when every case was done before
    print(markdown(rows, model))
    print(f"wrote {jpath} and {mpath}")


def _commit() -> str:
    import subprocess

    p = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                       text=True, cwd=Path(__file__).parent)
    return p.stdout.strip()


if __name__ == "__main__":
    main()
