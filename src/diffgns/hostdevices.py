"""Host (CPU) devices: how many this process gets, and which of them an MPM shards over.

XLA's CPU backend runs one program on one device with a thread pool, but the MPM's
particle-to-grid scatter runs on one thread: with two cores one stays idle for most of a
substep. Splitting the particles over two *host devices* (``shard_map``, one grid sum per
substep) keeps both busy: 1.36x faster at 8,100 particles and 2.00x at 32,400 on this
project's 2-core machine (``benchmarks/mpm_levers.py``, quiet, 2026-12-03; see
docs/performance.md). JAX fixes the number of CPU devices when its backend starts, so
diffgns asks for them as it is imported::

    import diffgns.interface        # (any diffgns module that uses JAX) calls request()
    MPM(scene)                      # devices="auto": shards when it pays (mpm_devices)

:func:`request` sets JAX's ``jax_num_cpu_devices`` to :func:`wanted` (``min(2, cores)``) if
nobody has chosen yet: not when JAX's backend already runs (a user who computed with JAX
before importing diffgns keeps the devices it has), not when the user set
``jax_num_cpu_devices``, ``JAX_NUM_CPU_DEVICES`` or ``--xla_force_host_platform_device_count``,
and not with ``DIFFGNS_HOST_DEVICES=1`` (any ``n`` asks for ``n``). On a GPU machine the
CPU devices are a side platform: the default backend stays the GPU and the MPM does not shard
(:func:`mpm_devices`), so code runs there unchanged.

Other JAX code is unaffected: it runs on the first device as before (the GNS trainer's
default mesh is one device per process, :func:`diffgns.distributed.data_mesh`).
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

from diffgns.errors import InputError

#: environment variable: host devices to ask for (``1`` turns the sharded MPM off)
ENV = "DIFFGNS_HOST_DEVICES"
#: host devices asked for by default (at most the machine's cores); measured with 2
DEFAULT_DEVICES = 2
#: ``MPM(devices="auto")`` shards scenes with at least this many particles (below it the
#: per-substep grid sum costs more than the scatter it splits; docs/performance.md)
AUTO_MIN_PARTICLES = 4096
#: the same in 3D: a 3D sand frame on two devices was 0.92x one device's speed at 12,992
#: particles and 1.50x at 43,296 (benchmarks/svd3_lever.py, 2026-12-04)
AUTO_MIN_PARTICLES_3D = 32768


def wanted() -> int:
    """Host devices to ask for: ``DIFFGNS_HOST_DEVICES`` if set, else ``min(2, cores)``
    (:func:`usable_cores`: a process pinned to one core gets one device).

    Raises:
        InputError: if ``DIFFGNS_HOST_DEVICES`` is not a positive integer.
    """
    text = os.environ.get(ENV)
    if text is None or not text.strip():
        return max(1, min(DEFAULT_DEVICES, usable_cores()))
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise InputError(ENV, f"{text!r} is not a positive integer",
                         "set it to the number of host devices, e.g. 2 (1 turns sharding off)")
    return n


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity, e.g. 1 under ``taskset -c 0``)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity call on this platform (macOS, Windows)
        return os.cpu_count() or 1


def user_chose() -> bool:
    """Whether the CPU device count was chosen outside diffgns (config, env or XLA flag)."""
    import jax

    chosen = int(getattr(jax.config, "jax_num_cpu_devices", -1))
    return (chosen >= 0 or "JAX_NUM_CPU_DEVICES" in os.environ
            or "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""))


def request() -> bool:
    """Ask JAX for :func:`wanted` CPU devices if it is still possible and nobody chose;
    returns whether the setting was made. Idempotent; cheap after the first call."""
    import jax
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized() or user_chose():
        return False
    n = wanted()
    if n > 1 or ENV in os.environ:
        jax.config.update("jax_num_cpu_devices", n)
    return True


def mpm_devices(devices: Any, n_particles: int, dim: int = 2) -> list[Any] | None:
    """The devices an MPM of ``n_particles`` shards over, or None for one device.

    Args:
        devices: ``"auto"`` (all local CPU devices when the default backend is the CPU, there
            are at least two and ``n_particles >= AUTO_MIN_PARTICLES``, in 3D
            :data:`AUTO_MIN_PARTICLES_3D`), ``None`` or ``1``
            (one device), an integer ``k >= 2`` (the first ``k`` local devices of the
            default backend), or a sequence of devices.
        n_particles: particles of the scene. dim: its dimension (2 or 3).

    Every scene may run sharded, 2D or 3D, any material: the stress has no library call
    (the 3D SVD is :func:`diffgns.mpm.linalg.svd3`'s Jacobi rotations; LAPACK's batched
    SVD, used before, deadlocked two host devices sharing one thread pool).

    Raises:
        InputError: for a count that is not an integer >= 1 or more devices than exist.
    """
    import jax

    if devices is None:
        return None
    if isinstance(devices, str):
        if devices != "auto":
            raise InputError("devices", f"{devices!r} is not a device choice",
                             "give 'auto', an integer >= 1 or a list of jax devices")
        local = jax.local_devices()
        if (jax.default_backend() != "cpu" or len(local) < 2
                or n_particles < (AUTO_MIN_PARTICLES_3D if dim == 3 else AUTO_MIN_PARTICLES)):
            return None
        return list(local)
    if isinstance(devices, Sequence):
        devs = list(devices)
        if not devs:
            raise InputError("devices", "an empty list", "give at least one device")
        return devs if len(devs) > 1 else None
    if isinstance(devices, bool) or not isinstance(devices, int) or devices < 1:
        raise InputError("devices", f"{devices!r} is not a device count",
                         "give 'auto', an integer >= 1 or a list of jax devices")
    if devices == 1:
        return None
    local = jax.local_devices()
    if devices > len(local):
        raise InputError("devices", f"{devices} devices asked for, this process has "
                         f"{len(local)} ({jax.default_backend()})",
                         f"on CPU set {ENV}={devices} before diffgns (and JAX) start, or "
                         "ask for fewer")
    return list(local[:devices])
