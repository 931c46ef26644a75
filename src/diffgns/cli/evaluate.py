"""``diffgns rollout`` (a trained GNS or MeshGraphNet against a reference trajectory) and
``diffgns hybrid`` (MPM, GNS and hybrid runs of one column collapse, side by side)."""
from __future__ import annotations

import json
from pathlib import Path

from diffgns.cli.checks import (
    count,
    finite,
    fraction_or_none,
    is_mesh_model,
    model_folder,
    positive,
)


def _rollout(args) -> int:
    from diffgns.io.files import check_input_file

    check_input_file(args.data, "--data", metadata=True)
    args.model = model_folder(args.model)
    if is_mesh_model(args.model):
        return _rollout_mesh(args)
    from diffgns.clamp import clamp_warning
    from diffgns.errors import InputError
    from diffgns.graph.data import load_trajectories
    from diffgns.graph.evaluate import rollout_reference, score
    from diffgns.graph.train_loop import load_model

    gns, params, info = load_model(args.model)
    refs, _ = load_trajectories(args.data, info.get("factor", 1), info.get("frame_stride", 1))
    ref = refs[args.index]
    dim = int(ref.positions.shape[-1])
    if dim != gns.config.dim:
        raise InputError("--data", f"trajectory {args.index} of {args.data} is {dim}D but the "
                         f"model {args.model} is {gns.config.dim}D",
                         f"roll a {dim}D model out on it (a GNS runs only in the dimension "
                         "it was trained in)")
    pred, sec = rollout_reference(gns, params, ref)
    s = score(pred, ref, start=gns.config.history)
    s["rollout_s"] = sec
    print(json.dumps(s, indent=2))
    warn = clamp_warning(s, "the GNS rollout")
    if warn:
        print(warn)
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        from diffgns.io.figures import animate
        from diffgns.io.figures3d import animate3d

        draw = animate3d if dim == 3 else animate
        draw([ref, pred], Path(args.out) / "rollout.gif", titles=["MPM", "GNS"], every=2)
        (Path(args.out) / "rollout_metrics.json").write_text(json.dumps(s, indent=2))
        print(f"animation written to {args.out}/rollout.gif")
    return 0


def _rollout_mesh(args) -> int:
    import numpy as np

    from diffgns.mesh.evaluate import evaluate_trajectory, pressure_force_coefficients
    from diffgns.mesh.figures import animate_vorticity, plot_lift, vorticity
    from diffgns.mesh.train import load_cylinder, load_model

    model, params, info = load_model(args.model)
    traj = load_cylinder(args.data)[args.index]
    r = evaluate_trajectory(model, params, traj, info["padding"])
    fields = {k: r.pop(k) for k in ("velocity", "pressure", "long_pressure")}
    print(json.dumps(r, indent=2))
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "rollout_metrics.json").write_text(json.dumps(r, indent=2))
        n, dt = len(traj["mesh_pos"]), float(traj["attrs"]["frame_dt"])
        animate_vorticity(traj["mesh_pos"], traj["cells"],
                          vorticity(traj["mesh_pos"], traj["cells"], traj["velocity"]),
                          vorticity(traj["mesh_pos"], traj["cells"], fields["velocity"][:, :n]),
                          out / "vorticity.gif", frame_dt=dt)
        cl = {"CFD": pressure_force_coefficients(traj, traj["pressure"][1:])[1],
              "MeshGraphNet": pressure_force_coefficients(traj, fields["long_pressure"])[1]}
        t = np.arange(1, len(cl["MeshGraphNet"]) + 1) * dt
        plot_lift(t, cl, out / "lift.png")
        print(f"vorticity.gif, lift.png and rollout_metrics.json written to {out}")
    return 0


