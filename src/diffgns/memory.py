"""Memory figures: process RSS and XLA's analysis of a compiled program (MB = 1e6 bytes).

Used by the inverse loops (:mod:`diffgns.inverse.solve`, :mod:`diffgns.inverse.lsq`,
:mod:`diffgns.inverse.gradients`) and the memory benchmarks. :func:`check_mappings` warns
before XLA's compiled code exhausts the kernel's memory-mapping limit.
"""
from __future__ import annotations

import resource
import warnings
from typing import Any

from diffgns.timing import measure, no_sync

MB = 1e6
XLA_FIELDS = ("temp_size_in_bytes", "argument_size_in_bytes", "output_size_in_bytes",
              "alias_size_in_bytes", "generated_code_size_in_bytes", "peak_memory_in_bytes")


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB (``ru_maxrss`` is KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / MB


def current_rss_mb() -> float:
    """Resident memory of this process now, MB (Linux /proc; 0 where unavailable)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * resource.getpagesize() / MB
    except OSError:  # pragma: no cover - non-Linux
        return 0.0


def memory_stats(compiled: Any) -> dict[str, float]:
    """XLA's memory analysis of a compiled executable (``jax.jit(f).lower(...).compile()``).

    Returns the byte counts the backend reports among :data:`XLA_FIELDS` (ints), and, when
    temp, argument, output and alias sizes are all there, ``total_bytes`` = argument +
    output + temp - alias, ``temp_mb`` and ``total_mb``; empty if there is no analysis.
    """
    m = compiled.memory_analysis()
    if m is None:
        return {}
    out: dict[str, float] = {k: int(getattr(m, k)) for k in XLA_FIELDS if hasattr(m, k)}
    if all(k in out for k in XLA_FIELDS[:4]):
        total = (out["temp_size_in_bytes"] + out["argument_size_in_bytes"]
                 + out["output_size_in_bytes"] - out["alias_size_in_bytes"])
        out.update(total_bytes=total, temp_mb=out["temp_size_in_bytes"] / MB,
                   total_mb=total / MB)
    return out


def compile_ahead(jitted: Any, *args: Any) -> tuple[Any, dict[str, Any]]:
    """Lower and compile ``jitted`` (a ``jax.jit`` function) for ``args`` ahead of time.

    Returns ``(executable, {"lower_s", "compile_s", "compile_cpu_s" (seconds; CPU of lowering
    and compiling), "memory": memory_stats(executable)})``.
    """
    low, lowered = measure(lambda: jitted.lower(*args), sync=no_sync)
    comp, exe = measure(lowered.compile, sync=no_sync)
    return exe, {"lower_s": low.wall_s, "compile_s": comp.wall_s,
                 "compile_cpu_s": low.cpu_s + comp.cpu_s, "memory": memory_stats(exe)}


def mappings() -> tuple[int, int]:
    """(memory mappings of this process, the kernel's ``vm.max_map_count``); (0, 0) where
    /proc is unavailable."""
    try:
        with open("/proc/self/maps") as f:
            n = sum(1 for _ in f)
        with open("/proc/sys/vm/max_map_count") as f:
            return n, int(f.read())
    except (OSError, ValueError):  # pragma: no cover - non-Linux
        return 0, 0


def check_mappings(fraction: float = 0.75, counts: tuple[int, int] | None = None) -> bool:
    """Warn (``ResourceWarning``) when this process holds more than ``fraction`` of the
    kernel's memory mappings; True if it did.

    XLA's CPU JIT maps every compiled program's code into its own sections, and the compiled
    programs of a process stay cached: a loop over many scenes of different sizes in one
    process (~85 hybrid runs, 2026-12-05) reached Linux's default limit of 65,530 and died
    with "LLVM ERROR: Unable to allocate section memory", without a Python traceback. The
    inverse jobs and the hybrid comparison call this once per run. ``counts``: (mappings,
    limit) instead of reading them (tests).
    """
    n, limit = mappings() if counts is None else counts
    if limit <= 0 or n <= fraction * limit:
        return False
    warnings.warn(
        f"this process holds {n} of the kernel's {limit} memory mappings "
        f"(vm.max_map_count), mostly XLA's compiled code; past the limit XLA aborts with "
        f"'LLVM ERROR: Unable to allocate section memory'. Between scenes call "
        f"jax.clear_caches() to free compiled programs, or raise vm.max_map_count.",
        ResourceWarning, stacklevel=2)
    return True
