"""GNS training: noisy one-step loss, optax, checkpoints with exact resume, data parallel.

The loss is the MSE of the normalised acceleration over non-kinematic particles, with
random-walk input noise and the target corrected for it. Batches are split over all visible
devices with ``jax.sharding`` (parameters replicated, batch sharded); XLA inserts the
gradient all-reduce. Randomness is a pure function of (seed, step), so a run resumed from a
checkpoint draws exactly the batches and noise an uninterrupted run would.
"""
from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm import tqdm

from diffgns.graph.features import random_walk_noise, target_acceleration
from diffgns.graph.gns import GNS
from diffgns.graph.neighbors import did_overflow, edges
from diffgns.trajectory import KINEMATIC


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Static training configuration.

    Attributes:
        steps: optimiser steps. batch_size: windows per step (split across devices).
        lr, lr_final, lr_decay_steps: Adam with exponential decay lr -> lr_final over
            lr_decay_steps, floored at lr_final.
        push_forward: extra unrolled steps (without gradient) before the loss step.
        momentum_weight: weight of the soft momentum-balance penalty: the squared error of
            the mean predicted acceleration (the total momentum change of the system per
            frame, equal masses) against the data's. 0 disables it.
        seed, log_every, validate_every, checkpoint_every.
    """

    steps: int = 20000
    batch_size: int = 2
    lr: float = 1e-3
    lr_final: float = 1e-5
    lr_decay_steps: int = 20000
    push_forward: int = 0
    momentum_weight: float = 0.0
    seed: int = 0
    log_every: int = 50
    validate_every: int = 2000
    checkpoint_every: int = 500


def make_optimizer(cfg: TrainConfig) -> optax.GradientTransformation:
    rate = (cfg.lr_final / cfg.lr) ** (1.0 / max(cfg.lr_decay_steps, 1))
    sched = optax.exponential_decay(cfg.lr, 1, rate, end_value=cfg.lr_final)
    return optax.adam(sched)


def pushed_target(window, hist, unroll: int):
    """Target acceleration (N, 2) for the input history ``hist``, in m/frame^2.

    ``window`` (L, N, 2) is the data, ``hist`` (N, C+1, 2) the input history: the noisy data
    (``unroll = 0``) or the model's own rollout from it after ``unroll`` push-forward steps,
    ending at data frame ``C + unroll``. Either way its offset from the data is treated as
    input noise (:func:`~diffgns.graph.features.target_acceleration`): the target corrects
    the *velocity* only, and the last frame's offset is carried to the target position.
    Asking the model to remove the whole position error in one step instead makes the target
    ~(position error)/frame^2, dozens of acceleration standard deviations, which swamps
    the loss (measured: normalised loss 1.46 against 0.0125 without pushing).
    """
    C = hist.shape[1] - 1
    truth = jnp.swapaxes(window[unroll: C + 1 + unroll], 0, 1)
    return target_acceleration(window[C + 1 + unroll], truth, hist - truth)


def window_loss(gns: GNS, params, window, particle_type, material, nbrs, key, unroll: int,
                momentum_weight: float):
    """Loss of one window (L, N, 2) of positions, L = history + 2 + unroll."""
    C = gns.config.history
    clean = jnp.swapaxes(window[: C + 1], 0, 1)  # (N, C+1, 2)
    noise = random_walk_noise(key, clean, gns.config.noise_std, particle_type)
    hist = clean + noise
    n = hist.shape[0]
    over = jnp.zeros((), bool)
    for k in range(unroll):  # push-forward: the model's own predictions, no gradient
        nb = gns.neighbors.update(hist[:, -1], nbrs)
        over |= did_overflow(nb)
        s, r, m = edges(nb, n)
        acc = jax.lax.stop_gradient(gns.acceleration(params, hist, particle_type, material,
                                                     s, r, m))
        x_next = 2 * hist[:, -1] - hist[:, -2] + acc
        x_next = jnp.where((particle_type == KINEMATIC)[:, None], window[C + 1 + k], x_next)
        hist = jnp.concatenate([hist[:, 1:], x_next[:, None]], axis=1)
    target = pushed_target(window, hist, unroll)  # noise and push-forward drift alike
    nb = gns.neighbors.update(hist[:, -1], nbrs)
    over |= did_overflow(nb)
    s, r, m = edges(nb, n)
    pred = gns.normalized_acceleration(params, hist, particle_type, material, s, r, m)
    tgt = gns.normalizer.acceleration.normalize(target)
    w = (particle_type != KINEMATIC).astype(pred.dtype)
    loss = jnp.sum(w * jnp.sum((pred - tgt) ** 2, -1)) / jnp.maximum(w.sum(), 1.0)
    if momentum_weight:
        dmean = jnp.sum(w[:, None] * (pred - tgt), 0) / jnp.maximum(w.sum(), 1.0)
        loss = loss + momentum_weight * jnp.sum(dmean**2)
    return loss, over


class Trainer:
    """Owns the jitted, device-parallel training step for one GNS and optimiser."""

    def __init__(self, gns: GNS, cfg: TrainConfig, devices=None):
        self.gns, self.cfg = gns, cfg
        self.opt = make_optimizer(cfg)
        devices = devices if devices is not None else jax.devices()
        self.mesh = Mesh(np.array(devices), ("data",))
        self.replicated = NamedSharding(self.mesh, PartitionSpec())
        self.batched = NamedSharding(self.mesh, PartitionSpec("data"))
        self._step = jax.jit(self._step_impl, donate_argnums=())

    def _batch_loss(self, params, batch, nbrs, key):
        B = batch["positions"].shape[0]
        keys = jax.random.split(key, B)
        f = lambda w, t, m, k: window_loss(self.gns, params, w, t, m, nbrs, k,
                                           self.cfg.push_forward, self.cfg.momentum_weight)
        losses, over = jax.vmap(f)(batch["positions"], batch["particle_type"],
                                   batch["material"], keys)
        return losses.mean(), jnp.any(over)

    def _step_impl(self, params, opt_state, batch, nbrs, key):
        (loss, over), grads = jax.value_and_grad(self._batch_loss, has_aux=True)(
            params, batch, nbrs, key)
        updates, new_opt = self.opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), new_opt, loss, over

    def shard(self, batch: dict) -> dict:
        """Put a host batch on the devices, split along the batch axis."""
        return {k: jax.device_put(np.asarray(v), self.batched) for k, v in batch.items()}

    def step(self, params, opt_state, batch, nbrs, key):
        """One optimiser step; returns (params, opt_state, loss, overflowed). On overflow the
        caller re-allocates ``nbrs`` and calls again with the same inputs (nothing applied)."""
        return self._step(params, opt_state, self.shard(batch), nbrs, key)


def step_with_reallocation(trainer: Trainer, params, opt_state, batch: dict, nbrs: dict, key,
                           max_retries: int = 6):
    """:meth:`Trainer.step` that (re)allocates the neighbour list of the batch's node count
    outside jit and redoes the step on overflow, with growing head-room (edge slots and
    cell-list slots), so no edge is ever dropped. ``nbrs`` maps node count -> list and is
    updated in place. Returns (params, opt_state, loss)."""
    C = trainer.gns.config.history
    pos = batch["positions"]
    n = pos.shape[2]
    for attempt in range(max_retries + 1):
        if n not in nbrs:
            nbrs[n] = trainer.gns.allocate(jnp.asarray(pos[0, C]))
        new_params, new_opt, loss, over = trainer.step(params, opt_state, batch, nbrs[n], key)
        if not bool(over):
            return new_params, new_opt, loss
        extra = (attempt + 1) * max(1, nbrs[n].idx.shape[1] // (2 * n))
        nbrs[n] = trainer.gns.allocate(jnp.asarray(pos[0, C]), extra_capacity=extra)
    raise RuntimeError(f"neighbour list overflowing after {max_retries} re-allocations")


# ----------------------------------------------------------------------- checkpoints
def save_checkpoint(path: Path, params, opt_state, step: int, extra: dict) -> None:
    """Atomically write params, optimiser state and step (msgpack) plus a JSON sidecar."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = serialization.to_bytes(dict(params=params, opt_state=opt_state,
                                       step=np.asarray(step)))
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(blob)
    tmp.replace(path)
    path.with_suffix(".json").write_text(json.dumps(dict(extra, step=step), indent=2,
                                                    default=str))


