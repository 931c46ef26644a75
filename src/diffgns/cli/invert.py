"""``diffgns invert``: fit scene parameters to an observation through any simulator.

    diffgns simulate --scene scenes/sand_into_obstacle.toml --frames 200 --out results/obs
    diffgns invert scenes/sand_into_obstacle.toml --fit friction_angle=40:0:90 \\
        --observation results/obs/trajectory.h5 --simulator mpm --out results/invert
    diffgns invert scenes/sand_into_obstacle.toml --fit friction_angle=40:0:90 \\
        --observed-runout 0.30 --frames 200 --simulator gns

The scene file gives everything not fitted. ``--fit name=start:lo:hi`` (repeatable) names a
parameter (any ``MPMParams`` leaf, see :mod:`diffgns.inverse.parameters`, or
``aspect_ratio`` for a scene of one rectangular body), its start and its bounds. The
observation is a trajectory (HDF5 from ``diffgns simulate`` or ``diffgns dataset``) or a
measured runout (m from the box's left wall). Learned simulators observe the scene as their
model folder says (particles per node, frame stride) and refuse a scene they do not support;
the MPM observes every particle and frame unless told otherwise (``--coarse-grain``,
``--frame-stride``, or a ``--model`` to copy them from). Prints a line per iteration; writes
``summary.json``, ``convergence.png`` and ``deposits.png`` to ``--out``.
"""
from __future__ import annotations

import sys
import time

from diffgns.cli.checks import count, finite, positive
from diffgns.cli.evaluate import SCHEDULE_OPTIONS, add_schedule_arguments, hybrid_schedule

#: as in :mod:`diffgns.inverse.job` (repeated so that building the parser imports no JAX)
SIMULATORS = ("mpm", "gns", "hybrid")
OBJECTIVES = ("runout", "runout-max", "runout-frame", "deposit")


def _error(msg: str) -> int:
    print(f"diffgns invert: error: {msg}", file=sys.stderr)
    return 2


def _load_observation(args):
    """(positions (T, N, 2), frame_dt s) of the observed trajectory."""
    from diffgns.io.dataset import iter_dataset

    trajs = list(iter_dataset(args.observation))
    if not -len(trajs) <= args.index < len(trajs):
        raise ValueError(f"{args.observation} holds {len(trajs)} trajectories; --index "
                         f"{args.index} is out of range")
    t = trajs[args.index]
    return t.positions, float(t.frame_dt)


def _n_frames(args, scene, stride: int, observed) -> int:
    """MPM frames of the rollouts: --frames, else the observation's duration."""
    if args.frames is not None:
        return args.frames
    if observed is None:
        raise ValueError("--observed-runout needs --frames (MPM frames until the runout is "
                         "measured)")
    pos, dt = observed
    per = dt / float(scene.frame_dt)
    if abs(per - round(per)) > 1e-6 or round(per) not in (1, stride):
        raise ValueError(f"the observation's frames ({dt:g} s) are neither the scene's MPM "
                         f"frames ({scene.frame_dt:g} s) nor every {stride}th of them")
    return (len(pos) - 1) * int(round(per))