def hybrid_schedule(args):
    """The :class:`~diffgns.hybrid.simulator.Schedule` of ``diffgns hybrid``'s arguments;
    what is not given is :data:`~diffgns.hybrid.simulator.DEFAULT_SCHEDULE`'s
    (``--warmup-settle none``: a warm-up of ``--warmup`` frames only)."""
    import dataclasses

    from diffgns.hybrid.simulator import DEFAULT_SCHEDULE

    given = {k: getattr(args, k) for k in SCHEDULE_OPTIONS if getattr(args, k) is not None}
    if given.get("warmup_settle") == "none":
        given["warmup_settle"] = None
    return dataclasses.replace(DEFAULT_SCHEDULE, **given)


#: the :class:`~diffgns.hybrid.simulator.Schedule` fields :func:`add_schedule_arguments`
#: sets (each option's default None: ``DEFAULT_SCHEDULE``'s value)
SCHEDULE_OPTIONS = ("warmup", "warmup_settle", "gns_frames", "mpm_frames", "handoff",
                    "particle_map", "adaptive_tol")


def _hybrid(args) -> int:
    import jax.numpy as jnp

    from diffgns.clamp import clamp_warning
    from diffgns.graph.train_loop import load_model
    from diffgns.hybrid.compare import compare, compare_scene
    from diffgns.inverse.simulators import DEFAULT_MODEL, default_model
    from diffgns.io.figures import animate
    from diffgns.trajectory import Trajectory

    sched = hybrid_schedule(args)
    scene = None
    if args.scene:
        from diffgns.scene.files import load_scene

        scene = load_scene(args.scene)
    if args.model is None:
        args.model = default_model(scene) if scene is not None else DEFAULT_MODEL
        print(f"model: {args.model} (the most accurate shipped model for this scene; "
              "--model to choose)", flush=True)
    print(f"schedule: {sched.label}", flush=True)
    model = load_model(model_folder(args.model))
    if scene is not None:
        reference = scene.replace(dx=scene.dx / args.reference_refine)
        out = compare_scene(model, scene, reference, sched, args.frames)
    else:
        out = compare(model, args.aspect_ratio, args.friction_angle, sched, args.frames,
                      args.reference_cells, args.cells_across)
    for w in out["warnings"]:
        print(f"warning: {args.model} {w}", flush=True)
    print(f"{'simulator':44s} {'runout err':>10s} {'pos err mm':>10s} {'time s':>8s} "
          f"{'clamped':>8s}")
    for r in out["rows"]:
        print(f"{r['label']:44s} {r['runout_error']:10.3f} "
              f"{1e3 * r['mean_position_error_m']:10.2f} {r['seconds']:8.3f} "
              f"{r['clamped_positions']:8d}")
    for r in out["rows"]:
        if "warmup_frames" in r and r["label"] == sched.label:
            print(f"{r['label']}: {r['warmup_frames']} MPM warm-up frames, MPM in "
                  f"{100 * r['mpm_fraction']:.0f}% of the {args.frames} frames")
        warn = clamp_warning(r, r["label"])
        if warn:
            print(warn)
        if r.get("f_kept_particles"):
            print(f"warning: {r['label']}: the reconstruct hand-off kept the deformation "
                  f"gradient of {r['f_kept_particles']} particle-frames whose node field "
                  "changed its area more than 4x in one frame (or folded it)")
    dest = Path(args.out)
    dest.mkdir(parents=True, exist_ok=True)
    (dest / "hybrid_comparison.json").write_text(json.dumps(out["rows"], indent=2))
    trajs = [Trajectory(positions=jnp.asarray(x), velocities=jnp.zeros_like(x),
                        particle_type=jnp.zeros(x.shape[1], jnp.int32),
                        material=jnp.zeros(x.shape[1]), frame_dt=out["frame_dt"],
                        bounds=out["bounds"])
             for x in out["positions"].values()]
    animate(trajs, dest / "hybrid.gif", titles=list(out["positions"]), every=2)
    print(f"comparison written to {dest}/hybrid.gif and hybrid_comparison.json")
    return 0


