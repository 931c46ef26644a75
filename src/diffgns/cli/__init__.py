"""The ``diffgns`` command: simulate scenes and generate datasets.

    diffgns simulate --scene scenes/column_collapse.toml --frames 200 --out results/sim
    diffgns simulate --column --aspect-ratio 2 --friction-angle 30 --out results/col
    diffgns dataset --kind column --aspect-ratios 0.5 1 2 --friction-angles 25 35 45 \
        --frames 320 --out data/columns.h5
    diffgns dataset --kind squares --n 20 --frames 320 --out data/squares.h5
    diffgns train --kind mesh --data data/cylinder_train.h5 --latent 64 --mp-steps 8 \
        --out runs/meshnet
    diffgns rollout --model runs/meshnet/model --data data/cylinder_test.h5 --out results/mgn
    diffgns symbolic --law spring
    diffgns dataset --kind cylinder --n 16 --seed 0 --frames 300 --out data/cylinder_train.h5
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from diffgns.errors import SceneError, UnstableError
from diffgns.models import model_path


def _simulate(args) -> int:
    from diffgns.io.outputs import run_mpm, write_outputs
    from diffgns.scene.builders import column_collapse
    from diffgns.scene.files import load_scene

    if args.scene:
        scene, L0 = load_scene(args.scene), None
    else:
        scene = column_collapse(width=args.width, aspect_ratio=args.aspect_ratio,
                                friction_angle=args.friction_angle,
                                cells_across=args.cells_across)
        L0 = args.width
    print(f"scene: {scene.n_particles} particles, grid {scene.grid_shape}, "
          f"{scene.substeps} substeps/frame (dt = {scene.substep_dt:.2e} s), "
          f"effects: {', '.join(sorted(scene.effects))}")
    traj, timing = run_mpm(scene, args.frames, dtype=args.dtype)
    summary = write_outputs(traj, scene, args.out, vtk_every=args.vtk_every, L0=L0,
                            extra=dict(timing=timing))
    print(json.dumps({k: v for k, v in summary.items() if k != "files"}, indent=2))
    print(f"outputs written to {args.out}")
    return 0


def _dataset(args) -> int:
    if args.kind == "cylinder":
        return _dataset_cylinder(args)
    from diffgns.io.datagen import generate_columns, generate_squares

    if args.kind == "column":
        path = generate_columns(args.out, args.aspect_ratios, args.friction_angles, args.frames,
                                width=args.width, cells_across=args.cells_across,
                                batch=args.batch, domain_length=args.domain_length,
                                domain_height=args.domain_height)
    else:
        kw = dict(dx=args.dx, size=args.size,
                  friction_angle=(min(args.friction_angles), max(args.friction_angles)))
        if args.domain_length and args.domain_height:
            kw["domain"] = ((0.0, args.domain_length), (0.0, args.domain_height))
        path = generate_squares(args.out, args.n, args.frames, seed=args.seed, **kw)
    print(f"dataset written to {path}")
    return 0


def _dataset_cylinder(args) -> int:
    from diffgns.mesh.datagen import CylinderRun, CylinderSampling, generate_cylinder

    try:
        sampling = CylinderSampling(re_range=tuple(args.re_range),
                                    u_max_range=tuple(args.u_max_range),
                                    radius_range=tuple(args.radius_range),
                                    cx_range=tuple(args.cx_range), cy_range=tuple(args.cy_range))
        run = CylinderRun(n_frames=args.frames, frame_dt=args.frame_dt, spinup=args.spinup,
                          size_cylinder=args.size_cylinder, size_far=args.size_far,
                          grading=args.grading, size_wake=args.size_wake or None,
                          cfl=args.cfl)
    except ValueError as e:
        raise SceneError(str(e)) from e
    path = generate_cylinder(args.out, args.n, seed=args.seed, sampling=sampling, run=run)
    print(f"dataset written to {path}")
    return 0


def _train(args) -> int:
    from diffgns.graph.train_loop import train
    from diffgns.graph.training import TrainConfig

    if args.kind == "mesh":
        return _train_mesh(args)
    if args.noise_std is None:
        args.noise_std = 6.7e-4
    tcfg = TrainConfig(steps=args.steps, batch_size=args.batch_size, lr=args.lr,
                       lr_final=args.lr_final, lr_decay_steps=args.lr_decay_steps or args.steps,
                       push_forward=args.push_forward, momentum_weight=args.momentum_weight,
                       seed=args.seed, validate_every=args.validate_every,
                       checkpoint_every=args.checkpoint_every)
    gns_kw = dict(radius=args.radius, latent=args.latent, mp_steps=args.mp_steps,
                  mlp_layers=args.mlp_layers, noise_std=args.noise_std,
                  attention=args.attention)
    train(args.data, args.out, gns_kw, tcfg, valid_path=args.valid, factor=args.coarse_grain,
          frame_stride=args.frame_stride, init_from=args.init_from)
    print(f"model written to {args.out}/model")
    return 0


def _train_mesh(args) -> int:
    from diffgns.graph.training import TrainConfig
    from diffgns.mesh.meshnet import MeshNetConfig
    from diffgns.mesh.train import train

    if len(args.data) != 1:
        raise SceneError("--kind mesh trains on one cylinder dataset (.h5); got "
                         f"{len(args.data)}")
    tcfg = TrainConfig(steps=args.steps, batch_size=args.batch_size, lr=args.lr,
                       lr_final=args.lr_final, lr_decay_steps=args.lr_decay_steps or args.steps,
                       push_forward=args.push_forward, seed=args.seed,
                       checkpoint_every=args.checkpoint_every)
    cfg = MeshNetConfig(latent=args.latent, mp_steps=args.mp_steps, mlp_layers=args.mlp_layers,
                        noise_std=0.02 if args.noise_std is None else args.noise_std,
                        viscosity_feature=not args.no_viscosity)
    train(args.data[0], args.out, cfg, tcfg, init_from=args.init_from)
    print(f"model written to {args.out}/model")
    return 0


def _rollout_mesh(args) -> int:
    from pathlib import Path

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


def _average(args) -> int:
    from diffgns.graph.train_loop import average_models

    try:
        out = average_models(args.models, args.out)
    except ValueError as e:
        print(f"diffgns average: error: {e}", file=sys.stderr)
        return 2
    print("averaged model written to", out)
    return 0


def _is_mesh_model(path) -> bool:
    from pathlib import Path

    meta = Path(path) / "model.json"
    return meta.exists() and json.loads(meta.read_text()).get("kind") == "meshgraphnet"


def _symbolic(args) -> int:
    from diffgns.interpret.pipeline import main as run_symbolic

    return run_symbolic(args)


def _rollout(args) -> int:
    if _is_mesh_model(args.model):
        return _rollout_mesh(args)
    from diffgns.graph.data import load_trajectories
    from diffgns.graph.evaluate import rollout_reference, score
    from diffgns.graph.train_loop import load_model
    from diffgns.io.figures import animate

    gns, params, info = load_model(args.model)
    refs, _ = load_trajectories(args.data, info.get("factor", 1), info.get("frame_stride", 1))
    ref = refs[args.index]
    pred, sec = rollout_reference(gns, params, ref)
    s = score(pred, ref, start=gns.config.history)
    s["rollout_s"] = sec
    print(json.dumps(s, indent=2))
    if args.out:
        from pathlib import Path

        Path(args.out).mkdir(parents=True, exist_ok=True)
        animate([ref, pred], Path(args.out) / "rollout.gif", titles=["MPM", "GNS"], every=2)
        (Path(args.out) / "rollout_metrics.json").write_text(json.dumps(s, indent=2))
        print(f"animation written to {args.out}/rollout.gif")
    return 0


def _hybrid(args) -> int:
    from pathlib import Path

    import numpy as np

    from diffgns.graph.train_loop import load_model
    from diffgns.hybrid.compare import compare
    from diffgns.hybrid.simulator import Schedule
    from diffgns.io.figures import animate
    from diffgns.trajectory import Trajectory

    sched = Schedule(warmup=args.warmup, gns_frames=args.gns_frames,
                     mpm_frames=args.mpm_frames, handoff=args.handoff,
                     adaptive_tol=args.adaptive_tol, particle_map=args.particle_map)
    out = compare(load_model(args.model), args.aspect_ratio, args.friction_angle, sched,
                  args.frames, args.reference_cells, args.cells_across)
    print(f"{'simulator':44s} {'runout err':>10s} {'pos err mm':>10s} {'time s':>8s}")
    for r in out["rows"]:
        print(f"{r['label']:44s} {r['runout_error']:10.3f} "
              f"{1e3 * r['mean_position_error_m']:10.2f} {r['seconds']:8.3f}")
    dest = Path(args.out)
    dest.mkdir(parents=True, exist_ok=True)
    (dest / "hybrid_comparison.json").write_text(json.dumps(out["rows"], indent=2))
    trajs = [Trajectory(positions=x, velocities=np.zeros_like(x),
                        particle_type=np.zeros(x.shape[1], np.int32),
                        material=np.zeros(x.shape[1]), frame_dt=out["frame_dt"],
                        bounds=out["bounds"])
             for x in out["positions"].values()]
    animate(trajs, dest / "hybrid.gif", titles=list(out["positions"]), every=2)
    print(f"comparison written to {dest}/hybrid.gif and hybrid_comparison.json")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="diffgns", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="run the MPM on a scene and write animation, plots, VTK")
    src = s.add_mutually_exclusive_group(required=True)
    src.add_argument("--scene", help="scene TOML file")
    src.add_argument("--column", action="store_true", help="a granular column collapse")
    s.add_argument("--width", type=float, default=0.1, help="column width, m")
    s.add_argument("--aspect-ratio", type=float, default=2.0)
    s.add_argument("--friction-angle", type=float, default=30.0, help="degrees")
    s.add_argument("--cells-across", type=int, default=10, help="grid cells across the column")
    s.add_argument("--frames", type=int, default=200)
    s.add_argument("--dtype", default=None, choices=[None, "float32", "float64"])
    s.add_argument("--vtk-every", type=int, default=10)
    s.add_argument("--out", default="results/simulate")
    s.set_defaults(func=_simulate)

    d = sub.add_parser("dataset", help="generate an HDF5 training set with the MPM or, for "
                       "--kind cylinder, the cylinder-flow CFD (resumable)")
    d.add_argument("--kind", choices=["column", "squares", "cylinder"], required=True)
    d.add_argument("--out", required=True, help="output .h5 file (resumes if it exists)")
    d.add_argument("--frames", type=int, default=320)
    d.add_argument("--aspect-ratios", type=float, nargs="+", default=[0.5, 1.0, 2.0, 3.0])
    d.add_argument("--friction-angles", type=float, nargs="+", default=[25.0, 35.0, 45.0])
    d.add_argument("--width", type=float, default=0.1)
    d.add_argument("--cells-across", type=int, default=10)
    d.add_argument("--domain-length", type=float, default=None, help="fixed box length, m")
    d.add_argument("--domain-height", type=float, default=None, help="fixed box height, m")
    d.add_argument("--batch", type=int, default=4, help="friction angles rolled out together")
    d.add_argument("--n", type=int, default=10,
                   help="number of square-flow / cylinder-flow trajectories")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--dx", type=float, default=0.02, help="cell size of square flows, m")
    d.add_argument("--size", type=float, default=0.2, help="side of the squares, m")
    c = d.add_argument_group("cylinder flow (--kind cylinder; ranges are MIN MAX, SI units)")
    c.add_argument("--re-range", type=float, nargs=2, default=[80.0, 160.0],
                   help="Reynolds number Ubar D / nu")
    c.add_argument("--u-max-range", type=float, nargs=2, default=[1.0, 2.0],
                   help="peak inflow speed Um, m/s (nu follows from Re)")
    c.add_argument("--radius-range", type=float, nargs=2, default=[0.04, 0.06])
    c.add_argument("--cx-range", type=float, nargs=2, default=[0.15, 0.35],
                   help="cylinder centre x, m")
    c.add_argument("--cy-range", type=float, nargs=2, default=[0.16, 0.25],
                   help="cylinder centre y, m")
    c.add_argument("--frame-dt", type=float, default=0.01, help="time between frames, s")
    c.add_argument("--spinup", type=float, default=35.0,
                   help="simulated time before the first stored frame, in units of D / Ubar")
    c.add_argument("--size-cylinder", type=float, default=0.008,
                   help="mesh edge length at the cylinder, m")
    c.add_argument("--size-far", type=float, default=0.035, help="largest mesh edge length, m")
    c.add_argument("--grading", type=float, default=0.25, help="mesh size growth, m/m")
    c.add_argument("--size-wake", type=float, default=0.014,
                   help="mesh edge length along 1 m of wake behind the cylinder, m (0: none)")
    c.add_argument("--cfl", type=float, default=0.15,
                   help="largest Um dt / h_min (sets the CFD time step)")
    d.set_defaults(func=_dataset)

    t = sub.add_parser("train", help="train a GNS (particles) or a MeshGraphNet (--kind mesh, "
                       "on a cylinder-flow dataset) (resumable)")
    t.add_argument("--kind", choices=["particles", "mesh"], default="particles")
    t.add_argument("--data", nargs="+", required=True, help="training datasets (.h5 or .npz)")
    t.add_argument("--valid", default=None, help="validation dataset for rollouts")
    t.add_argument("--out", required=True, help="run folder (checkpoint, logs, model/)")
    t.add_argument("--steps", type=int, default=20000)
    t.add_argument("--batch-size", type=int, default=2)
    t.add_argument("--lr", type=float, default=1e-3)
    t.add_argument("--lr-final", type=float, default=1e-5)
    t.add_argument("--lr-decay-steps", type=int, default=None)
    t.add_argument("--radius", type=float, default=0.015, help="connectivity radius, m")
    t.add_argument("--latent", type=int, default=128)
    t.add_argument("--mp-steps", type=int, default=10)
    t.add_argument("--mlp-layers", type=int, default=2)
    t.add_argument("--noise-std", type=float, default=None,
                   help="training noise: random walk in m (particles, default 6.7e-4) or "
                   "velocity noise in m/s (mesh, default 0.02)")
    t.add_argument("--attention", action="store_true")
    t.add_argument("--coarse-grain", type=int, default=1, help="MPM particles per GNS node")
    t.add_argument("--frame-stride", type=int, default=1, help="MPM frames per GNS frame")
    t.add_argument("--push-forward", type=int, default=0)
    t.add_argument("--momentum-weight", type=float, default=0.0)
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--validate-every", type=int, default=2000)
    t.add_argument("--checkpoint-every", type=int, default=500)
    t.add_argument("--init-from", default=None,
                   help="model folder to fine-tune from (same configuration, fresh optimiser)")
    t.add_argument("--no-viscosity", action="store_true",
                   help="mesh: do not give the flow's viscosity to the network")
    t.set_defaults(func=_train)

    r = sub.add_parser("rollout", help="roll a trained GNS or MeshGraphNet out against a "
                       "reference trajectory and animate both")
    r.add_argument("--model", required=True, help="model folder (params.msgpack, config.json)")
    r.add_argument("--data", required=True, help="dataset with reference trajectories")
    r.add_argument("--index", type=int, default=0)
    r.add_argument("--out", default=None, help="folder for the MPM-vs-GNS animation")
    r.set_defaults(func=_rollout)

    h = sub.add_parser("hybrid", help="hybrid GNS/MPM column collapse against MPM and GNS")
    h.add_argument("--model", default=str(model_path("gns_columns")))
    h.add_argument("--aspect-ratio", type=float, default=1.75)
    h.add_argument("--friction-angle", type=float, default=27.5, help="degrees")
    h.add_argument("--frames", type=int, default=125, help="GNS frames")
    h.add_argument("--warmup", type=int, default=5, help="MPM frames before the first GNS")
    h.add_argument("--gns-frames", type=int, default=5, help="M: GNS frames per segment")
    h.add_argument("--mpm-frames", type=int, default=2, help="K: MPM frames per segment")
    h.add_argument("--handoff", default="carry", choices=["carry", "reset", "reconstruct"])
    h.add_argument("--particle-map", default="affine", choices=["affine", "rigid"],
                   help="how MPM particles follow their GNS node in GNS frames")
    h.add_argument("--adaptive-tol", type=float, default=None,
                   help="energy-balance tolerance (J/kg) for adaptive switching")
    h.add_argument("--cells-across", type=int, default=None,
                   help="MPM resolution of GNS/hybrid runs (default: the model's data)")
    h.add_argument("--reference-cells", type=int, default=16,
                   help="resolution of the reference MPM")
    h.add_argument("--out", default="results/hybrid")
    h.set_defaults(func=_hybrid)

    from diffgns.interpret.pipeline import add_arguments

    a = sub.add_parser("average", help="uniform weight average of GNS models fine-tuned from "
                       "one parent (same network and normaliser)")
    a.add_argument("models", nargs="+", help="model folders")
    a.add_argument("--out", required=True, help="folder of the averaged model")
    a.set_defaults(func=_average)
    y = sub.add_parser("symbolic", help="recover n-body force laws from a message network "
                       "by symbolic regression")
    add_arguments(y)
    y.set_defaults(func=_symbolic)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (SceneError, UnstableError) as e:
        print(f"diffgns: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
