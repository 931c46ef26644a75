"""The one optimiser loop of every trained network in diffgns (GNS, MeshGraphNet, message nets).

:func:`fit` runs ``update(params, opt_state, step)`` until ``TrainConfig.steps`` and owns what
a training run needs around it, the same for every network:

* **exact resume**: ``out/checkpoint/`` (orbax, :mod:`diffgns.graph.checkpoints`: params,
  optimiser state, step, the seconds trained so far and the caller's host state, e.g.
  neighbour-list capacities; written atomically and asynchronously, with a JSON sidecar
  ``checkpoint.json``) is loaded if present, or a ``checkpoint.msgpack`` of an older run.
  Randomness must be a function of (seed, step) (:func:`step_rng`) and every other input of
  the step either in the checkpoint (``host_state``) or derived from it, so a resumed run is
  bit-identical to an uninterrupted one;
* **several processes** (:mod:`diffgns.distributed`): every process runs :func:`fit` with
  the same arguments; process 0 writes the logs, the sidecar and the validation, all save
  the checkpoint together (orbax), and a signal seen by any process stops all of them at
  the same step;
* **checkpoints** every ``checkpoint_every`` steps and at the end;
* **logging**: ``out/train_log.csv`` with columns ``step, <metrics>, lr, seconds``: the mean
  of each metric over the last ``log_every`` steps, the learning rate of the next step and
  the seconds of training so far (cumulative over resumes); a tqdm bar. On resume, rows
  after the checkpoint's step (written before a hard kill) are dropped;
* **validation** (optional): every ``validate_every`` steps and at the end, one JSON line of
  metrics in ``out/valid_log.jsonl``;
* **SIGINT and SIGTERM** (Ctrl-C, a batch scheduler's pre-emption): the step in flight
  finishes, the checkpoint of that step is written, one line says so and
  :class:`TrainingInterrupted` (a ``SystemExit`` with status 130 or 143) is raised; the same
  command then resumes. A second Ctrl-C (or a ``KeyboardInterrupt`` raised elsewhere)
  stops at once and writes the checkpoint of the last completed step;
* the **learning-rate schedule** (:func:`learning_rate`): Adam with exponential decay from
  ``lr`` to ``lr_final`` over ``lr_decay_steps``, held at ``lr_final`` after.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, Protocol

import jax
import numpy as np
import optax
from tqdm import tqdm

from diffgns.distributed import any_process, is_main, to_host
from diffgns.errors import Interrupted
from diffgns.graph.checkpoints import (  # re-exported: the checkpoint API of every network
    CHECKPOINT,
    LEGACY_CHECKPOINT,
    Checkpointer,
    checkpoint_host_state,
    has_checkpoint,
    load_checkpoint,
    save_checkpoint,
)

__all__ = ["CHECKPOINT", "LEGACY_CHECKPOINT", "HostState", "TrainConfig", "TrainingInterrupted",
           "checkpoint_host_state", "fit", "has_checkpoint", "learning_rate", "load_checkpoint",
           "make_optimizer", "save_checkpoint", "step_rng"]

#: ``update(params, opt_state, step) -> (params, opt_state, metrics)``; metrics: scalars
Update = Callable[[Any, Any, int], tuple[Any, Any, Sequence[Any]]]
#: ``update_many(params, opt_state, step, n) -> (params, opt_state, metrics)``: ``k`` steps,
#: ``1 <= k <= n``, from ``step`` in one device call; metrics: one (k,) array per column
UpdateMany = Callable[[Any, Any, int, int], tuple[Any, Any, Sequence[Any]]]


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Static training configuration.

    Attributes:
        steps: optimiser steps. batch_size: windows (graphs, samples) per step.
        lr, lr_final, lr_decay_steps: Adam with exponential decay lr -> lr_final over
            lr_decay_steps, floored at lr_final (:func:`learning_rate`).
        push_forward: extra unrolled steps (without gradient) before the loss step.
        unroll: GNS only: frames of the loss (>= 1). 1 is the one-step loss; K > 1 rolls the
            model K frames on its own predictions and averages the K one-step losses, the
            gradient flowing back through the rollout
            (:func:`diffgns.graph.training.window_loss`).
        momentum_weight: GNS only: weight of the soft momentum-balance penalty: the squared
            error of the mean predicted acceleration (the total momentum change of the system
            per frame, equal masses) against the data's. 0 disables it.
        huber_delta: GNS only: 0 for the MSE of the normalised acceleration; > 0 for the
            Huber loss, linear beyond this many standard deviations per component
            (:func:`diffgns.graph.training.window_loss`).
        target_scale_floor: GNS only: 0 for the plain loss; > 0 divides each window's loss
            by (its mean squared normalised target acceleration + this floor), so windows
            of violent impacts (targets of ~100 standard deviations) and of slow frictional
            flow weigh alike in a batch and in Adam's moment estimates
            (:func:`diffgns.graph.training.window_loss`).
        seed: seed of every random draw (:func:`step_rng`).
        log_every, validate_every, checkpoint_every: periods in steps of :func:`fit`.
        steps_per_call: optimiser steps per device call when the network provides
            ``update_many`` (:func:`fit`). XLA's CPU runtime maps and zeroes the whole
            temporary buffer of an executable at every call (3.5 GB per GNS training step
            at N = 2,025, 35% of its CPU time in the kernel); steps looped inside one call
            share one buffer. Results differ from ``steps_per_call = 1`` at float32
            round-off only; resume stays exact (the grouping is a function of the step).
    """

    steps: int = 20000
    batch_size: int = 2
    lr: float = 1e-3
    lr_final: float = 1e-5
    lr_decay_steps: int = 20000
    push_forward: int = 0
    unroll: int = 1
    momentum_weight: float = 0.0
    huber_delta: float = 0.0
    target_scale_floor: float = 0.0
    seed: int = 0
    log_every: int = 50
    validate_every: int = 2000
    checkpoint_every: int = 500
    steps_per_call: int = 4

    def __post_init__(self):
        if not self.huber_delta >= 0:
            raise ValueError(f"huber_delta must be >= 0, got {self.huber_delta}")
        if not (self.target_scale_floor >= 0 and self.target_scale_floor < float("inf")):
            raise ValueError(f"target_scale_floor must be a finite number >= 0, got "
                             f"{self.target_scale_floor}")
        if not (isinstance(self.unroll, int) and self.unroll >= 1):
            raise ValueError(f"unroll must be a frame count >= 1, got {self.unroll!r}")
        if self.steps_per_call < 1:
            raise ValueError(f"steps_per_call must be >= 1, got {self.steps_per_call}")


