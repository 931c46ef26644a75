"""Shared helpers for the diffgns benchmark scripts.

Timing rules used throughout (the benchmark machine is small and shared):

* every timed call ends with ``jax.block_until_ready`` (or ``ti.sync()``) before the clock
  stops, so asynchronous dispatch is never mistaken for speed;
* compile time is reported separately as ``first call - median steady call``;
* steady-state figures are medians of several repeats after warm-up, and every raw
  sample is stored in the JSON so the spread can be judged;
* every JSON records the exact command line and the machine it ran on.
"""
from __future__ import annotations

import datetime as _dt
import importlib.metadata as _md
import json
import os
import platform
import shlex
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

BENCH_DIR = Path(__file__).resolve().parent
RESULTS_DIR = BENCH_DIR / "results"


# ------------------------------------------------------------------------ plotting
def use_agg():
    """Select the non-interactive Agg backend and return ``matplotlib.pyplot``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# -------------------------------------------------------------------------- timing
def block(out: Any) -> Any:
    """Wait for every JAX array in ``out`` (any pytree); other leaves pass through."""
    import jax

    return jax.block_until_ready(out)


def timed(fn: Callable[[], Any], sync: Callable[[Any], Any] = block) -> tuple[float, float, Any]:
    """Run ``fn()`` once and synchronise its result with ``sync``.

    Returns (wall seconds, process CPU seconds summed over threads, result). On a shared
    machine the CPU time shows how much of the wall time this process actually ran.
    """
    c0, t0 = time.process_time(), time.perf_counter()
    out = fn()
    sync(out)
    return time.perf_counter() - t0, time.process_time() - c0, out


def summary(walls: Sequence[float], cpus: Sequence[float] | None = None) -> dict[str, Any]:
    """Median/min/max of wall times (s) with the raw samples (and CPU times if given)."""
    out = {
        "median_s": statistics.median(walls),
        "min_s": min(walls),
        "max_s": max(walls),
        "n": len(walls),
        "samples_s": [float(t) for t in walls],
    }
    if cpus is not None:
        out["cpu_median_s"] = statistics.median(cpus)
        out["cpu_samples_s"] = [float(t) for t in cpus]
    return out


def repeat_timing(fn: Callable[[], Any], repeats: int = 5, warmup: int = 1,
                  sync: Callable[[Any], Any] = block) -> dict[str, Any]:
    """Summary of ``repeats`` synchronised calls of ``fn`` after ``warmup`` calls."""
    for _ in range(warmup):
        sync(fn())
    runs = [timed(fn, sync)[:2] for _ in range(repeats)]
    return summary([w for w, _ in runs], [c for _, c in runs])


def compile_and_steady(fn: Callable[[], Any], repeats: int = 3,
                       sync: Callable[[Any], Any] = block) -> dict[str, Any]:
    """Time a freshly jitted call: the first call (compile + run), then ``repeats`` steady
    calls. ``compile_s`` is estimated as first call - median steady call."""
    first, first_cpu, _ = timed(fn, sync)
    out = repeat_timing(fn, repeats=repeats, warmup=0, sync=sync)
    out["first_call_s"] = first
    out["first_call_cpu_s"] = first_cpu
    out["compile_s"] = max(0.0, first - out["median_s"])
    return out


def warm_up_jax() -> None:
    """Initialise the JAX backend (client, thread pools) so the first measured compile
    does not also pay for it."""
    import jax.numpy as jnp

    block(jnp.arange(8.0).sum() + 1.0)


# ---------------------------------------------------------------------- machine info
def _version(dist: str) -> str | None:
    try:
        return _md.version(dist)
    except _md.PackageNotFoundError:
        return None


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def command_line() -> str:
    """The command that ran this process, as a shell-quoted string."""
    return shlex.join([sys.executable, *sys.argv])


def machine_info() -> dict[str, Any]:
    """Machine/software description stored with every result."""
    info: dict[str, Any] = {
        "date_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "command": command_line(),
        "cwd": os.getcwd(),
        "pythonpath": os.environ.get("PYTHONPATH"),
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpu_model": _cpu_model(),
        "cpu_count": os.cpu_count(),
        "python": sys.version.split()[0],
        "jax": _version("jax"),
        "jaxlib": _version("jaxlib"),
        "taichi": _version("taichi"),
        "numpy": _version("numpy"),
        "xla_flags": os.environ.get("XLA_FLAGS"),
    }
    if hasattr(os, "sched_getaffinity"):
        info["cpus_available"] = len(os.sched_getaffinity(0))
    if hasattr(os, "getloadavg"):
        info["loadavg_1_5_15_at_start"] = list(os.getloadavg())
    try:
        import jax

        info["jax_backend"] = jax.default_backend()
        info["jax_devices"] = [str(d) for d in jax.devices()]
        info["jax_enable_x64"] = bool(jax.config.jax_enable_x64)
    except Exception as e:  # pragma: no cover - informational only
        info["jax_error"] = repr(e)
    return info


def write_json(name: str, payload: dict[str, Any], machine: dict[str, Any] | None = None) -> Path:
    """Write ``payload`` plus machine info to ``benchmarks/results/<name>``, or to ``name``
    itself when it names a folder (e.g. ``/tmp/x.json``)."""
    doc = {"machine": machine if machine is not None else machine_info(), **payload}
    if hasattr(os, "getloadavg"):
        doc["machine"]["loadavg_1_5_15_at_end"] = list(os.getloadavg())
    path = Path(name) if Path(name).parent != Path(".") else RESULTS_DIR / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2, default=float) + "\n")
    return path


def fmt_rate(x: float) -> str:
    """Human-readable particle-substeps/s."""
    return f"{x / 1e6:.3f} M" if x >= 1e5 else f"{x / 1e3:.1f} k"