def run(args) -> int:
    import jax

    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    from diffgns.inverse.job import make_objective, make_simulator, solve
    from diffgns.inverse.observation import SceneObservation
    from diffgns.inverse.parameters import parse_fit, parse_scan
    from diffgns.inverse.simulators import default_model, load_gns
    from diffgns.scene.files import load_scene

    t_start = time.perf_counter()
    if args.simulator != "mpm" or args.model:
        if args.coarse_grain or args.frame_stride:
            raise ValueError("--coarse-grain and --frame-stride are for the MPM alone; with "
                             "--model (or a learned simulator) the model folder sets them")
    given = [f"--{k.replace('_', '-')}" for k in SCHEDULE_OPTIONS if getattr(args, k) is not None]
    if given and args.simulator != "hybrid":
        raise ValueError(f"{', '.join(given)} set the hybrid's schedule; use them with "
                         "--simulator hybrid")
    if args.frames is not None and args.frames < 1:
        raise ValueError(f"--frames must be >= 1, got {args.frames}")
    fits = [parse_fit(s) for s in args.fit]
    theta0 = {name: start for name, start, _ in fits}
    transforms = {name: tf for name, _, tf in fits if tf is not None}
    truth = dict(parse_fit(s)[:2] for s in args.truth)
    scan = dict(parse_scan(s) for s in args.scan) or None
    scene = load_scene(args.scene)
    if args.simulator != "mpm" and not args.model:
        args.model = default_model(scene)
        print(f"model: {args.model} (the most accurate shipped model for this scene; "
              "--model to choose)", flush=True)
    loaded = load_gns(args.model) if args.model else None
    info = loaded[2] if loaded else None
    stride = int(info.get("frame_stride", 1)) if info else (args.frame_stride or 1)
    observed = _load_observation(args) if args.observation else None
    n_frames = _n_frames(args, scene, stride, observed)
    if info is not None and args.simulator != "mpm":
        obs = SceneObservation.for_model(scene, info, n_frames, args.dtype, model=args.model)
    elif info is not None:  # the MPM seen as the model sees it (no support check)
        obs = SceneObservation(scene, n_frames, int(info.get("factor", 1)), stride, args.dtype)
    else:
        obs = SceneObservation(scene, n_frames, args.coarse_grain or 1, stride, args.dtype)
    for w in obs.warnings:
        print(f"warning: {args.model} {w}", flush=True)
    nodes, history = None, "mpm"
    if observed is not None:
        nodes = obs.observe_trajectory(*observed)
        if obs.same_particles(observed[0][0]):
            history = "observed"
    if args.history != "auto":
        history = args.history
    what = (f"{args.observation} [{args.index}]" if observed is not None
            else f"runout {args.observed_runout:g} m")
    print(f"scene {args.scene}: {scene.n_particles} particles -> {obs.n_nodes} nodes, "
          f"{obs.n_obs} frames of {obs.frame_dt * 1e3:g} ms ({n_frames} MPM frames of "
          f"{scene.substeps} substeps); observation: {what}; simulator: {args.simulator}"
          + (f" ({args.model}, history {history})" if args.simulator == "gns" else ""),
          flush=True)
    schedule = hybrid_schedule(args) if args.simulator == "hybrid" else None
    if schedule is not None:
        print(f"hybrid schedule: {schedule.label}", flush=True)
    sim = make_simulator(args.simulator, obs, args.model, loaded=loaded, observed=nodes,
                         history=history, block=args.block, theta0=theta0, schedule=schedule)
    name = args.objective or ("runout" if nodes is not None else "runout-max")
    objective = make_objective(name, obs, observed=nodes, frame=args.frame,
                               observed_runout=args.observed_runout, origin=args.origin,
                               center=args.center)
    solve(sim, objective, theta0, obs, args.out, transforms=transforms,
          optimizer=args.optimizer, lr=args.lr, max_iter=args.max_iter,
          step_tol=args.step_tol, gradient=args.gradient, observed=nodes, truth=truth,
          label=args.simulator, t_start=t_start, scan=scan, starts=args.starts,
          extra=dict(scene=str(args.scene), objective=name,
                     observation=what, model=str(args.model) if loaded else None,
                     history=history if args.simulator == "gns" else None))
    return 0


def _invert(args) -> int:
    from diffgns.io.files import check_input_file

    if args.observation:
        check_input_file(args.observation, "--observation")
    from diffgns.errors import SceneError
    from diffgns.graph.support import UnsupportedSceneError
    try:
        return run(args)
    except UnsupportedSceneError as e:
        return _error(f"{e}; use --simulator mpm, or a model trained on such scenes")
    except SceneError:
        raise  # diffgns: error: ... (exit 2)
    except (ValueError, FileNotFoundError, KeyError) as e:
        return _error(str(e))


