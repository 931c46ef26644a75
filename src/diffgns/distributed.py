"""Several processes (one machine or many hosts) on JAX's own distributed runtime.

One code path serves 1 process and N: every process runs the same program (SPMD,
"multi-controller" JAX). :func:`initialize` joins the processes through
``jax.distributed.initialize`` (a coordinator address, or auto-detection under SLURM, Open
MPI, ...), choosing JAX's gloo collectives on CPU so the gradient all-reduce works between
processes without a GPU. After it, ``jax.devices()`` lists the devices of every process.

* training: parameters and optimiser state are *replicated* over the global device mesh
  (:func:`replicate`), the global batch is *sharded* along its first axis
  (:func:`shard_batch`); XLA inserts the all-reduce of the gradient. Every process draws
  the same global batch from (seed, step) and places only its own rows;
* host side: :func:`to_host` reads a replicated array into numpy on any process,
  :func:`any_process` agrees on a flag (e.g. a SIGTERM seen by one process only),
  :func:`is_main` picks the process that writes logs and model files;
* data generation: :class:`diffgns.shard.Shard` (``--shard i/n`` or the process index and
  count) takes every n-th case of a list of per-sample specs.

Without :func:`initialize` (or with one process) every function reduces to the
single-process behaviour.
"""
from __future__ import annotations

import os
import re
from collections.abc import Sequence
from typing import Any, TypeVar

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from diffgns.errors import InputError

T = TypeVar("T")

#: environment variables read by :func:`initialize` when no argument is given
ENV_COORDINATOR = "DIFFGNS_COORDINATOR"
ENV_NUM_PROCESSES = "DIFFGNS_NUM_PROCESSES"
ENV_PROCESS_ID = "DIFFGNS_PROCESS_ID"


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None, *, auto: bool = False) -> bool:
    """Join a multi-process JAX run; returns whether one was joined.

    Args:
        coordinator: ``host:port`` of process 0's coordinator service (any free port).
        num_processes: processes in the run, >= 1.
        process_id: this process's index in ``[0, num_processes)``.
        auto: with no explicit argument, let JAX detect the cluster (SLURM ``srun``, Open
            MPI, ...) from its environment.

    Missing arguments are read from ``DIFFGNS_COORDINATOR``, ``DIFFGNS_NUM_PROCESSES`` and
    ``DIFFGNS_PROCESS_ID``. With none of them and ``auto`` false, nothing happens (one
    process). Must run before the first JAX computation. On CPU the cross-process
    collectives are JAX's gloo implementation.

    Raises:
        InputError: naming the option when the three values are incomplete or out of range.
    """
    coordinator = coordinator or os.environ.get(ENV_COORDINATOR) or None
    num_processes = num_processes if num_processes is not None else _env_int(ENV_NUM_PROCESSES)
    process_id = process_id if process_id is not None else _env_int(ENV_PROCESS_ID)
    explicit = (coordinator, num_processes, process_id)
    if all(v is None for v in explicit) and not auto:
        return False
    if any(v is not None for v in explicit):
        if any(v is None for v in explicit):
            raise InputError("--coordinator/--num-processes/--process-id",
                             "give all three or none",
                             "e.g. --coordinator localhost:12355 --num-processes 2 "
                             "--process-id 0 (or --distributed under SLURM)")
        assert num_processes is not None and process_id is not None
        if num_processes < 1:
            raise InputError("--num-processes", f"must be >= 1, got {num_processes}",
                             "give the number of processes of the run")
        if not 0 <= process_id < num_processes:
            raise InputError("--process-id", f"must be in [0, {num_processes}), got "
                             f"{process_id}", "number the processes 0 .. N-1")
        if not re.fullmatch(r"[^:\s]+:\d+", str(coordinator)):
            raise InputError("--coordinator", f"{coordinator!r} is not host:port",
                             "e.g. localhost:12355 (process 0's host, a free port)")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    if any(v is not None for v in explicit):
        jax.distributed.initialize(coordinator, num_processes, process_id)
    else:
        jax.distributed.initialize()
    return True


def _env_int(name: str) -> int | None:
    text = os.environ.get(name)
    if text is None or text == "":
        return None
    try:
        return int(text)
    except ValueError:
        raise InputError(name, f"{text!r} is not an integer", "set it to an integer") \
            from None


