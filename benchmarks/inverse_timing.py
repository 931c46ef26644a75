"""Per-iteration time of the inverse problem through the GNS, the MPM and the hybrid.

    .venv/bin/python benchmarks/inverse_timing.py [--simulators gns mpm hybrid]
        [--model gns_cg16_pfn] [--aspect-ratio 1.75] [--frames 250] [--rounds 3]
        [--threads 2|1|both] [--wait-quiet 600]

The set-up of ``examples/column_collapse_inverse.py`` and ``diffgns invert`` (the numbers of
[Inverse problems](docs/guides/inverse.md)): the observed MPM collapse of the model's training
column (aspect ratio 1.75, phi = 30 deg), seen as the GNS sees it (nodes, frames); the
objective "runout" (soft-max runout of the last observed frame, squared misfit); theta =
{friction_angle: 45 deg}, optimised as u = logit(phi / 90). Everything is built by the one
inverse path of the package (``diffgns.inverse.job.make_simulator`` / ``make_objective``;
the loss of ``job.solve``; the transforms of ``inverse.optimize``), so the programs timed here
are the ones an inversion runs.

What one iteration of ``diffgns.inverse.optimize`` costs is one call of its compiled program:
with AD gradients ``value_and_grad`` of the loss in u (``gradient="ad"``, the default); with
finite differences the loss at u and, per parameter, the two central evaluations
(``gradient="fd"``: 1 + 2 x parameters forward calls). So per simulator two programs are
compiled ahead of time (``diffgns.memory.compile_ahead``: lowering + compile time and XLA's
memory analysis, apart from the timing) - the AD gradient and the forward loss - and all of
them are timed in the same interleaved rounds (``diffgns.timing.interleave``: one call of
every program per round, the order reversed every other round, ``block_until_ready``, wall
and CPU time; medians). Ratios (MPM / GNS, hybrid / GNS, gradient / forward) are medians of
the per-round ratios. The host-side work of an iteration (the optimiser's update, a record
line) is not included: microseconds against seconds.

Under ``benchmarks/protocol.py`` (``--threads 2`` by default, ~5 min on a quiet 2-core machine;
``--threads both`` adds the same rounds pinned to one core, about as long again). Writes
``benchmarks/results/inverse_timing.json``.
"""
from __future__ import annotations

import argparse
import time

import protocol
from protocol import warm_up_jax

SIMULATORS = ("gns", "mpm", "hybrid")


