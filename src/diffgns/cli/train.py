"""``diffgns train`` (a particle GNS or, ``--kind mesh``, a MeshGraphNet; resumable) and
``diffgns average`` (a uniform weight average of fine-tuned GNS models)."""
from __future__ import annotations

import sys

from diffgns.cli.checks import count, non_negative, positive, probability
from diffgns.io.files import check_input_file


def _check_inputs(args) -> None:
    """Refuse missing or unreadable datasets before anything is created."""
    for path in args.data:
        check_input_file(path, "--data", metadata=True)
    if args.valid:
        check_input_file(args.valid, "--valid", metadata=True)

def join_if_asked(args) -> bool:
    """Join a multi-process run (before any JAX computation) if the options or the
    ``DIFFGNS_*`` variables ask for one; JAX is imported only then. Returns whether joined."""
    import os

    env = ("DIFFGNS_COORDINATOR", "DIFFGNS_NUM_PROCESSES", "DIFFGNS_PROCESS_ID")
    if not (args.distributed or args.coordinator or args.num_processes is not None
            or args.process_id is not None or any(os.environ.get(v) for v in env)):
        return False
    from diffgns.distributed import initialize

    return initialize(args.coordinator, args.num_processes, args.process_id,
                      auto=args.distributed)


def _train(args) -> int:
    _check_inputs(args)
    join_if_asked(args)
    from diffgns.graph.train_loop import train
    from diffgns.graph.training import TrainConfig

    if args.kind == "mesh":
        from diffgns.distributed import process_count
        from diffgns.errors import InputError

        if args.unroll != 1:
            raise InputError("--unroll", "is a particle-GNS option", "for a MeshGraphNet "
                             "use python -m diffgns.mesh.stages --stages UNTIL:NOISE:K")
        if process_count() > 1:
            raise InputError("--kind mesh", "trains in one process only",
                             "drop --distributed/--coordinator, or train --kind particles")
        return _train_mesh(args)
    if args.noise_std is None:
        args.noise_std = 6.7e-4
    tcfg = TrainConfig(steps=args.steps, batch_size=args.batch_size, lr=args.lr,
                       lr_final=args.lr_final, lr_decay_steps=args.lr_decay_steps or args.steps,
                       push_forward=args.push_forward, unroll=args.unroll,
                       momentum_weight=args.momentum_weight,
                       huber_delta=args.huber_delta,
                       target_scale_floor=args.target_scale_floor, seed=args.seed,
                       validate_every=args.validate_every, checkpoint_every=args.checkpoint_every,
                       steps_per_call=args.steps_per_call or TrainConfig.steps_per_call)
    gns_kw = dict(radius=args.radius, latent=args.latent, mp_steps=args.mp_steps,
                  mlp_layers=args.mlp_layers, noise_std=args.noise_std,
                  attention=args.attention, use_obstacles=args.obstacle_features)
    train(args.data, args.out, gns_kw, tcfg, valid_path=args.valid, factor=args.coarse_grain,
          frame_stride=args.frame_stride, init_from=args.init_from, pad_to=args.pad_nodes,
          family_weights=_weights(args.family_weights),
          early_windows=_early_windows(args.early_windows), mirror=args.mirror,
          active_windows=args.active_windows)
    from diffgns.distributed import is_main

    if is_main():
        print(f"model written to {args.out}/model")
    return 0


def _weights(text: str | None) -> dict | None:
    """``"squares=1,columns=2"`` -> {"squares": 1.0, "columns": 2.0}."""
    if not text:
        return None
    from diffgns.errors import InputError

    out = {}
    for item in text.split(","):
        name, _, w = item.partition("=")
        try:
            out[name.strip()] = float(w)
        except ValueError:
            raise InputError("--family-weights", f"{item!r} is not family=weight",
                             "e.g. --family-weights squares=1,columns=2") from None
    return out


