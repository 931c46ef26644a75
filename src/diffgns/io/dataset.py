"""Trajectory datasets on disk.

* **HDF5**, LagrangeBench-like (:class:`DatasetWriter`, :func:`load_dataset`,
  :func:`iter_dataset`): one group per trajectory named ``"00000"``, ``"00001"``, ... with
  datasets ``position`` (T, N, d) float32 m, ``velocity`` (T, N, d) float32 m/s,
  ``particle_type`` (N,) int32, ``material_property`` (N,) float32 (tan friction angle) and
  attributes ``frame_dt`` (s) and ``bounds`` ((d, 2), m); d = 2, or 3 for the 3D MPM
  (``diffgns simulate`` of a 3D scene; the GNS takes either). :meth:`DatasetWriter.finalize` writes
  the statistics to ``<stem>.metadata.json`` next to the file (``data/train.h5`` ->
  ``data/train.metadata.json``), so several splits can share a folder.
* **PyTorch GNS** ``.npz`` import and export: :mod:`diffgns.io.npz`.

Statistics are in frame units as GNS training expects: velocity ``x_t - x_{t-1}`` (m/frame)
and acceleration ``v_t - v_{t-1}`` (m/frame^2), not m/s.
"""
from __future__ import annotations

import json
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import h5py
import jax.numpy as jnp
import numpy as np

from diffgns.errors import InputError
from diffgns.io.files import (
    _TMP_PREFIX,
    _normalised,
    _short,
    check_h5_file,
    partial_path,
    write_text_atomic,
)
from diffgns.trajectory import Trajectory

_RESERVED_KEYS = frozenset({"bounds", "dim", "dt", "default_connectivity_radius", "vel_mean",
                            "vel_std", "acc_mean", "acc_std", "sequence_length",
                            "n_trajectories", "n_particles"})


