"""Trajectory datasets on disk.

Two layouts are supported:

* **HDF5** in a LagrangeBench-like layout, written by :class:`DatasetWriter` and read by
  :func:`load_dataset` / :func:`iter_dataset`. One group per trajectory, named ``"00000"``,
  ``"00001"``, ..., holding the datasets

  - ``position`` (T, N, 2) float32, m
  - ``velocity`` (T, N, 2) float32, m/s (optional on read: finite differences are used)
  - ``particle_type`` (N,) int32
  - ``material_property`` (N,) float32, tan(friction angle) (optional on read: zeros)

  and the group attributes ``frame_dt`` (s) and ``bounds`` ((2, 2), m). The dataset
  statistics are written by :meth:`DatasetWriter.finalize` to ``<stem>.metadata.json`` next to
  the file (``data/train.h5`` -> ``data/train.metadata.json``), so several splits can share a
  folder.

* **PyTorch GNS** ``.npz`` files (one entry per trajectory, each a tuple
  ``(positions, particle_type[, material_property])``) plus a ``metadata.json`` in the same
  folder, read by :func:`load_gns_npz` and written by :func:`write_gns_npz`.

Statistics are in frame units as GNS training expects: velocity ``x_t - x_{t-1}`` (m per
frame) and acceleration ``v_t - v_{t-1}`` (m per frame^2), not m/s.
"""
from __future__ import annotations

import json
import warnings
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Self

import h5py
import jax.numpy as jnp
import numpy as np

from .trajectory import Trajectory

_TMP_PREFIX = "_incomplete_"
_RESERVED_KEYS = frozenset({
    "bounds", "dim", "dt", "default_connectivity_radius", "vel_mean", "vel_std", "acc_mean",
    "acc_std", "sequence_length", "n_trajectories", "n_particles",
})


def metadata_path(path: str | Path) -> Path:
    """Path of the metadata file belonging to the HDF5 file ``path``: ``<dir>/<stem>.metadata.json``."""
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


class _RunningStats:
    """Per-component mean/std of (..., d) samples, merged with Chan's parallel formula."""

    def __init__(self) -> None:
        self.count = 0
        self.mean: np.ndarray | None = None
        self.m2: np.ndarray | None = None

    def update(self, samples: np.ndarray) -> None:
        samples = samples.reshape(-1, samples.shape[-1])
        n = samples.shape[0]
        if n == 0:
            return
        # numpy reductions use pairwise summation, so the per-batch moments are accurate in
        # the data dtype; merging happens in Python-float precision.
        mean_b = samples.mean(axis=0).tolist()
        m2_b = (samples.var(axis=0) * n).tolist()
        if self.count == 0:
            self.count, self.mean, self.m2 = n, np.array(mean_b), np.array(m2_b)
            return
        total = self.count + n
        delta = np.array(mean_b) - self.mean
        self.mean = self.mean + delta * (n / total)
        self.m2 = self.m2 + np.array(m2_b) + delta**2 * (self.count * n / total)
        self.count = total

    def result(self, what: str) -> tuple[list[float], list[float]]:
        if self.count == 0:
            raise ValueError(f"no {what} samples: every trajectory is too short")
        return self.mean.tolist(), np.sqrt(self.m2 / self.count).tolist()


def compute_statistics(positions: Iterable[np.ndarray]) -> dict:
    """Frame-unit statistics over trajectories given as positions arrays (T, N, d).

    Returns ``vel_mean``, ``vel_std`` (m/frame) and ``acc_mean``, ``acc_std`` (m/frame^2),
    each a list of length d (population std over all particles and frames).
    """
    vel_stats, acc_stats = _RunningStats(), _RunningStats()
    for pos in positions:
        vel = np.diff(np.asarray(pos), axis=0)
        vel_stats.update(vel)
        acc_stats.update(np.diff(vel, axis=0))
    vel_mean, vel_std = vel_stats.result("velocity")
    acc_mean, acc_std = acc_stats.result("acceleration")
    return {"vel_mean": vel_mean, "vel_std": vel_std, "acc_mean": acc_mean, "acc_std": acc_std}


def _check_trajectory(traj: Trajectory) -> None:
    if traj.positions.ndim != 3:
        raise ValueError(
            f"trajectory field 'positions' must be (T, N, 2), got shape {traj.positions.shape}"
        )
    t, n = traj.positions.shape[:2]
    expected = {
        "positions": (traj.positions.shape, (t, n, 2)),
        "velocities": (traj.velocities.shape, (t, n, 2)),
        "particle_type": (traj.particle_type.shape, (n,)),
        "material": (traj.material.shape, (n,)),
    }
    for name, (shape, want) in expected.items():
        if tuple(shape) != want:
            raise ValueError(f"trajectory field '{name}' has shape {tuple(shape)}, expected {want}")