def build(kind: str, column, model: str, loaded, observed, objective, theta0: dict,
          block: int | None) -> dict:
    """The AD-gradient and forward programs of simulator ``kind``, compiled ahead of time as
    ``inverse.optimize`` compiles them, with their compile times and XLA memory. A learned
    simulator's programs are run once here: the gradient through ``inverse.evaluate_redo``,
    which grows the neighbour list and recompiles if a rollout at ``theta0`` overflows it. The
    MPM (no list) runs its forward program once; its gradient's first call is the first
    round's (compiled ahead, so no compile in it)."""
    import jax

    from diffgns.inverse.job import make_simulator
    from diffgns.inverse.solve import evaluate_redo
    from diffgns.inverse.transforms import setup
    from diffgns.memory import compile_ahead

    sim = make_simulator(kind, column, model, loaded=loaded if kind != "mpm" else None,
                         observed=observed, block=block, theta0=theta0)
    _, u, to_theta = setup(theta0, None)

    def loss(theta):  # job.solve's loss
        pos, overflow = sim.simulate(theta)
        return objective(pos), {"overflow": overflow}

    f = lambda uu: loss(to_theta(uu))  # noqa: E731 - inverse.optimize's function of u
    out: dict = {"u": u}

    def compile_all():
        for name, fn in (("gradient", jax.value_and_grad(f, has_aux=True)), ("forward", f)):
            out[name], info = compile_ahead(jax.jit(fn), u)
            out[f"{name}_compile"] = info

    def evaluate(uu):  # (loss, aux) of the gradient program, as optimize's evaluate
        (value, aux), g = out["gradient"](uu)
        return value, aux, g

    compile_all()
    t0 = time.perf_counter()
    if kind == "mpm":  # no neighbour list, never overflows: spare the costliest call
        value, _ = out["forward"](u)
    else:
        value, _, _ = evaluate_redo(evaluate, compile_all, sim.reallocate, to_theta, u, 0)
        jax.block_until_ready(out["forward"](u))
    out["check_s"] = time.perf_counter() - t0
    out["loss"] = float(value)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--simulators", nargs="+", default=list(SIMULATORS), choices=SIMULATORS)
    ap.add_argument("--model", default=None, help="GNS model (default: the inverse default)")
    ap.add_argument("--aspect-ratio", type=float, default=1.75)
    ap.add_argument("--target-phi", type=float, default=30.0)
    ap.add_argument("--start-phi", type=float, default=45.0, help="theta of the timed calls")
    ap.add_argument("--frames", type=int, default=250,
                    help="MPM frames of 2.5 ms observed (250: 0.625 s, to rest)")
    ap.add_argument("--block", type=int, default=None,
                    help="jax.checkpoint block (frames; default the inverse job's per "
                         "simulator: GNS/hybrid 10, MPM 25)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds")
    ap.add_argument("--out", default="inverse_timing.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "inverse_timing")
    warm_up_jax()
    import jax

    from diffgns.inverse.job import make_objective
    from diffgns.inverse.simulators import (
        DEFAULT_MODEL,
        Column,
        ColumnCase,
        load_gns,
        model_info,
    )
    from diffgns.inverse.transforms import setup
    from diffgns.timing import interleave, measure, no_sync

    model = args.model or DEFAULT_MODEL
    column = Column(ColumnCase.from_model(model_info(model), args.aspect_ratio,
                                          n_frames=args.frames))
    obs_t, observed = measure(lambda: column.observation({"friction_angle": args.target_phi}),
                              sync=no_sync)
    loaded = load_gns(model) if set(args.simulators) - {"mpm"} else None
    objective = make_objective("runout", column, observed=observed)
    theta0 = {"friction_angle": args.start_phi}
    run.print(f"column a = {args.aspect_ratio:g}: {column.scene.n_particles} MPM particles -> "
              f"{column.n_nodes} nodes, {column.n_obs} observed frames "
              f"({column.n_frames * column.scene.substeps} MPM substeps); observation "
              f"{obs_t.wall_s:.1f} s")
    progs = {}
    for kind in args.simulators:
        progs[kind] = build(kind, column, model, loaded, observed, objective, theta0,
                            args.block)
        c = {k: progs[kind][f"{k}_compile"] for k in ("gradient", "forward")}
        cs = {k: v["lower_s"] + v["compile_s"] for k, v in c.items()}
        run.print(f"{kind}: compile gradient {cs['gradient']:.1f} s, forward "
                  f"{cs['forward']:.1f} s; XLA gradient temp "
                  f"{c['gradient']['memory'].get('temp_mb', 0):.0f} MB")

    contenders = {}
    for kind, p in progs.items():
        for name in ("gradient", "forward"):
            contenders[f"{kind} {name}"] = (lambda exe=p[name], u=p["u"]: exe(u))
    # compiled ahead and run once each in build(): no warm-up round
    rounds = interleave(contenders, max(1, args.rounds), warmup=False)
    rows = {}
    for kind, p in progs.items():
        g, f = rounds.summary(f"{kind} gradient"), rounds.summary(f"{kind} forward")
        n_par = len(p["u"])
        rows[kind] = dict(
            gradient=g, forward=f,
            compile_gradient_s=p["gradient_compile"]["lower_s"]
            + p["gradient_compile"]["compile_s"],
            compile_forward_s=p["forward_compile"]["lower_s"] + p["forward_compile"]["compile_s"],
            xla_gradient_memory=p["gradient_compile"]["memory"],
            xla_forward_memory=p["forward_compile"]["memory"],
            s_per_iteration_ad=g["median_s"],
            cpu_s_per_iteration_ad=g["cpu_median_s"],
            s_per_iteration_fd=(1 + 2 * n_par) * f["median_s"],
            fd_gradient_s=2 * n_par * f["median_s"],
            gradient_over_forward=rounds.ratio(f"{kind} gradient", f"{kind} forward"),
            loss=p["loss"], dloss_du={k: float(v) for k, v in
                                      rounds.outputs[f"{kind} gradient"][1].items()},
            dloss_dphi_deg=None)
        # d loss / d phi (per degree) from d loss / d u, as inverse.optimize records it
        tf = setup(theta0, None)[0]["friction_angle"]
        dth = float(jax.grad(tf.forward)(p["u"]["friction_angle"]))
        rows[kind]["dloss_dphi_deg"] = rows[kind]["dloss_du"]["friction_angle"] / dth
    ratios = {}
    if "gns" in progs:
        for kind in progs:
            if kind != "gns":
                ratios[f"{kind}_over_gns_iteration"] = rounds.ratio(f"{kind} gradient",
                                                                    "gns gradient")
                ratios[f"{kind}_over_gns_forward"] = rounds.ratio(f"{kind} forward",
                                                                  "gns forward")
    run.print(f"{'simulator':>9} {'s/iter (AD)':>11} {'CPU s':>7} {'forward s':>9} "
              f"{'FD iter s':>9} {'grad/fwd':>8} {'compile g s':>11} {'XLA grad MB':>11}")
    for kind, r in rows.items():
        run.print(f"{kind:>9} {r['s_per_iteration_ad']:>11.3f} {r['cpu_s_per_iteration_ad']:>7.2f} "
                  f"{r['forward']['median_s']:>9.3f} {r['s_per_iteration_fd']:>9.3f} "
                  f"{r['gradient_over_forward']:>8.2f} {r['compile_gradient_s']:>11.1f} "
                  f"{r['xla_gradient_memory'].get('temp_mb', 0):>11.0f}  dL/dphi "
                  f"{r['dloss_dphi_deg']:.4e} /deg")
    for k, v in ratios.items():
        run.print(f"{k}: {v:.3f} (median of {len(rounds.rounds)} per-round ratios)")
    payload = {
        "description": " ".join(__doc__.split("\n\n")[2:4]).replace("\n", " "),
        "model": str(model), "aspect_ratio": args.aspect_ratio, "target_phi": args.target_phi,
        "start_phi": args.start_phi, "frames": args.frames, "observed_frames": column.n_obs,
        "particles": column.scene.n_particles, "nodes": column.n_nodes,
        "block": args.block, "rounds": max(1, args.rounds),
        "observation_s": obs_t.wall_s, "simulators": rows, "ratios": ratios,
        "interleaved": rounds.to_json(),
        "fd_note": "an FD iteration of inverse.optimize = the loss + 2 central evaluations per "
                   "parameter (forward calls); fd_gradient_s = 2 per parameter, as "
                   "inverse.gradient_check counts it",
    }
    if run.mode == "both" and not run.pinned:
        payload["one_thread_pinned"] = child = run.pinned_child()
        ch = child.get("simulators") or {}
        for kind, r in rows.items():
            one = ch.get(kind, {}).get("s_per_iteration_ad")
            run.print(f"{kind} s/iteration (AD): 2 threads {r['s_per_iteration_ad']:.3f}; "
                      f"1 thread pinned {'refused' if one is None else f'{one:.3f}'}")
        for k, v in ratios.items():
            one = (child.get("ratios") or {}).get(k)
            run.print(f"{k}: " + protocol.both_ratios(v, one, child))
    path = run.finish(args.out, payload)
    run.print(f"wrote {path}")


if __name__ == "__main__":
    main()
