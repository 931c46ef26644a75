"""The one timing helper (diffgns.timing) and the memory figures (diffgns.memory), with a fake
clock where the numbers must be exact, and small real JAX programs where JAX is involved."""
from __future__ import annotations

import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns import memory, timing


class FakeClock:
    """A clock that the timed functions advance by hand."""

    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> None:
        self.t += dt


def test_measure_stops_the_clock_after_sync():
    clock = FakeClock()
    s, out = timing.measure(lambda: clock.advance(1.0) or "r", sync=lambda o: clock.advance(0.5),
                            clock=clock, cpu=clock)
    assert out == "r" and s.wall_s == pytest.approx(1.5) and s.cpu_s == pytest.approx(1.5)


def test_time_call_times_the_first_call_apart():
    clock = FakeClock()
    durations = iter([5.0, 1.0, 3.0, 2.0])
    t, _ = timing.time_call(lambda: clock.advance(next(durations)), repeats=3,
                            sync=timing.no_sync, clock=clock, cpu=lambda: 0.0)
    assert t["first_call_s"] == 5.0 and t["median_s"] == 2.0 and t["n"] == 3
    assert t["compile_s"] == pytest.approx(3.0) and t["samples_s"] == [1.0, 3.0, 2.0]
    assert t["cpu_median_s"] == 0.0 and "cpu_samples_s" in t


def test_interleave_alternates_the_order_and_keeps_every_round():
    calls = []
    res = timing.interleave({"A": lambda: calls.append("A"), "B": lambda: calls.append("B")},
                            rounds=4, sync=timing.no_sync)
    assert calls == ["A", "B"] + ["A", "B", "B", "A", "A", "B", "B", "A"]
    assert res.orders == [["A", "B"], ["B", "A"], ["A", "B"], ["B", "A"]]
    doc = res.to_json()
    assert len(doc["rounds"]) == 4 and doc["rounds"][1]["order"] == ["B", "A"]
    assert set(doc["summary"]) == {"A", "B"} and "compile_s" in doc["summary"]["A"]


def test_ratio_is_the_median_of_per_round_ratios():
    clock = FakeClock()
    walls = {"A": iter([9.0, 1.0, 2.0, 100.0]), "B": iter([9.0, 1.0, 4.0, 5.0])}
    res = timing.interleave({k: (lambda k=k: clock.advance(next(walls[k]))) for k in walls},
                            rounds=3, sync=timing.no_sync, clock=clock, cpu=clock)
    # per-round ratios A/B: 1, 0.5, 20 -> median 1; the ratio of medians would be 2/4
    assert res.ratio("A", "B") == pytest.approx(1.0)
    assert res.summary("A")["median_s"] / res.summary("B")["median_s"] == pytest.approx(0.5)
    assert res.ratio("A", "B", cpu=True) == pytest.approx(1.0)
    assert res.summary("A")["first_call_s"] == 9.0


def test_interleave_uses_each_contenders_own_sync():
    synced = []
    timing.interleave({"jax": lambda: 1, "torch": lambda: 2}, rounds=1, warmup=False,
                      sync={"jax": lambda o: synced.append(("jax", o)),
                            "torch": lambda o: synced.append(("torch", o))})
    assert synced == [("jax", 1), ("torch", 2)]


def test_cpu_seconds_counts_waited_for_children():
    before = timing.cpu_seconds()
    subprocess.run([sys.executable, "-c", "sum(i * i for i in range(3_000_000))"], check=True)
    assert timing.cpu_seconds() - before > 0.05


def test_time_call_with_a_given_first_call_calls_fn_only_repeats_times():
    clock = FakeClock()
    calls = []
    t, out = timing.time_call(lambda: calls.append(clock.advance(2.0)) or len(calls), repeats=2,
                              first=timing.Sample(7.0, 1.0), sync=timing.no_sync, clock=clock,
                              cpu=lambda: 0.0)
    assert len(calls) == 2 and out == 2
    assert t["first_call_s"] == 7.0 and t["first_call_cpu_s"] == 1.0
    assert t["compile_s"] == pytest.approx(5.0) and t["median_s"] == pytest.approx(2.0)


def test_compile_time_is_never_negative_and_repeats_must_be_positive():
    clock = FakeClock()
    durations = iter([1.0, 3.0])  # a first call faster than the steady one
    t, _ = timing.time_call(lambda: clock.advance(next(durations)), repeats=1,
                            sync=timing.no_sync, clock=clock, cpu=clock)
    assert t["compile_s"] == 0.0 and t["cpu_over_wall"] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="repeats"):
        timing.time_call(lambda: None, repeats=0)
    with pytest.raises(ValueError, match="rounds"):
        timing.interleave({"A": lambda: None}, rounds=0)
    with pytest.raises(ValueError, match="no samples"):
        timing.stats([])


def test_block_waits_for_every_jax_leaf_and_passes_others_through():
    out = timing.block({"a": jnp.ones(3) * 2.0, "n": 5, "s": "x"})
    assert out["n"] == 5 and out["s"] == "x"
    np.testing.assert_array_equal(np.asarray(out["a"]), [2.0, 2.0, 2.0])


def test_measure_of_a_jitted_call_returns_its_result():
    f = jax.jit(lambda x: (x**2).sum())
    s, out = timing.measure(lambda: f(jnp.arange(4.0)))
    assert float(out) == 14.0 and s.wall_s > 0 and s.cpu_s >= 0


# ------------------------------------------------------------------ memory
def test_memory_stats_of_a_compiled_program_adds_up():
    n = 1000
    exe, info = memory.compile_ahead(jax.jit(lambda x: jnp.cumsum(x) * 2.0),
                                     jnp.zeros(n, jnp.float32))
    np.testing.assert_allclose(np.asarray(exe(jnp.ones(n, jnp.float32)))[[0, -1]], [2.0, 2000.0])
    m = info["memory"]
    assert m["argument_size_in_bytes"] == 4 * n and m["output_size_in_bytes"] == 4 * n
    assert m["total_bytes"] == (m["temp_size_in_bytes"] + m["argument_size_in_bytes"]
                                + m["output_size_in_bytes"] - m["alias_size_in_bytes"])
    assert m["total_mb"] == pytest.approx(m["total_bytes"] / 1e6)
    assert info["lower_s"] > 0 and info["compile_s"] > 0 and info["compile_cpu_s"] >= 0


def test_rss_figures_are_in_mb_and_see_a_large_allocation():
    now = memory.current_rss_mb()
    assert 0 < now <= memory.peak_rss_mb() * 1.01
    # 60 MB of fresh anonymous pages, every page written: an allocation from the heap (np.ones)
    # can reuse pages an earlier test freed but the allocator kept resident (seen in the
    # full suite: growth 0.0), so map new memory explicitly
    import mmap

    a = mmap.mmap(-1, 60_000_000)
    page = mmap.PAGESIZE
    for i in range(0, len(a), page):
        a[i] = 1
    grown = memory.current_rss_mb() - now
    assert 59.0 < grown < 61.5, grown
    assert memory.peak_rss_mb() >= memory.current_rss_mb() * 0.99
    a.close()


def test_inverse_package_still_re_exports_the_memory_figures():
    from diffgns import inverse

    assert inverse.peak_rss_mb is memory.peak_rss_mb
    assert inverse.memory_stats is memory.memory_stats
    assert inverse.current_rss_mb is memory.current_rss_mb