def _attr_value(value):
    """Convert a user attribute to something HDF5 can store (JSON text as a fallback)."""
    if isinstance(value, (str, bytes, int, float, bool, np.generic, np.ndarray)):
        return value
    try:
        arr = np.asarray(value)
        if arr.dtype.kind in "biuf":
            return arr
    except (ValueError, TypeError):
        pass
    return json.dumps(value, default=str)


class DatasetWriter:
    """Append trajectories to an HDF5 file; see the module docstring for the layout.

    The file is opened in append mode, so reopening an existing file keeps its trajectories and
    :meth:`append` continues the key numbering. Every trajectory is written under a temporary
    name, moved to its final key and flushed, so an interrupted run leaves only complete groups
    (leftover temporary groups are removed on the next open).

    Args:
        path: the ``.h5`` file; parent folders are created.
        metadata_extra: extra JSON-serialisable entries for the metadata file. They are also
            stored in the file, so a resumed writer keeps them when given ``None``.
    """

    def __init__(self, path: str | Path, metadata_extra: dict | None = None):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = h5py.File(self.path, "a")
        for name in list(self._file.keys()):
            if name.startswith(_TMP_PREFIX):
                del self._file[name]
        if metadata_extra is None:
            stored = self._file.attrs.get("metadata_extra")
            metadata_extra = json.loads(stored) if stored is not None else {}
        clash = _RESERVED_KEYS.intersection(metadata_extra)
        if clash:
            self._file.close()
            raise ValueError(f"metadata_extra may not override computed keys {sorted(clash)}")
        self.metadata_extra = dict(metadata_extra)
        self._file.attrs["metadata_extra"] = json.dumps(self.metadata_extra, default=str)
        self._file.flush()

    def keys(self) -> list[str]:
        """Sorted keys of the stored trajectories."""
        return sorted(k for k in self._file if not k.startswith(_TMP_PREFIX))

    def __len__(self) -> int:
        return len(self.keys())

    def has(self, key: str) -> bool:
        """Whether a complete trajectory is stored under ``key``."""
        return not key.startswith(_TMP_PREFIX) and key in self._file

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
        if not key or key.startswith(_TMP_PREFIX) or "/" in key:
            raise ValueError(f"invalid trajectory key {key!r}")
        _check_trajectory(traj)
        tmp = _TMP_PREFIX + key
        if tmp in self._file:
            del self._file[tmp]
        grp = self._file.create_group(tmp)
        grp.create_dataset("position", data=np.asarray(traj.positions, dtype=np.float32))
        grp.create_dataset("velocity", data=np.asarray(traj.velocities, dtype=np.float32))
        grp.create_dataset("particle_type", data=np.asarray(traj.particle_type, dtype=np.int32))
        grp.create_dataset("material_property", data=np.asarray(traj.material, dtype=np.float32))
        grp.attrs["frame_dt"] = float(traj.frame_dt)
        grp.attrs["bounds"] = np.asarray(traj.bounds, dtype=float).reshape(2, 2)
        for name, value in (attrs or {}).items():
            grp.attrs[name] = _attr_value(value)
        if key in self._file:
            del self._file[key]
        self._file.move(tmp, key)
        self._file.flush()

    def finalize(self, connectivity_radius: float) -> dict:
        """Compute the dataset statistics and write :func:`metadata_path` (``<stem>.metadata.json``).

        Args:
            connectivity_radius: default graph connectivity radius in m.

        Returns:
            The metadata dict: ``bounds`` [[xmin, xmax], [ymin, ymax]] (the union over
            trajectories), ``dim``, ``dt`` (frame dt, s), ``default_connectivity_radius``,
            ``vel_mean``/``vel_std`` (m/frame), ``acc_mean``/``acc_std`` (m/frame^2),
            ``sequence_length`` (frames per trajectory), ``n_trajectories``, ``n_particles``
            (per trajectory), plus ``metadata_extra``.
        """
        keys = self.keys()
        if not keys:
            raise ValueError(f"{self.path}: no trajectories to finalize")
        dts = [float(self._file[k].attrs["frame_dt"]) for k in keys]
        if not np.allclose(dts, dts[0], rtol=1e-6, atol=0):
            raise ValueError(f"{self.path}: trajectories have different frame_dt {sorted(set(dts))}")
        all_bounds = np.stack([np.asarray(self._file[k].attrs["bounds"]) for k in keys])
        bounds = np.stack([all_bounds[:, :, 0].min(axis=0), all_bounds[:, :, 1].max(axis=0)], 1)
        stats = compute_statistics(self._file[k]["position"][()] for k in keys)
        meta = {
            "bounds": bounds.tolist(),
            "dim": 2,
            "dt": dts[0],
            "default_connectivity_radius": float(connectivity_radius),
            **stats,
            "sequence_length": [int(self._file[k]["position"].shape[0]) for k in keys],
            "n_trajectories": len(keys),
            "n_particles": [int(self._file[k]["position"].shape[1]) for k in keys],
            **self.metadata_extra,
        }
        metadata_path(self.path).write_text(json.dumps(meta, indent=2, default=str))
        return meta

    def close(self) -> None:
        """Flush and close the file (idempotent)."""
        if self._file.id.valid:
            self._file.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


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


