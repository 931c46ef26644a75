"""MeshGraphNet training in stages: input noise per stage and unrolled training through rollouts.

Issue 23's training levers, on the shared optimiser loop :func:`diffgns.graph.fit.fit`
(checkpoints, exact resume, SIGTERM):

* **stages** (:class:`Stage`): the noise std (m/s, on fluid-node input velocities) and the
  unroll length ``K`` are functions of the optimiser step, so one run anneals the noise (e.g.
  halving it stage by stage) and a resumed run is bit-identical to an uninterrupted one (the
  stage, batch and noise are functions of the step);
* **unrolled loss** (:func:`unrolled_loss`): from a data frame ``v_t`` (plus noise) the model
  rolls ``K`` frames on its own predictions and the loss is the mean over the ``K`` steps of
  the normalised one-step error against the data,
  ``|(v^model_{k+1} - v^data_{t+k+1}) / s_dv|^2`` on fluid/outflow nodes plus the pressure
  term; gradients flow back through the whole rollout (reverse mode through ``lax.scan``
  with every frame under ``jax.checkpoint``, :func:`diffgns.interface.scan_frames`, so
  memory is one frame's activations plus ``K`` carries). ``K = 1`` is exactly the one-step
  loss of :func:`diffgns.mesh.train._loss` (target against the noisy input);
* **push-forward** (``push = P`` in a stage): the model first rolls ``P`` frames from the
  noisy data frame without gradients, and the ``K``-frame loss starts from that state of its
  own, so the network learns to steer its own accumulated errors back to the data;
* **continuity term** (``--divergence-weight``): each frame's loss also weighs the discrete
  divergence of the velocity error (:func:`~diffgns.mesh.meshnet.divergence_loss`), the part
  of an error that breaks continuity: the spurious state long rollouts fall into at high Re
  (flow into the cylinder's front, a jet from its stagnation point) has 4-5x the data's
  divergence, and it rises before the drag collapses (issue 23, 2026-12-06);
* on SIGTERM or SIGINT the checkpoint is written (by :func:`~diffgns.graph.fit.fit`), then
  ``out/model`` from it, and the process exits with 143 / 130; the same command resumes;
* the normalisers hold the data statistics without the noise (unlike
  :func:`diffgns.mesh.train.train`), so changing the noise between stages does not change
  what the network sees.

``python -m diffgns.mesh.stages --data D --out RUN --stages 4000:0.005:1,8000:0.002:4:16``
trains (or resumes) a run; ``make meshnet-train`` runs the configuration of the shipped
checkpoint.
"""
from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from diffgns.errors import InputError, run_module
from diffgns.graph.fit import (
    TrainConfig,
    TrainingInterrupted,
    fit,
    load_checkpoint,
    make_optimizer,
    step_rng,
)
from diffgns.interface import scan_frames
from diffgns.io.dataset import read_metadata
from diffgns.io.files import check_input_file
from diffgns.mesh.meshnet import (
    FLUID,
    MeshGraph,
    MeshNet,
    MeshNetConfig,
    divergence_loss,
    near_wall,
    node_loss,
)
from diffgns.mesh.train import (
    fine_tune_start,
    graphs_of,
    load_cylinder,
    padded_fields,
    padding_for,
    pushed,
    save_model,
    stats_from_metadata,
)


@dataclasses.dataclass(frozen=True)
class Stage:
    """Training steps ``[previous until, until)``: input noise ``noise_std`` (m/s, >= 0),
    ``unroll`` frames per sample (>= 1; 1 = one-step loss) and ``push`` frames the model
    first rolls without gradients (>= 0, :func:`unrolled_loss`)."""

    until: int
    noise_std: float
    unroll: int = 1
    push: int = 0

    def __post_init__(self):
        if not (isinstance(self.until, int) and self.until >= 1):
            raise InputError("--stages", f"stage end {self.until!r} is not a step count >= 1")
        if not (np.isfinite(self.noise_std) and self.noise_std >= 0):
            raise InputError("--stages", f"noise {self.noise_std!r} must be >= 0 m/s")
        if not (isinstance(self.unroll, int) and self.unroll >= 1):
            raise InputError("--stages", f"unroll {self.unroll!r} must be a count >= 1")
        if not (isinstance(self.push, int) and self.push >= 0):
            raise InputError("--stages", f"push {self.push!r} must be a count >= 0")


