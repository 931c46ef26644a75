"""The command line's edge: bad arguments, recipes and files are refused with one line
``diffgns: error: <field>: <what>; <fix>`` and exit status 2 before anything is written;
interrupted datasets keep their finished trajectories (exit 130/143); ``--help`` imports no
JAX."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from diffgns.cli import main
from diffgns.io.dataset import load_dataset

TINY = ["--aspect-ratios", "0.5", "--friction-angles", "30", "--frames", "3",
        "--cells-across", "4"]


def _refused(argv, capsys, field: str) -> str:
    """Run ``argv``; assert exit 2 and one stderr line naming ``field``; return the line."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith(f"diffgns: error: {field}"), err
    assert "Traceback" not in err and ";" in err  # what is wrong; the fix
    return err


BAD = [  # (arguments after `diffgns`, the field named)
    (["dataset", "--kind", "column", "--friction-angles", "95"], "--friction-angles"),
    (["dataset", "--kind", "column", "--friction-angles", "-5"], "--friction-angles"),
    (["dataset", "--kind", "column", "--friction-angles", "nan"], "--friction-angles"),
    (["dataset", "--kind", "column", "--friction-angles"], "--friction-angles"),
    (["dataset", "--kind", "column", "--frames", "0"], "--frames"),
    (["dataset", "--kind", "column", "--frames", "-5"], "--frames"),
    (["dataset", "--kind", "column", "--frames", "1"], "--frames"),  # found by hypothesis
    (["dataset", "--kind", "column", "--aspect-ratios", "0"], "--aspect-ratios"),
    (["dataset", "--kind", "column", "--aspect-ratios", "-1"], "--aspect-ratios"),
    (["dataset", "--kind", "column", "--aspect-ratios", "inf"], "--aspect-ratios"),
    (["dataset", "--kind", "column", "--aspect-ratios", "1.05"], "--aspect-ratios"),
    (["dataset", "--kind", "column", "--width", "0"], "--aspect-ratios, --width"),
    (["dataset", "--kind", "column", "--dim", "3", "--domain-length", "1"], "--domain-length"),
    (["dataset", "--kind", "column", "--dim", "3", "--domain-height", "1"], "--domain-height"),
    (["dataset", "--kind", "column", "--dim", "3", "--aspect-ratios", "1.05"],
     "--aspect-ratios"),
    (["dataset", "--kind", "squares", "--dim", "3"], "--dim"),
    (["dataset", "--kind", "column", "--dim", "4"], "--dim"),
    (["dataset", "--kind", "squares", "--n", "0"], "--n"),
    (["dataset", "--kind", "squares", "--size", "2"], "--size"),
    (["dataset", "--kind", "squares", "--dx", "0"], "--dx"),
    (["dataset", "--kind", "squares", "--friction-angles", "20", "95"], "--friction-angles"),
    (["simulate", "--column", "--frames", "0"], "--frames"),
    (["simulate", "--column", "--frames", "-5"], "--frames"),
    (["simulate", "--column", "--frames", "1"], "--frames"),
    (["simulate", "--column", "--dtype", "None"], "--dtype"),
    (["simulate", "--column", "--friction-angle", "95"], "--friction-angle"),
    (["simulate", "--column", "--aspect-ratio", "0"], "--aspect-ratio"),
    (["simulate", "--column", "--vtk-every", "0"], "--vtk-every"),
    (["train", "--data", "x.h5", "--steps", "0"], "--steps"),
    (["hybrid", "--warmup", "0"], "--warmup"),
    (["hybrid", "--warmup-settle", "1.5"], "--warmup-settle"),
    (["hybrid", "--warmup-settle", "0"], "--warmup-settle"),
    (["hybrid", "--adaptive-tol", "-1"], "--adaptive-tol"),
]


