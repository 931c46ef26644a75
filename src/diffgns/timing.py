"""The one timing helper of the library and the benchmarks (issues 20 and 22).

* :func:`measure` -- one call: wall seconds and process CPU seconds side by side (user +
  system time of all threads of this process, plus that of any child process it waited
  for), the clock stopped only after ``jax.block_until_ready`` (or the given ``sync``);
* :func:`time_call` -- the first call (compile + run) timed apart, then the median of
  ``repeats`` steady calls; ``compile_s = first call - median steady call``;
* :func:`interleave` -- A/B (or A/B/C...) rounds: every round times one call of each
  contender, the order alternating round by round (A B, B A, ...), so that a change in the
  machine's load hits all alike; a ratio is the median of the per-round ratios and every
  round is kept (:meth:`Interleaved.to_json`).

All times are seconds. CPU time over wall time shows how many cores a call kept busy (about
1 pinned, up to 2 on a two-core machine); a CPU time well below the wall time on an unpinned
run means the process was waiting for the cores.
"""
from __future__ import annotations

import resource
import statistics
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

Sync = Callable[[Any], Any]
"""``result -> anything``: waits until ``result`` is computed (the clock stops after it)."""
Clock = Callable[[], float]
"""``() -> seconds`` (wall clock or CPU clock; tests pass fake clocks)."""


def block(out: Any) -> Any:
    """Wait for every JAX array in ``out`` (any pytree); other leaves pass through."""
    import jax

    return jax.block_until_ready(out)


def no_sync(out: Any) -> Any:
    """For calls that synchronise themselves (NumPy, torch on CPU, Taichi after ``ti.sync``)."""
    return out


def cpu_seconds() -> float:
    """User + system CPU seconds of this process (all threads) and its waited-for children."""
    s = resource.getrusage(resource.RUSAGE_SELF)
    c = resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


@dataclass(frozen=True)
class Sample:
    """One timed call: wall seconds and CPU seconds (of this process)."""

    wall_s: float
    cpu_s: float


def measure(fn: Callable[[], Any], sync: Sync = block, clock: Clock = time.perf_counter,
            cpu: Clock = cpu_seconds) -> tuple[Sample, Any]:
    """Call ``fn()``, ``sync`` its result, and return ``(Sample, result)``."""
    c0, t0 = cpu(), clock()
    out = fn()
    sync(out)
    return Sample(clock() - t0, cpu() - c0), out


def stats(samples: Sequence[Sample]) -> dict[str, Any]:
    """Summary of timed calls (seconds): ``median_s``, ``min_s``, ``max_s``, ``n``,
    ``cpu_median_s``, ``cpu_over_wall`` (None for a zero median), and every sample
    (``samples_s``, ``cpu_samples_s``)."""
    if not samples:
        raise ValueError("stats: no samples")
    walls = [s.wall_s for s in samples]
    cpus = [s.cpu_s for s in samples]
    med, cpu_med = statistics.median(walls), statistics.median(cpus)
    return {"median_s": med, "min_s": min(walls), "max_s": max(walls), "n": len(walls),
            "cpu_median_s": cpu_med, "cpu_over_wall": cpu_med / med if med > 0 else None,
            "samples_s": walls, "cpu_samples_s": cpus}


def with_first(summary: dict[str, Any], first: Sample) -> dict[str, Any]:
    """``summary`` (:func:`stats`) with the first call apart: ``first_call_s``,
    ``first_call_cpu_s`` and ``compile_s = max(0, first call - median steady call)``."""
    summary.update(first_call_s=first.wall_s, first_call_cpu_s=first.cpu_s,
                   compile_s=max(0.0, first.wall_s - summary["median_s"]))
    return summary


def time_call(fn: Callable[[], Any], repeats: int = 5, sync: Sync = block,
              first: Sample | None = None, clock: Clock = time.perf_counter,
              cpu: Clock = cpu_seconds) -> tuple[dict[str, Any], Any]:
    """Time ``fn``: its first call apart, then ``repeats`` steady calls.

    ``first``: the first call's sample when the caller already made it (e.g. a call that
    also sized a neighbour list); ``fn`` is then called ``repeats`` times only. Returns
    (:func:`stats` of the steady calls with :func:`with_first`'s keys, the last result).
    """
    if repeats < 1:
        raise ValueError(f"time_call: repeats must be >= 1, got {repeats}")
    if first is None:
        first, _ = measure(fn, sync, clock, cpu)
    steady = []
    out = None
    for _ in range(repeats):
        s, out = measure(fn, sync, clock, cpu)
        steady.append(s)
    return with_first(stats(steady), first), out


def round_order(names: Sequence[str], r: int) -> list[str]:
    """The order of round ``r``: as given for even rounds, reversed for odd ones."""
    return list(names) if r % 2 == 0 else list(names)[::-1]


@dataclass
class Interleaved:
    """The rounds of :func:`interleave` (every sample kept; seconds)."""

    names: list[str]
    first: dict[str, Sample] = field(default_factory=dict)
    rounds: list[dict[str, Sample]] = field(default_factory=list)
    orders: list[list[str]] = field(default_factory=list)
    outputs: dict[str, Any] = field(default_factory=dict)

    def samples(self, name: str) -> list[Sample]:
        """The samples of contender ``name``, one per round."""
        return [r[name] for r in self.rounds]

    def summary(self, name: str) -> dict[str, Any]:
        """:func:`stats` of ``name`` over the rounds, with its first call apart."""
        res = stats(self.samples(name))
        return with_first(res, self.first[name]) if name in self.first else res

    def ratio(self, a: str, b: str, cpu: bool = False) -> float:
        """Median over rounds of time(a) / time(b) (wall, or CPU with ``cpu``)."""
        def t(s: Sample) -> float:
            return s.cpu_s if cpu else s.wall_s

        return statistics.median(t(r[a]) / t(r[b]) for r in self.rounds)

    def to_json(self) -> dict[str, Any]:
        """``{"rounds": [{order, wall_s: {name: s}, cpu_s: {name: s}}], "summary": {name:
        :meth:`summary`}}``."""
        return {
            "rounds": [{"order": o, "wall_s": {k: r[k].wall_s for k in o},
                        "cpu_s": {k: r[k].cpu_s for k in o}}
                       for o, r in zip(self.orders, self.rounds)],
            "summary": {k: self.summary(k) for k in self.names},
        }


def interleave(contenders: Mapping[str, Callable[[], Any]], rounds: int,
               sync: Sync | Mapping[str, Sync] = block, warmup: bool = True,
               clock: Clock = time.perf_counter, cpu: Clock = cpu_seconds) -> Interleaved:
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