def _read_group(path: Path, key: str, grp: h5py.Group, meta: dict | None) -> Trajectory:
    where = f"{path}: group '{key}'"
    if "position" not in grp:
        raise ValueError(f"{where}: missing dataset 'position'")
    pos = grp["position"][()]
    if pos.ndim != 3 or pos.shape[-1] != 2:
        raise ValueError(f"{where}: 'position' must have shape (T, N, 2), got {pos.shape}")
    n = pos.shape[1]
    if "particle_type" not in grp:
        raise ValueError(f"{where}: missing dataset 'particle_type'")
    ptype = grp["particle_type"][()]
    if ptype.shape != (n,):
        raise ValueError(f"{where}: 'particle_type' must have shape ({n},), got {ptype.shape}")

    def attr(name: str, meta_name: str):
        if name in grp.attrs:
            return grp.attrs[name]
        if meta is not None and meta_name in meta:
            return meta[meta_name]
        raise ValueError(f"{where}: missing attribute '{name}' (and no '{meta_name}' in metadata)")

    frame_dt = float(attr("frame_dt", "dt"))
    bounds_arr = np.asarray(attr("bounds", "bounds"), dtype=float)
    if bounds_arr.shape != (2, 2):
        raise ValueError(f"{where}: 'bounds' must have shape (2, 2), got {bounds_arr.shape}")
    bounds = tuple(tuple(float(b) for b in row) for row in bounds_arr)

    if "velocity" in grp:
        vel = grp["velocity"][()]
        if vel.shape != pos.shape:
            raise ValueError(f"{where}: 'velocity' must have shape {pos.shape}, got {vel.shape}")
    else:
        vel = finite_difference_velocity(pos, frame_dt)
    if "material_property" in grp:
        mat = grp["material_property"][()]
        if mat.ndim == 0:
            mat = np.full((n,), mat)
        if mat.shape != (n,):
            raise ValueError(f"{where}: 'material_property' must have shape ({n},), got {mat.shape}")
    else:
        mat = np.zeros((n,), dtype=pos.dtype)
    return Trajectory(
        positions=jnp.asarray(pos), velocities=jnp.asarray(vel),
        particle_type=jnp.asarray(ptype, dtype=jnp.int32), material=jnp.asarray(mat),
        frame_dt=frame_dt, bounds=bounds,
    )


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


def _unpack_gns_entry(name: str, entry) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    if isinstance(entry, np.ndarray) and entry.dtype == object:
        entry = list(entry.reshape(-1)) if entry.ndim else entry.item()
    if not isinstance(entry, (tuple, list)) or len(entry) not in (2, 3):
        raise ValueError(
            f"npz entry '{name}': expected a tuple (positions, particle_type[, material_property])"
        )
    pos, ptype = np.asarray(entry[0]), np.asarray(entry[1])
    mat = np.asarray(entry[2]) if len(entry) == 3 else None
    if pos.ndim != 3:
        raise ValueError(f"npz entry '{name}': positions must be (T, N, d), got shape {pos.shape}")
    if pos.shape[-1] != 2:
        raise ValueError(f"npz entry '{name}': positions must be 2-D (d=2), got d={pos.shape[-1]}")
    n = pos.shape[1]
    if ptype.shape != (n,):
        raise ValueError(f"npz entry '{name}': particle_type must be ({n},), got {ptype.shape}")
    if mat is not None:
        if mat.ndim == 0:
            mat = np.full((n,), mat)
        if mat.shape != (n,):
            raise ValueError(
                f"npz entry '{name}': material_property must be scalar or ({n},), got {mat.shape}"
            )
    return pos, ptype, mat