def process_index() -> int:
    """This process's index (0 without :func:`initialize`)."""
    return jax.process_index()


def process_count() -> int:
    """Number of processes of the run (1 without :func:`initialize`)."""
    return jax.process_count()


def is_main() -> bool:
    """Whether this is process 0, the one that writes logs, sidecars and model files."""
    return jax.process_index() == 0


# ----------------------------------------------------------------------- arrays
def process_devices() -> list[Any]:
    """The first device of every process (one per process, in process order): the default
    data-parallel mesh. A process may hold more (diffgns asks JAX for two host devices on a
    2-core CPU, :mod:`diffgns.hostdevices`, for the sharded MPM); training uses them only
    when given them explicitly."""
    first: dict[int, Any] = {}
    for d in jax.devices():
        first.setdefault(d.process_index, d)
    return [first[i] for i in sorted(first)]


def data_mesh(devices: Sequence[Any] | None = None) -> Mesh:
    """A 1-D mesh with axis ``"data"`` over ``devices`` (default: one device per process,
    :func:`process_devices`)."""
    devs = list(devices) if devices is not None else process_devices()
    return Mesh(np.array(devs), ("data",))


def replicated(mesh: Mesh | None = None) -> NamedSharding:
    """The sharding that holds a full copy on every device of ``mesh`` (:func:`data_mesh`)."""
    return NamedSharding(mesh if mesh is not None else data_mesh(), PartitionSpec())


def _global(x, sharding: NamedSharding) -> jax.Array:
    if isinstance(x, jax.Array) and x.sharding == sharding:
        return x
    if isinstance(x, jax.Array) and x.is_fully_addressable:
        if sharding.is_fully_addressable:
            return jax.device_put(x, sharding)
        x = np.asarray(x)
    host = np.asarray(x)
    return jax.make_array_from_callback(host.shape, sharding, _rows_of(host))


def replicate(tree: T, sharding: NamedSharding | None = None) -> T:
    """``tree`` with every array leaf a global array replicated by ``sharding``
    (:func:`replicated`). Every process must pass equal values; leaves already so placed are
    kept as they are."""
    sharding = sharding if sharding is not None else replicated()
    return jax.tree.map(lambda x: _global(x, sharding), tree)


def shard_batch(batch: dict, sharding: NamedSharding, axis: int = 0) -> dict:
    """Host arrays of the *global* batch (the same on every process; batch axis B at
    ``axis``, 0 unless several steps' batches are stacked in front) as global arrays split
    along B by ``sharding``; each process places only the rows of its own devices. B must be
    a multiple of the mesh size."""
    out = {}
    n = sharding.mesh.size
    for k, v in batch.items():
        host = np.asarray(v)
        if host.shape[axis] % n:
            raise InputError("--batch-size", f"{host.shape[axis]} is not a multiple of the "
                             f"{n} devices of the run",
                             f"use a multiple of {n} (the global batch is split evenly)")
        out[k] = jax.make_array_from_callback(host.shape, sharding, _rows_of(host))
    return out


def _rows_of(host: np.ndarray):
    """The callback of ``jax.make_array_from_callback``: index -> that block of ``host``."""
    def rows(idx):
        return host[idx]
    return rows


def to_host(tree: T) -> T:
    """``tree`` with every array leaf a numpy array; a replicated global array is read from
    this process's own copy, so any process may call it without communication."""
    def leaf(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            if not x.is_fully_replicated:
                raise ValueError("to_host needs replicated arrays; gather a sharded one with "
                                 "jax.experimental.multihost_utils.process_allgather")
            return np.asarray(x.addressable_data(0))
        return np.asarray(x) if isinstance(x, jax.Array) else x
    return jax.tree.map(leaf, tree)


def any_process(flag: bool) -> bool:
    """Whether ``flag`` is true on any process (all processes must call it)."""
    if jax.process_count() == 1:
        return bool(flag)
    from jax.experimental import multihost_utils

    return bool(np.any(multihost_utils.process_allgather(np.int32(bool(flag)))))


def barrier(name: str) -> None:
    """Wait until every process reaches the barrier ``name`` (no-op in one process)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)