def _early_windows(text: str | None) -> tuple[int, float] | None:
    """``"5:4"`` -> (5, 4.0): windows starting in the first 5 frames drawn 4 times as often."""
    if not text:
        return None
    from diffgns.errors import InputError

    frames, _, weight = text.partition(":")
    try:
        out = (int(frames), float(weight))
    except ValueError:
        out = (-1, 0.0)
    if out[0] < 1 or not (out[1] > 0 and out[1] != float("inf")):
        raise InputError("--early-windows", f"{text!r} is not FRAMES:WEIGHT",
                         "e.g. --early-windows 5:4 (frames >= 1, weight > 0)")
    return out


def _train_mesh(args) -> int:
    from diffgns.errors import SceneError
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


def _average(args) -> int:
    from diffgns.cli.checks import is_mesh_model, model_folder
    from diffgns.graph import train_loop
    from diffgns.mesh import train as mesh_train

    mesh = is_mesh_model(model_folder(args.models[0], "models"))
    average_models = mesh_train.average_models if mesh else train_loop.average_models
    try:
        out = average_models(args.models, args.out)
    except ValueError as e:
        print(f"diffgns average: error: {e}", file=sys.stderr)
        return 2
    print("averaged model written to", out)
    return 0


def add_distributed_arguments(p) -> None:
    """The options that join a multi-process run (docs/guides/distributed.md)."""
    g = p.add_argument_group("several processes (jax.distributed; docs/guides/distributed.md)")
    g.add_argument("--distributed", action="store_true",
                   help="join the run JAX detects from the environment (SLURM srun, Open MPI)")
    g.add_argument("--coordinator", default=None,
                   help="host:port of process 0's coordinator (a free port), with "
                   "--num-processes and --process-id (or DIFFGNS_COORDINATOR, ...)")
    g.add_argument("--num-processes", type=count, default=None,
                   help="processes of the run, count (default: one, or DIFFGNS_NUM_PROCESSES)")
    g.add_argument("--process-id", type=int, default=None,
                   help="this process's index in 0 .. N-1 (or DIFFGNS_PROCESS_ID)")


