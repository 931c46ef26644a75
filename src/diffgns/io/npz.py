"""PyTorch-GNS ``.npz`` datasets: import (:func:`load_gns_npz`) and export (:func:`write_gns_npz`).

One entry per trajectory, a tuple ``(positions (T, N, 2) m, particle_type (N,)
[, material_property (N,) or scalar])``, with a ``metadata.json`` in the same folder
(``bounds``, ``dt`` and the frame-unit statistics of
:func:`diffgns.io.dataset.compute_statistics`). The HDF5 layout diffgns writes itself is
:mod:`diffgns.io.dataset`.
"""
from __future__ import annotations

import json
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from diffgns.io.dataset import (
    _as_bounds,
    _as_material,
    _check_trajectory,
    _make_trajectory,
    _require,
    compute_statistics,
    finite_difference_velocity,
    read_metadata,
)
from diffgns.trajectory import Trajectory

__all__ = ["load_gns_npz", "write_gns_npz"]


def _unpack_gns_entry(name: str, entry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    where = f"npz entry '{name}'"
    if isinstance(entry, np.ndarray) and entry.dtype == object:
        entry = list(entry.reshape(-1)) if entry.ndim else entry.item()
    _require(isinstance(entry, (tuple, list)) and len(entry) in (2, 3),
             f"{where}: expected a tuple (positions, particle_type[, material_property])")
    pos, ptype = np.asarray(entry[0]), np.asarray(entry[1])
    _require(pos.ndim == 3, f"{where}: positions must be (T, N, d), got shape {pos.shape}")
    _require(pos.shape[-1] == 2, f"{where}: positions must be 2-D (d=2), got d={pos.shape[-1]}")
    n = pos.shape[1]
    _require(ptype.shape == (n,), f"{where}: particle_type must be ({n},), got {ptype.shape}")
    mat = _as_material(entry[2], n, where) if len(entry) == 3 else np.zeros((n,), pos.dtype)
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
    meta = read_metadata(meta_path)
    _require("bounds" in meta, f"{meta_path}: missing key 'bounds'")
    bounds = _as_bounds(meta["bounds"], str(meta_path))
    if "dt" in meta:
        dt = float(meta["dt"])
    else:
        dt = Trajectory.__dataclass_fields__["frame_dt"].default
        warnings.warn(f"{meta_path}: no 'dt', using the default frame dt {dt} s", stacklevel=2)

    trajs = []
    with np.load(path_npz, allow_pickle=True) as data:
        _require(bool(data.files), f"{path_npz}: no trajectories")
        for name in data.files:
            pos, ptype, mat = _unpack_gns_entry(name, data[name])
            vel = finite_difference_velocity(pos, dt)
            trajs.append(_make_trajectory(pos, vel, ptype, mat, dt, bounds))
    return trajs, meta


def write_gns_npz(path: str | Path, trajectories: Sequence[Trajectory], write_metadata: bool = True,
                  connectivity_radius: float | None = None) -> Path:
    """Write trajectories in the PyTorch-GNS ``.npz`` layout.

    Entries are ``simulation_trajectory_<i>`` object arrays ``(positions, particle_type,
    material_property)``. With ``write_metadata``, ``metadata.json`` in the same folder is
    (over)written with ``bounds``, ``dim``, ``dt``, ``sequence_length`` (frames of the first
    trajectory), the frame-unit statistics of :func:`compute_statistics` and, if given,
    ``default_connectivity_radius``. Returns the ``.npz`` path.
    """
    path = Path(path)
    _require(len(trajectories) > 0, "write_gns_npz needs at least one trajectory")
    path.parent.mkdir(parents=True, exist_ok=True)
    entries: dict[str, Any] = {}
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
        meta = {"bounds": [list(b) for b in first.bounds], "dim": 2, "dt": float(first.frame_dt),
                "sequence_length": int(first.n_frames),
                **compute_statistics(np.asarray(t.positions) for t in trajectories)}
        if connectivity_radius is not None:
            meta["default_connectivity_radius"] = float(connectivity_radius)
        path.with_name("metadata.json").write_text(json.dumps(meta, indent=2))
    return path
