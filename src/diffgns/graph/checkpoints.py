"""Training checkpoints through orbax: params, optimiser state, step and host state.

A run folder holds ``checkpoint/`` (an orbax :class:`~orbax.checkpoint.CheckpointManager`
directory: one step folder ``checkpoint/<step>/`` with the arrays under ``state`` and the
JSON host state under ``host``; the newest only) and the sidecar ``checkpoint.json`` (the
run description and the step, for people). Orbax writes each step to a temporary folder and
renames it when complete, so a run killed during a save keeps the previous checkpoint; it
is multi-process safe: every process calls :meth:`Checkpointer.save` with the same
(replicated) arrays and orbax writes them once. Saves are asynchronous: the step returns
while the files are written; :meth:`Checkpointer.wait` waits for them.

Runs written before orbax left ``checkpoint.msgpack`` (flax msgpack: params, opt_state,
step, host) instead; :func:`load_checkpoint`, :func:`checkpoint_host_state` and
:meth:`Checkpointer.restore` read both, so such a run resumes (its next save is in orbax).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp
from flax import serialization

from diffgns.distributed import is_main, replicated, to_host

#: the orbax checkpoint folder of a run folder
CHECKPOINT = "checkpoint"
#: the flax msgpack checkpoint of runs written before orbax (read, never written)
LEGACY_CHECKPOINT = "checkpoint.msgpack"


def _json_ready(value):
    """``value`` with numpy arrays and scalars as lists and Python numbers (JSON host state)."""
    return json.loads(json.dumps(value, default=lambda x: np.asarray(x).tolist()))


def _abstract(template):
    """Shapes and dtypes of ``template`` placed replicated on every device of the run."""
    rep = replicated()
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(np.shape(x), np.asarray(x).dtype
                                                       if not isinstance(x, jax.Array)
                                                       else x.dtype, sharding=rep), template)


class Checkpointer:
    """The orbax checkpoints of one run folder (newest kept).

    Args:
        out: the run folder; ``out/checkpoint`` is created on the first save.
    """

    def __init__(self, out: str | Path):
        self.out = Path(out).absolute()
        self.directory = self.out / CHECKPOINT
        self._manager = ocp.CheckpointManager(
            self.directory, options=ocp.CheckpointManagerOptions(max_to_keep=1, create=False))

    def latest_step(self) -> int | None:
        """The step of the newest complete orbax checkpoint (None if there is none)."""
        return self._manager.latest_step()

    def exists(self) -> bool:
        """Whether the run folder holds a checkpoint (orbax or legacy msgpack)."""
        return self.latest_step() is not None or (self.out / LEGACY_CHECKPOINT).exists()

    def save(self, step: int, params, opt_state, host: dict | None = None,
             extra: dict | None = None) -> None:
        """Start writing the checkpoint of ``step`` (all processes call it); ``host``:
        JSON-able host state; ``extra``: the run description of the sidecar (process 0)."""
        self.directory.mkdir(parents=True, exist_ok=True)
        state = dict(params=params, opt_state=opt_state, step=np.asarray(step, np.int64))
        self._manager.save(int(step), args=ocp.args.Composite(
            state=ocp.args.StandardSave(state), host=ocp.args.JsonSave(_json_ready(host or {}))),
            force=True)
        if is_main():
            side = self.out / "checkpoint.json"
            tmp = side.with_suffix(".json.tmp")
            tmp.write_text(json.dumps(dict(extra or {}, step=int(step)), indent=2, default=str))
            tmp.replace(side)

    def wait(self) -> None:
        """Block until every started save is on disk."""
        self._manager.wait_until_finished()

    def restore(self, params_template, opt_state_template) -> tuple[Any, Any, int, dict]:
        """(params, opt_state, step, host) of the newest checkpoint: orbax if any, else the
        legacy ``checkpoint.msgpack``. The templates give the pytree structure; orbax arrays
        come back replicated on every device of the run. FileNotFoundError if none."""
        step = self.latest_step()
        if step is None:
            legacy = self.out / LEGACY_CHECKPOINT
            if not legacy.exists():
                raise FileNotFoundError(f"no checkpoint in {self.out}")
            return _read_msgpack(legacy, params_template, opt_state_template)
        target = dict(params=params_template, opt_state=opt_state_template,
                      step=np.asarray(0, np.int64))
        got = self._manager.restore(step, args=ocp.args.Composite(
            state=ocp.args.StandardRestore(_abstract(target)), host=ocp.args.JsonRestore()))
        state = jax.tree.unflatten(jax.tree.structure(target), jax.tree.leaves(got.state))
        return (state["params"], state["opt_state"], int(to_host(state["step"])),
                dict(got.host or {}))

    def close(self) -> None:
        """Wait for the saves and release the manager's threads."""
        self._manager.close()


