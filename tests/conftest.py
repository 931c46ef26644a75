import atexit
import os
import shutil
import tempfile

import jax
import pytest

# the test process has the two host devices diffgns asks for on a 2-core machine, on any
# machine (tests/test_mpm_sharded.py), asked for before any test module starts JAX
os.environ.setdefault("DIFFGNS_HOST_DEVICES", "2")
from diffgns import hostdevices  # noqa: E402

hostdevices.request()

# A persistent compilation cache per test process, removed at exit: tests build the same
# programs through new closures (a trainer, a simulator per test), which jit's in-memory cache
# does not share but the disk cache, keyed by the compiled module, does: the default suite took
# 12:05 with it against 13:21 without, on a quiet machine (2026-12-06, 22:56 and 23:53 UTC;
# the training-loop tests halve, e.g. a resumed run 27 -> 11 s). One directory per process:
# without `filelock` JAX writes entries unlocked, so xdist workers do not share one. Results
# are the same programs' (the key includes the module and jaxlib). A JAX_COMPILATION_CACHE_DIR
# set by the caller wins (e.g. to keep a cache between runs).
if not os.environ.get("JAX_COMPILATION_CACHE_DIR"):
    _cache_dir = tempfile.mkdtemp(prefix="diffgns-test-jax-cache-")
    atexit.register(shutil.rmtree, _cache_dir, ignore_errors=True)
    jax.config.update("jax_compilation_cache_dir", _cache_dir)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)


@pytest.fixture
def x64():
    """Run a test in float64."""
    prev = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", prev)


# Parametrized cases too slow for the default suite (seconds in the full suite on
# 2026-12-03, loaded machine); they run with `make test-slow`. The other cases of the same
# tests stay in the default suite.
SLOW_CASES = {
    "test_interface_conformance.py::test_gradient_finite_and_checkpointed_equals_plain[hybrid]":
        146,
    "test_interface_conformance.py::test_gradient_finite_and_checkpointed_equals_plain[mpm]": 65,
    "test_interface_conformance.py::test_jit_equals_eager_and_no_recompilation[hybrid]": 47,
    # 49 s on a quiet machine (2026-12-06, 23:53 UTC); devices=2 (40 s) runs the same
    # shuffled layout, with padding, against the scene order
    "test_mpm_sharded.py::test_shuffled_order_gives_the_frames_clamps_and_gradient_of_the_"
    "scene_order[1]": 49,
}


@pytest.hookimpl(tryfirst=True)  # before `-m 'not slow'` deselects
def pytest_collection_modifyitems(config, items):
    matched = set()
    for item in items:
        for case in SLOW_CASES:
            if item.nodeid.endswith(case):
                item.add_marker(pytest.mark.slow)
                matched.add(case)
    # a renamed test must not silently leave its slow case in the default suite (checked when
    # whole files are collected, not single tests picked by node id)
    if any("::" in str(a) for a in config.args):
        return
    files = {item.nodeid.split("::")[0].rsplit("/", 1)[-1] for item in items}
    stale = [c for c in SLOW_CASES if c.split("::")[0] in files and c not in matched]
    if stale:
        raise pytest.UsageError(f"tests/conftest.py SLOW_CASES names no collected test: {stale}")
