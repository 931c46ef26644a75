"""Memory figures the inverse loops record: process RSS and XLA's analysis of a program."""
from __future__ import annotations

import resource
from typing import Any


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, MB (ru_maxrss is KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def current_rss_mb() -> float:
    """Resident memory of this process now, MB (Linux /proc; 0 where unavailable)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * resource.getpagesize() / 2**20
    except OSError:  # pragma: no cover - non-Linux
        return 0.0


def memory_stats(compiled: Any) -> dict[str, int]:
    """XLA memory analysis of a compiled executable (``jax.jit(f).lower(...).compile()``),
    bytes: temp, argument, output, alias (whichever the backend reports)."""
    m = compiled.memory_analysis()
    keys = ("temp_size_in_bytes", "argument_size_in_bytes", "output_size_in_bytes",
            "alias_size_in_bytes")
    return {k: int(getattr(m, k)) for k in keys if m is not None and hasattr(m, k)}
