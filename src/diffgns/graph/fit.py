"""The one optimiser loop of every trained network in diffgns (GNS, MeshGraphNet, message nets).

:func:`fit` runs ``update(params, opt_state, step)`` until ``TrainConfig.steps`` and owns what
a training run needs around it, the same for every network:

* **resume**: ``out/checkpoint.msgpack`` (params, optimiser state, step; msgpack, written
  atomically with a JSON sidecar) is loaded if present. Randomness must be a function of
  (seed, step) (:func:`step_rng`), so a resumed run draws exactly the batches and noise an
  uninterrupted one would;
* **checkpoints** every ``checkpoint_every`` steps and at the end;
* **logging**: ``out/train_log.csv`` with columns ``step, <metrics>, lr, seconds``: the mean
  of each metric over the last ``log_every`` steps, the learning rate of the next step and
  the seconds since this call; a tqdm bar;
* **validation** (optional): every ``validate_every`` steps and at the end, one JSON line of
  metrics in ``out/valid_log.jsonl``;
* **SIGTERM** (e.g. a batch scheduler's pre-emption): the step in flight finishes, the
  checkpoint is written and :class:`TrainingInterrupted` (a ``SystemExit`` with status 143)
  is raised; the same command then resumes. Ctrl-C (``KeyboardInterrupt``) also writes the
  checkpoint of the last completed step before propagating;
* the **learning-rate schedule** (:func:`learning_rate`): Adam with exponential decay from
  ``lr`` to ``lr_final`` over ``lr_decay_steps``, held at ``lr_final`` after.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np
import optax
from flax import serialization
from tqdm import tqdm

CHECKPOINT = "checkpoint.msgpack"

#: ``update(params, opt_state, step) -> (params, opt_state, metrics)``; metrics: scalars
Update = Callable[[Any, Any, int], tuple[Any, Any, Sequence[Any]]]


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Static training configuration.

    Attributes:
        steps: optimiser steps. batch_size: windows (graphs, samples) per step.
        lr, lr_final, lr_decay_steps: Adam with exponential decay lr -> lr_final over
            lr_decay_steps, floored at lr_final (:func:`learning_rate`).
        push_forward: extra unrolled steps (without gradient) before the loss step.
        momentum_weight: GNS only: weight of the soft momentum-balance penalty: the squared
            error of the mean predicted acceleration (the total momentum change of the system
            per frame, equal masses) against the data's. 0 disables it.
        seed: seed of every random draw (:func:`step_rng`).
        log_every, validate_every, checkpoint_every: periods in steps of :func:`fit`.
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


def learning_rate(cfg: TrainConfig) -> optax.Schedule:
    """step -> learning rate: ``lr * r^step`` with ``r = (lr_final / lr)^(1 / lr_decay_steps)``,
    held at ``lr_final`` from ``lr_decay_steps`` on."""
    rate = (cfg.lr_final / cfg.lr) ** (1.0 / max(cfg.lr_decay_steps, 1))
    return optax.exponential_decay(cfg.lr, 1, rate, end_value=cfg.lr_final)


def make_optimizer(cfg: TrainConfig) -> optax.GradientTransformation:
    """Adam on the :func:`learning_rate` schedule."""
    return optax.adam(learning_rate(cfg))


def step_rng(seed: int, step: int) -> tuple[np.random.Generator, jax.Array]:
    """(numpy Generator, jax key) for ``step``: a pure function of (seed, step)."""
    return (np.random.default_rng([seed, step]),
            jax.random.fold_in(jax.random.PRNGKey(seed), step))


# ----------------------------------------------------------------------- checkpoints
def save_checkpoint(path: Path, params, opt_state, step: int, extra: dict) -> None:
    """Atomically write params, optimiser state and step (msgpack) plus a JSON sidecar
    (``extra`` and the step) next to it."""
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
    """Restore (params, opt_state, step) saved by :func:`save_checkpoint`; the templates
    give the pytree structure."""
    target = dict(params=params_template, opt_state=opt_state_template, step=np.asarray(0))
    d = serialization.from_bytes(target, Path(path).read_bytes())
    return d["params"], d["opt_state"], int(d["step"])


def has_checkpoint(out: str | Path) -> bool:
    """Whether the run folder ``out`` holds a checkpoint :func:`fit` would resume from."""
    return (Path(out) / CHECKPOINT).exists()


# ----------------------------------------------------------------------- the loop
class TrainingInterrupted(SystemExit):
    """Raised by :func:`fit` after a SIGTERM, once the checkpoint of the last completed step
    is written. Uncaught, the process exits with status 143 (128 + SIGTERM) and no
    traceback; running the same command again resumes from ``checkpoint``."""

    def __init__(self, step: int, checkpoint: Path):
        super().__init__(128 + int(signal.SIGTERM))
        self.step, self.checkpoint = step, checkpoint


@contextlib.contextmanager
def _sigterm_flag() -> Iterator[dict]:
    """A dict whose ``"set"`` turns True on SIGTERM while the context is open (the handler is
    installed only in the main thread, where Python delivers signals; restored after)."""
    flag = {"set": False}
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return

    def handler(signum, frame):
        flag["set"] = True

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield flag
    finally:
        signal.signal(signal.SIGTERM, old if old is not None else signal.SIG_DFL)


def fit(update: Update, params, opt_state, tcfg: TrainConfig, out: str | Path, info: dict,
        columns: Sequence[str], *, desc: str = "train", progress: bool = True,
        validate: Callable[[Any], dict] | None = None, show: Sequence[str] = ()):
    """Train from ``out``'s checkpoint (or from ``params``, ``opt_state`` at step 0).

    Args:
        update: ``(params, opt_state, step) -> (params, opt_state, metrics)``, one optimiser
            step; it must draw its batch and key from ``step`` (e.g. :func:`step_rng`) for
            exact resume. ``metrics``: scalars named by ``columns``.
        params, opt_state: the start, and the templates of the checkpoint's pytrees.
        tcfg: steps, periods and the learning-rate schedule (logged).
        out: run folder (``checkpoint.msgpack`` + ``.json``, ``train_log.csv``,
            ``valid_log.jsonl``); created if missing.
        info: JSON-able run description written next to every checkpoint.
        validate: params -> {name: float}, run every ``validate_every`` steps and at the
            end; ``show`` names the metrics printed under the progress bar.
    Returns:
        (params, opt_state, step) with ``step == tcfg.steps``.
    Raises:
        TrainingInterrupted: on SIGTERM, after writing the checkpoint.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt, step = out / CHECKPOINT, 0
    if ckpt.exists():
        params, opt_state, step = load_checkpoint(ckpt, params, opt_state)
        print(f"resumed from {ckpt} at step {step}")
    lr = learning_rate(tcfg)
    log = (out / "train_log.csv").open("a")
    if step == 0:
        log.write(",".join(["step", *columns, "lr", "seconds"]) + "\n")
    t0, hist = time.perf_counter(), []
    bar = tqdm(total=tcfg.steps, initial=step, desc=desc, disable=not progress)
    done = (params, opt_state, step)  # the last completed step, stored in one assignment
    try:
        with _sigterm_flag() as term:
            while step < tcfg.steps:
                new_params, new_opt, metrics = update(params, opt_state, step)
                done = (new_params, new_opt, step + 1)
                params, opt_state, step = done
                hist.append([float(m) for m in metrics])
                bar.update(1)
                last = step == tcfg.steps
                if step % tcfg.log_every == 0 or last or term["set"]:
                    mean = np.mean(hist, axis=0)
                    log.write(f"{step}," + ",".join(f"{m:.6g}" for m in mean)
                              + f",{float(lr(step)):.3g},{time.perf_counter() - t0:.1f}\n")
                    log.flush()
                    bar.set_postfix({c: f"{m:.4g}" for c, m in zip(columns, mean)})
                    hist = []
                if step % tcfg.checkpoint_every == 0 or last or term["set"]:
                    save_checkpoint(ckpt, params, opt_state, step, info)
                if term["set"]:
                    bar.write(f"SIGTERM: checkpoint of step {step} written to {ckpt}; run "
                              "the same command again to resume")
                    raise TrainingInterrupted(step, ckpt)
                if validate is not None and (step % tcfg.validate_every == 0 or last):
                    res = {k: float(v) for k, v in validate(params).items()}
                    with (out / "valid_log.jsonl").open("a") as f:
                        f.write(json.dumps(dict(step=step, **res)) + "\n")
                    if show:
                        bar.write(f"step {step}: valid "
                                  + ", ".join(f"{k} {res[k]:.3f}" for k in show))
    except KeyboardInterrupt:
        save_checkpoint(ckpt, *done, info)
        raise
    finally:
        bar.close()
        log.close()
    return params, opt_state, step