def load_gns_npz(
    path_npz: str | Path, metadata_json: str | Path | None = None
) -> tuple[list[Trajectory], dict]:
    """Load a PyTorch-GNS ``.npz`` dataset.

    Args:
        path_npz: ``.npz`` whose entries are each ``(positions (T, N, 2) m, particle_type (N,)
            [, material_property (N,) or scalar])``.
        metadata_json: metadata file; defaults to ``metadata.json`` next to ``path_npz``. Needs
            ``bounds`` [[xmin, xmax], [ymin, ymax]]; ``dt`` (frame dt, s) falls back to the
            :class:`Trajectory` default with a warning.

    Returns:
        (trajectories, metadata). Velocities (m/s) are finite differences of the positions
        divided by dt (frame 0 gets the forward difference); a missing material is zeros.
    """
    path_npz = Path(path_npz)
    meta_path = Path(metadata_json) if metadata_json else path_npz.with_name("metadata.json")
    if not meta_path.exists():
        raise FileNotFoundError(f"metadata file {meta_path} for {path_npz} does not exist")
    meta = json.loads(meta_path.read_text())
    if "bounds" not in meta:
        raise ValueError(f"{meta_path}: missing key 'bounds'")
    bounds_arr = np.asarray(meta["bounds"], dtype=float)
    if bounds_arr.shape != (2, 2):
        raise ValueError(f"{meta_path}: 'bounds' must be [[xmin, xmax], [ymin, ymax]]")
    bounds = tuple(tuple(float(b) for b in row) for row in bounds_arr)
    if "dt" in meta:
        dt = float(meta["dt"])
    else:
        dt = Trajectory.__dataclass_fields__["frame_dt"].default
        warnings.warn(f"{meta_path}: no 'dt', using the default frame dt {dt} s", stacklevel=2)

    trajs = []
    with np.load(path_npz, allow_pickle=True) as data:
        if not data.files:
            raise ValueError(f"{path_npz}: no trajectories")
        for name in data.files:
            pos, ptype, mat = _unpack_gns_entry(name, data[name])
            if mat is None:
                mat = np.zeros((pos.shape[1],), dtype=pos.dtype)
            trajs.append(Trajectory(
                positions=jnp.asarray(pos),
                velocities=jnp.asarray(finite_difference_velocity(pos, dt)),
                particle_type=jnp.asarray(ptype, dtype=jnp.int32), material=jnp.asarray(mat),
                frame_dt=dt, bounds=bounds,
            ))
    return trajs, meta


def write_gns_npz(
    path: str | Path,
    trajectories: Sequence[Trajectory],
    write_metadata: bool = True,
    connectivity_radius: float | None = None,
) -> Path:
    """Write trajectories in the PyTorch-GNS ``.npz`` layout.

    Entries are ``simulation_trajectory_<i>`` object arrays ``(positions, particle_type,
    material_property)``. With ``write_metadata``, ``metadata.json`` in the same folder is
    (over)written with ``bounds``, ``dim``, ``dt``, ``sequence_length`` (frames of the first
    trajectory), the frame-unit statistics of :func:`compute_statistics` and, if given,
    ``default_connectivity_radius``. Returns the ``.npz`` path.
    """
    path = Path(path)
    if not trajectories:
        raise ValueError("write_gns_npz needs at least one trajectory")
    path.parent.mkdir(parents=True, exist_ok=True)
    entries = {}
    for i, traj in enumerate(trajectories):
        _check_trajectory(traj)
        entry = np.empty(3, dtype=object)
        entry[:] = [np.asarray(traj.positions), np.asarray(traj.particle_type),
                    np.asarray(traj.material)]
        entries[f"simulation_trajectory_{i}"] = entry
    with open(path, "wb") as fh:  # an open handle keeps np.savez from appending ".npz"
        np.savez(fh, **entries)
    if write_metadata:
        first = trajectories[0]
        meta = {
            "bounds": [list(b) for b in first.bounds],
            "dim": 2,
            "dt": float(first.frame_dt),
            "sequence_length": int(first.n_frames),
            **compute_statistics(np.asarray(t.positions) for t in trajectories),
        }
        if connectivity_radius is not None:
            meta["default_connectivity_radius"] = float(connectivity_radius)
        path.with_name("metadata.json").write_text(json.dumps(meta, indent=2))
    return path