@pytest.mark.parametrize("argv,field", BAD, ids=[" ".join(a[:1] + a[-2:]) for a, _ in BAD])
def test_bad_argument_refused_before_writing(tmp_path, capsys, argv, field):
    out = tmp_path / "new" / ("d.h5" if argv[0] == "dataset" else "o")
    _refused([*argv, "--out", str(out)], capsys, field)
    assert not (tmp_path / "new").exists()


def test_bad_scene_file_names_it(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[scene]\ndx = 0.01\n[[bodies]]\nshape = {type='rectangle', x0=0, y0=0, "
                   "x1=0.1, y1=0.1}\nmaterial = {type='sand', friction_angle=95}\n")
    err = _refused(["simulate", "--scene", str(bad), "--out", str(tmp_path / "o")], capsys,
                   f"--scene {bad}")
    assert "friction_angle" in err and not (tmp_path / "o").exists()


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """A one-trajectory dataset stamped with the recipe of ``diffgns dataset --kind column
    TINY`` (its trajectory is random: no MPM compile in this module)."""
    from diffgns.io.datagen import column_recipe
    from diffgns.io.dataset import DatasetWriter
    from diffgns.trajectory import Trajectory

    path = tmp_path_factory.mktemp("tiny") / "tiny.h5"
    recipe = column_recipe([0.5], [30.0], 3, 0.1, 4, domain_length=None, domain_height=None)
    pos = np.random.default_rng(0).random((4, 8, 2)).astype(np.float32)
    traj = Trajectory(positions=pos, velocities=np.zeros_like(pos),
                      particle_type=np.zeros(8, np.int32), material=np.zeros(8, np.float32),
                      frame_dt=2.5e-3, bounds=((0.0, 1.0), (0.0, 1.0)))
    with DatasetWriter(path, recipe=recipe) as w:
        w.write("00000", traj)
        w.finalize(connectivity_radius=0.05)
    return path


@pytest.fixture
def truncated(tmp_path, tiny) -> Path:
    bad = tmp_path / "trunc.h5"
    bad.write_bytes(tiny.read_bytes()[:3000])
    return bad


@pytest.mark.parametrize("command", [
    ["train", "--data", "{f}", "--out", "{o}"],
    ["train", "--kind", "mesh", "--data", "{f}", "--out", "{o}"],
    ["rollout", "--model", "gns_columns", "--data", "{f}", "--out", "{o}"],
    ["invert", "s.toml", "--fit", "friction_angle=40:0:90", "--observation", "{f}",
     "--out", "{o}"],
])
def test_missing_or_truncated_input_refused(tmp_path, capsys, truncated, command):
    field = command[command.index("{f}") - 1]
    capsys.readouterr()
    for f, what in [(tmp_path / "missing.h5", "does not exist"),
                    (truncated, "not a readable HDF5 file (truncated")]:
        out = tmp_path / "runs" / "x"
        err = _refused([a.format(f=f, o=out) for a in command], capsys, field)
        assert str(f) in err and what in err
        assert not (tmp_path / "runs").exists()  # no empty output folder


def test_model_path_that_does_not_exist_refused(tmp_path, capsys, tiny):
    capsys.readouterr()
    err = _refused(["rollout", "--model", str(tmp_path / "runs" / "gns" / "model"), "--data",
                    str(tiny), "--out", str(tmp_path / "r")], capsys, "--model")
    assert "not an existing path" in err and not (tmp_path / "r").exists()


def test_dataset_without_metadata_refused_by_train_and_rollout(tmp_path, capsys, tiny):
    bare = tmp_path / "bare.h5"
    bare.write_bytes(tiny.read_bytes())  # no bare.metadata.json beside it
    capsys.readouterr()
    for argv in (["train", "--data", str(bare)], ["rollout", "--model", "gns_columns",
                                                  "--data", str(bare)]):
        err = _refused([*argv, "--out", str(tmp_path / "o")], capsys, "--data")
        assert "has no metadata" in err and "bare.metadata.json" in err
    assert not (tmp_path / "o").exists()


def test_resume_with_another_recipe_refused(tmp_path, capsys, tiny):
    path = tmp_path / "d.h5"
    path.write_bytes(tiny.read_bytes())
    before = path.read_bytes()
    capsys.readouterr()
    err = _refused(["dataset", "--kind", "column", "--aspect-ratios", "0.5", "1",
                    "--friction-angles", "30", "--frames", "5", "--cells-across", "4",
                    "--out", str(path)], capsys, f"--out {path}")
    assert "aspect_ratios [0.5, 1.0] (file: [0.5])" in err and "n_frames 5 (file: 3)" in err
    assert path.read_bytes() == before  # untouched
    assert main(["dataset", "--kind", "column", *TINY, "--out", str(path)]) == 0  # resumes
    assert len(load_dataset(path)) == 1  # the one sample was there: nothing regenerated


def test_out_is_a_folder_or_unreadable(tmp_path, capsys, truncated):
    capsys.readouterr()
    _refused(["dataset", "--kind", "column", *TINY, "--out", str(tmp_path)], capsys, "--out")
    before = truncated.read_bytes()
    _refused(["dataset", "--kind", "column", *TINY, "--out", str(truncated)], capsys, "--out")
    assert truncated.read_bytes() == before


def test_help_imports_no_jax():
    code = ("import sys, diffgns.cli as c; c.build_parser([]); "
            "c.main(['simulate', '--column', '--frames', '0']); "
            "print(sorted(m for m in ('jax', 'jax_md', 'flax', 'h5py', 'optax') "
            "if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=60)
    assert r.stdout.strip() == "[]", r.stdout + r.stderr
    assert "diffgns: error: --frames: 0 is not a count" in r.stderr


@pytest.mark.parametrize("argv, message", [
    (["dataset", "--kind", "column", "--friction-angles", "95", "--out", "x.h5"],
     "--friction-angles: Sand.friction_angle = 95.0 is outside (0, 90)"),
    (["dataset", "--kind", "squares", "--n", "2", "--size", "9", "--out", "x.h5"],
     "--size, --dx: squares of 9 m do not fit"),
])
def test_scene_rule_errors_import_no_jax(tmp_path, argv, message):
    """Recipes are validated by building their scenes (diffgns.scene.recipes), which needs
    no JAX: the refusal prints before any heavy import (fast CLI)."""
    code = ("import sys, diffgns.cli as c; rc = c.main(sys.argv[1:]); "
            "print(rc, sorted(m for m in ('jax', 'jax_md', 'flax', 'h5py', 'optax') "
            "if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True,
                       timeout=60, cwd=tmp_path)
    assert r.stdout.strip() == "2 []", r.stdout + r.stderr
    assert message in r.stderr
    assert not list(tmp_path.iterdir())


def test_public_names_still_import():
    import diffgns

    code = ("import sys, diffgns; assert 'jax' not in sys.modules; "
            "from diffgns import MPM, Scene, rollout, Trajectory, SceneError; "
            "print(MPM.__name__, 'jax' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120)
    assert r.stdout.split() == ["MPM", "True"], r.stderr
    assert all(getattr(diffgns, name) is not None for name in diffgns.__all__)
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        diffgns.nope  # noqa: B018


def _default_sigint() -> None:
    """In the child before exec: SIGINT back to its default. pytest-xdist workers (and
    background jobs of a non-interactive shell) ignore SIGINT, a child inherits that, and
    Python then installs no KeyboardInterrupt handler: Ctrl-C would never reach diffgns."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _wait_for_first(path: Path, proc, timeout: float = 60.0) -> None:
    t0 = time.monotonic()
    while proc.poll() is None and time.monotonic() - t0 < timeout:
        try:
            with h5py.File(path, "r") as f:
                if "00000" in f:
                    return
        except (OSError, KeyError):  # not created yet, or mid-write
            pass
        time.sleep(0.05)
    raise AssertionError(f"no trajectory in {path} after {timeout} s")


@pytest.mark.parametrize("sig,code", [
    (signal.SIGINT, 130), pytest.param(signal.SIGTERM, 143, marks=pytest.mark.slow)])
def test_interrupted_dataset_keeps_finished_trajectories(tmp_path, sig, code):
    out = tmp_path / "d" / "cols.h5"
    # four trajectories: on a loaded machine the signal may arrive a trajectory late, and
    # there must still be work left to interrupt
    argv = ["dataset", "--kind", "column", "--aspect-ratios", "0.5", "1", "1.5", "2",
            "--friction-angles", "30", "--frames", "10", "--cells-across", "4", "--out",
            str(out)]
    env = dict(os.environ, HDF5_USE_FILE_LOCKING="FALSE")
    proc = subprocess.Popen([sys.executable, "-m", "diffgns.cli", *argv], env=env,
                            preexec_fn=_default_sigint,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait_for_first(out.with_name("cols.h5.partial"), proc)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == code, err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"diffgns: interrupted by {sig.name}; ") and "resume" in last
    assert "Traceback" not in err
    assert not out.exists()  # only the resumable .partial
    kept = load_dataset(out.with_name("cols.h5.partial"))
    assert 1 <= len(kept) < 4
    if sig == signal.SIGTERM:  # (slow) resume: completes, keeps what was there, renames
        assert main(argv) == 0
        again = load_dataset(out)
        assert len(again) == 4 and not out.with_name("cols.h5.partial").exists()
        np.testing.assert_array_equal(np.asarray(again[0].positions),
                                      np.asarray(kept[0].positions))
        clean = tmp_path / "clean.h5"  # bit-identical to an uninterrupted run
        assert main([*argv[:-1], str(clean)]) == 0
        with h5py.File(out, "r") as a, h5py.File(clean, "r") as b:
            assert sorted(a) == sorted(b)
            for k in b:
                for name in b[k]:
                    np.testing.assert_array_equal(a[k][name][()], b[k][name][()])


def test_cylinder_resume_with_another_recipe_refused(tmp_path, capsys):
    from diffgns.cli.checks import Parser
    from diffgns.cli.data import _cylinder_recipe, register
    from diffgns.io.dataset import H5TrajectoryFile

    path = tmp_path / "cyl.h5"
    parser = Parser(prog="diffgns")
    register(parser.add_subparsers(dest="command"))
    made = parser.parse_args(["dataset", "--kind", "cylinder", "--n", "2", "--out", str(path)])
    with H5TrajectoryFile(path, recipe=_cylinder_recipe(made)) as f:  # a finished trajectory
        f._store("00000", {"time": [0.0]}, {})
    before = path.read_bytes()
    capsys.readouterr()
    err = _refused(["dataset", "--kind", "cylinder", "--n", "3", "--cfl", "0.1", "--out",
                    str(path)], capsys, f"--out {path}")
    assert "cfl 0.1 (file: 0.15)" in err and " n " not in err  # more trajectories: fine
    assert path.read_bytes() == before


@pytest.mark.slow
@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_interrupted_simulate_leaves_nothing(tmp_path, sig, code):
    """Interrupted mid-run (the process used to crash with SIGSEGV while tearing down the
    interrupted XLA computation): one line, 130/143, no output folder, no staging folder."""
    proc = subprocess.Popen([sys.executable, "-m", "diffgns.cli", "simulate", "--column",
                            "--frames", "2000", "--cells-across", "4", "--out",
                            str(tmp_path / "sim" / "out")], preexec_fn=_default_sigint,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    time.sleep(8)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == code, err
    assert err.strip().splitlines()[-1] == f"diffgns: interrupted by {sig.name}"
    assert list(tmp_path.iterdir()) == []


def _fake_cylinder_case(case, run, progress):
    """A tiny trajectory with the arrays of a cylinder-flow case (no CFD)."""
    n, f = 4, 3
    rng = np.random.default_rng(int(case["reynolds"]))
    arrays = dict(mesh_pos=rng.random((n, 2)), cells=np.array([[0, 1, 2], [1, 2, 3]]),
                  node_type=np.zeros(n, np.int32), on_cylinder=np.zeros(n, bool),
                  velocity=rng.random((f, n, 2)), pressure=rng.random((f, n)),
                  time=np.arange(f) * 0.1, cd=np.ones(f), cl=np.zeros(f))
    return arrays, dict(frame_dt=0.1, reynolds=case["reynolds"])


def test_cylinder_dataset_is_staged_until_complete(tmp_path, monkeypatch, capsys):
    """An interrupted cylinder dataset stays at <out>.partial (never under the final name);
    the same command resumes it, renames it and writes the metadata beside the final name."""
    import diffgns.mesh.datagen as datagen

    calls = []

    def interrupted(case, run, progress):
        calls.append(case)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return _fake_cylinder_case(case, run, progress)

    path = tmp_path / "cyl.h5"
    cmd = ["dataset", "--kind", "cylinder", "--n", "3", "--out", str(path)]
    monkeypatch.setattr(datagen, "simulate_case", interrupted)
    assert main(cmd) == 130
    assert "1 finished trajectory kept in" in capsys.readouterr().err  # what is kept is said
    partial = tmp_path / "cyl.h5.partial"
    assert not path.exists() and partial.exists()
    monkeypatch.setattr(datagen, "simulate_case", _fake_cylinder_case)
    assert main(cmd) == 0
    assert path.exists() and not partial.exists()
    assert json.loads((tmp_path / "cyl.metadata.json").read_text())["n_trajectories"] == 3


@pytest.mark.parametrize("argv,field", [
    (["train", "--lr", "-1"], "--lr"), (["train", "--lr-final", "0"], "--lr-final"),
    (["train", "--radius", "-0.01"], "--radius"), (["train", "--noise-std", "-1"], "--noise-std"),
    (["invert", "--fit", "friction_angle", "--step-tol", "0"], "--step-tol")])
def test_signed_options_refused(tmp_path, capsys, argv, field):
    """A negative learning rate reached optax and ended in a TypeError traceback."""
    base = ["--data", str(tmp_path / "d.h5")] if argv[0] == "train" else []
    _refused([*argv, *base, "--out", str(tmp_path / "o")], capsys, field)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("line,where", [
    ("domain = [1.0, 0.5]", "[scene].domain"), ("domain = [[0, 1], [0]]", "[scene].domain"),
    ("gravity = [0.0, 'down']", "[scene].gravity")])
def test_malformed_scene_fields_refused(tmp_path, capsys, line, where):
    """Wrong-shaped [scene] fields ended in a TypeError traceback."""
    f = tmp_path / "s.toml"
    f.write_text(f"[scene]\ndx = 0.01\n{line}\n[[bodies]]\nshape = {{type='rectangle', x0=0.0, "
                 "y0=0.0, x1=0.1, y1=0.1}\nmaterial = {type='sand', friction_angle=30}\n")
    err = _refused(["simulate", "--scene", str(f), "--out", str(tmp_path / "o")], capsys,
                   f"--scene {f}")
    assert where in err and not (tmp_path / "o").exists()


def test_scene_file_errors_import_no_jax(tmp_path):
    """A scene file breaking a rule is refused before JAX is imported (it took 5-9 s)."""
    f = tmp_path / "s.toml"
    f.write_text("[scene]\ndx = 0.01\ndomain = [[0.0, 1.0], [0.0, 0.5]]\n[[bodies]]\nshape = "
                 "{type='rectangle', x0=0.0, y0=0.0, x1=0.1, y1=0.1}\nmaterial = "
                 "{type='sand', friction_angle=95}\n")
    code = ("import sys, diffgns.cli as c; rc = c.main(sys.argv[1:]); "
            "print(rc, sorted(m for m in ('jax', 'jax_md', 'flax', 'h5py') if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code, "simulate", "--scene", str(f), "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, timeout=60)
    assert r.stdout.strip() == "2 []", r.stdout + r.stderr
    assert "friction_angle = 95" in r.stderr and not (tmp_path / "o").exists()
