"""Property-based tests of the command line's edge (hypothesis): generated invalid and edge
arguments of ``diffgns dataset`` and ``diffgns simulate`` end in exit status 0 or 2, never an
uncaught exception, and a refused command leaves nothing on disk."""
import contextlib
import io
import math
import tempfile
from pathlib import Path

import h5py
import pytest
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from diffgns.cli import main

FAST = settings(max_examples=25, deadline=None,
                suppress_health_check=[HealthCheck.too_slow])


def _run(argv: list[str]) -> tuple[int, str]:
    """``diffgns argv`` in-process: (exit status, stderr). Any uncaught exception fails."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = main(argv)
    return rc, err.getvalue()


def _num(x: float) -> str:
    return repr(x) if math.isfinite(x) else str(x)  # 'nan', 'inf', '-inf'


def _assert_refused(rc: int, err: str, root: Path) -> None:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2, err
    assert len(lines) == 1 and lines[0].startswith("diffgns: error: --"), err
    assert ";" in lines[0]  # what is wrong; the fix
    assert not any(root.iterdir()), list(root.rglob("*"))  # nothing written


bad_angle = st.one_of(st.floats(max_value=0.0), st.floats(min_value=90.0),
                      st.sampled_from([math.nan, math.inf, -math.inf]))
bad_count = st.integers(max_value=0)
bad_frames = st.integers(max_value=1)
bad_positive = st.one_of(st.floats(max_value=0.0), st.sampled_from([math.nan, math.inf]))
good_angle = st.floats(min_value=1.0, max_value=89.0)


@st.composite
def bad_column_recipe(draw) -> list[str]:
    """Column-dataset arguments with at least one invalid field (the others valid)."""
    fields = dict(frames=["3"], angles=["30"], ratios=["0.5"], width=["0.1"], cells=["4"])
    broken = draw(st.sets(st.sampled_from(sorted(fields)), min_size=1))
    if "frames" in broken:
        fields["frames"] = [str(draw(bad_frames))]
    if "angles" in broken:
        good = draw(st.lists(good_angle, max_size=2))
        fields["angles"] = [_num(a) for a in [*good, draw(bad_angle)]]
    if "ratios" in broken:
        fields["ratios"] = [_num(draw(bad_positive))]
    if "width" in broken:
        fields["width"] = [_num(draw(bad_positive))]
    if "cells" in broken:
        fields["cells"] = [str(draw(bad_count))]
    return ["dataset", "--kind", "column", "--frames", *fields["frames"],
            "--friction-angles", *fields["angles"], "--aspect-ratios", *fields["ratios"],
            "--width", *fields["width"], "--cells-across", *fields["cells"]]


@FAST
@given(bad_column_recipe())
def test_invalid_column_recipe_refused_and_nothing_written(argv):
    with tempfile.TemporaryDirectory() as d:
        rc, err = _run([*argv, "--out", str(Path(d) / "sub" / "cols.h5")])
        _assert_refused(rc, err, Path(d))


@FAST
@given(n=st.integers(max_value=3), frames=st.integers(max_value=3),
       lo=st.one_of(good_angle, bad_angle), size=st.sampled_from(["0", "-0.2", "5", "0.001"]))
def test_invalid_squares_recipe_refused(n, frames, lo, size):
    with tempfile.TemporaryDirectory() as d:
        rc, err = _run(["dataset", "--kind", "squares", "--n", str(n), "--frames", str(frames),
                        "--friction-angles", _num(lo), "40", "--size", size, "--dx", "0.05",
                        "--out", str(Path(d) / "sq.h5")])
        _assert_refused(rc, err, Path(d))


@FAST
@given(frames=st.one_of(bad_frames, st.just(2)), vtk=st.one_of(bad_count, st.just(1)),
       angle=st.one_of(bad_angle, st.just(30.0)), ratio=st.one_of(bad_positive, st.just(0.5)))
def test_invalid_simulate_refused(frames, vtk, angle, ratio):
    assume(frames < 2 or vtk < 1 or not 0 < angle < 90 or not ratio > 0)
    with tempfile.TemporaryDirectory() as d:
        rc, err = _run(["simulate", "--column", "--frames", str(frames), "--vtk-every",
                        str(vtk), "--friction-angle", _num(angle), "--aspect-ratio",
                        _num(ratio), "--cells-across", "4", "--out", str(Path(d) / "o")])
        _assert_refused(rc, err, Path(d))


@pytest.mark.slow  # each valid run compiles the MPM (~5 s)
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(angle=st.sampled_from([0.0, 1e-3, 45.0, 89.999, 90.0]),
       frames=st.sampled_from([0, 1, 2]))
@example(angle=1e-3, frames=2)  # a valid run at the edge of the range
def test_edge_column_recipe_runs_or_is_refused(angle, frames):
    """At the edges of the valid range: a complete file (no .partial) or nothing at all."""
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "cols.h5"
        rc, err = _run(["dataset", "--kind", "column", "--aspect-ratios", "0.5",
                        "--friction-angles", _num(angle), "--frames", str(frames),
                        "--cells-across", "4", "--out", str(out)])
        assert rc in (0, 2), err
        if rc == 2:
            _assert_refused(rc, err, Path(d))
        else:
            assert sorted(p.name for p in Path(d).iterdir()) == ["cols.h5",
                                                                 "cols.metadata.json"]
            with h5py.File(out, "r") as f:
                assert list(f) == ["00000"] and f["00000/position"].shape[0] == frames + 1