def load_checkpoint(path: Path, params_template, opt_state_template):
    """Restore (params, opt_state, step) saved by :func:`save_checkpoint`."""
    target = dict(params=params_template, opt_state=opt_state_template, step=np.asarray(0))
    d = serialization.from_bytes(target, Path(path).read_bytes())
    return d["params"], d["opt_state"], int(d["step"])


def step_rng(seed: int, step: int):
    """(numpy Generator, jax key) for ``step``: a pure function of (seed, step)."""
    return (np.random.default_rng([seed, step]),
            jax.random.fold_in(jax.random.PRNGKey(seed), step))


def timed_steps(trainer: Trainer, params, opt_state, batch, nbrs, n: int = 5) -> float:
    """Median seconds per step on a fixed batch (after one warm-up step)."""
    key = jax.random.PRNGKey(0)
    out = trainer.step(params, opt_state, batch, nbrs, key)
    jax.block_until_ready(out)
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        jax.block_until_ready(trainer.step(params, opt_state, batch, nbrs, key))
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def fit_loop(update, params, opt_state, step: int, tcfg: TrainConfig, out: Path, info: dict,
             columns: Sequence[str], desc: str = "train", progress: bool = True):
    """The optimiser loop shared by the MeshGraphNet and message-network trainers.

    ``update(params, opt_state, step) -> (params, opt_state, metrics)`` does one step (it
    draws its batch and key from ``step``, e.g. with :func:`step_rng`, so a resumed run
    repeats an uninterrupted one exactly); ``metrics`` are scalars named by ``columns``.
    Appends their means over every ``log_every`` steps to ``out/train_log.csv`` (with the
    seconds since this call) and writes ``out/checkpoint.msgpack`` every
    ``checkpoint_every`` steps and at the end. Returns (params, opt_state, step).
    """
    ckpt = Path(out) / "checkpoint.msgpack"
    log = (Path(out) / "train_log.csv").open("a")
    if step == 0:
        log.write(",".join(["step", *columns, "seconds"]) + "\n")
    t0, hist = time.perf_counter(), []
    bar = tqdm(total=tcfg.steps, initial=step, desc=desc, disable=not progress)
    while step < tcfg.steps:
        params, opt_state, metrics = update(params, opt_state, step)
        step += 1
        hist.append([float(m) for m in metrics])
        bar.update(1)
        if step % tcfg.log_every == 0 or step == tcfg.steps:
            mean = np.mean(hist, axis=0)
            log.write(f"{step}," + ",".join(f"{m:.6g}" for m in mean)
                      + f",{time.perf_counter() - t0:.1f}\n")
            log.flush()
            bar.set_postfix({c: f"{m:.4g}" for c, m in zip(columns, mean)})
            hist = []
        if step % tcfg.checkpoint_every == 0 or step == tcfg.steps:
            save_checkpoint(ckpt, params, opt_state, step, info)
    bar.close()
    log.close()
    return params, opt_state, step
