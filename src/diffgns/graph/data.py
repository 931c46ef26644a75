"""Training data for the GNS: windows of trajectories, frame stride, coarse-graining.

A training sample is a window of ``history + 2`` consecutive (strided) frames of one
trajectory: ``history + 1`` input positions and the next position as target. Trajectories
with the same number of nodes form a group; a batch holds windows of one group, so every
jitted training step sees one of a few static shapes.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diffgns.graph.geometry import obstacle_array, walls_array
from diffgns.io.dataset import compute_statistics, iter_dataset, read_metadata
from diffgns.io.npz import load_gns_npz
from diffgns.trajectory import KINEMATIC, Trajectory


def coarse_grain_map(x0: np.ndarray, factor: int) -> np.ndarray:
    """Cluster index (N,) of each particle: particles are binned on a square (2D) or cubic
    (3D) lattice whose cells hold ~``factor`` particles of the initial configuration ``x0``
    (N, d): the cell side is the particles' nearest-neighbour spacing times ``factor^(1/d)``
    (2D: 16 particles of a 4 x 4 arrangement per node; 3D: 8 of a 2 x 2 x 2 one). Clusters
    are numbered in lexicographic order of their cells. factor = 1 keeps every particle."""
    if factor == 1:
        return np.arange(len(x0))
    x0 = np.asarray(x0)
    dim = x0.shape[-1]
    if x0.ndim != 2 or dim not in (2, 3):
        raise ValueError(f"coarse_grain_map: positions must be (N, 2) or (N, 3), got "
                         f"{x0.shape}")
    probe = np.random.default_rng(0).choice(len(x0), min(len(x0), 256), replace=False)
    d2 = ((x0[probe, None] - x0[None]) ** 2).sum(-1)
    d2[np.arange(len(probe)), probe] = np.inf
    d = np.sqrt(d2.min(1))  # nearest-neighbour spacing of a sample of particles
    spacing = float(np.median(d)) * (np.sqrt(factor) if dim == 2 else np.cbrt(factor))
    cell = np.floor((x0 - x0.min(0)) / spacing + 1e-6).astype(np.int64)
    key = cell[:, 0]
    for k in range(1, dim):  # lexicographic key of the cell (< 1,000,003 cells per axis)
        key = key * 1_000_003 + cell[:, k]
    _, idx = np.unique(key, return_inverse=True)
    return idx.reshape(-1)


def cluster_means(a: np.ndarray, cid: np.ndarray) -> np.ndarray:
    """Means over the clusters ``cid`` (N,) (:func:`coarse_grain_map`) of ``a`` (..., N, k):
    shape (..., cid.max() + 1, k) (float64: the sums divided by the integer counts)."""
    n = int(cid.max()) + 1
    out = np.zeros((*a.shape[:-2], n, a.shape[-1]), a.dtype)
    np.add.at(out, (..., cid, slice(None)), a)
    return out / np.bincount(cid, minlength=n)[:, None]


def coarse_grain(traj: Trajectory, factor: int, frame_stride: int = 1,
                 cid: np.ndarray | None = None) -> Trajectory:
    """Nodes = cluster means of ``factor`` particles (:func:`coarse_grain_map`, 2D or 3D);
    frames every ``frame_stride``-th. ``cid`` (N,) gives the clusters instead (e.g. another
    run's map of the same particles, whose frame 0 would bin differently)."""
    pos = np.asarray(traj.positions)[::frame_stride]
    vel = np.asarray(traj.velocities)[::frame_stride]
    ptype = np.asarray(traj.particle_type)
    mat = np.asarray(traj.material)
    if cid is not None and len(cid) != pos.shape[1]:
        raise ValueError(f"coarse_grain: {len(cid)} cluster indices for {pos.shape[1]} "
                         f"particles")
    if factor > 1 or cid is not None:
        cid = coarse_grain_map(pos[0], factor) if cid is None else np.asarray(cid)
        n = cid.max() + 1
        pos, vel = cluster_means(pos, cid), cluster_means(vel, cid)
        first = np.zeros(n, np.int64)
        first[cid[::-1]] = np.arange(len(cid))[::-1]
        ptype, mat = ptype[first], mat[first]
    return Trajectory(positions=pos, velocities=vel, particle_type=ptype, material=mat,
                      frame_dt=traj.frame_dt * frame_stride, bounds=traj.bounds,
                      obstacles=traj.obstacles)


def load_trajectories(path: str | Path, factor: int = 1, frame_stride: int = 1
                      ) -> tuple[list[Trajectory], dict]:
    """Trajectories and metadata from an HDF5 dataset or a PyTorch-GNS ``.npz``."""
    path = Path(path)
    if path.suffix == ".npz":
        trajs, meta = load_gns_npz(path)
    else:
        trajs, meta = list(iter_dataset(path)), read_metadata(path)
    trajs = [coarse_grain(t, factor, frame_stride) for t in trajs]
    return trajs, meta


def check_one_dimension(trajs, what: str = "the trajectories") -> int:
    """The spatial dimension (2 or 3) shared by ``trajs`` (positions (T, N, d)); ValueError
    naming the counts when they mix dimensions (one GNS is for one d)."""
    dims: dict[int, int] = {}
    for t in trajs:
        d = int(np.shape(t.positions)[-1])
        dims[d] = dims.get(d, 0) + 1
    if len(dims) != 1:
        got = ", ".join(f"{n} {d}D" for d, n in sorted(dims.items())) or "none"
        raise ValueError(f"{what} mix dimensions ({got}); a GNS is trained on one: give only "
                         "2D or only 3D datasets")
    return next(iter(dims))


def frame_statistics(trajs: list[Trajectory]) -> dict:
    """Velocity and acceleration mean/std in frame units over ``trajs`` (after striding and
    coarse-graining, so they match what the GNS sees); see :func:`compute_statistics`."""
    return compute_statistics(np.asarray(t.positions) for t in trajs)


def mirror_window(positions: np.ndarray, bounds, obstacles=()) -> tuple[np.ndarray, list]:
    """Reflect a window and its box obstacles about the box's vertical mid-plane.

    Args:
        positions: (L, N, d) positions, m (padding nodes parked outside the box stay
            outside it).
        bounds: ``((xmin, xmax), ...)`` of the box, m.
        obstacles: box obstacles ``[lo..., hi...]`` (2d numbers each), m.
    Returns:
        positions with x -> xmin + xmax - x, and the obstacles as a list of reflected boxes
        (x extents swapped so that lo < hi still holds).
    """
    s = float(bounds[0][0]) + float(bounds[0][1])
    x = np.array(positions, copy=True)
    x[..., 0] = s - x[..., 0]
    obs = np.asarray(obstacles, float)
    if obs.size == 0:
        return x, []
    d = obs.shape[-1] // 2
    obs = obs.reshape(-1, 2 * d).copy()
    obs[:, 0], obs[:, d] = s - obs[:, d], s - obs[:, 0]
    return x, obs.tolist()


def window_activity(positions: np.ndarray, particle_type: np.ndarray, history: int,
                    length: int) -> np.ndarray:
    """How much each window's targets differ from one motion shared by all its nodes.

    The activity of frame t is the RMS over the non-kinematic nodes of the deviation of their
    acceleration (second difference of positions) from the frame's mean acceleration: zero
    in free flight and at rest (every node accelerates alike), large where contacts act
    (an impact, a release, a flow); a window's activity is the largest over its target
    frames ``start + history .. start + length - 2``.

    Args:
        positions: (T, N, d) positions of one trajectory, m.
        particle_type: (N,) types; KINEMATIC nodes are left out.
        history: velocities in the input (C); length: frames per window (C + 2 + unroll).
    Returns:
        (T - length + 1,) activity of each window start, m per frame^2.
    """
    x = np.asarray(positions, np.float64)[:, np.asarray(particle_type) != KINEMATIC]
    a = x[2:] - 2.0 * x[1:-1] + x[:-2]  # (T - 2, N, d): acceleration of frames 1 .. T - 2
    if a.shape[1] == 0:  # only kinematic nodes: nothing moves of itself
        act = np.zeros(len(a))
    else:
        act = np.sqrt(((a - a.mean(1, keepdims=True)) ** 2).sum(-1).mean(1))
    n_starts = len(x) - length + 1
    targets = length - history - 1  # target frames per window: 1 + unroll
    # frame f's activity is act[f - 1]; window s's targets are frames s + C .. s + C + unroll
    return np.stack([act[history - 1 + k: history - 1 + k + n_starts]
                     for k in range(targets)]).max(0)


@dataclass
class WindowSampler:
    """Random windows of ``history + 2 + unroll`` frames, one node-count group per batch,
    each with the walls and box obstacles of its trajectory (``Trajectory.bounds``,
    ``Trajectory.obstacles``), the obstacles padded to the most any trajectory has
    (:func:`diffgns.graph.geometry.parked`). The trajectories must share one dimension
    (2D or 3D).

    ``early_frames``, ``early_weight``: the windows starting in a trajectory's first
    ``early_frames`` (strided) frames are drawn ``early_weight`` times as often as the others
    (a flow's release from rest is a few windows of ~100 per trajectory); 0 and 1 draw
    starts uniformly (and exactly as before these options existed).

    ``mirror``: probability that a window is reflected about its box's vertical mid-plane
    (:func:`mirror_window`: x -> xmin + xmax - x, obstacles too). Gravity is vertical and
    the walls' friction the same on both sides, so a reflected window is the MPM's flow of
    the reflected scene; a model trained on columns against the left wall alone fails on
    their mirror images (`gns_cg16_pfn` on the granular validation columns: 1-2% position
    error against the left wall, 92-143% against the right). 0 draws no random number
    (windows exactly as before the option existed).

    ``active_weight``: a window start is drawn with probability proportional to ``1 +
    active_weight * A / mean(A)`` within its trajectory, A its :func:`window_activity` and
    the mean over every window of every trajectory: impacts and releases, a few frames of
    ~250 in a thrown mass's trajectory, are drawn more often than free flight and rest.
    Combined with the early windows by multiplication; 0 leaves the starts as they were."""

    trajs: list
    history: int = 5
    unroll: int = 0
    early_frames: int = 0
    early_weight: float = 1.0
    mirror: float = 0.0
    active_weight: float = 0.0

    def __post_init__(self):
        if not (isinstance(self.early_frames, int) and self.early_frames >= 0
                and np.isfinite(self.early_weight) and self.early_weight > 0):
            raise ValueError(f"early windows: early_frames = {self.early_frames!r} must be an "
                             f"integer >= 0 (frames) and early_weight = {self.early_weight!r} "
                             "a finite number > 0")
        if not 0.0 <= self.mirror <= 1.0:
            raise ValueError(f"mirror = {self.mirror!r} must be a probability in [0, 1]")
        if not (np.isfinite(self.active_weight) and self.active_weight >= 0):
            raise ValueError(f"active windows: active_weight = {self.active_weight!r} must be "
                             "a finite number >= 0")
        check_one_dimension(self.trajs, "the training trajectories")
        self.max_obstacles = max([len(getattr(t, "obstacles", ())) for t in self.trajs] + [0])
        self.groups: dict[int, list[int]] = {}
        for i, t in enumerate(self.trajs):
            self.groups.setdefault(t.n_particles, []).append(i)
        self.length = self.history + 2 + self.unroll
        for t in self.trajs:
            if t.n_frames < self.length:
                raise ValueError(f"a trajectory has {t.n_frames} frames, fewer than the window "
                                 f"{self.length}")
        sizes = np.array([sum(self.trajs[i].n_frames - self.length + 1 for i in g)
                          for g in self.groups.values()], float)
        self._p = sizes / sizes.sum()
        self._keys = list(self.groups)
        self._start_cdf = self.start_cdfs()

    def start_cdfs(self) -> list[np.ndarray] | None:
        """Per trajectory, the cumulative weights of its window starts (early windows times
        active windows), or None when every start is equally likely."""
        early = self.early_frames > 0 and self.early_weight != 1.0
        if not early and self.active_weight == 0:
            return None
        weights = []
        for t in self.trajs:
            w = np.ones(t.n_frames - self.length + 1)
            w[:self.early_frames] = self.early_weight
            weights.append(w)
        if self.active_weight:
            acts = [window_activity(t.positions, t.particle_type, self.history, self.length)
                    for t in self.trajs]
            scale = float(np.mean(np.concatenate(acts)))
            if scale > 0:
                weights = [w * (1.0 + self.active_weight * a / scale)
                           for w, a in zip(weights, acts)]
        return [np.cumsum(w) for w in weights]

    def sample(self, rng: np.random.Generator, batch: int,
               group_rng: np.random.Generator | None = None) -> dict:
        """A batch: positions (B, L, N, d), particle_type (B, N), material (B, N), walls
        (B, d, 2) m, obstacles (B, K, 2d) m. The node-count group is drawn from
        ``group_rng`` when given (several steps drawn with one such generator share a group,
        so they run in one device call), else from ``rng``."""
        n = self._keys[(group_rng or rng).choice(len(self._keys), p=self._p)]
        return self.windows(rng, self.groups[n], batch)

    def windows(self, rng: np.random.Generator, members: list[int], batch: int) -> dict:
        """``batch`` random windows of the trajectories ``members`` (one node count)."""
        pos, ptype, mat, walls, obs = [], [], [], [], []
        for _ in range(batch):
            i = members[rng.integers(len(members))]
            t = self.trajs[i]
            x, p, m = self.window(t, self.draw_start(rng, i))
            o = getattr(t, "obstacles", ())
            if self.mirror and rng.random() < self.mirror:
                x, o = mirror_window(x, t.bounds, o)
            pos.append(x)
            ptype.append(p)
            mat.append(m)
            walls.append(walls_array(t.bounds))
            obs.append(obstacle_array(o, self.max_obstacles, len(t.bounds)))
        dtype = pos[0].dtype
        return dict(positions=np.stack(pos), particle_type=np.stack(ptype),
                    material=np.stack(mat), walls=np.stack(walls).astype(dtype),
                    obstacles=np.stack(obs).astype(dtype))

    def draw_start(self, rng: np.random.Generator, i: int) -> int:
        """A window start of trajectory ``i``: uniform, or weighted by :meth:`start_cdfs`
        (early and active windows)."""
        n_starts = self.trajs[i].n_frames - self.length + 1
        if self._start_cdf is None:
            return int(rng.integers(0, n_starts))
        cdf = self._start_cdf[i]
        return min(int(np.searchsorted(cdf, rng.random() * cdf[-1], side="right")),
                   n_starts - 1)

    def window(self, t: Trajectory, start: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The window of ``t`` from frame ``start``: positions (L, N, d), particle_type
        (N,), material (N,)."""
        return (np.asarray(t.positions[start:start + self.length]),
                np.asarray(t.particle_type), np.asarray(t.material))
