"""The one timing helper of the benchmarks (issues 20 and 22).

* :func:`measure` -- one call: wall seconds and process CPU seconds side by side (user +
  system time of all threads of this process, plus that of any child process it waited
  for), the clock stopped only after ``jax.block_until_ready`` (or the given ``sync``);
* :func:`time_call` -- the first call (compile + run) timed apart, then the median of
  ``repeats`` steady calls; ``compile_s = first call - median steady call``;
* :func:`interleave` -- A/B (or A/B/C...) rounds: every round times one call of each
  contender, the order alternating round by round (A B, B A, ...), so that a change in the
  machine's load hits all alike; a ratio is the median of the per-round ratios and every
  round is kept for the JSON.

CPU time over wall time shows how many cores a call kept busy (about 1 pinned, up to 2 on
the two-core machine); a CPU time well below the wall time on an unpinned run means the
process was waiting for the cores.
"""
from __future__ import annotations

import resource
import statistics
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

Sync = Callable[[Any], Any]


def block(out: Any) -> Any:
    """Wait for every JAX array in ``out`` (any pytree); other leaves pass through."""
    import jax

    return jax.block_until_ready(out)


def no_sync(out: Any) -> Any:
    """For calls that synchronise themselves (torch on CPU, Taichi after ``ti.sync``)."""
    return out


def cpu_seconds() -> float:
    """User + system CPU seconds of this process (all threads) and its waited-for children."""
    s = resource.getrusage(resource.RUSAGE_SELF)
    c = resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


@dataclass(frozen=True)
class Sample:
    """One timed call: wall seconds and CPU seconds."""

    wall_s: float
    cpu_s: float


def measure(fn: Callable[[], Any], sync: Sync = block,
            clock: Callable[[], float] = time.perf_counter,
            cpu: Callable[[], float] = cpu_seconds) -> tuple[Sample, Any]:
    """Call ``fn()``, ``sync`` its result, and return (Sample, result)."""
    c0, t0 = cpu(), clock()
    out = fn()
    sync(out)
    return Sample(clock() - t0, cpu() - c0), out


def stats(samples: Sequence[Sample]) -> dict[str, Any]:
    """Median / min / max wall seconds, median CPU seconds, CPU/wall, and every sample."""
    walls = [s.wall_s for s in samples]
    cpus = [s.cpu_s for s in samples]
    med = statistics.median(walls)
    return {"median_s": med, "min_s": min(walls), "max_s": max(walls), "n": len(walls),
            "cpu_median_s": statistics.median(cpus),
            "cpu_over_wall": statistics.median(cpus) / med if med > 0 else None,
            "samples_s": walls, "cpu_samples_s": cpus}


def time_call(fn: Callable[[], Any], repeats: int = 5, sync: Sync = block,
              first: Sample | None = None, clock: Callable[[], float] = time.perf_counter,
              cpu: Callable[[], float] = cpu_seconds) -> tuple[dict[str, Any], Any]:
    """Time ``fn``: its first call apart, then ``repeats`` steady calls.

    ``first``: the first call's sample when the caller already made it (e.g. a call that
    also sized a neighbour list). Returns (:func:`stats` + ``first_call_s``,
    ``first_call_cpu_s``, ``compile_s``; the last result).
    """
    if repeats < 1:
        raise ValueError(f"time_call: repeats must be >= 1, got {repeats}")
    out = None
    if first is None:
        first, out = measure(fn, sync, clock, cpu)
    steady = []
    for _ in range(repeats):
        s, out = measure(fn, sync, clock, cpu)
        steady.append(s)
    res = stats(steady)
    res.update(first_call_s=first.wall_s, first_call_cpu_s=first.cpu_s,
               compile_s=max(0.0, first.wall_s - res["median_s"]))
    return res, out


def round_order(names: Sequence[str], r: int) -> list[str]:
    """The order of round ``r``: as given for even rounds, reversed for odd ones."""
    return list(names) if r % 2 == 0 else list(names)[::-1]