def parse_stages(text: str) -> tuple[Stage, ...]:
    """``"UNTIL:NOISE:K:P,..."`` (K optional, default 1; P optional, default 0), ends
    increasing."""
    out = []
    for part in text.split(","):
        f = part.strip().split(":")
        if len(f) not in (2, 3, 4):
            raise InputError("--stages", f"{part!r} is not UNTIL:NOISE[:K[:P]]",
                             "e.g. 4000:0.005:1,8000:0.0025:4,9000:0.0025:4:16")
        try:
            until, noise = int(f[0]), float(f[1])
            k, push = (int(x) for x in f[2:] + ["1", "0"][len(f) - 2:])
        except ValueError:
            raise InputError("--stages", f"{part!r}: UNTIL, K and P must be integers, NOISE "
                             "a number") from None
        out.append(Stage(until, noise, k, push))
    ends = [s.until for s in out]
    if ends != sorted(set(ends)):
        raise InputError("--stages", f"stage ends {ends} must increase")
    return tuple(out)


def stage_at(stages: Sequence[Stage], step: int) -> Stage:
    """The stage of optimiser step ``step`` (0-based; the last stage beyond its end)."""
    for s in stages:
        if step < s.until:
            return s
    return stages[-1]


def parse_oversample(text: str) -> tuple[float, float, float]:
    """``"LO-HI:FACTOR"`` or ``"LO:FACTOR"`` (HI infinite): trajectories at Reynolds numbers
    in ``[LO, HI]`` are drawn FACTOR (>= 1) times as often as the others. Returns (LO, HI,
    FACTOR)."""
    f = text.strip().split(":")
    bounds = f[0].split("-") if len(f) == 2 else []
    try:
        lo, hi = float(bounds[0]), float(bounds[1]) if len(bounds) == 2 else np.inf
        factor = float(f[1])
    except (ValueError, IndexError):
        raise InputError("--oversample-re", f"{text!r} is not LO-HI:FACTOR or LO:FACTOR",
                         "e.g. 200:3 or 75-100:3") from None
    if len(bounds) > 2 or not (np.isfinite(lo) and 0 < lo <= hi and np.isfinite(factor)
                               and factor >= 1):
        raise InputError("--oversample-re", f"{text!r}: needs 0 < LO <= HI and FACTOR >= 1")
    return lo, hi, factor


def trajectory_weights(reynolds: Sequence[float] | np.ndarray, lo: float, hi: float,
                       factor: float) -> np.ndarray:
    """Sampling probability of each trajectory (sums to 1): ``factor`` for ``lo <= Re <=
    hi``, 1 otherwise. Refused if no trajectory is in the range (the option would do
    nothing)."""
    re = np.asarray(reynolds, float)
    inside = (re >= lo) & (re <= hi)
    if not inside.any():
        raise InputError("--oversample-re", f"no trajectory has Re in [{lo:g}, {hi:g}] (the "
                         f"data span Re {re.min():g}-{re.max():g})")
    w = np.where(inside, factor, 1.0)
    return w / w.sum()


