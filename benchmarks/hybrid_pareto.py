"""Accuracy against wall time of the MPM, the GNS and hybrid GNS/MPM schedules (issue 5).

    python benchmarks/hybrid_pareto.py [--models gns_cg16_pf gns_cg16 ...]
        [--schedules GNS K2M5 K4M4 K8M2 ...] [--other-schedules GNS K4M4]
        [--cases 0.75:37.5 1.75:27.5 2.75:27.5 | squares:9100000 ...] [--rounds 3]
        [--threads both]

On held-out column collapses (aspect ratios and friction angles not in the GNS training set)
or random family scenes (``--cases squares:9100000 ...``: one generator scene at every
resolution, cells per 0.1 m), every simulator is scored against a fine MPM reference
(``--reference-cells`` cells): final runout error and the material-point position error
(mean over particles and frames; see ``diffgns.hybrid.compare``). The reference is not
timed; it is kept in ``--reference-cache`` (a file per case, resolution and frame count), so
that a quiet-machine run need not spend its window on it. Every run is also scored against
the MPM at the finest of ``--mpm-cells`` (16 cells: the simulator ``gns_cg16*`` were trained
to emulate and that their hybrids run): for those models that isolates the learned error,
which the hybrid's MPM frames correct, from the discretisation error that they share with
that MPM. A second Pareto front is drawn on these "own-MPM" errors (the 16-cell MPM itself,
with zero error, is not a candidate).

Timing (``benchmarks/protocol.py``, ``diffgns.timing``): every simulator of every case (the
MPMs alone, the GNS alone, the hybrid schedules; built by ``diffgns.hybrid.compare``, the
code ``diffgns hybrid`` runs) is first called once - compile, and for a learned simulator the
neighbour-list sizing, timed apart (``compile_s`` = that call - the median steady call) - and
then all of them are timed in the same ``--rounds`` interleaved rounds (one steady call of
each per round, the order reversed every other round, ``block_until_ready``, wall and CPU
time). A simulator's time is the median over rounds of its time summed over the cases; its
speed-up over the MPM at its model's own resolution is the median of the per-round ratios of
those sums. The Pareto front (mean position error against time) is marked in the table and
the plot beside the JSON (``<out>.png``).

The target of issue 5 is checked on both fronts and recorded under ``target``: a hybrid on
the front with less than half the error of the GNS it runs (same model, same reference).

Schedules are named ``GNS`` (the GNS alone after the MPM warm-up), ``K<k>M<m>`` (k MPM frames
after every m GNS frames), ``K<k>A<tol>`` (adaptive: a GNS segment of at most 20 frames ends
when the energy-balance deviation exceeds tol J/kg), with ``:reset``/``:reconstruct`` (the
hand-off of the deformation gradient; default carry), ``:rigid`` (particles follow their
node rigidly; default affine), ``:W<n>`` (n MPM warm-up frames instead of
``Schedule()``'s) and ``:S<f>`` (the warm-up lasts until the kinetic energy is below f of
its peak: ``Schedule.warmup_settle``), e.g. ``K4M4:reset``, ``GNS:rigid``, ``GNS:W100``
(the MPM for the first 100 frames, then the GNS alone), ``K2M8:S0.1``.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import protocol
from protocol import warm_up_jax

from diffgns import MPM, rollout_jit
from diffgns.graph.train_loop import load_model
from diffgns.hybrid.compare import (
    column_scene,
    family_scene,
    make_hybrid,
    model_cells,
    score_against,
)
from diffgns.hybrid.handoff import HANDOFFS, PARTICLE_MAPS
from diffgns.hybrid.simulator import DEFAULT_SCHEDULE, HybridParams, Schedule
from diffgns.timing import block, interleave, measure

CASES = ["0.75:37.5", "1.75:27.5", "2.75:27.5"]
QUICK_CASE = "1.75:27.5"
#: every schedule of the 2026-12-01 table (the first model's set before --schedules existed)
FULL = ["GNS", "K1M10", "K2M10", "K2M5", "K4M4", "K4M2", "K8M2", "K2A0.02", "K2A0.005",
        "K4M4:reset", "K4M4:reconstruct", "GNS:rigid", "K4M4:rigid"]
SHORT = ["GNS", "K2M5", "K4M4"]  # the other models' schedules in that table
QUICK = ["GNS", "K2M5", "K4M4"]
#: the default set (~10 min on a quiet 2-core machine): the simulators behind the published
#: speed-ups (gns_cg16_pf K=8 M=2, gns_cg16 K=4 M=4) and the MPMs of the front
DEFAULT_MODELS = ("gns_cg16_pf", "gns_cg16")
DEFAULT_OTHER = ("GNS", "K4M4")
DEFAULT_CACHE = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / \
    "diffgns" / "hybrid_pareto"


def parse_schedule(spec: str) -> Schedule:
    """A :class:`Schedule` from its name (see the module docstring): ``GNS``, ``K4M4``,
    ``K2A0.02``, with ``:reset``, ``:reconstruct``, ``:rigid`` or ``:W<n>``."""
    head, *opts = spec.split(":")
    kw: dict = {}
    for o in opts:
        if o in HANDOFFS:
            kw["handoff"] = o
        elif o in PARTICLE_MAPS:
            kw["particle_map"] = o
        elif re.fullmatch(r"W\d+", o):
            kw["warmup"] = int(o[1:])
        elif re.fullmatch(r"S0?\.\d+", o):
            kw["warmup_settle"] = float(o[1:])
        else:
            raise argparse.ArgumentTypeError(f"schedule {spec!r}: unknown option {o!r}")
    if head == "GNS":
        return Schedule(gns_frames=1, mpm_frames=0, **kw)
    m = re.fullmatch(r"K(\d+)M(\d+)", head)
    if m:
        return Schedule(gns_frames=int(m[2]), mpm_frames=int(m[1]), **kw)
    m = re.fullmatch(r"K(\d+)A([0-9.eE-]+)", head)
    if m:
        return Schedule(gns_frames=20, mpm_frames=int(m[1]), adaptive_tol=float(m[2]), **kw)
    raise argparse.ArgumentTypeError(f"schedule {spec!r}: use GNS, K<k>M<m> or K<k>A<tol>")


def schedule_name(sched: Schedule) -> str:
    """The name :func:`parse_schedule` reads back (``GNS``, ``K2M5``, ``K2M5:reset``, ...)."""
    if sched.mpm_frames == 0:
        name = "GNS"
    elif sched.adaptive_tol:
        name = f"K{sched.mpm_frames}A{sched.adaptive_tol:g}"
    else:
        name = f"K{sched.mpm_frames}M{sched.gns_frames}"
    default = Schedule()
    opts = [o for o, d in ((sched.handoff, default.handoff),
                           (sched.particle_map, default.particle_map)) if o != d]
    if sched.warmup != default.warmup:
        opts.append(f"W{sched.warmup}")
    if sched.warmup_settle is not None:
        opts.append(f"S{sched.warmup_settle:g}")
    return ":".join([name, *opts])


#: the default set: the GNS alone, the fixed K=8 M=2 and the library's default schedule
#: (``DEFAULT_SCHEDULE``, by its name: it follows the default when that changes)
DEFAULT_SCHEDULES = ("GNS", "K8M2", schedule_name(DEFAULT_SCHEDULE))


@dataclass(frozen=True)
class Case:
    """A case of the front: the column collapse of the models' training data (``a``, ``phi``:
    aspect ratio, friction angle in degrees) or a random family scene (``family``, ``seed``:
    :func:`diffgns.hybrid.compare.family_scene`, the same scene at every resolution)."""

    spec: str  # "1.75:27.5" or "squares:9100000"
    a: float = 0.0
    phi: float = 0.0
    family: str = ""
    seed: int = 0

    def scene(self, cells: int, info: dict):
        """The case's scene with the MPM at ``cells`` cells (across the column; per 0.1 m
        for a family scene)."""
        if self.family:
            return family_scene(self.family, self.seed, cells)
        return column_scene(self.a, self.phi, cells, info)


def parse_case(spec: str) -> Case:
    """``"a:phi"`` (a column of the models' training data) or ``"family:seed"`` (a random
    scene of :data:`diffgns.scene.families.ALL_FAMILIES`)."""
    from diffgns.scene.families import ALL_FAMILIES

    head, _, tail = spec.partition(":")
    if head in ALL_FAMILIES:
        if not tail.isdigit():
            raise argparse.ArgumentTypeError(f"case {spec!r}: use family:seed with an integer "
                                             "seed >= 0, e.g. squares:9100000")
        return Case(spec, family=head, seed=int(tail))
    try:
        a, phi = (float(v) for v in spec.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"case {spec!r}: use aspect_ratio:friction_angle (e.g. 1.75:27.5) or family:seed "
            f"with a family of {ALL_FAMILIES} (e.g. squares:9100000)") from None
    return Case(spec, a=a, phi=phi)


# ---------------------------------------------------------------- simulator calls
def mpm_source_hash() -> str:
    """Hash of the code a 2D column collapse runs (``diffgns/mpm``, the column builder and
    the scene types it uses, ``interface.py``): a cached reference made by other code is not
    reused."""
    import diffgns

    root = Path(diffgns.__file__).parent
    scene = [root / "scene" / f"{m}.py" for m in ("builders", "core", "elements", "materials",
                                                   "shapes")]
    files = sorted([*root.glob("mpm/**/*.py"), *scene, root / "interface.py"])
    h = hashlib.sha1()
    for f in files:
        h.update(f.relative_to(root).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def reference(case: Case, cells: int, info: dict, n_frames: int, stride: int,
              cache: Path | None) -> tuple[np.ndarray, dict]:
    """(positions (n_frames+1, N, 2) on GNS frames, record) of the untimed reference MPM, from
    ``cache`` when it holds this case (keyed by the scene, the frames and the hash of the MPM's
    source, :func:`mpm_source_hash`)."""
    scene = case.scene(cells, info)
    key = hashlib.sha1(json.dumps([case.spec, cells, n_frames, stride, repr(scene),
                                   scene.n_particles, scene.substeps, mpm_source_hash()]
                                  ).encode()).hexdigest()[:12]
    tag = case.spec.replace(":", "_")
    path = None if cache is None else cache / f"ref_{tag}_c{cells}_{key}.npz"
    if path is not None and path.exists():
        return np.load(path)["positions"], {"cache": str(path), "cached": True, "key": key}
    sim = MPM(scene)
    p, s = sim.params(), sim.init()
    t, frames = measure(lambda: rollout_jit(sim, p, s, n_frames=n_frames * stride)[0])
    pos = np.asarray(frames.positions)[::stride]
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, positions=pos)
    return pos, {"cache": None if path is None else str(path), "cached": False, "key": key,
                 "first_call_s": t.wall_s}


def mpm_call(scene, n_frames: int, stride: int):
    """Zero-argument call -> positions on GNS frames of the jitted MPM alone (not yet
    compiled)."""
    sim = MPM(scene)
    p, s = sim.params(), sim.init()
    return lambda: rollout_jit(sim, p, s, n_frames=n_frames * stride)[0].positions[::stride]


def hybrid_call(scene, gns, gp, info: dict, schedule: Schedule, n_frames: int):
    """(zero-argument steady call -> HybridResult, the first call's sample, its result) of a
    hybrid (or GNS-only) run of ``n_frames`` frames: the first call (compile + neighbour-list
    sizing) is made here, the steady call reuses the list it sized."""
    hyb = make_hybrid(scene, gns, info, schedule)  # diffgns.hybrid.compare: the walls too
    params = HybridParams(hyb.mpm.params(), gp)
    s = hyb.mpm.init()
    sync = lambda r: block((r.positions, r.nodes, r.mode))  # noqa: E731
    first, (res, start) = measure(lambda: hyb.run(params, s, n_frames),
                                  sync=lambda r: sync(r[0]))
    return (lambda: hyb.run(params, s, n_frames, state=start)[0]), sync, first, res


# ---------------------------------------------------------------- analysis
def pareto(points):
    """Indices of points (time, error) not dominated by any other (lower is better)."""
    keep = []
    for i, (t, e) in enumerate(points):
        if not any((t2 <= t and e2 <= e) and (t2 < t or e2 < e)
                   for j, (t2, e2) in enumerate(points) if j != i):
            keep.append(i)
    return keep


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--models", nargs="+", default=list(DEFAULT_MODELS),
                    help="model folders or shipped names; the first runs --schedules, the "
                         f"others --other-schedules (default {' '.join(DEFAULT_MODELS)})")
    ap.add_argument("--schedules", nargs="+", type=parse_schedule,
                    default=[parse_schedule(x) for x in DEFAULT_SCHEDULES],
                    help="schedules of the first model (see the module docstring; default "
                         f"{' '.join(DEFAULT_SCHEDULES)})")
    ap.add_argument("--other-schedules", nargs="+", type=parse_schedule,
                    default=[parse_schedule(x) for x in DEFAULT_OTHER],
                    help=f"schedules of the other models (default {' '.join(DEFAULT_OTHER)})")
    ap.add_argument("--cases", nargs="+", type=parse_case,
                    default=[parse_case(c) for c in CASES], metavar="A:PHI|FAMILY:SEED",
                    help="held-out columns of the models' training data (aspect ratio:"
                         "friction angle, deg) or random family scenes (family:seed; "
                         "resolutions are then cells per 0.1 m)")
    ap.add_argument("--frames", type=int, default=125, help="GNS frames (0.625 s)")
    ap.add_argument("--reference-cells", type=int, default=32)
    ap.add_argument("--reference-cache", default=str(DEFAULT_CACHE),
                    help="folder of the reference trajectories ('' : no cache)")
    ap.add_argument("--mpm-cells", type=int, nargs="+", default=[4, 8, 12, 16])
    ap.add_argument("--rounds", "--repeats", type=int, default=3, dest="rounds",
                    help="interleaved rounds (steady calls of every simulator)")
    ap.add_argument("--full", action="store_true",
                    help="the 2026-12-01 set: gns_cg16_pf gns_cg16 gns_columns gns_small, "
                         f"the first with {' '.join(FULL)}, the others {' '.join(SHORT)}")
    ap.add_argument("--quick", action="store_true",
                    help=f"one case ({QUICK_CASE}), schedules {' '.join(QUICK)} for all models")
    ap.add_argument("--prepare-references", action="store_true",
                    help="only compute the untimed references into --reference-cache (any "
                         "load) and exit; a quiet run then finds them there")
    ap.add_argument("--out", default="hybrid_pareto_rounds.json",
                    help="results file (the 2026-12-01 record hybrid_pareto.json is kept)")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    if args.full:
        args.models = ["gns_cg16_pf", "gns_cg16", "gns_columns", "gns_small"]
        args.schedules = [parse_schedule(x) for x in FULL]
        args.other_schedules = [parse_schedule(x) for x in SHORT]
    if args.quick:
        args.cases = [parse_case(QUICK_CASE)]
        args.schedules = args.other_schedules = [parse_schedule(x) for x in QUICK]
    run = protocol.start(args, "hybrid_pareto", timed=not args.prepare_references)
    warm_up_jax()
    models = {Path(m).name: load_model(m) for m in args.models}
    info0 = next(iter(models.values()))[2]  # all models share the training box
    stride = info0.get("frame_stride", 1)
    own_cells = max(args.mpm_cells)  # the resolution of the learned-error reference
    cache = Path(args.reference_cache) if args.reference_cache else None
    if args.prepare_references:
        for case in args.cases:
            _, rec = reference(case, args.reference_cells, info0, args.frames, stride, cache)
            run.print(f"reference {case.spec}: {rec}")
        return
    calls, syncs, firsts, rows, refs = {}, {}, {}, [], []
    for case in args.cases:
        ref, rec = reference(case, args.reference_cells, info0, args.frames, stride, cache)
        refs.append(dict(case=case.spec, cells=args.reference_cells, **rec))
        run.print(f"case {case.spec}: reference MPM {args.reference_cells} cells "
                  + ("from the cache" if rec["cached"] else "computed"), tag=False)
        case_rows, positions = [], {}
        for cells in args.mpm_cells:
            label = f"MPM {cells} cells"
            name = f"{label} @ {case.spec}"
            calls[name] = mpm_call(case.scene(cells, info0), args.frames, stride)
            syncs[name] = block
            firsts[name], x = measure(calls[name])
            positions[name] = np.asarray(x)
            case_rows.append(dict(name=name, case=case.spec, family="MPM", label=label,
                                  cells=cells, mpm_fraction=1.0))
        for i, (mname, (gns, gp, info)) in enumerate(models.items()):
            scene = case.scene(model_cells(info), info)
            for sched in (args.schedules if i == 0 else args.other_schedules):
                label = f"{sched.label} [{mname}]"
                name = f"{label} @ {case.spec}"
                calls[name], syncs[name], firsts[name], res = hybrid_call(
                    scene, gns, gp, info, sched, args.frames)
                positions[name] = np.asarray(res.positions)
                case_rows.append(dict(name=name, case=case.spec,
                                      family="GNS" if sched.mpm_frames == 0 else "hybrid",
                                      label=label, model=mname, own_cells=model_cells(info),
                                      mpm_fraction=res.mpm_fraction, **res.clamp_summary()))
        own = positions[f"MPM {own_cells} cells @ {case.spec}"]
        for r in case_rows:  # errors: against the reference and the own-resolution MPM
            x = positions[r["name"]]
            r.update(score_against(x, ref))
            o = score_against(x, own)
            r.update(own_mpm_runout_error=o["runout_error"],
                     own_mpm_position_error_m=o["mean_position_error_m"])
            run.print(f"{r['label']:52s} {case.spec} error "
                      f"{1e3 * r['mean_position_error_m']:.2f} mm, first call "
                      f"{firsts[r['name']].wall_s:.1f} s", tag=False)
        rows += case_rows
    run.print(f"{len(calls)} simulator runs, {args.rounds} interleaved rounds", tag=False)
    rounds = interleave(calls, max(1, args.rounds), sync=syncs, warmup=False)
    rounds.first.update(firsts)  # the first calls (compile, sizing) were made above
    for r in rows:
        t = rounds.summary(r["name"])
        r.update(seconds=t["median_s"], cpu_seconds=t["cpu_median_s"],
                 seconds_all=t["samples_s"], compile_s=t["compile_s"],
                 first_call_s=t["first_call_s"])
    table = aggregate(rows, rounds)
    target = check_target(table)
    payload = dict(cases=[c.spec for c in args.cases], frames=args.frames, own_mpm_cells=own_cells,
                   reference=refs, models=list(models),
                   schedules=[s.label for s in args.schedules],
                   other_schedules=[s.label for s in args.other_schedules],
                   rounds=max(1, args.rounds), rows=rows, table=table, target=target,
                   interleaved=rounds.to_json()["rounds"])
    print_table(run, table)
    for k, v in target.items():
        run.print(f"target against {k}: {v}")
    if run.mode == "both" and not run.pinned:
        payload["one_thread_pinned"] = child = run.pinned_child()
        one = {r["label"]: r.get("speedup_vs_own_mpm") for r in child.get("table", [])}
        for r in table:
            if r.get("speedup_vs_own_mpm") is not None:
                run.print(f"{r['label']} speed-up over the {r['own_mpm']}: "
                          + protocol.both_ratios(r["speedup_vs_own_mpm"], one.get(r["label"]),
                                                 child, 2))
    run.finish(args.out, payload, lambda p: plot(table, p.with_suffix(".png"),
                                                 args.reference_cells, own_cells))


def aggregate(rows, rounds):
    """One table row per simulator: errors averaged over the cases; time = median over the
    rounds of the time summed over the cases (wall and CPU); speed-up over the MPM at the
    model's own resolution = median of the per-round ratios of those sums."""
    labels = list(dict.fromkeys(r["label"] for r in rows))
    totals = {}
    for lab in labels:
        names = [r["name"] for r in rows if r["label"] == lab]
        totals[lab] = dict(wall=[sum(rd[n].wall_s for n in names) for rd in rounds.rounds],
                           cpu=[sum(rd[n].cpu_s for n in names) for rd in rounds.rounds])
    table = []
    for lab in labels:
        rs = [r for r in rows if r["label"] == lab]
        wall, cpu = totals[lab]["wall"], totals[lab]["cpu"]
        table.append(dict(label=lab, family=rs[0]["family"],
                          seconds=float(np.median(wall)), cpu_seconds=float(np.median(cpu)),
                          seconds_per_round=wall, cases=len(rs),
                          compile_s=float(sum(r["compile_s"] for r in rs)),
                          runout_error=float(np.mean([r["runout_error"] for r in rs])),
                          mean_position_error_m=float(np.mean(
                              [r["mean_position_error_m"] for r in rs])),
                          final_position_error_m=float(np.mean(
                              [r["final_position_error_m"] for r in rs])),
                          mpm_fraction=float(np.mean([r["mpm_fraction"] for r in rs]))))
        own = f"MPM {rs[0]['own_cells']} cells" if "own_cells" in rs[0] else None
        if own in totals:
            table[-1]["own_mpm"] = own
            table[-1]["speedup_vs_own_mpm"] = float(np.median(
                [o / t for o, t in zip(totals[own]["wall"], wall)]))
        if "own_mpm_position_error_m" in rs[0]:
            table[-1]["own_mpm_position_error_m"] = float(np.mean(
                [r["own_mpm_position_error_m"] for r in rs]))
            table[-1]["own_mpm_runout_error"] = float(np.mean(
                [r["own_mpm_runout_error"] for r in rs]))
    for key, err in (("pareto", "mean_position_error_m"),
                     ("pareto_own", "own_mpm_position_error_m")):
        # the own-MPM reference itself (zero error) is not a candidate of its own front
        cand = [i for i, r in enumerate(table) if r["family"] != "reference"
                and err in r and not (key == "pareto_own" and r[err] == 0.0)]
        front = pareto([(table[i]["seconds"], table[i][err]) for i in cand])
        for k, i in enumerate(cand):
            table[i][key] = k in front
    return table


def model_of(label: str) -> str | None:
    return label.rsplit("[", 1)[1].rstrip("]") if "[" in label else None


def check_target(table) -> dict:
    """Hybrid rows on each front with less than half the error of their model's GNS alone
    (same particle map): ``{reference: [{label, error_m, gns_error_m, ratio, seconds}]}``."""
    out = {}
    gns = {(model_of(r["label"]), "rigid" in r["label"]): r for r in table
           if r["family"] == "GNS"}
    for key, err, ref in (("pareto", "mean_position_error_m", "fine MPM reference"),
                          ("pareto_own", "own_mpm_position_error_m", "own-resolution MPM")):
        hits = []
        for r in table:
            base = gns.get((model_of(r["label"]), "rigid" in r["label"]))
            if r["family"] != "hybrid" or base is None or err not in r:
                continue
            ratio = r[err] / base[err]
            if r.get(key) and ratio < 0.5:
                hits.append(dict(label=r["label"], error_m=r[err], gns_error_m=base[err],
                                 ratio=ratio, seconds=r["seconds"]))
        out[ref] = hits
    return out


def print_table(run, table):
    run.print(f"{'simulator':52s} {'time s':>8s} {'CPU s':>7s} {'x own MPM':>9s} {'MPM %':>6s} "
              f"{'runout err':>10s} {'pos err mm':>10s} {'final mm':>9s} {'vs own MPM mm':>13s} "
              "front own-front")
    for r in table:
        own = r.get("own_mpm_position_error_m")
        own = f"{1e3 * own:13.2f}" if own is not None else f"{'':13s}"
        sp = r.get("speedup_vs_own_mpm")
        sp = f"{sp:9.2f}" if sp is not None else f"{'':9s}"
        run.print(f"{r['label']:52s} {r['seconds']:8.3f} {r['cpu_seconds']:7.2f} {sp} "
                  f"{100 * r['mpm_fraction']:6.0f} "
                  f"{r['runout_error']:10.3f} {1e3 * r['mean_position_error_m']:10.2f} "
                  f"{1e3 * r['final_position_error_m']:9.2f} {own} "
                  f"{'*' if r.get('pareto') else '':5s} {'*' if r.get('pareto_own') else ''}")


def plot(table, path: Path, reference_cells: int, own_cells: int):
    plt = protocol.use_agg()
    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    marks = {"MPM": ("s", "tab:blue"), "GNS": ("^", "tab:red"), "hybrid": ("o", "tab:green")}
    panels = (("mean_position_error_m", "pareto",
               f"total error: against the {reference_cells}-cell MPM"),
              ("own_mpm_position_error_m", "pareto_own",
               f"learned error: against the {own_cells}-cell MPM the GNS emulates"))
    for ax, (err, key, title) in zip(axes, panels):
        rows = [r for r in table if r["family"] != "reference" and r.get(err)]
        for r in rows:
            m, c = marks[r["family"]]
            ax.scatter(r["seconds"], 1e3 * r[err], marker=m, color=c,
                       edgecolor="k" if r.get(key) else "none", s=60, zorder=3)
            ax.annotate(r["label"].replace(" (carry)", ""), (r["seconds"], 1e3 * r[err]),
                        fontsize=5, xytext=(3, 3), textcoords="offset points")
        if key == "pareto_own":  # the own-resolution MPM itself: zero error, off the log axis
            t_own = [r["seconds"] for r in table if r["label"] == f"MPM {own_cells} cells"]
            for t in t_own:
                ax.axvline(t, color="tab:blue", ls=":", lw=1,
                           label=f"MPM {own_cells} cells (this panel's reference)")
        front = sorted((r["seconds"], 1e3 * r[err]) for r in rows if r.get(key))
        if front:
            ax.plot(*zip(*front), "k--", lw=0.8, label="Pareto front")
        for fam, (m, c) in marks.items():
            ax.scatter([], [], marker=m, color=c, label=fam)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("wall time, s (steady state, summed over the cases; median of rounds)")
        ax.set_ylabel("mean material-point position error, mm")
        ax.set_title(title, fontsize=10)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


if __name__ == "__main__":
    main()