def metadata_path(path: str | Path) -> Path:
    """Metadata file of the HDF5 file ``path``: ``<dir>/<stem>.metadata.json``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.metadata.json")


def finite_difference_velocity(positions: np.ndarray, dt: float) -> np.ndarray:
    """Velocities (T, N, d) in m/s from positions (T, N, d) in m sampled every ``dt`` s.

    Frame t >= 1 gets the backward difference ``(x_t - x_{t-1}) / dt``; frame 0 gets the forward
    difference ``(x_1 - x_0) / dt``. A single-frame trajectory gets zero velocity.
    """
    positions = np.asarray(positions)
    vel = np.zeros_like(positions)
    if positions.shape[0] > 1:
        vel[1:] = (positions[1:] - positions[:-1]) / dt
        vel[0] = vel[1]
    return vel


def _pooled(parts: list[tuple[int, list, list]], what: str) -> tuple[list, list]:
    """Mean and population std of the union of sample sets given as (count, mean, m2)."""
    _require(bool(parts), f"no {what} samples: every trajectory is too short")
    counts, means, m2 = (np.array([p[i] for p in parts]) for i in range(3))
    mean = (counts[:, None] * means).sum(axis=0) / counts.sum()
    var = (m2 + counts[:, None] * (means - mean) ** 2).sum(axis=0) / counts.sum()
    return mean.tolist(), np.sqrt(var).tolist()


def compute_statistics(positions: Iterable[np.ndarray]) -> dict:
    """Frame-unit statistics over trajectories given as positions arrays (T, N, d).

    Returns ``vel_mean``, ``vel_std`` (m/frame) and ``acc_mean``, ``acc_std`` (m/frame^2),
    each a list of length d (population std over all particles and frames). Trajectories are
    processed one at a time, so the dataset never has to fit in memory.
    """
    vel_parts, acc_parts = [], []
    for pos in positions:
        vel = np.diff(np.asarray(pos), axis=0)
        for parts, x in ((vel_parts, vel), (acc_parts, np.diff(vel, axis=0))):
            x = x.reshape(-1, x.shape[-1])
            if len(x):  # numpy's pairwise sums keep these accurate in the data dtype
                parts.append((len(x), x.mean(axis=0).tolist(), (x.var(axis=0) * len(x)).tolist()))
    vel_mean, vel_std = _pooled(vel_parts, "velocity")
    acc_mean, acc_std = _pooled(acc_parts, "acceleration")
    return {"vel_mean": vel_mean, "vel_std": vel_std, "acc_mean": acc_mean, "acc_std": acc_std}


def _require(ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(message)


def _as_bounds(value, where: str, dim: int = 2) -> tuple:
    arr = np.asarray(value, dtype=float)
    _require(arr.shape == (dim, 2), f"{where}: 'bounds' must be [[xmin, xmax], [ymin, ymax]"
             + ("]" if dim == 2 else ", [zmin, zmax]]"))
    return tuple(tuple(float(b) for b in row) for row in arr)


def _as_material(mat, n: int, where: str, name: str = "material_property") -> np.ndarray:
    mat = np.asarray(mat)
    mat = np.full((n,), mat) if mat.ndim == 0 else mat
    _require(mat.shape == (n,), f"{where}: '{name}' must be scalar or ({n},), got {mat.shape}")
    return mat


def _check_trajectory(traj: Trajectory, dims: tuple[int, ...] = (2,)) -> None:
    shape = tuple(traj.positions.shape)
    want = " or ".join(f"(T, N, {d})" for d in dims)
    _require(len(shape) == 3 and shape[-1] in dims,
             f"trajectory field 'positions' must be {want}, got {shape}")
    for name, want in [("velocities", shape), ("particle_type", shape[1:2]),
                       ("material", shape[1:2])]:
        got = tuple(getattr(traj, name).shape)
        _require(got == want, f"trajectory field '{name}' has shape {got}, expected {want}")


def _attr_value(value):
    """HDF5-storable form of a user attribute: strings and numbers as is, else JSON text."""
    if isinstance(value, (str, bytes)):
        return value
    try:
        arr = np.asarray(value)
    except ValueError:  # ragged sequences
        arr = np.asarray(None)
    return arr if arr.dtype.kind in "biuf" else json.dumps(value, default=str)


class H5TrajectoryFile:
    """Append-mode HDF5 file of trajectory groups, shared by the dataset writers.

    Reopening an existing file keeps its trajectories. Every group is written under a
    temporary name, moved to its final key and flushed, so an interrupted run leaves only
    complete groups (leftover temporary groups are removed on the next open).
    ``metadata_extra`` (JSON-serialisable) is stored in the file, so a resumed writer keeps it
    when given ``None``.

    Args:
        path: the ``.h5`` file; missing parent folders are created.
        metadata_extra: see above.
        recipe: JSON-serialisable description of everything that shapes the trajectories
            (kind, frames, parameters, seed, resolution, ...), stored as the file attribute
            ``recipe``. Reopening a file that holds trajectories with a different recipe (or
            none) raises :class:`~diffgns.errors.InputError` naming the fields that differ,
            before anything is written.
        staged: a new file is written as ``<path>.partial`` (:func:`partial_path`) and
            renamed to ``path`` when the ``with`` block ends without an exception; an
            existing ``<path>.partial`` is resumed, an existing ``path`` is extended in place.

    Leaving the ``with`` block by an exception removes a file this writer created if it holds
    no trajectory (and the folders it created, if empty); otherwise the file stays, valid and
    resumable.
    """

    def __init__(self, path: str | Path, metadata_extra: dict | None = None,
                 recipe: dict | None = None, staged: bool = False):
        self.final_path = Path(path)
        self.path = self.final_path
        if staged and not self.final_path.exists():
            self.path = partial_path(self.final_path)
        self._created = not self.path.exists()
        self._new_dirs = [d for d in reversed(self.path.parents) if not d.exists()]
        if not self._created:
            check_h5_file(self.path, str(self.path))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = h5py.File(self.path, "a")
        try:
            if recipe is not None:
                self._check_recipe(recipe)
        except BaseException:
            self._file.close()
            self._discard_if_empty()
            raise
        for name in [k for k in self._file if k.startswith(_TMP_PREFIX)]:
            del self._file[name]  # left by an interrupted write
        if metadata_extra is None:
            metadata_extra = json.loads(self._file.attrs.get("metadata_extra", "{}"))
        self.metadata_extra = dict(metadata_extra)
        self._file.attrs["metadata_extra"] = json.dumps(self.metadata_extra, default=str)
        self._file.flush()

    def _check_recipe(self, recipe: dict) -> None:
        """Refuse a file whose trajectories were made by another recipe; store ``recipe``."""
        want = _normalised(recipe)
        stored = self._file.attrs.get("recipe")
        if self.keys():
            if stored is None:
                raise InputError(str(self.path), "holds trajectories but no recipe fingerprint "
                                 "(written by an older diffgns), so a resume cannot be checked",
                                 "delete it or write to another file")
            have = json.loads(stored)
            diff = [f"{k} {_short(want.get(k))} (file: {_short(have.get(k))})"
                    for k in sorted(set(want) | set(have)) if want.get(k) != have.get(k)]
            if diff:
                raise InputError(str(self.path), "was made by a different recipe: "
                                 + ", ".join(diff),
                                 "rerun with the file's arguments to resume, or write to "
                                 "another file")
        self._file.attrs["recipe"] = json.dumps(want)

    def _discard_if_empty(self) -> None:
        """Remove the file and the folders this writer created if it holds no trajectory."""
        if not self._created or not self.path.exists():
            return
        with h5py.File(self.path, "r") as f:
            empty = not any(not k.startswith(_TMP_PREFIX) for k in f)
        if empty:
            self.path.unlink()
            for d in reversed(self._new_dirs):
                if d.exists() and not any(d.iterdir()):
                    d.rmdir()

    def keys(self) -> list[str]:
        """Sorted keys of the stored trajectories."""
        return sorted(k for k in self._file if not k.startswith(_TMP_PREFIX))

    def __len__(self) -> int:
        return len(self.keys())

    def has(self, key: str) -> bool:
        """Whether a complete trajectory is stored under ``key``."""
        return not key.startswith(_TMP_PREFIX) and key in self._file

    def _store(self, key: str, datasets: dict, attrs: dict) -> None:
        """Write one group atomically: ``datasets`` name -> array (stored with its dtype),
        ``attrs`` as group attributes (:func:`_attr_value`); replaces ``key``; flushes."""
        _require(bool(key) and not key.startswith(_TMP_PREFIX) and "/" not in key,
                 f"invalid trajectory key {key!r}")
        tmp = _TMP_PREFIX + key
        if tmp in self._file:
            del self._file[tmp]
        grp = self._file.create_group(tmp)
        for name, data in datasets.items():
            grp.create_dataset(name, data=data)
        for name, value in attrs.items():
            grp.attrs[name] = _attr_value(value)
        if key in self._file:
            del self._file[key]
        self._file.move(tmp, key)
        self._file.flush()

    def copy_group(self, source: h5py.Group, key: str) -> None:
        """Store the trajectory group ``source`` (of another file) under ``key``, byte for
        byte (HDF5 copy of its datasets and attributes), atomically as :meth:`_store`."""
        _require(bool(key) and not key.startswith(_TMP_PREFIX) and "/" not in key,
                 f"invalid trajectory key {key!r}")
        tmp = _TMP_PREFIX + key
        if tmp in self._file:
            del self._file[tmp]
        self._file.copy(source, tmp)
        if key in self._file:
            del self._file[key]
        self._file.move(tmp, key)
        self._file.flush()

    def close(self) -> None:
        """Flush and close the file (idempotent)."""
        if self._file.id.valid:
            self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()
        if exc_type is not None:
            self._discard_if_empty()
        elif self.path != self.final_path:
            os.replace(self.path, self.final_path)
            self.path = self.final_path


class DatasetWriter(H5TrajectoryFile):
    """Append trajectories to an HDF5 file; see the module docstring for the layout and
    :class:`H5TrajectoryFile` for resume and atomic writes; :meth:`append` continues the key
    numbering.

    Args:
        path: the ``.h5`` file; parent folders are created.
        metadata_extra: extra JSON-serialisable entries for the metadata file.
        recipe, staged: see :class:`H5TrajectoryFile`.
    """

    def __init__(self, path: str | Path, metadata_extra: dict | None = None,
                 recipe: dict | None = None, staged: bool = False):
        clash = sorted(_RESERVED_KEYS.intersection(metadata_extra or {}))
        _require(not clash, f"metadata_extra may not override computed keys {clash}")
        super().__init__(path, metadata_extra, recipe=recipe, staged=staged)

    def _next_index(self) -> int:
        indices = [int(k) for k in self.keys() if k.isdigit()]
        return max(indices) + 1 if indices else 0

    def append(self, traj: Trajectory, attrs: dict | None = None) -> str:
        """Store ``traj`` under the next free key (one past the largest numeric key)."""
        key = f"{self._next_index():05d}"
        self.write(key, traj, attrs)
        return key

    def write(self, key: str, traj: Trajectory, attrs: dict | None = None) -> None:
        """Store ``traj`` under ``key``, replacing any trajectory already there.

        ``attrs`` are stored as group attributes (numbers, strings and numeric arrays as is,
        anything else as JSON text). The file is flushed before returning.
        """
        _check_trajectory(traj, dims=(2, 3))
        datasets = dict(position=np.asarray(traj.positions, dtype=np.float32),
                        velocity=np.asarray(traj.velocities, dtype=np.float32),
                        particle_type=np.asarray(traj.particle_type, dtype=np.int32),
                        material_property=np.asarray(traj.material, dtype=np.float32))
        extra = dict(attrs or {})
        if traj.obstacles and "obstacles" not in extra:  # the scene's box obstacles, m
            d2 = 2 * np.shape(traj.positions)[-1]  # [lo..., hi...] per box: 2 numbers per axis
            extra["obstacles"] = np.asarray(traj.obstacles, float).reshape(-1, d2)
        self._store(key, datasets, dict(
            frame_dt=float(traj.frame_dt),
            bounds=np.asarray(traj.bounds, dtype=float).reshape(-1, 2), **extra))

    def finalize(self, connectivity_radius: float) -> dict:
        """Compute the statistics and write ``<stem>.metadata.json`` (:func:`metadata_path`).

        Returns the metadata dict: ``bounds`` [[xmin, xmax], [ymin, ymax](, [zmin, zmax])]
        (union over the trajectories), ``dim`` (2 or 3), ``dt`` (frame dt, s),
        ``default_connectivity_radius`` (m),
        ``vel_mean``/``vel_std`` (m/frame), ``acc_mean``/``acc_std`` (m/frame^2),
        ``sequence_length`` and ``n_particles`` (lists, one per trajectory), ``n_trajectories``,
        plus ``metadata_extra``.
        """
        keys = self.keys()
        _require(bool(keys), f"{self.path}: no trajectories to finalize")
        dts = [float(self._file[k].attrs["frame_dt"]) for k in keys]
        _require(np.allclose(dts, dts[0], rtol=1e-6, atol=0),
                 f"{self.path}: trajectories differ in frame_dt {sorted(set(dts))}")
        shapes = [self._file[k]["position"].shape for k in keys]
        dims = sorted({int(sh[-1]) for sh in shapes})
        _require(len(dims) == 1, f"{self.path}: trajectories mix dimensions {dims}")
        all_bounds = np.stack([np.asarray(self._file[k].attrs["bounds"]) for k in keys])
        bounds = np.stack([all_bounds[:, :, 0].min(axis=0), all_bounds[:, :, 1].max(axis=0)], 1)
        meta = {
            "bounds": bounds.tolist(), "dim": dims[0], "dt": dts[0],
            "default_connectivity_radius": float(connectivity_radius),
            **compute_statistics(self._file[k]["position"][()] for k in keys),
            "sequence_length": [int(sh[0]) for sh in shapes], "n_trajectories": len(keys),
            "n_particles": [int(sh[1]) for sh in shapes], **self.metadata_extra,
        }
        write_text_atomic(metadata_path(self.final_path), json.dumps(meta, indent=2, default=str))
        return meta


def read_metadata(path: str | Path) -> dict:
    """Read the metadata of a dataset.

    ``path`` is a metadata ``.json`` file or an ``.h5`` file, whose ``<stem>.metadata.json`` is
    used, falling back to ``metadata.json`` in the same folder.
    """
    path = Path(path)
    if path.suffix != ".json":
        candidates = [metadata_path(path), path.with_name("metadata.json")]
        found = [c for c in candidates if c.exists()]
        if not found:
            raise FileNotFoundError(f"no metadata for {path}: tried {[str(c) for c in candidates]}")
        path = found[0]
    return json.loads(path.read_text())


def _make_trajectory(pos, vel, ptype, mat, frame_dt: float, bounds: tuple,
                     obstacles: tuple = ()) -> Trajectory:
    return Trajectory(positions=jnp.asarray(pos), velocities=jnp.asarray(vel),
                      particle_type=jnp.asarray(ptype, dtype=jnp.int32),
                      material=jnp.asarray(mat), frame_dt=frame_dt, bounds=bounds,
                      obstacles=obstacles)


def _read_group(path: Path, key: str, grp: h5py.Group, meta: dict | None) -> Trajectory:
    where = f"{path}: group '{key}'"
    for name in ("position", "particle_type"):
        _require(name in grp, f"{where}: missing dataset '{name}'")
    pos, ptype = grp["position"][()], grp["particle_type"][()]
    _require(pos.ndim == 3 and pos.shape[-1] in (2, 3),
             f"{where}: 'position' must have shape (T, N, 2) or (T, N, 3), got {pos.shape}")
    n = pos.shape[1]
    _require(ptype.shape == (n,), f"{where}: 'particle_type' must be ({n},), got {ptype.shape}")

    def attr(name: str, meta_name: str):
        if name in grp.attrs:
            return grp.attrs[name]
        _require(meta is not None and meta_name in meta,
                 f"{where}: missing attribute '{name}' (and no '{meta_name}' in metadata)")
        return meta[meta_name]

    frame_dt = float(attr("frame_dt", "dt"))
    bounds = _as_bounds(attr("bounds", "bounds"), where, dim=pos.shape[-1])
    vel = grp["velocity"][()] if "velocity" in grp else finite_difference_velocity(pos, frame_dt)
    _require(vel.shape == pos.shape, f"{where}: 'velocity' must be {pos.shape}, got {vel.shape}")
    mat = (_as_material(grp["material_property"][()], n, where) if "material_property" in grp
           else np.zeros((n,), dtype=pos.dtype))
    d2 = 2 * pos.shape[-1]  # an obstacle box is 2 numbers per axis
    obs = np.asarray(grp.attrs.get("obstacles", np.zeros((0, d2))), float)
    _require(obs.size % d2 == 0, f"{where}: 'obstacles' must be rows of {d2} numbers (a box "
             f"per row in {d2 // 2}D), got shape {obs.shape}")
    obs = obs.reshape(-1, d2)
    return _make_trajectory(pos, vel, ptype, mat, frame_dt, bounds,
                            tuple(tuple(float(c) for c in o) for o in obs))


def iter_dataset(path: str | Path, keys: Sequence[str] | None = None) -> Iterator[Trajectory]:
    """Yield the trajectories of an HDF5 dataset in key order (or the given ``keys``).

    Missing ``velocity`` is rebuilt by :func:`finite_difference_velocity`, missing
    ``material_property`` becomes zeros, and missing ``frame_dt``/``bounds`` attributes are taken
    from the metadata file (``dt``/``bounds``) if there is one, so plain LagrangeBench files load.

    Raises:
        ValueError: naming the group and field when a dataset is missing or has wrong dims.
        KeyError: when one of ``keys`` is not a trajectory group.
    """
    path = Path(path)
    try:
        meta = read_metadata(path)
    except FileNotFoundError:
        meta = None
    with h5py.File(path, "r") as f:
        if keys is None:
            keys = sorted(k for k in f if not k.startswith(_TMP_PREFIX))
        for key in keys:
            if not isinstance(f.get(key), h5py.Group):
                raise KeyError(f"{path}: no trajectory group '{key}'")
            yield _read_group(path, key, f[key], meta)


def load_dataset(path: str | Path) -> list[Trajectory]:
    """All trajectories of an HDF5 dataset, in key order; see :func:`iter_dataset`."""
    return list(iter_dataset(path))
