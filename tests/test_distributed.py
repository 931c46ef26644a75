"""Several processes on JAX's distributed runtime (diffgns.distributed, diffgns.shard,
diffgns.io.shards): two real OS processes on this machine (localhost coordinator, gloo CPU
collectives) train a GNS to the parameters of a one-process run on the same global batch,
and generate dataset shards whose merge equals a one-process dataset byte for byte."""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from flax import serialization

from diffgns.cli import main
from diffgns.errors import InputError
from diffgns.io.datagen import column_jobs
from diffgns.io.shards import merge_shards, shard_path
from diffgns.scene.recipes import column_samples
from diffgns.shard import Shard

GNS_ARGS = ["--steps", "3", "--batch-size", "2", "--radius", "0.045", "--latent", "8",
            "--mp-steps", "1", "--mlp-layers", "1", "--noise-std", "1e-4", "--lr", "3e-3",
            "--checkpoint-every", "2", "--validate-every", "1000"]
SQUARES_ARGS = ["--kind", "squares", "--n", "3", "--frames", "3", "--seed", "0", "--dx",
                "0.05", "--size", "0.2"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _two_processes(args: list[str], cwd: Path, timeout: float = 900) -> list[str]:
    """Run ``diffgns <args>`` as processes 0 and 1 of one jax.distributed run; return their
    outputs (stdout + stderr); fail if either exits non-zero."""
    port = _free_port()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.pop("XLA_FLAGS", None)  # one CPU device per process
    procs = [subprocess.Popen([sys.executable, "-m", "diffgns.cli", *args, "--coordinator",
                               f"localhost:{port}", "--num-processes", "2", "--process-id",
                               str(i)], cwd=cwd, env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True) for i in range(2)]
    outs = []
    try:
        for p in procs:
            outs.append(p.communicate(timeout=timeout)[0])
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for i, (p, out) in enumerate(zip(procs, outs)):
        assert p.returncode == 0, f"process {i} exited {p.returncode}:\n{out[-3000:]}"
    return outs


# ----------------------------------------------------------------------- shards of work
def test_shard_parse_select_and_refusals():
    assert Shard.parse("0/2") == Shard(0, 2) and Shard.parse(" 1 / 3 ") == Shard(1, 3)
    items = list("abcdefg")
    parts = [Shard(i, 3).select(items) for i in range(3)]
    assert parts == [list("adg"), list("be"), list("cf")]
    assert sorted(sum(parts, [])) == items  # disjoint and complete
    assert [Shard(1, 3).owns(i) for i in range(5)] == [False, True, False, False, True]
    for bad in ("2/2", "-1/2", "1/0", "a/b", "1", "1/2/3"):
        with pytest.raises(InputError) as e:
            Shard.parse(bad)
        assert str(e.value).startswith("--shard: ") and "\n" not in str(e.value)


@pytest.mark.parametrize("bad", ["2/2", "-1/2", "1/0", "a/b"])
def test_cli_refuses_bad_shard_in_one_line(tmp_path, capsys, bad):
    rc = main(["dataset", *SQUARES_ARGS, "--out", str(tmp_path / "d.h5"), f"--shard={bad}"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.startswith("diffgns: error: --shard: ") and "\n" not in err
    assert not any(tmp_path.iterdir())  # nothing written


def test_column_shards_are_whole_vmap_batches():
    """A column shard owns whole batches of the one-process run (so the merged file holds
    the bytes that run writes), round robin over the aspect ratios; together all samples."""
    samples = column_samples([0.5, 1.0, 2.0], [25.0, 30.0, 35.0, 40.0, 45.0])
    jobs = column_jobs(samples, [0.5, 1.0, 2.0], batch=2)
    assert [len(j) for j in jobs] == [2, 2, 1] * 3
    for job in jobs:
        assert len({samples[i]["aspect_ratio"] for i in job}) == 1
    mine = [sorted(i for j in Shard(k, 2).select(jobs) for i in j) for k in range(2)]
    assert sorted(mine[0] + mine[1]) == list(range(len(samples)))
    assert abs(len(mine[0]) - len(mine[1])) <= 2


# ----------------------------------------------------------------------- training
# slow (the default suite is over its budget): `make test-distributed` runs this file's 11
# tests in 125 s on this 2-core machine with nothing else running (2026-12-03 11:30 UTC;
# 437.6 s for this test alone at load ~20)
@pytest.mark.slow
def test_two_processes_train_like_one_process(tmp_path):
    """Two processes (one CPU device each, the batch of 2 split one window per process,
    gradient all-reduced over gloo) end with the parameters of a one-process run on the same
    global batches, to float32 round-off; only process 0 writes the run's files."""
    from diffgns.io.npz import write_gns_npz
    from test_resume import _blocks

    write_gns_npz(tmp_path / "train.npz", _blocks())
    t0 = time.perf_counter()
    outs = _two_processes(["train", "--data", "train.npz", "--out", "two", *GNS_ARGS],
                          tmp_path)
    seconds = time.perf_counter() - t0
    assert main(["train", "--data", str(tmp_path / "train.npz"), "--out",
                 str(tmp_path / "one"), *GNS_ARGS]) == 0
    one, two = ((tmp_path / d / "model" / "params.msgpack").read_bytes() for d in ("one", "two"))
    a = serialization.msgpack_restore(one)
    b = serialization.msgpack_restore(two)
    import jax

    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert jax.tree.structure(a) == jax.tree.structure(b)
    scale = max(float(np.abs(x).max()) for x in la)
    diff = max(float(np.abs(x - y).max()) for x, y in zip(la, lb))
    assert diff <= 1e-6 * scale, f"two processes differ by {diff} (scale {scale})"
    # the run really trained: three Adam steps of lr ~3e-3 moved the parameters
    rows = (tmp_path / "two" / "train_log.csv").read_text().splitlines()
    assert rows[0].startswith("step,loss") and [r.split(",")[0] for r in rows[1:]] == ["3"]
    assert json.loads((tmp_path / "two" / "checkpoint.json").read_text())["step"] == 3
    assert sorted(p.name for p in (tmp_path / "two" / "checkpoint").iterdir()) == ["3"]
    assert sum("model written" in o for o in outs) >= 1
    print(f"two-process training test: {seconds:.1f} s (indicative, machine shared)")


# ----------------------------------------------------------------------- datasets
def _dump(path: Path) -> dict:
    """Every key, array (with dtype) and attribute of an HDF5 dataset, and its metadata."""
    out: dict = {}
    with h5py.File(path, "r") as f:
        out["attrs"] = {k: str(f.attrs[k]) for k in f.attrs}
        for k in f:
            g = f[k]
            out[k] = ({n: (g[n].dtype.str, g[n][()].tobytes()) for n in g},
                      {n: np.asarray(g.attrs[n]).tobytes() for n in g.attrs})
    out["metadata"] = json.loads(path.with_name(f"{path.stem}.metadata.json").read_text())
    return out


@pytest.fixture(scope="module")
def sharded(tmp_path_factory):
    """Two processes of one jax.distributed run generate their shards and process 0
    merges them; and the same dataset from one process."""
    d = tmp_path_factory.mktemp("shards")
    t0 = time.perf_counter()
    _two_processes(["dataset", *SQUARES_ARGS, "--out", "two.h5"], d)
    seconds = time.perf_counter() - t0
    assert main(["dataset", *SQUARES_ARGS, "--out", str(d / "one.h5")]) == 0
    return d, seconds


# slow: see above (`make test-distributed`, 125 s for the file on a quiet machine; this
# fixture took 684 s at load ~22)
@pytest.mark.slow
def test_two_process_dataset_equals_one_process(sharded):
    d, seconds = sharded
    shards = [shard_path(d / "two.h5", Shard(i, 2)) for i in range(2)]
    with h5py.File(shards[0]) as f0, h5py.File(shards[1]) as f1:
        assert (sorted(f0), sorted(f1)) == (["00000", "00002"], ["00001"])
        assert json.loads(f1.attrs["recipe"])["shard"] == "1/2"
    one, two = _dump(d / "one.h5"), _dump(d / "two.h5")
    assert sorted(one) == sorted(two) == ["00000", "00001", "00002", "attrs", "metadata"]
    assert one == two  # same keys, bytes, attributes, recipe and metadata
    print(f"two-process dataset test: {seconds:.1f} s (indicative, machine shared)")


@pytest.mark.slow  # the shards of the fixture above
def test_shard_resume_and_merge_command(sharded, capsys):
    """An explicit --shard run on a finished shard skips its trajectories; `diffgns dataset
    --merge` of the shards equals the one-process file; bad merges are refused."""
    d, _ = sharded
    shards = [shard_path(d / "two.h5", Shard(i, 2)) for i in range(2)]
    before = shards[1].stat().st_mtime_ns
    t0 = time.perf_counter()
    assert main(["dataset", *SQUARES_ARGS, "--out", str(d / "two.h5"), "--shard", "1/2"]) == 0
    assert time.perf_counter() - t0 < 30  # nothing simulated (a flow takes longer here)
    assert _dump(shards[1])["00001"] == _dump(d / "one.h5")["00001"]
    assert before <= shards[1].stat().st_mtime_ns
    assert main(["dataset", "--merge", str(shards[1]), str(shards[0]), "--out",
                 str(d / "merged.h5")]) == 0
    assert _dump(d / "merged.h5") == _dump(d / "one.h5")
    capsys.readouterr()
    with pytest.raises(InputError, match="shard.*missing"):
        merge_shards([shards[0]], d / "x.h5")
    with pytest.raises(InputError, match="again"):
        merge_shards([shards[0], shards[0]], d / "x.h5")
    with pytest.raises(InputError, match="not a dataset shard"):
        merge_shards([d / "one.h5"], d / "x.h5")
    with pytest.raises(InputError, match="exists"):
        merge_shards(shards, d / "merged.h5")
    assert main(["dataset", "--merge", str(shards[0]), "--out", str(d / "y.h5")]) == 2
    assert capsys.readouterr().err.startswith("diffgns: error: shards: shard(s) 1/2 missing")
    assert not (d / "y.h5").exists()


def test_initialize_refuses_incomplete_or_out_of_range_options(monkeypatch):
    from diffgns.distributed import initialize

    for name in ("DIFFGNS_COORDINATOR", "DIFFGNS_NUM_PROCESSES", "DIFFGNS_PROCESS_ID"):
        monkeypatch.delenv(name, raising=False)
    assert initialize() is False  # nothing asked: one process, JAX untouched
    cases = [(("localhost:1", 2, None), "give all three"),
             (("localhost:1", 2, 2), "--process-id: must be in [0, 2)"),
             (("localhost:1", 0, 0), "--num-processes: must be >= 1"),
             (("localhost", 2, 0), "--coordinator: 'localhost' is not host:port")]
    for args, message in cases:
        with pytest.raises(InputError) as e:
            initialize(*args)
        assert message in str(e.value) and "\n" not in str(e.value)
    monkeypatch.setenv("DIFFGNS_NUM_PROCESSES", "two")
    with pytest.raises(InputError, match="DIFFGNS_NUM_PROCESSES: 'two' is not an integer"):
        initialize()


def test_one_process_placement_round_trips_exactly():
    """In one process the global-array helpers are exact identities on the values."""
    import jax
    from jax.sharding import NamedSharding, PartitionSpec

    from diffgns.distributed import data_mesh, replicate, replicated, shard_batch, to_host

    tree = {"w": np.arange(6, dtype=np.float32).reshape(2, 3), "n": np.int32(3)}
    rep = replicate(tree)
    assert all(x.sharding == replicated() for x in jax.tree.leaves(rep))
    back = to_host(rep)
    assert np.array_equal(back["w"], tree["w"]) and back["n"] == 3
    mesh = data_mesh()
    # one device per process by default, though this process has two host devices
    # (tests/conftest.py): the second is the sharded MPM's, not the trainer's
    assert len(jax.local_devices()) >= 2 and list(mesh.devices.flat) == [jax.devices()[0]]
    batch = shard_batch({"x": np.arange(4.0 * len(mesh.devices.flat)).reshape(-1, 2)},
                        NamedSharding(mesh, PartitionSpec("data")))
    assert batch["x"].shape == (2 * len(mesh.devices.flat), 2)
