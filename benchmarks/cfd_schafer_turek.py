"""Schäfer & Turek (1996) benchmark 2D-2 with the diffgns P2/P1 projection solver.

Channel 2.2 x 0.41 m, cylinder D = 0.1 m at (0.2, 0.2), Um = 1.5 m/s (Ubar = 1 m/s),
nu = 1e-3 m^2/s, Re = 100. Reference intervals: St = f D / Ubar in [0.295, 0.305],
cD,max in [3.22, 3.24], cL,max in [0.99, 1.01]; we accept cD,max and cL,max within 2% of the
interval. The periodic figures are taken over the last ``--window`` seconds.

    python benchmarks/cfd_schafer_turek.py            # the dataset mesh (~2.1k vertices)
    python benchmarks/cfd_schafer_turek.py --size-cylinder 0.005 --size-far 0.02 \
        --grading 0.2 --size-wake 0.01 --dt 2.5e-4 --out cfd_schafer_turek_fine.json

Writes ``benchmarks/results/<out>`` (JSON) and a cD/cL plot with the same stem (.png).
Wall time per simulated second excludes assembly/factorisation (reported as ``setup_s``);
the whole run's wall and CPU time are reported beside it (``benchmarks/timing.py``). Under
``benchmarks/protocol.py``; ``--threads 1`` runs it pinned to one core with one BLAS/OpenMP
thread, for comparable timings.
"""
from __future__ import annotations

import argparse
import sys

import protocol

from diffgns.mesh.analysis import shedding_metrics, shedding_onset
from diffgns.mesh.cfd import FlowParams, run_case
from diffgns.mesh.geometry import ChannelGeometry, build_mesh
from diffgns.timing import measure, no_sync

TARGETS = dict(strouhal=(0.295, 0.305), cd_max=(3.22, 3.24), cl_max=(0.99, 1.01))
TOL = dict(strouhal=0.0, cd_max=0.02, cl_max=0.02)


def within(name: str, value: float) -> bool:
    lo, hi = TARGETS[name]
    return lo * (1 - TOL[name]) <= value <= hi * (1 + TOL[name])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--size-cylinder", type=float, default=0.008, help="edge length at the "
                   "cylinder, m")
    p.add_argument("--size-far", type=float, default=0.035, help="largest edge length, m")
    p.add_argument("--grading", type=float, default=0.25, help="growth of edge length, m/m")
    p.add_argument("--size-wake", type=float, default=0.014, help="edge length along the "
                   "wake line, m (0: no wake refinement)")
    p.add_argument("--wake-length", type=float, default=1.0, help="wake line length, m")
    p.add_argument("--dt", type=float, default=5e-4, help="time step, s")
    p.add_argument("--t-end", type=float, default=8.0, help="simulated time, s")
    p.add_argument("--window", type=float, default=2.0, help="last seconds analysed")
    p.add_argument("--kick", type=float, default=0.0, help="spin pulse (units of Ubar)")
    p.add_argument("--standard", action="store_true", help="standard (not rotational) "
                   "pressure correction")
    p.add_argument("--out", default="cfd_schafer_turek.json", help="JSON name or path")
    protocol.add_arguments(p)
    args = p.parse_args(argv)
    run = protocol.start(args, "cfd_schafer_turek")
    mesh = build_mesh(ChannelGeometry(), size_cylinder=args.size_cylinder,
                      size_far=args.size_far, grading=args.grading,
                      size_wake=args.size_wake or None, wake_length=args.wake_length)
    prm = FlowParams(u_max=1.5, nu=1e-3, dt=args.dt, kick=args.kick, kick_time=0.5,
                     rotational=not args.standard)
    run.print(f"mesh: {mesh.n_nodes} vertices, {len(mesh.cells)} triangles; dt = "
              f"{args.dt:g} s; {args.t_end:g} s simulated")
    total, res = measure(lambda: run_case(mesh, prm, args.t_end, frame_dt=args.t_end,
                                          record_start=args.t_end, progress=True), sync=no_sync)
    met = shedding_metrics(res.times, res.cd, res.cl, args.t_end - args.window, 0.1, 1.0)
    checks = {k: bool(within(k, met[k])) for k in TARGETS}
    summary = dict(
        n_vertices=mesh.n_nodes, n_triangles=int(len(mesh.cells)),
        n_velocity_dofs=res.info["n_velocity_dofs"], mesh_sizes=mesh.sizes, dt=args.dt,
        t_end=args.t_end, window_s=args.window, kick=args.kick,
        rotational=not args.standard, strouhal=met["strouhal"], cd_max=met["cd_max"],
        cl_max=met["cl_max"], cd_mean=met["cd_mean"], cl_min=met["cl_min"],
        n_periods=met["n_periods"], cl_amplitude_drift=met["cl_amplitude_drift"],
        shedding_onset_s=shedding_onset(res.times, res.cl), max_cfl=res.info["max_cfl"],
        wall_time_s=res.wall_time_s, setup_s=res.setup_s,
        wall_per_sim_second=res.wall_per_sim_second, total_wall_s=total.wall_s,
        total_cpu_s=total.cpu_s,
        ms_per_step=1e3 * res.wall_time_s / res.info["n_steps"],
        targets=TARGETS, tolerance=TOL, within_target=checks, all_within=all(checks.values()))
    payload = dict(case="schafer_turek_2d2", summary=summary)
    path = run.finish(args.out, payload,
                      lambda p: plot(res, met, mesh, args, p.with_suffix(".png")))
    for k in ("n_vertices", "dt", "strouhal", "cd_max", "cl_max", "wall_per_sim_second",
              "total_cpu_s", "shedding_onset_s", "all_within"):
        run.print(f"{k:>22s}: {summary[k]}")
    run.print(f"written {path}")
    return 0


def plot(res, met, mesh, args, png) -> None:
    plt = protocol.use_agg()
    fig, ax = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    ax[0].plot(res.times, res.cd, lw=0.8)
    ax[0].axhspan(*TARGETS["cd_max"], color="g", alpha=0.3, label="cD,max reference")
    ax[0].set_ylabel("cD")
    ax[0].set_ylim(min(3.0, met["cd_min"] - 0.05), 3.4)
    ax[0].legend(loc="lower right")
    ax[1].plot(res.times, res.cl, lw=0.8)
    ax[1].axhspan(*TARGETS["cl_max"], color="g", alpha=0.3, label="cL,max reference")
    ax[1].set_ylabel("cL")
    ax[1].set_xlabel("t (s)")
    ax[1].legend(loc="lower right")
    ax[0].set_title(f"Schäfer-Turek 2D-2: {mesh.n_nodes} vertices, dt = {args.dt:g} s, "
                    f"St = {met['strouhal']:.4f}, cD,max = {met['cd_max']:.4f}, "
                    f"cL,max = {met['cl_max']:.4f}", fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
