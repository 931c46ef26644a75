"""Cylinder-flow datasets on disk (HDF5 + ``<stem>.metadata.json``).

Meshes differ between trajectories, so each trajectory is its own group ``"00000"``,
``"00001"``, ... holding

=================  ============  =========  ===============================================
dataset            shape         dtype      meaning
=================  ============  =========  ===============================================
``mesh_pos``       (N, 2)        float64    vertex coordinates, m
``cells``          (n_cells, 3)  int32      triangles (vertex indices, counter-clockwise)
``node_type``      (N,)          int32      FLUID 0, WALL 1, INFLOW 2, OUTFLOW 3
                                            (:mod:`diffgns.mesh.geometry`)
``on_cylinder``    (N,)          bool       wall nodes on the cylinder surface
``velocity``       (T, N, 2)     float32    velocity at the vertices, m/s
``pressure``       (T, N)        float32    kinematic pressure p/rho, m^2/s^2
``time``           (T,)          float64    simulated time of each frame, s
``cd``, ``cl``     (T,)          float64    drag and lift coefficients at the frames
=================  ============  =========  ===============================================

N vertices, T frames (as in :mod:`diffgns.io.dataset`), ``n_cells`` triangles.

with group attributes for the physics and cost (``reynolds``, ``u_max``, ``nu``, ``center``,
``radius``, ``length``, ``height``, ``frame_dt``, ``dt``, ``cfd_wall_per_sim_second``, ...).
As in :mod:`diffgns.io.dataset`, each group is written under a temporary name and moved into
place, so an interrupted run leaves only complete trajectories and resumes by skipping them.
"""
from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np

from diffgns.io.dataset import _TMP_PREFIX, H5TrajectoryFile, metadata_path
from diffgns.io.files import write_text_atomic
from diffgns.mesh.geometry import FLUID, INFLOW, NODE_TYPE_NAMES, OUTFLOW, WALL

_ARRAYS = ("mesh_pos", "cells", "node_type", "on_cylinder", "velocity", "pressure", "time",
           "cd", "cl")


class CylinderDatasetWriter(H5TrajectoryFile):
    """Append-mode writer of cylinder-flow trajectories; see the module docstring (resume and
    atomic writes come from :class:`diffgns.io.dataset.H5TrajectoryFile`)."""

    def write(self, key: str, arrays: dict, attrs: dict) -> None:
        """Store one trajectory; ``arrays`` holds the datasets of the module docstring."""
        missing = [k for k in _ARRAYS if k not in arrays]
        if missing:
            raise ValueError(f"cylinder trajectory {key!r}: missing arrays {missing}")
        n = len(arrays["mesh_pos"])
        f = len(arrays["time"])
        want = dict(mesh_pos=(n, 2), node_type=(n,), on_cylinder=(n,), velocity=(f, n, 2),
                    pressure=(f, n), cd=(f,), cl=(f,))
        for name, shape in want.items():
            if np.shape(arrays[name]) != shape:
                raise ValueError(f"cylinder trajectory {key!r}: '{name}' has shape "
                                 f"{np.shape(arrays[name])}, expected {shape}")
        dtypes = dict(mesh_pos=np.float64, cells=np.int32, node_type=np.int32, on_cylinder=bool,
                      velocity=np.float32, pressure=np.float32, time=np.float64,
                      cd=np.float64, cl=np.float64)
        self._store(key, {name: np.asarray(arrays[name], dtype=dt)
                          for name, dt in dtypes.items()}, attrs)

    def finalize(self) -> dict:
        """Write ``<stem>.metadata.json``: frame dt, sizes, per-trajectory parameters and
        normalisation statistics over all trajectories and frames:

        * ``velocity_mean``/``velocity_std`` (m/s, per component, all nodes);
        * ``velocity_change_mean``/``velocity_change_std`` (m/s per frame, FLUID and OUTFLOW
          nodes: the MeshGraphNet target);
        * ``pressure_mean``/``pressure_std`` (m^2/s^2, all nodes).
        """
        keys = self.keys()
        if not keys:
            raise ValueError(f"{self.path}: no trajectories to finalize")
        acc = {k: [0, 0.0, 0.0] for k in ("u", "du", "p")}

        def add(name, x):
            x = np.asarray(x, np.float64).reshape(-1, x.shape[-1] if x.ndim > 1 else 1)
            c, s, s2 = acc[name]
            acc[name] = [c + len(x), s + x.sum(0), s2 + (x**2).sum(0)]

        per, dts = [], []
        for k in keys:
            g = self._file[k]
            u, p, nt = g["velocity"][()], g["pressure"][()], g["node_type"][()]
            add("u", u)
            add("p", p[..., None])
            add("du", np.diff(u, axis=0)[:, (nt == FLUID) | (nt == OUTFLOW)])
            dts.append(float(g.attrs["frame_dt"]))
            per.append(dict(key=k, n_nodes=int(u.shape[1]), n_frames=int(u.shape[0]),
                            **{a: _json_attr(g.attrs[a]) for a in g.attrs}))
        if not np.allclose(dts, dts[0], rtol=1e-9):
            raise ValueError(f"{self.path}: trajectories differ in frame_dt {sorted(set(dts))}")

        def stats(name):
            c, s, s2 = acc[name]
            mean = s / c
            return mean.tolist(), np.sqrt(np.maximum(s2 / c - mean**2, 0.0)).tolist()

        (um, us), (dm, ds), (pm, ps) = stats("u"), stats("du"), stats("p")
        meta = dict(kind="cylinder", dt=dts[0], dim=2, n_trajectories=len(keys),
                    node_types={name: code for code, name in NODE_TYPE_NAMES.items()},
                    velocity_mean=um, velocity_std=us, velocity_change_mean=dm,
                    velocity_change_std=ds, pressure_mean=pm[0], pressure_std=ps[0],
                    sequence_length=[t["n_frames"] for t in per],
                    n_nodes=[t["n_nodes"] for t in per], trajectories=per,
                    **self.metadata_extra)
        write_text_atomic(metadata_path(self.final_path),
                          json.dumps(meta, indent=2, default=str) + "\n")
        return meta

def _json_attr(v):
    if isinstance(v, bytes):
        v = v.decode()
    if isinstance(v, str):
        try:
            return json.loads(v)
        except ValueError:
            return v
    return v.tolist() if isinstance(v, np.ndarray) else v.item() if hasattr(v, "item") else v


def iter_cylinder_dataset(path: str | Path) -> Iterator[tuple[str, dict, dict]]:
    """Yield ``(key, arrays, attrs)`` per trajectory of a cylinder dataset, in key order.

    Raises:
        ValueError: a group misses one of the datasets of the module docstring or has
            node types outside FLUID/WALL/INFLOW/OUTFLOW.
    """
    with h5py.File(path, "r") as f:
        for key in sorted(k for k in f if not k.startswith(_TMP_PREFIX)):
            g = f[key]
            missing = [a for a in _ARRAYS if a not in g]
            if missing:
                raise ValueError(f"{path}: group '{key}' misses datasets {missing}")
            arrays = {a: g[a][()] for a in _ARRAYS}
            if not np.isin(arrays["node_type"], [FLUID, WALL, INFLOW, OUTFLOW]).all():
                raise ValueError(f"{path}: group '{key}' has unknown node types")
            yield key, arrays, {a: _json_attr(g.attrs[a]) for a in g.attrs}
