"""The GNS training run: data, normaliser, neighbour lists per node count, validation
rollouts and the model folder, around the shared loop :func:`diffgns.graph.fit.fit`
(checkpoints, exact resume, logs, SIGTERM, learning-rate schedule). Used by ``diffgns train``.

Runs in one process or several (:mod:`diffgns.distributed`; every process calls
:func:`train` with the same arguments, process 0 writes the files).

Files in ``out_dir``: ``checkpoint/`` (orbax; + ``checkpoint.json``: step, configs),
``train_log.csv`` (step, loss, lr, seconds), ``valid_log.jsonl`` (validation metrics),
``model/`` (the final model: ``params.msgpack`` and ``config.json``, loadable with
:func:`load_model`).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from diffgns.distributed import barrier, is_main, to_host
from diffgns.errors import InputError
from diffgns.graph.checkpoints import load_checkpoint
from diffgns.graph.data import (
    WindowSampler,
    check_one_dimension,
    frame_statistics,
    load_trajectories,
)
from diffgns.graph.evaluate import evaluate
from diffgns.graph.features import ParticleStats
from diffgns.graph.fit import (
    TrainConfig,
    TrainingInterrupted,
    average_params,
    fit,
    has_checkpoint,
    step_rng,
)
from diffgns.graph.geometry import obstacle_array
from diffgns.graph.gns import GNS, GNSConfig
from diffgns.graph.sampling import FamilyWindowSampler
from diffgns.graph.training import (
    NeighborLists,
    Trainer,
    step_with_reallocation,
    steps_with_reallocation,
)
from diffgns.models import model_dir, model_path

#: third seed word of the generator that draws a block's node-count group (train's draw)
_GROUP_STREAM = 1


def save_model(out: Path, gns: GNS, params, info: dict) -> None:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "params.msgpack").write_bytes(serialization.to_bytes(params))
    norm = dict(vel_mean=gns.normalizer.velocity.mean.tolist(),
                vel_std=gns.normalizer.velocity.std.tolist(),
                acc_mean=gns.normalizer.acceleration.mean.tolist(),
                acc_std=gns.normalizer.acceleration.std.tolist())
    cfg = dataclasses.asdict(gns.config)
    info = {k: v for k, v in info.items() if k not in ("gns", "normalizer")}
    (out / "config.json").write_text(json.dumps(dict(gns=cfg, normalizer=norm, **info),
                                                indent=2, default=str))


def load_model(path: str | Path) -> tuple[GNS, dict, dict]:
    """(GNS, params, info) from a model folder written by :func:`save_model`, a training
    run folder holding one in ``model/``, or a shipped model's name
    (:func:`diffgns.models.model_dir`; a wrong path raises its ``ModelFolderError``)."""
    path = model_dir(path, "config.json")
    info = json.loads((path / "config.json").read_text())
    g = dict(info["gns"])
    g["bounds"] = tuple(tuple(b) for b in g["bounds"])
    cfg = GNSConfig(**g)
    n = info["normalizer"]
    norm = ParticleStats.from_metadata(dict(vel_mean=n["vel_mean"], vel_std=n["vel_std"],
                                          acc_mean=n["acc_mean"], acc_std=n["acc_std"]), 0.0)
    src = info.get("source") or {}
    gns = GNS(cfg, norm, frame_dt=float(src.get("dt", 2.5e-3)) * int(info.get("frame_stride", 1)))
    C = cfg.history
    template = gns.init_network(jax.random.PRNGKey(0),
                                (jnp.zeros((2, C + 1, cfg.dim)) + 0.5,
                                 jnp.zeros(2, jnp.int32), jnp.zeros(2)))
    params = serialization.from_bytes(template, (path / "params.msgpack").read_bytes())
    return gns, params, info


def average_models(paths, out: str | Path) -> Path:
    """Write to ``out`` the uniform average of the parameters of models ``paths`` (a "model
    soup"). Meant for models fine-tuned from one parent: their networks and normalisers must
    be identical (only the training noise and the neighbour-list head-room, recorded in the
    config, may differ; the first model's config is kept). Returns ``out``."""
    if len(paths) < 2:
        raise ValueError("average_models needs at least two models")
    for p in paths:
        _gns_folder(p)
    models = [load_model(p) for p in paths]
    g0, _, info0 = models[0]
    for p, (g, _, info) in zip(paths[1:], models[1:]):
        if diff := _network_difference(g0.config, g.config):
            raise ValueError(f"cannot average {p} with {paths[0]}: different configuration "
                             f"(first, this) = {diff}")
        if info["normalizer"] != info0["normalizer"]:
            raise ValueError(f"cannot average {p} with {paths[0]}: different normaliser")
    avg = average_params([m[1] for m in models])
    info = dict(info0, averaged_from=[str(p) for p in paths])
    save_model(Path(out), g0, avg, info)
    return Path(out)


def _granular_source(paths) -> dict:
    """What the MPM of the scene-family datasets ``paths`` was (their recipes): ``dx`` (m),
    ``particles_per_cell``, its transfer (``flip``) and the sand (``material``: E, nu, rho,
    cohesion; Pa, kg/m^3), so that :func:`~diffgns.graph.support.check_scene` refuses a
    scene at another resolution, with another transfer or of another sand. Datasets that
    differ in any of them are refused."""
    from diffgns.io.families_data import read_ranges
    from diffgns.scene.families import FamilyRanges
    from diffgns.scene.materials import Sand

    got = {}
    for p in paths:
        ranges = read_ranges(p)
        # files made before the recipe recorded E or flip had the defaults
        sand = Sand(E=float(ranges.get("young_modulus", FamilyRanges().young_modulus)))
        got[str(p)] = dict(dx=ranges["dx"], particles_per_cell=ranges["particles_per_cell"],
                           flip=float(ranges.get("flip", 0.0)),
                           material={k: float(getattr(sand, k))
                                     for k in ("E", "nu", "rho", "cohesion")})
    if len({json.dumps(v, sort_keys=True) for v in got.values()}) > 1:
        raise InputError("--data", f"the datasets were made by different MPMs (resolution, "
                         f"transfer or sand: {got})", "train on data of one MPM and one sand")
    return next(iter(got.values()))


def friction_range(trajs) -> list[float] | None:
    """``[lo, hi]``, degrees: the friction angles of the trajectories' material input
    (``Trajectory.material``, tan(friction angle) per particle; zeros, data without a
    material, are skipped); None when no trajectory has one."""
    tan = [np.asarray(t.material, np.float64).ravel() for t in trajs]
    tan_all = np.concatenate(tan) if tan else np.zeros(0)
    tan_all = tan_all[tan_all > 0]
    if not tan_all.size:
        return None
    from diffgns.scene.materials import friction_angle_of_feature

    return [friction_angle_of_feature(tan_all.min()), friction_angle_of_feature(tan_all.max())]


def build(train_paths, gns_kw: dict, factor: int = 1, frame_stride: int = 1):
    """Load training data and build the GNS whose normaliser matches it. The data fix the
    model's dimension (2D or 3D: the axes of the union of the training boxes); datasets of
    mixed dimension are refused (:class:`~diffgns.errors.InputError`)."""
    trajs, meta, dims = [], {}, {}
    for p in train_paths:
        t, m = load_trajectories(p, factor, frame_stride)
        dims[str(p)] = _dimension(t, f"--data {p}")
        trajs += t
        meta = meta or m
    if len(set(dims.values())) > 1:
        raise InputError("--data", "the datasets mix dimensions (" + ", ".join(
            f"{p}: {d}D" for p, d in dims.items()) + ")",
            "train a GNS on 2D or on 3D data, not both")
    if gns_kw.get("use_obstacles"):
        for i, t in enumerate(trajs):
            try:
                obstacle_array(t.obstacles, 0, len(t.bounds))
            except ValueError as e:
                raise InputError("--obstacle-features", f"training trajectory {i}: {e}",
                                 "store each obstacle as [lo..., hi...] with one pair per axis "
                                 "of the data") from None
    stats = frame_statistics(trajs)
    # What the data came from (e.g. the MPM resolution a hybrid must pair this model with).
    stats["source"] = {k: meta[k] for k in ("kind", "width", "cells_across", "dt", "bounds")
                       if k in meta}
    if meta.get("kind") == "granular":  # the MPM and its sand, from the files' recipes
        stats["source"].update(_granular_source(train_paths))
    # every training box: the network saw each trajectory's own walls (graph.geometry), so
    # the model supports those boxes (graph.support)
    stats["source"]["boxes"] = sorted({tuple(map(tuple, np.asarray(t.bounds, float).tolist()))
                                       for t in trajs})
    if (phi := friction_range(trajs)) is not None:  # graph.support warns outside it
        stats["source"]["friction_angle"] = phi
    bounds = gns_kw.pop("bounds", None) or _union_bounds(trajs)
    if trajs and len(bounds) != len(trajs[0].bounds):
        raise InputError("bounds", f"{len(bounds)}D bounds for {len(trajs[0].bounds)}D data",
                         "give bounds of the data's dimension, or none (the union of the "
                         "training boxes)")
    cfg = GNSConfig(bounds=bounds, **gns_kw)
    frame_dt = float(trajs[0].frame_dt) if trajs else 2.5e-3
    return GNS(cfg, ParticleStats.from_metadata(stats, cfg.noise_std), frame_dt), trajs, stats


def _initial_model(path, gns: GNS):
    """(GNS with the model's normaliser, its params) from ``path``; the config must match
    except for the training noise ``noise_std``, the neighbour-list head-room
    ``capacity_multiplier`` and the cell-list extent ``bounds`` (see
    :func:`_network_difference`; the model's normaliser, which folded in its own noise, is
    kept; the requested config is used). A model without obstacle inputs may start one with
    them (:func:`with_obstacle_inputs`): it then predicts what the model did, obstacles
    ignored, until training teaches it otherwise."""
    dim = len(json.loads((_gns_folder(path) / "config.json").read_text())["gns"]["bounds"])
    if dim != gns.config.dim:  # before loading: refused at once
        raise InputError("--init-from", f"model {path} is {dim}D but the training data are "
                         f"{gns.config.dim}D", "fine-tune a model of the data's dimension, "
                         "or train from scratch")
    base, params, _ = load_model(path)
    diff = _network_difference(base.config, gns.config)
    if diff.get("use_obstacles") == (False, True):
        params = with_obstacle_inputs(params, base.config)
        del diff["use_obstacles"]
    if diff:
        raise ValueError(f"--init-from model {path} has a different configuration: "
                         f"(model, requested) = {diff}")
    return GNS(gns.config, base.normalizer, gns.frame_dt), params


def with_obstacle_inputs(params, config: GNSConfig):
    """The parameters of a model without obstacle inputs (``config.use_obstacles`` False),
    widened for the ``1 + d`` obstacle columns of :func:`diffgns.graph.features.node_features`
    (after the wall distances): zero rows in the node encoder's first kernel, so that the
    widened network computes exactly what the model did whatever the obstacle features."""
    if config.use_obstacles:
        raise ValueError("with_obstacle_inputs: the model already has obstacle inputs")
    d = config.dim
    at = d * config.history + 2 * d  # velocity history, then wall distances
    layer = params["params"]["node_encoder"]["hidden_0"]
    k = layer["kernel"]
    wide = jnp.concatenate([k[:at], jnp.zeros((1 + d, k.shape[1]), k.dtype), k[at:]])
    return {**params, "params": {
        **params["params"], "node_encoder": {**params["params"]["node_encoder"],
                                             "hidden_0": {**layer, "kernel": wide}}}}


def _gns_folder(p) -> Path:
    """The particle-GNS model folder of ``p`` (itself or ``p/model``); ValueError if its
    ``config.json`` describes another network, ``ModelFolderError`` if there is none."""
    path = model_path(p)
    for folder in (path, path / "model"):
        if (folder / "config.json").is_file():
            if "gns" not in json.loads((folder / "config.json").read_text()):
                raise ValueError(f"{p} is not a particle GNS model folder")
            return folder
    return model_dir(p, "config.json")


def _network_difference(a: GNSConfig, b: GNSConfig) -> dict:
    """{field: (a's, b's)} of the config fields in which a and b differ, ignoring the training
    noise ``noise_std``, the neighbour-list head-room ``capacity_multiplier`` and the
    neighbour list's extent ``bounds`` (the walls are inputs, :mod:`diffgns.graph.geometry`;
    no weight depends on the box) (empty when they describe the same network)."""
    return {k: (getattr(a, k), getattr(b, k)) for k in dataclasses.asdict(a)
            if k not in ("noise_std", "capacity_multiplier", "bounds")
            and getattr(a, k) != getattr(b, k)}


def _union_bounds(trajs):
    """The union of the trajectories' boxes, ((lo, hi), ...) m, one pair per axis."""
    b = np.array([t.bounds for t in trajs])  # (n, d, 2)
    return tuple((float(b[:, k, 0].min()), float(b[:, k, 1].max()))
                 for k in range(b.shape[1]))


def _dimension(trajs, what: str) -> int:
    """The one dimension (2 or 3) of ``trajs`` (positions and boxes); InputError naming
    ``what`` when they mix dimensions or a box does not match its positions."""
    try:
        dim = check_one_dimension(trajs, "its trajectories")
    except ValueError as e:
        raise InputError(what, str(e)) from None
    bad = [i for i, t in enumerate(trajs) if len(t.bounds) != dim]
    if bad:
        raise InputError(what, f"trajectories {bad} have {dim}D positions but boxes of another "
                         "dimension", "rewrite the dataset (bounds: one [lo, hi] per axis)")
    return dim


def _families(train_paths) -> list[str] | None:
    """The scene family of every training trajectory (in :func:`load_trajectories` order),
    or None when no file records families (e.g. column or squares datasets)."""
    from diffgns.io.families_data import read_families

    out: list[str] = []
    for p in train_paths:
        out += list(read_families(p).values()) if Path(p).suffix != ".npz" else []
    return out if any(out) else None


def make_sampler(gns: GNS, trajs, tcfg: TrainConfig, families=None, pad_to: int = 1,
                 family_weights: dict | None = None,
                 early_windows: tuple[int, float] | None = None, mirror: float = 0.0,
                 active_windows: float = 0.0) -> WindowSampler:
    """The training windows: per scene family (equal weights unless ``family_weights``),
    node counts padded up to a multiple of ``pad_to`` (fewer compiled programs), when
    ``families`` names one per trajectory; else plain node-count groups. ``early_windows``
    ``(frames, weight)``: windows starting in each trajectory's first ``frames`` (strided)
    frames drawn ``weight`` times as often (:class:`WindowSampler`); ``mirror``: probability
    of reflecting a window about its box's vertical mid-plane
    (:func:`~diffgns.graph.data.mirror_window`); ``active_windows``: weight of a window's
    activity in drawing its start (:func:`~diffgns.graph.data.window_activity`)."""
    frames, weight = early_windows or (0, 1.0)
    extra = tcfg.push_forward + tcfg.unroll - 1  # frames past the one-step window
    early = dict(early_frames=int(frames), early_weight=float(weight), mirror=float(mirror),
                 active_weight=float(active_windows))
    if families is None:
        if pad_to > 1 or family_weights:
            raise InputError("--pad-nodes/--family-weights", "the training data records no "
                             "scene families", "use data of diffgns dataset --kind granular, "
                             "or drop these options")
        return WindowSampler(trajs, gns.config.history, extra, **early)
    if len(families) != len(trajs):
        raise ValueError(f"{len(families)} families for {len(trajs)} trajectories")
    return FamilyWindowSampler(trajs, gns.config.history, extra, **early,
                               families=families, weights=family_weights, pad_to=pad_to,
                               bounds=gns.config.bounds, radius=gns.config.radius)


def train(train_paths, out_dir, gns_kw: dict, tcfg: TrainConfig, valid_path=None,
          factor: int = 1, frame_stride: int = 1, n_valid: int = 2, progress: bool = True,
          init_from=None, pad_to: int = 1, family_weights: dict | None = None,
          early_windows: tuple[int, float] | None = None, mirror: float = 0.0,
          active_windows: float = 0.0):
    """Train (or resume) a GNS; returns (gns, params).

    Datasets that record a scene family per trajectory (``diffgns dataset --kind
    granular``) are sampled per family (:func:`make_sampler`; ``pad_to``,
    ``family_weights``; ``early_windows``, ``mirror`` and ``active_windows`` for any data);
    every window carries its trajectory's walls and obstacles (:mod:`diffgns.graph.geometry`).

    ``init_from``: a model folder whose parameters start a fresh run (fine-tuning, e.g. with
    push-forward); its configuration must equal the one requested here, and the run keeps its
    normalisation statistics. Ignored when ``out_dir`` already holds a checkpoint (resume).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    gns, trajs, stats = build(train_paths, dict(gns_kw), factor, frame_stride)
    valid = load_trajectories(valid_path, factor, frame_stride)[0][:n_valid] if valid_path \
        else []
    if valid and (d := _dimension(valid, f"--valid {valid_path}")) != gns.config.dim:
        raise InputError("--valid", f"{valid_path} is {d}D but the training data are "
                         f"{gns.config.dim}D", f"validate on {gns.config.dim}D data")
    families = _families(train_paths)
    sampler = make_sampler(gns, trajs, tcfg, families, pad_to, family_weights, early_windows,
                           mirror, active_windows)
    trainer = Trainer(gns, tcfg)
    C = gns.config.history
    t0 = trajs[0]
    if init_from is not None:
        # the model (and its normaliser) of init_from, also when resuming: the checkpoint's
        # params were trained in that normaliser's units, not in the data's with this noise
        gns, params = _initial_model(init_from, gns)
        trainer = Trainer(gns, tcfg)
        if not has_checkpoint(out):
            print(f"fine-tuning from {init_from}")
    else:  # a new network (or a resumed one, whose params the checkpoint replaces)
        params = gns.init_network(jax.random.PRNGKey(tcfg.seed),
                                  (jnp.swapaxes(jnp.asarray(t0.positions[: C + 1]), 0, 1),
                                   jnp.asarray(t0.particle_type), jnp.asarray(t0.material)))
    source = stats.pop("source")
    info = dict(gns=dataclasses.asdict(gns.config), train=dataclasses.asdict(tcfg),
                stats=stats, data=[str(p) for p in train_paths], factor=factor,
                frame_stride=frame_stride, source=source, pad_to=pad_to,
                family_weights=family_weights, early_windows=early_windows, mirror=mirror,
                active_windows=active_windows,
                families=None if families is None else sorted(set(families)))
    if is_main():
        (out / "train_config.json").write_text(json.dumps(info, indent=2, default=str))
    nbrs = NeighborLists()  # capacities checkpointed: exact resume

    K = tcfg.steps_per_call

    def draw(s: int):
        # (batch, key) of step s, a function of (seed, s) alone (exact resume). The node-count
        # group comes from a stream of its own, per block of K steps, so the steps of a block
        # share it (one device call, update_many) and the windows are the same for any K
        # when there is one group
        rng, key = step_rng(tcfg.seed, s)
        group_rng = np.random.default_rng([tcfg.seed, s - s % K, _GROUP_STREAM])
        return sampler.sample(rng, tcfg.batch_size, group_rng), key

    def update(params, opt_state, step):
        batch, key = draw(step)
        params, opt_state, loss = step_with_reallocation(trainer, params, opt_state, batch,
                                                         nbrs, key)
        return params, opt_state, (loss,)

    def update_many(params, opt_state, step, n):
        # the batches of steps step.. step+n-1, cut where the node count changes (one
        # device call runs one node count); a function of the step alone (exact resume)
        batches, keys = [], []
        for s in range(step, step + n):
            b, key = draw(s)
            if batches and b["positions"].shape != batches[0]["positions"].shape:
                break
            batches.append(b)
            keys.append(key)
        params, opt_state, losses = steps_with_reallocation(trainer, params, opt_state,
                                                            batches, nbrs, keys)
        return params, opt_state, (losses,)

    validate = (lambda p: evaluate(gns, p, valid)["mean"]) if valid else None
    opt_state = trainer.opt.init(params)
    try:
        params, opt_state, step = fit(
            update, params, opt_state, tcfg, out, info, ["loss"], desc="train",
            progress=progress, validate=validate, host_state=nbrs, update_many=update_many,
            show=("runout_rel_error", "final_position_error_rel_displacement"))
    except TrainingInterrupted as e:  # SIGTERM/SIGINT: also the model of the checkpoint
        if is_main():  # (to evaluate a run part-way; the same command resumes it)
            params, _, step = load_checkpoint(e.checkpoint, params, opt_state)
            save_model(out / "model_partial", gns, to_host(params),
                       dict(info, steps=step, partial=True))
        raise
    params = to_host(params)
    if is_main():
        save_model(out / "model", gns, params, dict(info, steps=step))
    barrier("diffgns-train-model-written")
    return gns, params
