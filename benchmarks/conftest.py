"""pytest-benchmark runs (``pytest benchmarks/ --benchmark-enable``) under the measuring
protocol of ``protocol.py``: refused (exit 3) when the 1-minute load at start exceeds
``--max-load``, unless ``--allow-loaded``; the protocol block goes into the saved machine info
and every loaded run's summary line says INVALID."""
from __future__ import annotations

import argparse

import protocol
import pytest

_RUN: protocol.Run | None = None


def pytest_addoption(parser):
    g = parser.getgroup("measuring protocol (benchmarks/protocol.py)")
    g.addoption("--max-load", type=float, default=protocol.MAX_LOAD,
                help="refuse to benchmark when the 1-minute load at start exceeds this")
    g.addoption("--allow-loaded", action="store_true",
                help="benchmark anyway; the results are marked INVALID")


def pytest_configure(config):
    global _RUN
    if not config.getoption("benchmark_enable", default=False):
        return  # timing disabled (the default): nothing is measured
    args = argparse.Namespace(threads="2", max_load=config.getoption("max_load"),
                              allow_loaded=config.getoption("allow_loaded"), wait_quiet=0.0,
                              result_to=None)
    try:
        _RUN = protocol.start(args, "test_bench_mpm")
    except SystemExit as e:
        pytest.exit("refused: machine loaded (see the line above)", returncode=e.code)


def pytest_benchmark_update_machine_info(config, machine_info):
    if _RUN is not None:
        machine_info["protocol"] = _RUN.metadata()


@pytest.hookimpl(trylast=True)
def pytest_terminal_summary(terminalreporter):
    if _RUN is not None and not _RUN.valid:
        terminalreporter.write_line(_RUN.label("these timings were taken on a loaded machine"))