@dataclass
class Interleaved:
    """The rounds of :func:`interleave` (every sample kept)."""

    names: list[str]
    first: dict[str, Sample] = field(default_factory=dict)
    rounds: list[dict[str, Sample]] = field(default_factory=list)
    orders: list[list[str]] = field(default_factory=list)
    outputs: dict[str, Any] = field(default_factory=dict)

    def samples(self, name: str) -> list[Sample]:
        return [r[name] for r in self.rounds]

    def summary(self, name: str) -> dict[str, Any]:
        """:func:`stats` of ``name`` over the rounds, with its first call apart."""
        res = stats(self.samples(name))
        if name in self.first:
            f = self.first[name]
            res.update(first_call_s=f.wall_s, first_call_cpu_s=f.cpu_s,
                       compile_s=max(0.0, f.wall_s - res["median_s"]))
        return res

    def ratio(self, a: str, b: str, cpu: bool = False) -> float:
        """Median over rounds of time(a) / time(b) (wall, or CPU with ``cpu``)."""
        key = "cpu_s" if cpu else "wall_s"
        return statistics.median(getattr(r[a], key) / getattr(r[b], key) for r in self.rounds)

    def to_json(self) -> dict[str, Any]:
        return {
            "rounds": [{"order": o, "wall_s": {k: r[k].wall_s for k in o},
                        "cpu_s": {k: r[k].cpu_s for k in o}}
                       for o, r in zip(self.orders, self.rounds)],
            "summary": {k: self.summary(k) for k in self.names},
        }


def interleave(contenders: Mapping[str, Callable[[], Any]], rounds: int,
               sync: Sync | Mapping[str, Sync] = block, warmup: bool = True,
               clock: Callable[[], float] = time.perf_counter,
               cpu: Callable[[], float] = cpu_seconds) -> Interleaved:
    """Time ``rounds`` rounds of one call of every contender, alternating the order.

    ``warmup``: first call each (compile), timed apart, before round 0. ``sync``: one
    function, or one per contender. The last output of each contender is kept.
    """
    if rounds < 1:
        raise ValueError(f"interleave: rounds must be >= 1, got {rounds}")
    names = list(contenders)
    syncs = {k: (sync[k] if isinstance(sync, Mapping) else sync) for k in names}
    res = Interleaved(names)
    if warmup:
        for k in names:
            res.first[k], res.outputs[k] = measure(contenders[k], syncs[k], clock, cpu)
    for r in range(rounds):
        order = round_order(names, r)
        this = {}
        for k in order:
            this[k], res.outputs[k] = measure(contenders[k], syncs[k], clock, cpu)
        res.rounds.append(this)
        res.orders.append(order)
    return res


# ---------------------------------------------------------------------- memory
def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MB (1e6 bytes; Linux KiB units)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6


def xla_memory(compiled) -> dict[str, Any]:
    """XLA's memory analysis of a compiled executable, bytes and MB (1e6 bytes);
    ``total`` = argument + output + temp - alias."""
    m = compiled.memory_analysis()
    fields = ("temp_size_in_bytes", "argument_size_in_bytes", "output_size_in_bytes",
              "alias_size_in_bytes", "generated_code_size_in_bytes", "peak_memory_in_bytes")
    out: dict[str, Any] = {f: int(getattr(m, f)) for f in fields if hasattr(m, f)}
    total = (out["temp_size_in_bytes"] + out["argument_size_in_bytes"]
             + out["output_size_in_bytes"] - out["alias_size_in_bytes"])
    out.update(total_bytes=total, temp_mb=out["temp_size_in_bytes"] / 1e6, total_mb=total / 1e6)
    return out


def compile_ahead(jitted, *args) -> tuple[Any, dict[str, Any]]:
    """Lower and compile ``jitted`` for ``args`` ahead of time: (executable, {lower_s,
    compile_s, compile_cpu_s, memory (:func:`xla_memory`)})."""
    low, lowered = measure(lambda: jitted.lower(*args), sync=no_sync)
    comp, exe = measure(lowered.compile, sync=no_sync)
    return exe, {"lower_s": low.wall_s, "compile_s": comp.wall_s,
                 "compile_cpu_s": low.cpu_s + comp.cpu_s, "memory": xla_memory(exe)}


def warm_up_jax() -> None:
    """Initialise the JAX backend (client, thread pools) so that the first measured
    compile does not also pay for it."""
    import jax.numpy as jnp

    block(jnp.arange(8.0).sum() + 1.0)


def fmt_rate(x: float) -> str:
    """Human-readable rate (particle-substeps/s)."""
    return f"{x / 1e6:.3f} M" if x >= 1e5 else f"{x / 1e3:.1f} k"
