"""Tests of diffgns.io.dataset (HDF5 layout, resume, metadata statistics) and diffgns.io.npz
(PyTorch-GNS npz import and export)."""
from __future__ import annotations

import json

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

from diffgns.errors import InputError
from diffgns.io.dataset import (
    DatasetWriter,
    finite_difference_velocity,
    iter_dataset,
    load_dataset,
    metadata_path,
    read_metadata,
)
from diffgns.io.files import check_h5_file, partial_path, staged_dir
from diffgns.io.npz import load_gns_npz, write_gns_npz
from diffgns.trajectory import FLUID, SAND, Trajectory

DT = 0.0025
BOUNDS = ((0.0, 1.0), (0.0, 0.5))


def make_traj(seed: int = 0, n_frames: int = 6, n_particles: int = 5) -> Trajectory:
    """Random float32-representable trajectory, so HDF5 round trips are exact."""
    rng = np.random.default_rng(seed)
    pos = rng.random((n_frames, n_particles, 2)).astype(np.float32)
    vel = rng.normal(size=(n_frames, n_particles, 2)).astype(np.float32)
    ptype = np.where(np.arange(n_particles) % 2 == 0, SAND, FLUID).astype(np.int32)
    mat = rng.random(n_particles).astype(np.float32)
    return Trajectory(positions=jnp.asarray(pos), velocities=jnp.asarray(vel),
                      particle_type=jnp.asarray(ptype), material=jnp.asarray(mat),
                      frame_dt=DT, bounds=BOUNDS)


def constant_acceleration_traj(n_frames: int = 8, n_particles: int = 4) -> tuple:
    """Positions with exactly constant per-frame velocity increments (frame units)."""
    acc = np.array([0.25, -0.5])  # m / frame^2, exact in binary
    v0 = np.array([0.5, 1.0])
    k = np.arange(n_frames)[:, None, None]
    x0 = np.arange(n_particles)[None, :, None] * np.array([1.0, 2.0])
    pos = x0 + v0 * k + 0.5 * acc * k * (k - 1)  # x_k - x_{k-1} = v0 + acc (k - 1)
    traj = Trajectory(positions=jnp.asarray(pos, dtype=jnp.float32),
                      velocities=jnp.zeros(pos.shape), particle_type=jnp.full(n_particles, SAND),
                      material=jnp.zeros(n_particles), frame_dt=DT,
                      bounds=((0.0, 64.0), (0.0, 64.0)))
    return traj, pos, acc


def assert_same(a: Trajectory, b: Trajectory) -> None:
    np.testing.assert_array_equal(np.asarray(a.positions), np.asarray(b.positions))
    np.testing.assert_array_equal(np.asarray(a.velocities), np.asarray(b.velocities))
    np.testing.assert_array_equal(np.asarray(a.particle_type), np.asarray(b.particle_type))
    np.testing.assert_array_equal(np.asarray(a.material), np.asarray(b.material))
    assert a.frame_dt == b.frame_dt
    assert a.bounds == b.bounds


def test_hdf5_round_trip_is_exact(tmp_path):
    path = tmp_path / "train.h5"
    trajs = [make_traj(0), make_traj(1, n_frames=4, n_particles=7)]
    with DatasetWriter(path) as w:
        keys = [w.append(t, attrs={"seed": i, "scene": {"name": "column"}})
                for i, t in enumerate(trajs)]
        assert keys == ["00000", "00001"]
        assert len(w) == 2 and w.keys() == keys and w.has("00001") and not w.has("00002")
    loaded = load_dataset(path)
    assert len(loaded) == 2
    for a, b in zip(trajs, loaded, strict=True):
        assert_same(a, b)
    assert [t.n_particles for t in iter_dataset(path)] == [5, 7]
    with h5py.File(path, "r") as f:
        grp = f["00001"]
        assert grp["position"].dtype == np.float32 and grp["particle_type"].dtype == np.int32
        assert grp.attrs["seed"] == 1
        assert json.loads(grp.attrs["scene"]) == {"name": "column"}
        np.testing.assert_array_equal(grp.attrs["bounds"], np.asarray(BOUNDS))