def draw_windows(rng: np.random.Generator, n_traj: int, n_frames: int, unroll: int,
                 batch: int, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(trajectory index (batch,), window frame indices (batch, unroll + 1)) of one step:
    trajectories uniform, or with probabilities ``weights`` (n_traj,); window starts uniform
    in ``[0, n_frames - unroll)``."""
    if weights is None:
        ti = rng.integers(0, n_traj, batch)
    else:
        ti = rng.choice(n_traj, batch, p=weights)
    fi = rng.integers(0, n_frames - unroll, batch)
    return ti, fi[:, None] + np.arange(unroll + 1)


def unrolled_loss(model: MeshNet, params, graph: MeshGraph, v_win: jax.Array, p_win: jax.Array,
                  key: jax.Array, noise_std, checkpoint: bool = True,
                  near_wall_weight: float = 1.0, push: int = 0,
                  near_wall_noise: float = 1.0,
                  push_mask: jax.Array | None = None,
                  divergence_weight: float = 0.0) -> jax.Array:
    """Weighted mean normalised error of a ``K``-frame model rollout against the data.

    With ``push = P > 0`` the model first rolls ``P`` frames from the noisy frame ``t``
    without gradients (the push-forward trick: the ``K`` frames of the loss then start from
    the model's own drifted state, ``v^model_{t+P}``, and learn to steer it back to the data
    ``t+P+1..t+P+K``).

    Args:
        v_win: (P + K + 1, N, 2) data velocities of frames t..t+P+K, m/s.
        p_win: (P + K, N) data pressures of frames t+1..t+P+K, m^2/s^2.
        key: noise key; ``noise_std`` (m/s, scalar, may be traced) on fluid nodes of frame t.
        checkpoint: every frame under ``jax.checkpoint`` (same values, less memory).
        near_wall_weight: static weight of the first fluid ring off the walls in the node
            mean (:func:`~diffgns.mesh.meshnet.loss_weights`; 1 = every node alike).
        push: static count ``P >= 0`` of gradient-free frames before the loss.
        near_wall_noise: static factor on the noise std of the first fluid ring off the
            walls (:func:`~diffgns.mesh.meshnet.near_wall`; 1 = the same noise everywhere).
        push_mask: traced bool scalar, or None (= True). False: this window is not pushed;
            its ``K`` frames start from the noisy data frame ``t+P`` instead (the same
            noise), so pushed and unpushed windows share one compiled step.
        divergence_weight: static weight ``lambda >= 0`` of the continuity term added to
            each frame's loss, ``lambda * divergence_loss(err_v)``
            (:func:`~diffgns.mesh.meshnet.divergence_loss`: the discrete divergence of the
            velocity error, model minus data, over the rms velocity-change scale, times the
            edge scale); 0 = off.
    Returns:
        scalar loss (dimensionless).
    """
    v0 = v_win[0]
    noise = noise_std * jax.random.normal(key, v0.shape, v0.dtype)
    if near_wall_noise != 1.0:
        noise = noise * jnp.where(near_wall(graph), near_wall_noise, 1.0)[:, None]
    noise = jnp.where((graph.node_type == FLUID)[:, None], noise, 0.0)
    v_in = v0 + noise
    s_dv = model.stats.target.std[:2]
    if push:  # boundary nodes carry no noise, so v_in holds them at the data's values
        v_push = pushed(model, params, graph, v_in, push)
        if push_mask is None:
            v_in = v_push
        else:  # an unpushed window is the data window from frame t+P, boundaries included
            v_in = jnp.where(push_mask, v_push, v_win[push] + noise)
            v0 = jnp.where(push_mask, v0, v_win[push])

    def body(v, data):
        v_next, p_next = data
        new_v, p = model.advance(params, graph, v, v0)  # boundary nodes held at the data
        err_v = (new_v - v_next) / s_dv
        err_p = (p - p_next) / model.stats.target.std[2]
        loss = node_loss(graph, err_v, err_p, near_wall_weight)
        if divergence_weight:
            # one scale for both components, so e's divergence is the error's divergence
            e = (new_v - v_next) / jnp.sqrt(jnp.mean(s_dv**2))
            loss = loss + divergence_weight * divergence_loss(graph, e, model.stats.edge_scale)
        return new_v, loss

    _, losses = scan_frames(body, v_in, (v_win[1 + push:], p_win[push:]),
                            checkpoint_block=1 if checkpoint else None)
    return losses.mean()


def _check(stages: Sequence[Stage], tcfg: TrainConfig, n_frames: int) -> None:
    if not stages:
        raise InputError("--stages", "no stage given", "e.g. 4000:0.005:1")
    if stages[-1].until != tcfg.steps:
        raise InputError("--stages", f"the last stage ends at {stages[-1].until}, the run at "
                         f"{tcfg.steps} steps", "make them equal")
    k = max(s.unroll + s.push for s in stages)
    if k > n_frames - 1:
        raise InputError("--stages", f"push + unroll {k} needs {k + 1} frames; the "
                         f"trajectories have {n_frames}")


def train_staged(train_path, out_dir, cfg: MeshNetConfig, tcfg: TrainConfig,
                 stages: Sequence[Stage], progress: bool = True, near_wall_weight: float = 1.0,
                 init_from=None, near_wall_noise: float = 1.0,
                 oversample_re: tuple[float, float, float] | None = None,
                 push_min_re: float | None = None,
                 divergence_weight: float = 0.0) -> tuple[MeshNet, dict]:
    """Train (or resume) a MeshGraphNet through ``stages`` on a cylinder dataset; writes
    ``out_dir/checkpoint.msgpack``, ``train_log.csv`` (loss, noise, unroll per logged step)
    and ``out_dir/model``. ``near_wall_weight``, ``near_wall_noise``: see
    :func:`unrolled_loss`. ``init_from``: a
    model folder of the same configuration to start from (its params and normalisers,
    :func:`diffgns.mesh.train.fine_tune_start`; a fresh optimiser, steps counted from 0; a
    resumed run keeps that model's normalisers). ``oversample_re``: (LO, HI, FACTOR), draw the
    trajectories at LO <= Re <= HI FACTOR times as often (:func:`trajectory_weights`; None =
    uniform). ``push_min_re``: push-forward stages push only the windows of trajectories at
    Re >= this (the others start their K frames from the data; None = every window).
    ``divergence_weight``: weight of the continuity term of :func:`unrolled_loss` (0 = off).
    Returns (model, params)."""
    if not (np.isfinite(near_wall_weight) and near_wall_weight > 0):
        raise InputError("--near-wall-weight", f"must be a weight > 0, got {near_wall_weight}")
    if not (np.isfinite(near_wall_noise) and near_wall_noise >= 0):
        raise InputError("--near-wall-noise", f"must be a factor >= 0, got {near_wall_noise}")
    if not (np.isfinite(divergence_weight) and divergence_weight >= 0):
        raise InputError("--divergence-weight", f"must be a weight >= 0, got "
                         f"{divergence_weight}")
    out = Path(out_dir)
    trajs = load_cylinder(train_path)
    padding = padding_for(trajs)
    vel, pres = padded_fields(trajs, padding[0])
    T, F = vel.shape[:2]
    _check(stages, tcfg, F)
    reynolds = np.array([float(t["attrs"]["reynolds"]) for t in trajs])
    weights = None if oversample_re is None else trajectory_weights(reynolds, *oversample_re)
    if push_min_re is not None and not (reynolds >= push_min_re).any():
        raise InputError("--push-min-re", f"no trajectory has Re >= {push_min_re:g} (the "
                         f"data span Re {reynolds.min():g}-{reynolds.max():g})")
    pushes = np.ones(T, bool) if push_min_re is None else reynolds >= push_min_re
    model = MeshNet(cfg, stats_from_metadata(read_metadata(train_path), trajs, 0.0,
                                             cfg.viscosity_feature),
                    frame_dt=float(trajs[0]["attrs"]["frame_dt"]))
    graphs = graphs_of(trajs, padding)
    model.check_graph(graphs)
    opt = make_optimizer(tcfg)
    params = model.init_network(jax.random.PRNGKey(tcfg.seed),
                                jax.tree_util.tree_map(lambda a: a[0], graphs))
    if init_from is not None:
        params, stats = fine_tune_start(init_from, cfg, params, model.stats)
        model = MeshNet(cfg, stats, frame_dt=model.frame_dt)
    updates: dict = {}

    def update_fn(push: int):
        def batch_loss(params, g, v, p, key, noise, mask):
            keys = jax.random.split(key, v.shape[0])
            f = lambda g1, v1, p1, k1, m1: unrolled_loss(
                model, params, g1, v1, p1, k1, noise, near_wall_weight=near_wall_weight,
                push=push, near_wall_noise=near_wall_noise,
                push_mask=None if push_min_re is None else m1,
                divergence_weight=divergence_weight)
            return jax.vmap(f)(g, v, p, keys, mask).mean()

        @jax.jit
        def update(params, opt_state, g, v, p, key, noise, mask):
            loss, grads = jax.value_and_grad(batch_loss)(params, g, v, p, key, noise, mask)
            upd, opt_state = opt.update(grads, opt_state, params)
            return optax.apply_updates(params, upd), opt_state, loss
        return update

    def one_step(params, opt_state, step):
        st = stage_at(stages, step)
        k = st.unroll
        if (k, st.push) not in updates:
            updates[k, st.push] = update_fn(st.push)
        rng, key = step_rng(tcfg.seed, step)
        ti, win = draw_windows(rng, T, F, st.push + k, tcfg.batch_size, weights)
        g = jax.tree_util.tree_map(lambda a: a[ti], graphs)
        params, opt_state, loss = updates[k, st.push](
            params, opt_state, g, vel[ti[:, None], win], pres[ti[:, None], win[:, 1:]], key,
            jnp.asarray(st.noise_std, vel.dtype), jnp.asarray(pushes[ti]))
        return params, opt_state, (loss, st.noise_std, k)

    info = dict(train=dataclasses.asdict(tcfg), data=str(train_path), n_trajectories=T,
                stages=[dataclasses.asdict(s) for s in stages],
                frame_dt=float(trajs[0]["attrs"]["frame_dt"]), trainer="diffgns.mesh.stages",
                near_wall_weight=near_wall_weight, near_wall_noise=near_wall_noise,
                init_from=None if init_from is None else str(init_from),
                trajectory_weights=None if weights is None else weights.tolist(),
                push_min_re=push_min_re, divergence_weight=divergence_weight)
    opt_state = opt.init(params)
    try:
        params, _, step = fit(one_step, params, opt_state, tcfg, out, info,
                              ["loss", "noise_std", "unroll"], desc="meshgraphnet stages",
                              progress=progress)
    except TrainingInterrupted as e:  # SIGTERM/SIGINT: the model of the checkpoint, then exit
        params, _, step = load_checkpoint(e.checkpoint, params, opt_state)
        save_model(out / "model", model, params, padding, dict(info, steps=step))
        raise
    save_model(out / "model", model, params, padding, dict(info, steps=step))
    return model, params


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m diffgns.mesh.stages",
                                description="train a MeshGraphNet in stages (resumable)")
    p.add_argument("--data", required=True, help="cylinder dataset (.h5 with metadata)")
    p.add_argument("--out", required=True, help="run folder (resumed if it has a checkpoint)")
    p.add_argument("--stages", required=True, help="UNTIL:NOISE[:K[:P]],...: steps, noise "
                   "(m/s), unroll frames, gradient-free push frames before them; the last "
                   "UNTIL is the run's length")
    p.add_argument("--latent", type=int, default=64)
    p.add_argument("--mp-steps", type=int, default=6)
    p.add_argument("--batch-size", type=int, default=2)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--lr-final", type=float, default=1e-5)
    p.add_argument("--lr-decay-steps", type=int, default=None, help="default: the run length")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--checkpoint-every", type=int, default=250)
    p.add_argument("--near-wall-weight", type=float, default=1.0,
                   help="loss weight of the first fluid ring off the walls (default 1)")
    p.add_argument("--near-wall-noise", type=float, default=1.0,
                   help="factor on the input-noise std of the first fluid ring off the walls "
                   "(default 1)")
    p.add_argument("--init-from", default=None,
                   help="model folder of the same configuration to start from")
    p.add_argument("--oversample-re", default=None, metavar="LO[-HI]:FACTOR",
                   help="draw trajectories at LO <= Re (<= HI) FACTOR times as often "
                   "(default: uniform)")
    p.add_argument("--push-min-re", type=float, default=None, metavar="RE",
                   help="push-forward stages push only the windows of trajectories at Re >= "
                   "RE; the others start from the data (default: every window)")
    p.add_argument("--divergence-weight", type=float, default=0.0, metavar="LAMBDA",
                   help="weight of the continuity term: the discrete divergence of the "
                   "velocity error per frame (default 0 = off)")
    a = p.parse_args(argv)
    check_input_file(a.data, "--data", metadata=True)
    stages = parse_stages(a.stages)
    n = stages[-1].until
    for name in ("latent", "mp_steps", "batch_size"):
        if getattr(a, name) < 1:
            raise InputError(f"--{name.replace('_', '-')}", f"must be >= 1, got "
                             f"{getattr(a, name)}")
    if not (a.lr > 0 and a.lr_final > 0):
        raise InputError("--lr/--lr-final", f"must be > 0, got {a.lr}, {a.lr_final}")
    tcfg = TrainConfig(steps=n, batch_size=a.batch_size, lr=a.lr, lr_final=a.lr_final,
                       lr_decay_steps=a.lr_decay_steps or n, seed=a.seed,
                       checkpoint_every=a.checkpoint_every)
    cfg = MeshNetConfig(latent=a.latent, mp_steps=a.mp_steps, noise_std=stages[0].noise_std)
    train_staged(a.data, a.out, cfg, tcfg, stages, near_wall_weight=a.near_wall_weight,
                 near_wall_noise=a.near_wall_noise,
                 init_from=a.init_from,
                 oversample_re=None if a.oversample_re is None else parse_oversample(
                     a.oversample_re), push_min_re=a.push_min_re,
                 divergence_weight=a.divergence_weight)
    print(f"model written to {a.out}/model")
    return 0


if __name__ == "__main__":  # pragma: no cover
    run_module(main)