def average_params(trees: Sequence[Any]) -> Any:
    """Uniform average of parameter pytrees of one structure (a "model soup" of fine-tunes of
    one parent; every network's ``diffgns average`` checks compatibility, then calls this)."""
    return jax.tree.map(lambda *a: sum(a) / len(a), *trees)


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
class HostState(Protocol):
    """State a training step keeps on the host besides params and optimiser state that
    shapes its computation (e.g. neighbour-list capacities, which set the edge-array length
    and so the floating-point summation order). :func:`fit` stores it in every checkpoint
    and hands it back on resume, so a resumed run computes exactly what an uninterrupted one
    does."""

    def state_dict(self) -> dict:
        """JSON-able snapshot (str keys; ints, floats, strings, lists; numpy arrays are
        stored as lists)."""
        ...

    def load_state_dict(self, state: dict) -> None:
        """Restore a :meth:`state_dict` snapshot."""
        ...


# ----------------------------------------------------------------------- the loop
class TrainingInterrupted(SystemExit, Interrupted):  # type: ignore[misc]
    """Raised by :func:`fit` after SIGINT (status 130) or SIGTERM (143), once the checkpoint
    is written. Uncaught, the process exits with that status and no traceback; the command
    line reports it as any interruption; running the same command again resumes from
    ``checkpoint`` (a ``Path``) at ``step``."""

    def __init__(self, step: int, checkpoint: Path, signum: int = int(signal.SIGTERM)):
        SystemExit.__init__(self, 128 + int(signum))
        self.signum, self.code = int(signum), 128 + int(signum)
        self.step, self.checkpoint = step, checkpoint
        self.reported = False  # set once the message is printed
        self.detail = (f"checkpoint of step {step} written to {checkpoint}; run the same "
                       "command again to resume")

    def __str__(self) -> str:
        return f"training interrupted by {signal.Signals(self.signum).name}; {self.detail}"