def test_resume_keeps_groups_and_continues_keys(tmp_path):
    path = tmp_path / "data.h5"
    with DatasetWriter(path, metadata_extra={"scene": "collapse"}) as w:
        w.append(make_traj(0))
        w.append(make_traj(1))
    with DatasetWriter(path) as w:  # reopened in append mode
        assert w.keys() == ["00000", "00001"]
        assert w.append(make_traj(2)) == "00002"
        w.write("00005", make_traj(5))  # explicit key, as resumable generation does
        assert w.append(make_traj(6)) == "00006"
        w.write("00001", make_traj(7))  # rewriting a key replaces it
        assert w.metadata_extra == {"scene": "collapse"}
        meta = w.finalize(connectivity_radius=0.03)
    assert meta["scene"] == "collapse" and meta["n_trajectories"] == 5
    loaded = load_dataset(path)
    for traj, seed in zip(loaded, [0, 7, 2, 5, 6], strict=True):
        assert_same(traj, make_traj(seed))


def test_interrupted_write_is_discarded(tmp_path):
    path = tmp_path / "data.h5"
    with DatasetWriter(path) as w:
        w.append(make_traj(0))
    with h5py.File(path, "a") as f:  # simulate a crash in the middle of a write
        f.create_group("_incomplete_00001").create_dataset("position", data=np.zeros((2, 2, 2)))
    assert len(load_dataset(path)) == 1
    with DatasetWriter(path) as w:
        assert w.keys() == ["00000"]
        assert w.append(make_traj(1)) == "00001"
    with h5py.File(path, "r") as f:
        assert sorted(f.keys()) == ["00000", "00001"]


def test_metadata_statistics_constant_acceleration(tmp_path):
    traj, pos, acc = constant_acceleration_traj()
    path = tmp_path / "const.h5"
    with DatasetWriter(path, metadata_extra={"gravity": -9.81}) as w:
        w.append(traj)
        w.append(traj)
        meta = w.finalize(connectivity_radius=0.015)
    assert metadata_path(path) == tmp_path / "const.metadata.json"
    on_disk = json.loads(metadata_path(path).read_text())
    assert on_disk == meta == read_metadata(path) == read_metadata(metadata_path(path))
    np.testing.assert_allclose(meta["acc_mean"], acc, rtol=0, atol=1e-12)
    np.testing.assert_allclose(meta["acc_std"], [0.0, 0.0], rtol=0, atol=1e-12)
    vel = np.diff(pos, axis=0).reshape(-1, 2)
    np.testing.assert_allclose(meta["vel_mean"], vel.mean(0), rtol=1e-12)
    np.testing.assert_allclose(meta["vel_std"], vel.std(0), rtol=1e-12)
    assert meta["dt"] == DT and meta["dim"] == 2 and meta["gravity"] == -9.81
    assert meta["default_connectivity_radius"] == 0.015
    assert meta["bounds"] == [[0.0, 64.0], [0.0, 64.0]]
    assert meta["sequence_length"] == [8, 8] and meta["n_particles"] == [4, 4]
    assert meta["n_trajectories"] == 2


def test_metadata_statistics_pooled_over_trajectories(tmp_path):
    trajs = [make_traj(0, n_frames=6, n_particles=5), make_traj(3, n_frames=9, n_particles=3)]
    with DatasetWriter(tmp_path / "d.h5") as w:
        for t in trajs:
            w.append(t)
        meta = w.finalize(connectivity_radius=0.1)
    pos = [np.asarray(t.positions, dtype=np.float64) for t in trajs]
    vel = [np.diff(p, axis=0) for p in pos]
    acc = np.concatenate([np.diff(v, axis=0).reshape(-1, 2) for v in vel])
    vel = np.concatenate([v.reshape(-1, 2) for v in vel])
    for key, ref in [("vel_mean", vel.mean(0)), ("vel_std", vel.std(0)),
                     ("acc_mean", acc.mean(0)), ("acc_std", acc.std(0))]:
        np.testing.assert_allclose(meta[key], ref, rtol=1e-5, atol=1e-7, err_msg=key)
        assert len(meta[key]) == 2


def test_writer_rejects_bad_input(tmp_path):
    with pytest.raises(ValueError, match="dt"):
        DatasetWriter(tmp_path / "x.h5", metadata_extra={"dt": 1.0})
    bad = make_traj(0).replace(material=jnp.zeros(3))
    with DatasetWriter(tmp_path / "y.h5") as w:
        with pytest.raises(ValueError, match="material"):
            w.append(bad)
        with pytest.raises(ValueError, match="no trajectories"):
            w.finalize(0.1)
        assert len(w) == 0