def register(sub) -> None:
    """Add the ``invert`` parser to ``sub``."""
    p = sub.add_parser("invert", help="fit scene parameters (friction angle, ...) to an "
                       "observed trajectory or runout through the MPM, a GNS or the hybrid",
                       description=__doc__.split("\n\n")[-1])
    p.add_argument("scene", help="scene TOML file")
    p.add_argument("--fit", action="append", required=True, metavar="NAME=START:LO:HI",
                   help="a parameter to fit, its start and bounds (repeatable), e.g. "
                   "friction_angle=40:0:90, 'wall_mu[bottom]=0.3:0:2', aspect_ratio=2:0.25:4")
    o = p.add_mutually_exclusive_group(required=True)
    o.add_argument("--observation", help="observed trajectory, HDF5 (diffgns simulate/dataset)")
    o.add_argument("--observed-runout", type=finite,
                   help="observed runout, m from --origin (3D: radius, m, about --center)")
    p.add_argument("--index", type=int, default=0,
                   help="trajectory of --observation, integer (default 0)")
    p.add_argument("--frames", type=count, default=None,
                   help="MPM frames to simulate, count (default: the observation's duration)")
    p.add_argument("--objective", default=None, choices=list(OBJECTIVES),
                   help="runout: soft final runout (default with a trajectory); runout-max: "
                   "farthest node (default with --observed-runout); runout-frame: soft runout "
                   "at --frame; deposit: deposit profile at --frame")
    p.add_argument("--frame", type=int, default=-1,
                   help="observed frame of the objective, integer (negative: from the end; "
                   "default -1)")
    p.add_argument("--origin", type=finite, default=None,
                   help="x from which runouts are measured, m (default: the left wall)")
    p.add_argument("--center", type=finite, nargs=2, default=None, metavar=("CX", "CZ"),
                   help="3D: measure runouts as the radius about the vertical axis x = CX, "
                   "z = CZ, m (default: the axis of the scene's cylinder body; else x from "
                   "--origin)")
    p.add_argument("--simulator", default="mpm", choices=list(SIMULATORS),
                   help="simulator of the forward model (default mpm)")
    p.add_argument("--model", default=None,
                   help="GNS model folder or shipped name (gns/hybrid; default: the most "
                   "accurate shipped model that supports the scene without a warning: "
                   "gns_cg16_pfn for columns against the left wall, gns_general for "
                   "obstacles, moving bodies or the right wall); "
                   "with the MPM: observe as this model does")
    g = p.add_argument_group("the hybrid's schedule (--simulator hybrid; defaults: those of "
                             "`diffgns hybrid`)")
    add_schedule_arguments(g)
    p.add_argument("--history", default="auto", choices=["auto", "observed", "mpm"],
                   help="GNS initial frames: the observed ones, or a differentiable MPM "
                   "start-up at the trial parameters (auto: observed when the observation "
                   "has the scene's particles)")
    p.add_argument("--coarse-grain", type=count, default=None,
                   help="MPM only: particles per observed node (default 1)")
    p.add_argument("--frame-stride", type=count, default=None,
                   help="MPM only: MPM frames per observed frame (default 1)")
    p.add_argument("--optimizer", default="gauss-newton", choices=["gauss-newton", "adam", "sgd"],
                   help="optimiser (default gauss-newton)")
    p.add_argument("--lr", type=positive, default=None,
                   help="gauss-newton: step scale (1); adam/sgd: learning rate on the "
                   "transformed parameters (0.1)")
    p.add_argument("--max-iter", type=count, default=20,
                   help="optimiser iterations at most, count (default 20)")
    p.add_argument("--step-tol", type=positive, default=0.01,
                   help="stop when every step is below this (parameter units)")
    p.add_argument("--gradient", default="auto", choices=["auto", "ad", "fd"],
                   help="ad: automatic differentiation; fd: finite differences; auto: ad "
                   "until a step raises the loss or revisits a point, then back to the best "
                   "point with differences over 1%% of each parameter and a halved step "
                   "(default auto)")
    p.add_argument("--block", type=int, default=None,
                   help="frames per jax.checkpoint block (default MPM 25, GNS/hybrid 10; 0: "
                   "none)")
    p.add_argument("--scan", action="append", default=[], metavar="NAME=LO:HI:N",
                   help="start from the lowest loss of N values of NAME from LO to HI "
                   "(forward runs; for a loss with several minima), e.g. "
                   "friction_angle=15:50:8")
    p.add_argument("--starts", type=int, default=1,
                   help="with --scan: run the local method from this many of the lowest "
                   "scan points and keep the lowest end (a minimum's basin can be narrower "
                   "than the grid; default 1)")
    p.add_argument("--truth", action="append", default=[], metavar="NAME=VALUE",
                   help="the true value when known (figures and summary error)")
    p.add_argument("--dtype", default=None, choices=["float32", "float64"],
                   help="floating-point precision (default: JAX's, float32 unless "
                   "JAX_ENABLE_X64 is set)")
    p.add_argument("--out", default="results/invert",
                   help="output folder (summary.json, figures) (default results/invert)")
    p.set_defaults(func=_invert)