def _read_msgpack(path: Path, params_template, opt_state_template):
    raw = serialization.msgpack_restore(Path(path).read_bytes())
    host = raw.pop("host", {}) or {}
    target = dict(params=params_template, opt_state=opt_state_template, step=np.asarray(0))
    d = serialization.from_state_dict(target, raw)
    return d["params"], d["opt_state"], int(d["step"]), host


def _run_folder(path: str | Path) -> Path:
    """The run folder of ``path``: a run folder, its ``checkpoint`` folder or its legacy
    ``checkpoint.msgpack``."""
    path = Path(path)
    return path.parent if path.name in (CHECKPOINT, LEGACY_CHECKPOINT) else path


def save_checkpoint(path: str | Path, params, opt_state, step: int, extra: dict,
                    host: dict | None = None) -> None:
    """Write (and wait for) the checkpoint of ``step`` in the run folder ``path`` (or its
    ``checkpoint`` folder): params, optimiser state, step, ``host`` (JSON-able) and the
    sidecar with ``extra``."""
    ck = Checkpointer(_run_folder(path))
    ck.save(step, params, opt_state, host, extra)
    ck.close()


def load_checkpoint(path: str | Path, params_template, opt_state_template):
    """(params, opt_state, step) of the checkpoint of a run folder ``path`` (or its
    ``checkpoint`` folder, or a legacy ``.msgpack`` file); the templates give the structure."""
    path = Path(path)
    if path.suffix == ".msgpack" and path.is_file():
        return _read_msgpack(path, params_template, opt_state_template)[:3]
    ck = Checkpointer(_run_folder(path))
    try:
        return ck.restore(params_template, opt_state_template)[:3]
    finally:
        ck.close()


def checkpoint_host_state(path: str | Path) -> dict:
    """The ``host`` dict of a checkpoint (``{}`` for one written before it existed):
    ``seconds`` (float, training time so far) and ``state`` (the caller's host state).
    ``path`` as for :func:`load_checkpoint`."""
    path = Path(path)
    if path.suffix == ".msgpack" and path.is_file():
        return serialization.msgpack_restore(path.read_bytes()).get("host", {}) or {}
    ck = Checkpointer(_run_folder(path))
    try:
        step = ck.latest_step()
        if step is None:
            legacy = ck.out / LEGACY_CHECKPOINT
            if not legacy.exists():
                raise FileNotFoundError(f"no checkpoint in {ck.out}")
            return serialization.msgpack_restore(legacy.read_bytes()).get("host", {}) or {}
        got = ck._manager.restore(step, args=ocp.args.Composite(host=ocp.args.JsonRestore()))
        return dict(got.host or {})
    finally:
        ck.close()


def has_checkpoint(out: str | Path) -> bool:
    """Whether the run folder ``out`` holds a checkpoint :func:`~diffgns.graph.fit.fit`
    would resume from (orbax or legacy)."""
    out = Path(out)
    return ((out / CHECKPOINT).is_dir() and any(p.name.isdigit() for p in
                                                (out / CHECKPOINT).iterdir())) \
        or (out / LEGACY_CHECKPOINT).exists()