@pytest.mark.parametrize(
    ("mutate", "field"),
    [
        (lambda g: g.__delitem__("position"), "position"),
        (lambda g: (g.__delitem__("position"), g.create_dataset("position", data=np.zeros((4, 2)))),
         "position"),
        (lambda g: (g.__delitem__("velocity"),
                    g.create_dataset("velocity", data=np.zeros((6, 5, 3)))), "velocity"),
        (lambda g: g.__delitem__("particle_type"), "particle_type"),
        (lambda g: (g.__delitem__("material_property"),
                    g.create_dataset("material_property", data=np.zeros(2))), "material_property"),
        (lambda g: g.attrs.__delitem__("frame_dt"), "frame_dt"),
    ],
)
def test_invalid_file_errors_name_group_and_field(tmp_path, mutate, field):
    path = tmp_path / "bad.h5"
    with DatasetWriter(path) as w:
        w.append(make_traj(0))
        w.append(make_traj(1))
    with h5py.File(path, "a") as f:
        mutate(f["00001"])
    with pytest.raises(ValueError, match=rf"group '00001'.*'{field}'"):
        load_dataset(path)


def test_lagrangebench_style_file_without_velocity(tmp_path):
    """Only position and particle_type per group, dt and bounds in metadata.json."""
    pos = np.cumsum(np.full((5, 3, 2), 0.01), axis=0)
    path = tmp_path / "train.h5"
    with h5py.File(path, "w") as f:
        grp = f.create_group("00000")
        grp.create_dataset("position", data=pos)
        grp.create_dataset("particle_type", data=np.zeros(3, dtype=np.int32))
    (tmp_path / "metadata.json").write_text(json.dumps({"dt": 0.01, "bounds": [[0, 1], [0, 2]]}))
    (traj,) = load_dataset(path)
    np.testing.assert_allclose(np.asarray(traj.velocities), 1.0, rtol=1e-5)
    assert traj.frame_dt == 0.01 and traj.bounds == ((0.0, 1.0), (0.0, 2.0))
    np.testing.assert_array_equal(np.asarray(traj.material), 0.0)


def test_finite_difference_velocity():
    pos = np.array([0.0, 1.0, 3.0, 6.0])[:, None, None] * np.ones((1, 2, 2))
    vel = finite_difference_velocity(pos, 0.5)
    np.testing.assert_array_equal(vel[:, 0, 0], [2.0, 2.0, 4.0, 6.0])
    np.testing.assert_array_equal(finite_difference_velocity(pos[:1], 0.5), 0.0)


def test_gns_npz_round_trip(tmp_path):
    trajs = [make_traj(0), make_traj(1, n_frames=3, n_particles=4)]
    path = write_gns_npz(tmp_path / "train.npz", trajs, connectivity_radius=0.02)
    loaded, meta = load_gns_npz(path)
    assert meta["dt"] == DT and meta["default_connectivity_radius"] == 0.02
    assert len(loaded) == 2
    for a, b in zip(trajs, loaded, strict=True):
        np.testing.assert_array_equal(np.asarray(a.positions), np.asarray(b.positions))
        np.testing.assert_array_equal(np.asarray(a.particle_type), np.asarray(b.particle_type))
        np.testing.assert_array_equal(np.asarray(a.material), np.asarray(b.material))
        assert b.frame_dt == DT and b.bounds == BOUNDS
        ref = finite_difference_velocity(np.asarray(a.positions), DT)
        np.testing.assert_allclose(np.asarray(b.velocities), ref, rtol=1e-6)


def test_gns_npz_pytorch_style_tuples(tmp_path):
    """Entries saved as plain tuples (scalar material, no material) and a default dt."""
    pos = np.linspace(0, 1, 4 * 3 * 2).reshape(4, 3, 2)
    entry_a = np.empty(3, dtype=object)
    entry_a[:] = [pos, np.full(3, SAND), 0.7]
    entry_b = np.empty(2, dtype=object)
    entry_b[:] = [pos[:, :2], np.full(2, FLUID)]
    np.savez(tmp_path / "valid.npz", a=entry_a, b=entry_b)
    (tmp_path / "meta.json").write_text(json.dumps({"bounds": [[0, 1], [0, 1]]}))
    with pytest.warns(UserWarning, match="dt"):
        trajs, _ = load_gns_npz(tmp_path / "valid.npz", tmp_path / "meta.json")
    np.testing.assert_allclose(np.asarray(trajs[0].material), 0.7)
    np.testing.assert_array_equal(np.asarray(trajs[1].material), 0.0)
    assert trajs[0].frame_dt == Trajectory.__dataclass_fields__["frame_dt"].default


