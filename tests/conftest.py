import jax
import pytest


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
}


@pytest.hookimpl(tryfirst=True)  # before `-m 'not slow'` deselects
def pytest_collection_modifyitems(config, items):
    for item in items:
        if any(item.nodeid.endswith(case) for case in SLOW_CASES):
            item.add_marker(pytest.mark.slow)