def add_schedule_arguments(h) -> None:
    """The hybrid schedule's options (``diffgns hybrid`` and ``diffgns invert --simulator
    hybrid``), read back by :func:`hybrid_schedule`."""
    # defaults None: DEFAULT_SCHEDULE's (the jax-free parser does not import the hybrid)
    h.add_argument("--warmup", type=count, default=None,
                   help="MPM frames before the first GNS frame, count >= 1; with "
                   "a settling warm-up the least (default 5)")
    h.add_argument("--warmup-settle", type=fraction_or_none, default=None,
                   metavar="FRACTION",
                   help="the warm-up lasts until the flow's kinetic energy per unit mass has "
                   "fallen below FRACTION (in (0, 1)) of its peak; 'none': a fixed frame count "
                   "(default 0.05: the MPM runs the fast phase of the flow, however long "
                   "it lasts; hybrid guide)")
    h.add_argument("--gns-frames", type=count, default=None,
                   help="M: GNS frames per segment, count (default 8)")
    h.add_argument("--mpm-frames", type=int, default=None,
                   help="K: MPM frames per segment, count >= 0 (default 2)")
    h.add_argument("--handoff", default=None, choices=["carry", "reset", "reconstruct"],
                   help="state handed from GNS to MPM: carry the MPM state, reset it, or "
                   "reconstruct it from the nodes (default carry)")
    h.add_argument("--particle-map", default=None, choices=["affine", "rigid"],
                   help="how MPM particles follow their GNS node in GNS frames (default "
                   "affine)")
    h.add_argument("--adaptive-tol", type=positive, default=None,
                   help="energy-balance tolerance (J/kg) for adaptive switching")


def register(sub) -> None:
    """Add the ``rollout`` and ``hybrid`` parsers to ``sub``."""
    r = sub.add_parser("rollout", help="roll a trained GNS or MeshGraphNet out against a "
                       "reference trajectory and animate both")
    r.add_argument("--model", required=True,
                   help="model folder (params.msgpack, config.json) or shipped model name")
    r.add_argument("--data", required=True, help="dataset with reference trajectories")
    r.add_argument("--index", type=int, default=0,
                   help="trajectory of --data, integer (negative: from the end; default 0)")
    r.add_argument("--out", default=None, help="folder for the MPM-vs-GNS animation")
    r.set_defaults(func=_rollout)

    h = sub.add_parser("hybrid", help="hybrid GNS/MPM run of a scene (default: a column "
                       "collapse of the model's training data) against the MPM and the GNS")
    h.add_argument("--model", default=None,
                   help="model folder or shipped name (default: the most accurate shipped "
                   "model for the scene, as `diffgns invert` picks it; gns_cg16_pfn for the "
                   "column)")
    h.add_argument("--scene", default=None,
                   help="scene TOML file (instead of the column options below); the "
                   "reference MPM has --reference-refine times finer cells")
    h.add_argument("--reference-refine", type=count, default=2,
                   help="with --scene: reference cell size = scene dx / this")
    h.add_argument("--aspect-ratio", type=finite, default=1.75,
                   help="column height / width, dimensionless (default 1.75)")
    h.add_argument("--friction-angle", type=finite, default=27.5,
                   help="friction angle, degrees in (0, 90) (default 27.5)")
    h.add_argument("--frames", type=count, default=125, help="GNS frames, count (default 125)")
    add_schedule_arguments(h)
    h.add_argument("--cells-across", type=count, default=None,
                   help="MPM cells across the column in GNS/hybrid runs, count (default: the "
                   "model's data)")
    h.add_argument("--reference-cells", type=count, default=None,
                   help="cells across the column of the reference MPM, count (default: twice "
                   "the model's, 32 for gns_cg16_pfn)")
    h.add_argument("--out", default="results/hybrid",
                   help="output folder (default results/hybrid)")
    h.set_defaults(func=_hybrid)