def test_gns_npz_errors(tmp_path):
    write_gns_npz(tmp_path / "x.npz", [make_traj(0)], write_metadata=False)
    with pytest.raises(FileNotFoundError, match="metadata"):
        load_gns_npz(tmp_path / "x.npz")
    (tmp_path / "metadata.json").write_text(json.dumps({"dt": 0.1}))
    with pytest.raises(ValueError, match="bounds"):
        load_gns_npz(tmp_path / "x.npz")
    (tmp_path / "metadata.json").write_text(json.dumps({"dt": 0.1, "bounds": [[0, 1], [0, 1]]}))
    entry = np.empty(2, dtype=object)
    entry[:] = [np.zeros((3, 4, 3)), np.zeros(4)]
    np.savez(tmp_path / "x.npz", traj3d=entry)
    with pytest.raises(ValueError, match=r"'traj3d'.*d=3"):
        load_gns_npz(tmp_path / "x.npz")
    entry[:] = [np.zeros((3, 4, 2)), np.zeros(5)]
    np.savez(tmp_path / "x.npz", wrongtype=entry)
    with pytest.raises(ValueError, match=r"'wrongtype'.*particle_type"):
        load_gns_npz(tmp_path / "x.npz")
    np.savez(tmp_path / "x.npz", plain=np.zeros((3, 4, 2)))
    with pytest.raises(ValueError, match=r"'plain'.*tuple"):
        load_gns_npz(tmp_path / "x.npz")


# ------------------------------------------------- staged writes, recipes, input checks
RECIPE = dict(kind="test", n_frames=6, angles=[25.0, 35.0])


def test_staged_writer_builds_partial_and_renames_on_success(tmp_path):
    path = tmp_path / "new" / "d.h5"
    with DatasetWriter(path, recipe=RECIPE, staged=True) as w:
        w.write("00000", make_traj(0))
        assert w.path == partial_path(path) and partial_path(path).exists()
        assert not path.exists()
        w.finalize(connectivity_radius=0.1)
    assert path.exists() and not partial_path(path).exists()
    assert metadata_path(path).exists()  # next to the final name, not the .partial
    assert json.loads(h5py.File(path, "r").attrs["recipe"]) == RECIPE


def test_failure_before_any_trajectory_leaves_nothing(tmp_path):
    path = tmp_path / "a" / "b" / "d.h5"
    with pytest.raises(KeyboardInterrupt), DatasetWriter(path, recipe=RECIPE, staged=True):
        raise KeyboardInterrupt
    assert not (tmp_path / "a").exists()


def test_failure_after_a_trajectory_keeps_a_resumable_partial(tmp_path):
    path = tmp_path / "d.h5"
    with pytest.raises(RuntimeError), DatasetWriter(path, recipe=RECIPE, staged=True) as w:
        w.write("00000", make_traj(0))
        raise RuntimeError("stop")
    assert not path.exists() and len(load_dataset(partial_path(path))) == 1
    with DatasetWriter(path, recipe=RECIPE, staged=True) as w:  # resume
        assert w.has("00000")
        w.write("00001", make_traj(1))
    assert [k for k in h5py.File(path, "r")] == ["00000", "00001"]
    assert not partial_path(path).exists()


@pytest.mark.parametrize("staged", [False, True])
def test_resume_with_another_recipe_is_refused_untouched(tmp_path, staged):
    path = tmp_path / "d.h5"
    with DatasetWriter(path, recipe=RECIPE) as w:
        w.write("00000", make_traj(0))
    before = path.read_bytes()
    other = dict(RECIPE, n_frames=12, angles=[25.0], seed=3)
    with pytest.raises(InputError) as e:
        DatasetWriter(path, recipe=other, staged=staged)
    msg = str(e.value)
    assert msg.startswith(f"{path}: was made by a different recipe: ")
    assert "angles [25.0] (file: [25.0, 35.0])" in msg and "n_frames 12 (file: 6)" in msg
    assert "seed 3 (file: null)" in msg and "kind" not in msg
    assert path.read_bytes() == before
    with DatasetWriter(path, recipe=RECIPE, staged=staged) as w:  # the same recipe resumes
        assert w.has("00000")