def register(sub) -> None:
    """Add the ``train`` and ``average`` parsers to ``sub``."""
    t = sub.add_parser("train", help="train a GNS (particles) or a MeshGraphNet (--kind mesh, "
                       "on a cylinder-flow dataset) (resumable)")
    t.add_argument("--kind", choices=["particles", "mesh"], default="particles",
                   help="particles: a GNS on MPM datasets; mesh: a MeshGraphNet on a "
                   "cylinder-flow dataset (default particles)")
    t.add_argument("--data", nargs="+", required=True, help="training datasets (.h5 or .npz)")
    t.add_argument("--valid", default=None,
                   help="validation dataset (.h5) for rollouts (default: none)")
    t.add_argument("--out", required=True, help="run folder (checkpoint, logs, model/)")
    t.add_argument("--steps", type=count, default=20000,
                   help="optimiser steps, count (default 20000)")
    t.add_argument("--batch-size", type=count, default=2,
                   help="training samples per step, count (default 2)")
    t.add_argument("--lr", type=positive, default=1e-3,
                   help="initial learning rate (Adam), dimensionless (default 1e-3)")
    t.add_argument("--lr-final", type=positive, default=1e-5,
                   help="learning-rate floor of the exponential decay (default 1e-5)")
    t.add_argument("--lr-decay-steps", type=count, default=None,
                   help="steps over which the learning rate decays to --lr-final, count "
                   "(default --steps)")
    t.add_argument("--radius", type=positive, default=0.015,
                   help="particles: connectivity radius, m (default 0.015)")
    t.add_argument("--latent", type=count, default=128,
                   help="width of the latent vectors and MLPs, count (default 128)")
    t.add_argument("--mp-steps", type=count, default=10,
                   help="message-passing steps, count (default 10)")
    t.add_argument("--mlp-layers", type=count, default=2,
                   help="hidden layers per MLP, count (default 2)")
    t.add_argument("--noise-std", type=non_negative, default=None,
                   help="training noise: random walk in m (particles, default 6.7e-4) or "
                   "velocity noise in m/s (mesh, default 0.02)")
    t.add_argument("--attention", action="store_true",
                   help="particles: attention-weighted message aggregation")
    t.add_argument("--coarse-grain", type=count, default=1,
                   help="particles: MPM particles per GNS node, count (default 1)")
    t.add_argument("--frame-stride", type=count, default=1,
                   help="particles: MPM frames per GNS frame, count (default 1)")
    t.add_argument("--push-forward", type=int, default=0,
                   help="extra unrolled steps of push-forward training, count >= 0 "
                   "(default 0)")
    t.add_argument("--unroll", type=count, default=1,
                   help="particles: frames of the loss, count >= 1: K > 1 rolls the model K "
                   "frames on its own predictions and back-propagates through them "
                   "(default 1: the one-step loss)")
    t.add_argument("--momentum-weight", type=non_negative, default=0.0,
                   help="particles: weight of the momentum-conservation loss, "
                   "dimensionless (default 0)")
    t.add_argument("--huber-delta", type=non_negative, default=0.0,
                   help="particles: Huber loss on the normalised acceleration, linear beyond "
                   "this many standard deviations per component; 0 = MSE (default 0)")
    t.add_argument("--target-scale-floor", type=non_negative, default=0.0, metavar="F",
                   help="particles: divide each window's loss by its mean squared normalised "
                   "target + F (a relative error: impacts and slow flow weigh alike); "
                   "0 = off (default 0)")
    t.add_argument("--seed", type=int, default=0, help="random seed, integer (default 0)")
    t.add_argument("--validate-every", type=count, default=2000,
                   help="steps between validation rollouts, count (default 2000)")
    t.add_argument("--checkpoint-every", type=count, default=500,
                   help="steps between checkpoints, count (default 500)")
    t.add_argument("--steps-per-call", type=count, default=None,
                   help="particles: optimiser steps per device call (default: TrainConfig's; "
                        "XLA's CPU runtime maps its temporary buffer once per call, so several "
                        "steps per call are faster; 1 = one step per call)")
    t.add_argument("--pad-nodes", type=count, default=1,
                   help="particles, datasets with scene families: pad each window's node count "
                        "up to a multiple of this (fewer compiled programs; default 1 = none)")
    t.add_argument("--family-weights", default=None, metavar="F=W,...",
                   help="particles, datasets with scene families: sampling weight per family, "
                        "e.g. squares=1,columns=2 (default equal)")
    t.add_argument("--early-windows", default=None, metavar="FRAMES:WEIGHT",
                   help="particles: draw the windows that start in each trajectory's first "
                        "FRAMES (strided) frames WEIGHT times as often, e.g. 5:4 (a flow's "
                        "release from rest)")
    t.add_argument("--active-windows", type=non_negative, default=0.0, metavar="W",
                   help="particles: draw each window start with weight 1 + W x its activity "
                        "over the mean (how much its nodes' accelerations differ: impacts, "
                        "releases, flows above free flight and rest; default 0 = uniform)")
    t.add_argument("--mirror", type=probability, default=0.0, metavar="P",
                   help="particles: reflect each training window about its box's vertical "
                        "mid-plane with probability P (flows to both sides from one-sided "
                        "data; default 0)")
    t.add_argument("--obstacle-features", action="store_true",
                   help="particles: give the network the distance and normal to the nearest "
                        "box obstacle (datasets that record obstacles, e.g. --kind granular)")
    t.add_argument("--init-from", default=None,
                   help="model folder to fine-tune from (same configuration, fresh optimiser)")
    t.add_argument("--no-viscosity", action="store_true",
                   help="mesh: do not give the flow's viscosity to the network")
    add_distributed_arguments(t)
    t.set_defaults(func=_train)

    a = sub.add_parser("average", help="uniform weight average of GNS or MeshGraphNet models "
                       "fine-tuned from one parent (same network and normaliser)")
    a.add_argument("models", nargs="+", help="model folders")
    a.add_argument("--out", required=True, help="folder of the averaged model")
    a.set_defaults(func=_average)