_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def _signal_flag() -> Iterator[dict]:
    """A dict whose ``"signum"`` becomes the number of the first SIGINT or SIGTERM received
    while the context is open; a second SIGINT raises ``KeyboardInterrupt`` at once. The
    handlers are installed only in the main thread, where Python delivers signals, and
    restored after."""
    flag: dict = {"signum": None}
    if threading.current_thread() is not threading.main_thread():
        yield flag
        return

    def handler(signum, frame):
        if flag["signum"] is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt
        flag["signum"] = flag["signum"] or signum

    old = {s: signal.signal(s, handler) for s in _SIGNALS}
    try:
        yield flag
    finally:
        for s, h in old.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


def _trim_logs(out: Path, step: int) -> None:
    """Drop the rows of ``train_log.csv`` and ``valid_log.jsonl`` after ``step`` (written
    after the last checkpoint by a run that was then killed), so the resumed run's rows
    follow on without repeats."""
    log = out / "train_log.csv"
    if log.exists():
        lines = log.read_text().splitlines(keepends=True)
        keep = lines[:1] + [r for r in lines[1:] if _int(r.split(",", 1)[0]) <= step]
        if keep != lines:
            log.write_text("".join(keep))
    valid = out / "valid_log.jsonl"
    if valid.exists():
        lines = valid.read_text().splitlines(keepends=True)
        keep = [r for r in lines if r.strip() and json.loads(r).get("step", 0) <= step]
        if keep != lines:
            valid.write_text("".join(keep))


