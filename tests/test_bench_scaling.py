"""The pure helpers of benchmarks/scaling.py: cost-law fit, crossover, the same-column mapping
between MPM particles and GNS nodes, the node lattice, and the report tables (no timing)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import scaling  # noqa: E402

from diffgns.models import model_path  # noqa: E402


def test_fit_power_law_recovers_exponent_and_prefactor():
    n = np.array([1024, 4096, 16384, 65536])
    fit = scaling.fit_power_law(n, 3e-4 * n ** 1.2)
    assert fit["a"] == pytest.approx(3e-4, rel=1e-9)
    assert fit["b"] == pytest.approx(1.2, rel=1e-9)
    assert fit["r2"] == pytest.approx(1.0)
    assert (fit["n_min"], fit["n_max"], fit["points"]) == (1024, 65536, 4)
    np.testing.assert_allclose(scaling.law(fit, n), 3e-4 * n ** 1.2, rtol=1e-9)


def test_fit_power_law_least_squares_with_noise_and_bad_points():
    n = np.array([1e3, 4e3, 1.6e4, 6.4e4, 2.56e5])
    noise = np.array([1.1, 0.9, 1.05, 0.95, 1.0])
    fit = scaling.fit_power_law([*n, 5e3, -1.0], [*(2.0 * n ** 0.8 * noise), 0.0, 1.0])
    assert fit["points"] == 5  # zero cost and negative N dropped
    assert fit["b"] == pytest.approx(0.8, abs=0.03)
    assert 0.98 < fit["r2"] < 1.0
    assert scaling.fit_power_law([1024, 1024], [1.0, 2.0]) is None
    assert scaling.fit_power_law([], []) is None


def _law(a, b, lo=1e3, hi=3e5):
    return {"a": a, "b": b, "r2": 1.0, "n_min": lo, "n_max": hi, "points": 3}


def test_crossover_solves_mpm_law_equal_gns_law_of_same_column():
    # ratio(N) = 1e-4 N / (1e-2 (N/16)^0.5) = 0.04 sqrt(N) = 1 at N = 625
    mpm, gns = _law(1e-4, 1.0, 1e2, 1e4), _law(1e-2, 0.5, 1e1, 1e3)
    c = scaling.crossover(mpm, gns, 16)
    assert c["n_mpm"] == pytest.approx(625.0)
    assert c["n_gns"] == pytest.approx(625.0 / 16)
    assert c["gns_cheaper"] == "above"
    assert c["in_measured_range"]
    n = c["n_mpm"]
    assert scaling.law(mpm, n) == pytest.approx(scaling.law(gns, n / 16))
    # the GNS scaling worse: it pays below the crossover; range checked on both laws
    c2 = scaling.crossover(_law(1e-4, 1.0), _law(1e-6, 1.5), 16)
    assert c2["gns_cheaper"] == "below"
    assert not scaling.crossover(_law(1e-4, 1.0, 1e4, 1e5), gns, 16)["in_measured_range"]


def test_crossover_with_equal_exponents_has_no_size():
    c = scaling.crossover(_law(1e-3, 1.0), _law(1e-5, 1.0), 16)
    assert c["n_mpm"] is None and c["gns_cheaper"] == "everywhere"
    assert scaling.crossover(_law(1e-5, 1.0), _law(1e-3, 1.0), 16)["gns_cheaper"] == "nowhere"


def test_model_geometry_of_the_shipped_model():
    info = json.loads((model_path(scaling.MODEL) / "config.json").read_text())
    geo = scaling.model_geometry(info)
    assert geo["dx"] == pytest.approx(0.1 / 16)
    assert geo["particle_spacing"] == pytest.approx(0.1 / 32)
    assert geo["factor"] == 16
    assert geo["node_spacing"] == pytest.approx(0.0125)  # a 4 x 4 block of particles
    with pytest.raises(ValueError, match="source.width"):
        scaling.model_geometry({"factor": 16})


def test_same_column_sizes_and_mapping():
    assert scaling.mpm_cells(1024) == 16
    assert all(4 * scaling.mpm_cells(n) ** 2 == n for n in scaling.SIZES)
    assert all(scaling.gns_nodes_across(n) ** 2 == n for n in scaling.SIZES)
    assert scaling.gns_sizes((1024, 4096, 16384), 16) == [64, 256, 1024, 4096, 16384]
    assert scaling.gns_sizes((100, 1024), 16) == [64, 100, 1024]  # 100 // 16 < 16 nodes
    # an MPM column of c cells across is c / 2 GNS nodes across: the same width
    geo = {"dx": 0.1 / 16, "node_spacing": 0.0125}
    for n in (1024, 65536):
        c = scaling.mpm_cells(n)
        m = scaling.gns_nodes_across(4 * c * c // 16)
        assert m * geo["node_spacing"] == pytest.approx(c * geo["dx"])


def test_lattice_spacing_and_neighbour_count():
    x = scaling.lattice(12, 0.0125)
    assert x.shape == (144, 2) and x.dtype == np.float32
    assert x.min() == pytest.approx(0.00625) and x.max() == pytest.approx(11.5 * 0.0125)
    d = np.linalg.norm(x[:, None] - x[None], axis=-1)
    interior = np.all((x > 3 * 0.0125) & (x < 9 * 0.0125), axis=1)
    # radius 0.032 m at 12.5 mm: 20 neighbours inside the column (strictly < R, no self)
    counts = ((d < 0.032) & (d > 0)).sum(1)
    assert set(counts[interior]) == {20}


def test_frames_per_call_targets_about_a_second():
    assert scaling.frames_per_call(1e-3, 40) == 25  # 0.04 s per frame
    assert scaling.frames_per_call(10.0, 1) == 1
    assert scaling.frames_per_call(1e-7, 1) == 400


def _row(kind, n, s_step, dt):
    return {"sim": kind, "n_particles": n, "n_target": n, "s_per_step": s_step,
            "s_per_sim_s": s_step / dt, "xla_total_mb": 1.0, "peak_rss_delta_mb": 2.0}


def test_physical_pairs_and_tables():
    mpm = [_row("mpm", 1024, 1e-3, 5e-5), _row("mpm", 4096, 4e-3, 5e-5),
           _row("mpm", 100, 1e-4, 5e-5)]  # 100 particles: no whole node count
    gns = [_row("gns", 64, 0.02, 5e-3), _row("gns", 1024, 0.2, 5e-3),
           {"sim": "gns", "n_particles": 256, "skipped": "XLA needs 1 MB"}]
    pairs = scaling.physical_pairs(mpm, gns, 16)
    assert [(p["mpm_particles"], p["gns_nodes"]) for p in pairs] == [(1024, 64)]
    assert pairs[0]["mpm_over_gns"] == pytest.approx((1e-3 / 5e-5) / (0.02 / 5e-3))
    table = scaling.cost_table(mpm, gns).splitlines()
    assert [ln.split()[0] for ln in table[1:-1]] == ["64", "100", "256", "1024", "4096"]
    assert "skipped" in table[3]
    assert table[4].split()[1:3] == ["0.001", "20"]
    assert "MPM/GNS > 1: the GNS is cheaper" in scaling.pair_table(pairs, 16)


def test_summary_lines_report_crossover_side_and_range():
    laws = {"mpm": _law(1e-4, 1.0, 1e2, 1e4), "gns": _law(1e-2, 0.6, 1e2, 1e4),
            "gns_same_column": _law(1e-2, 0.5, 1e1, 1e3)}
    cross = scaling.crossover(laws["mpm"], laws["gns_same_column"], 16)
    lines = scaling.summary_lines(laws, cross, 16)
    assert "N^1.000" in lines[0] and "N^0.600" in lines[1] and "N^0.500" in lines[2]
    assert "at N = 625 MPM particles" in lines[3] and "inside" in lines[3]
    assert "cheaper above" in lines[3]
    far = scaling.crossover(_law(1e-4, 1.0, 1e4, 1e5), laws["gns_same_column"], 16)
    assert "OUTSIDE (extrapolated)" in scaling.summary_lines(laws, far, 16)[3]
    pairs = [{"mpm_particles": 1024, "mpm_over_gns": 0.5},
             {"mpm_particles": 4096, "mpm_over_gns": 2.0}]
    assert scaling.summary_lines(laws, cross, 16, pairs)[-1] == (
        "measured MPM/GNS on the same columns: 0.5 to 2; the GNS is cheaper on the columns "
        "of 4096 MPM particles")
    assert scaling.summary_lines(laws, cross, 16, pairs[1:])[-1].endswith(
        "the GNS is cheaper on every measured column")
    assert "no fit" in scaling.summary_lines({"mpm": None, "gns": None}, None, 16)[0]