def test_file_without_recipe_is_not_resumed_blindly(tmp_path):
    path = tmp_path / "d.h5"
    with DatasetWriter(path) as w:
        w.write("00000", make_traj(0))
    with pytest.raises(InputError, match="no recipe fingerprint"):
        DatasetWriter(path, recipe=RECIPE)


def test_check_h5_file_messages(tmp_path):
    good = tmp_path / "good.h5"
    with DatasetWriter(good) as w:
        w.write("00000", make_traj(0))
    check_h5_file(good, "--data", trajectories=True)
    empty = tmp_path / "empty.h5"
    h5py.File(empty, "w").close()
    trunc = tmp_path / "trunc.h5"
    trunc.write_bytes(good.read_bytes()[:2000])
    for path, what in [(tmp_path / "nope.h5", "does not exist"), (tmp_path, "is not a file"),
                       (trunc, "is not a readable HDF5 file (truncated file"),
                       (empty, "holds no trajectory")]:
        with pytest.raises(InputError) as e:
            check_h5_file(path, "--data", trajectories=True)
        assert str(e.value).startswith(f"--data: {path} ") and what in str(e.value)


def test_staged_dir_publishes_only_on_success(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("old")
    with pytest.raises(RuntimeError), staged_dir(out) as tmp:
        (tmp / "keep.txt").write_text("new")
        raise RuntimeError
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no leftover temporary folder
    assert (out / "keep.txt").read_text() == "old"
    with staged_dir(out) as tmp:
        (tmp / "keep.txt").write_text("new")
        (tmp / "sub").mkdir()
    assert (out / "keep.txt").read_text() == "new" and (out / "sub").is_dir()
    fresh = tmp_path / "x" / "y"
    with pytest.raises(RuntimeError), staged_dir(fresh):
        raise RuntimeError
    assert not (tmp_path / "x").exists()


def test_3d_column_dataset_holds_the_axisymmetric_columns_and_resumes(tmp_path):
    """``diffgns dataset --kind column --dim 3``: each sample is the cylinder of
    axisymmetric_column (radius = --width) at its friction angle, (T, N, 3), with a 3D
    recipe; a 2D recipe's fingerprint is unchanged (no ``dim`` key), so older 2D files
    still resume."""
    from diffgns.io.datagen import column_recipe, generate_columns
    from diffgns.io.dataset import H5TrajectoryFile
    from diffgns.scene.builders3d import axisymmetric_column

    assert "dim" not in column_recipe([1.0], [30.0], 3, 0.1, 4)
    assert column_recipe([1.0], [30.0], 3, 0.1, 4, dim=3)["dim"] == 3
    path = tmp_path / "c3d.h5"
    generate_columns(path, [1.0], [25.0, 35.0], 3, width=0.05, cells_across=2, batch=2,
                     progress=False, dim=3, domain_length=None, domain_height=None)
    with h5py.File(path) as f:
        assert sorted(f) == ["00000", "00001"]
        for key, phi in (("00000", 25.0), ("00001", 35.0)):
            g = f[key]
            assert float(g.attrs["friction_angle"]) == phi
            x = g["position"][...]
            scene = axisymmetric_column(radius=0.05, aspect_ratio=1.0, friction_angle=phi,
                                        cells_across=2)
            x0 = scene.particles()["x"]
            assert x.shape == (4, x0.shape[0], 3)
            np.testing.assert_allclose(x[0], x0, atol=1e-6)
            assert np.isfinite(x).all() and (x[-1, :, 1] < x[0, :, 1] + 1e-6).all()
            np.testing.assert_allclose(np.asarray(g.attrs["bounds"]),
                                       np.asarray(scene.domain), atol=1e-9)
        assert json.loads(f.attrs["recipe"])["dim"] == 3
    assert json.loads((tmp_path / "c3d.metadata.json").read_text())["dim"] == 3
    assert len(H5TrajectoryFile(path)) == 2
    # the finished file is resumed as complete: nothing is re-run
    generate_columns(path, [1.0], [25.0, 35.0], 3, width=0.05, cells_across=2, batch=2,
                     progress=False, dim=3, domain_length=None, domain_height=None)