def _chunk(step: int, tcfg: TrainConfig, validating: bool) -> int:
    """Steps of the device call starting at ``step``: up to the next multiple of
    ``steps_per_call`` and never past a log, checkpoint or validation step or the end, so
    every period is honoured and a run stopped at any call boundary resumes into the same
    grouping as an uninterrupted one (the grouping is a function of ``step`` alone)."""
    periods = [tcfg.steps_per_call, tcfg.log_every, tcfg.checkpoint_every]
    if validating:
        periods.append(tcfg.validate_every)
    end = min([tcfg.steps] + [(step // p + 1) * p for p in periods if p > 0])
    return max(1, end - step)


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:  # a torn last line
        return 1 << 62


def fit(update: Update, params, opt_state, tcfg: TrainConfig, out: str | Path, info: dict,
        columns: Sequence[str], *, desc: str = "train", progress: bool = True,
        validate: Callable[[Any], dict] | None = None, show: Sequence[str] = (),
        host_state: HostState | None = None, update_many: UpdateMany | None = None):
    """Train from ``out``'s checkpoint (or from ``params``, ``opt_state`` at step 0).

    Args:
        update: ``(params, opt_state, step) -> (params, opt_state, metrics)``, one optimiser
            step; it must draw its batch and key from ``step`` (e.g. :func:`step_rng`) for
            exact resume. ``metrics``: scalars named by ``columns``.
        params, opt_state: the start, and the templates of the checkpoint's pytrees.
        tcfg: steps, periods and the learning-rate schedule (logged).
        out: run folder (``checkpoint/`` + ``checkpoint.json``, ``train_log.csv``,
            ``valid_log.jsonl``); created if missing.
        info: JSON-able run description written next to every checkpoint.
        validate: params -> {name: float}, run every ``validate_every`` steps and at the
            end; ``show`` names the metrics printed under the progress bar.
        host_state: what else ``update`` keeps between steps that changes its result; saved
            with every checkpoint and restored on resume (:class:`HostState`).
        update_many: ``(params, opt_state, step, n) -> (params, opt_state, metrics)``,
            the same steps as ``update`` but up to ``n`` of them in one device call (it may
            do fewer, e.g. where the batches change shape; at least one), metrics one
            ``(k,)`` array per column. Used when ``tcfg.steps_per_call > 1``; ``n`` is
            :func:`_chunk`'s. Signals are acted on between calls.
    Returns:
        (params, opt_state, step) with ``step == tcfg.steps``.
    Raises:
        TrainingInterrupted: on SIGINT or SIGTERM (or ``KeyboardInterrupt``), after
            writing the checkpoint.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    main = is_main()  # process 0 writes the logs; every process saves (orbax is collective)
    checkpointer, step, seconds = Checkpointer(out), 0, 0.0
    ckpt = checkpointer.directory
    if checkpointer.exists():
        params, opt_state, step, host = checkpointer.restore(params, opt_state)
        seconds = float(host.get("seconds", 0.0))
        if host_state is not None and "state" in host:
            host_state.load_state_dict(host["state"])
        if main:
            _trim_logs(out, step)
            print(f"resumed from {out} at step {step}")
    lr = learning_rate(tcfg)
    log = (out / "train_log.csv").open("a") if main else open(os.devnull, "w")
    if step == 0:
        log.write(",".join(["step", *columns, "lr", "seconds"]) + "\n")
    t0, hist = time.perf_counter() - seconds, []
    bar = tqdm(total=tcfg.steps, initial=step, desc=desc, disable=not (progress and main))
    done = (params, opt_state, step)  # the last completed step, stored in one assignment

    def save(p, s, k):
        host = dict(seconds=time.perf_counter() - t0)
        if host_state is not None:
            host["state"] = host_state.state_dict()
        checkpointer.save(k, p, s, host, info)

    try:
        try:
            with _signal_flag() as sig:
                while step < tcfg.steps:
                    if update_many is not None and tcfg.steps_per_call > 1:
                        n = _chunk(step, tcfg, validate is not None)
                        new_params, new_opt, metrics = update_many(params, opt_state, step, n)
                        rows = np.stack([np.asarray(m, float).reshape(-1)
                                         for m in to_host(list(metrics))], 1)
                        if not 1 <= len(rows) <= n:
                            raise RuntimeError(f"update_many did {len(rows)} steps, asked "
                                               f"for 1 to {n}")
                    else:
                        new_params, new_opt, metrics = update(params, opt_state, step)
                        rows = np.array([[float(m) for m in to_host(list(metrics))]])
                    done = (new_params, new_opt, step + len(rows))
                    params, opt_state, step = done
                    hist.extend(rows.tolist())
                    bar.update(len(rows))
                    stop = any_process(sig["signum"] is not None)  # all stop at one step
                    last = step == tcfg.steps
                    if step % tcfg.log_every == 0 or last or stop:
                        mean = np.mean(hist, axis=0)
                        log.write(f"{step}," + ",".join(f"{m:.6g}" for m in mean)
                                  + f",{float(lr(step)):.3g},{time.perf_counter() - t0:.1f}\n")
                        log.flush()
                        bar.set_postfix({c: f"{m:.4g}" for c, m in zip(columns, mean)})
                        hist = []
                    if step % tcfg.checkpoint_every == 0 or last or stop:
                        save(params, opt_state, step)
                    if stop:
                        raise TrainingInterrupted(step, ckpt, sig["signum"] or signal.SIGTERM)
                    if validate is not None and main and (step % tcfg.validate_every == 0
                                                          or last):
                        res = {k: float(v) for k, v in validate(to_host(params)).items()}
                        with (out / "valid_log.jsonl").open("a") as f:
                            f.write(json.dumps(dict(step=step, **res)) + "\n")
                        if show:
                            bar.write(f"step {step}: valid "
                                      + ", ".join(f"{k} {res[k]:.3f}" for k in show))
        except KeyboardInterrupt:
            save(*done)
            raise TrainingInterrupted(done[2], ckpt, int(signal.SIGINT)) from None
    except TrainingInterrupted as e:
        if main:
            bar.write(str(e), file=sys.stderr)
        e.reported = True  # the command line prints no second line
        raise
    finally:
        bar.close()
        log.close()
        checkpointer.close()  # waits for the asynchronous saves
    return params, opt_state, step
