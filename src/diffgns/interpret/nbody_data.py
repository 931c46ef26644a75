"""n-body datasets on disk and as edge samples.

Trajectories are stored with the project's HDF5 layout (:class:`diffgns.io.dataset.DatasetWriter`):
``position``/``velocity`` (T, N, 2), with per-trajectory attributes ``mass`` (N,) kg and
``radius`` (N,) m, and the system's :class:`NBodyConfig` in the metadata (``nbody``).

:func:`edge_samples` turns frames into what the message network and the symbolic regression
see: for every ordered pair (receiver i, sender j), edge features

    [dx, dy, d, dvx, dvy, m_i, m_j, r_i, r_j]      (units m, m, m, m/s, m/s, kg, kg, m, m)

with ``dx = x_j - x_i`` (minimum image when periodic) and ``dv = v_j - v_i``, the true pair
force ``F_ij`` (N) and the receivers' true accelerations (m/s^2).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from diffgns.interpret.nbody import (
    NBodyConfig,
    initial_state,
    pair_forces,
    pair_geometry,
    rollout,
)
from diffgns.io.dataset import DatasetWriter, read_metadata
from diffgns.trajectory import Trajectory

EDGE_FEATURES = ("dx", "dy", "d", "dvx", "dvy", "m_i", "m_j", "r_i", "r_j")
EDGE_UNITS = {"dx": "m", "dy": "m", "d": "m", "dvx": "m/s", "dvy": "m/s", "m_i": "kg",
              "m_j": "kg", "r_i": "m", "r_j": "m"}


def generate(path: str | Path, cfg: NBodyConfig, n_trajectories: int, n_frames: int,
             seed: int = 0, progress: bool = True) -> Path:
    """Simulate ``n_trajectories`` systems and write them to ``path`` (HDF5 + metadata).

    Resumes: trajectories already in the file are kept and generation continues from the
    next index (the initial state of trajectory t depends only on (seed, t)). Inverse-square
    trajectories where two bodies come closer than ``cfg.min_distance`` are re-drawn.
    """
    cfg.check_stable()
    run = jax.jit(lambda x, v, m, r: rollout(cfg, x, v, m, r, n_frames))
    bounds = ((0.0, cfg.box), (0.0, cfg.box))
    with DatasetWriter(path, {"nbody": dataclasses.asdict(cfg)}) as writer:
        start = len(writer)
        for t in tqdm(range(start, n_trajectories), desc=f"n-body {cfg.law}",
                      disable=not progress, initial=start, total=n_trajectories):
            for attempt in range(100):
                rng = np.random.default_rng([seed, t, attempt])
                x0, v0, mass, radius = initial_state(cfg, rng)
                xs, vs = (np.asarray(a) for a in run(x0, v0, mass, radius))
                if not np.all(np.isfinite(xs)):
                    continue
                if cfg.law == "inverse_square":
                    diff = xs[:, :, None] - xs[:, None]
                    if cfg.periodic:
                        diff -= cfg.box * np.round(diff / cfg.box)
                    d = np.linalg.norm(diff, axis=-1) + np.eye(cfg.n_bodies) * 1e9
                    if d.min() < cfg.min_distance:
                        continue
                    if not cfg.periodic:
                        lo, hi = xs.min(axis=(0, 1)), xs.max(axis=(0, 1))
                        bounds = ((float(lo[0]), float(hi[0])), (float(lo[1]), float(hi[1])))
                break
            else:
                raise RuntimeError(f"trajectory {t}: no valid draw in 100 attempts; "
                                   "lower speed or G, or raise min_distance")
            traj = Trajectory(positions=xs, velocities=vs,
                              particle_type=np.zeros(cfg.n_bodies, np.int32),
                              material=np.zeros(cfg.n_bodies), frame_dt=cfg.frame_dt,
                              bounds=bounds)
            writer.write(f"{t:05d}", traj, attrs=dict(mass=mass, radius=radius,
                                                       attempt=attempt))
        writer.finalize(connectivity_radius=cfg.box)
    return Path(path)


def load(path: str | Path):
    """Read an n-body dataset: (cfg, list of dicts with position, velocity, mass, radius)."""
    import h5py

    meta = read_metadata(path)
    if "nbody" not in meta:
        raise ValueError(f"{path}: not an n-body dataset (no 'nbody' entry in its metadata)")
    nb = dict(meta["nbody"])
    for key in ("mass_range", "radius_range"):
        nb[key] = tuple(nb[key])
    cfg = NBodyConfig(**nb)
    trajs = []
    with h5py.File(path, "r") as f:
        for key in sorted(k for k in f if k.isdigit()):
            g = f[key]
            trajs.append(dict(position=g["position"][()].astype(np.float64),
                              velocity=g["velocity"][()].astype(np.float64),
                              mass=np.asarray(g.attrs["mass"], np.float64),
                              radius=np.asarray(g.attrs["radius"], np.float64)))
    return cfg, trajs


def _frame_edges(cfg: NBodyConfig):
    """jit-able (x, v, mass, radius) -> (features (E, 9), force (E, 2), recv (E,), acc (N, 2))."""
    n = cfg.n_bodies
    recv, send = np.nonzero(~np.eye(n, dtype=bool))

    def fn(x, v, mass, radius):
        dx, d = pair_geometry(cfg, x)
        forces = pair_forces(cfg, x, v, mass, radius)
        dv = v[None, :, :] - v[:, None, :]
        feats = jnp.concatenate([
            dx[recv, send], d[recv, send][:, None], dv[recv, send],
            mass[recv][:, None], mass[send][:, None],
            radius[recv][:, None], radius[send][:, None]], axis=-1)
        acc = forces.sum(axis=1) / mass[:, None]
        return feats, forces[recv, send], acc

    return fn, recv, send


def edge_samples(cfg: NBodyConfig, trajs: list[dict], frame_step: int = 1) -> dict:
    """Graphs of every ``frame_step``-th frame of every trajectory.

    Returns a dict of numpy arrays: ``edges`` (G, E, 9) features (see :data:`EDGE_FEATURES`),
    ``force`` (G, E, 2) true pair forces in N, ``acc`` (G, N, 2) true accelerations in m/s^2,
    ``node`` (G, N, 2) node features [mass, radius], and the static ``receivers`` and
    ``senders`` (E,) index arrays (E = N (N - 1), all ordered pairs).
    """
    fn, recv, send = _frame_edges(cfg)
    batched = jax.jit(jax.vmap(fn, (0, 0, None, None)))
    feats, forces, accs, nodes = [], [], [], []
    for tr in trajs:
        x, v = tr["position"][::frame_step], tr["velocity"][::frame_step]
        f, F, a = (np.asarray(o) for o in batched(x, v, tr["mass"], tr["radius"]))
        feats.append(f)
        forces.append(F)
        accs.append(a)
        nodes.append(np.broadcast_to(np.stack([tr["mass"], tr["radius"]], -1),
                                     (len(x), cfg.n_bodies, 2)))
    return dict(edges=np.concatenate(feats), force=np.concatenate(forces),
                acc=np.concatenate(accs), node=np.concatenate(nodes),
                receivers=recv.astype(np.int32), senders=send.astype(np.int32))


def describe(path: str | Path) -> str:
    """One-line summary of a dataset (for logs)."""
    meta = read_metadata(path)
    return json.dumps(dict(n_trajectories=meta["n_trajectories"], law=meta["nbody"]["law"],
                           frames=meta["sequence_length"][0]))
