"""Per-family sampling of training windows (issue 21): a general GNS trains on several scene
families (:mod:`diffgns.scene.families`) whose trajectories differ in number and length; drawn
in proportion to their windows, a family with many long trajectories would crowd out the
others. :class:`FamilyWindowSampler` draws the family of each batch with the given weights,
then a node-count group of that family in proportion to its windows, then windows, as
:class:`~diffgns.graph.data.WindowSampler` does.

Random scenes have many node counts (~100 in 200 trajectories of the granular data), and
every count is one more compilation of the training step. With ``pad_to = k`` the sampler
groups trajectories by their node count rounded up to a multiple of ``k`` and pads each
window with :func:`pad_nodes`: kinematic nodes (type 3: masked from the loss, no training
noise) parked in a row ``2 R`` below the floor (2D and 3D), ``1.5 R`` apart, so they have no
edge to any particle in the box nor to each other, and the loss and every real node's prediction are
those of the unpadded window.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from diffgns.graph.data import WindowSampler
from diffgns.trajectory import KINEMATIC

__all__ = ["FamilyWindowSampler", "pad_nodes"]


def pad_nodes(positions: np.ndarray, particle_type: np.ndarray, material: np.ndarray,
              n_total: int, bounds, radius: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pad one window to ``n_total`` nodes with parked kinematic nodes.

    Args:
        positions: (L, N, d) window, m; particle_type, material: (N,).
        n_total: node count after padding (>= N).
        bounds: ``((xmin, xmax), (ymin, ymax)(, (zmin, zmax)))`` of the box the real nodes
            are in, m.
        radius: connectivity radius R, m.

    Returns:
        positions (L, n_total, d) with the padding nodes at ``(xmin + 1.5 R k, ymin - 2 R)``
        (3D: ``(xmin + 1.5 R k, ymin - 2 R, zmin)``) in every frame, particle_type
        (n_total,) with KINEMATIC padding, material (n_total,) with 0 padding. The parked row
        lies outside the box: fine for the all-pairs neighbour list (up to 1,024 nodes,
        every model here); a cell list sized from the box would need the box widened.
    """
    n = positions.shape[1]
    p = n_total - n
    if p < 0:
        raise ValueError(f"pad_nodes: n_total = {n_total} is below the window's {n} nodes")
    lower = [float(lo) for lo, _ in bounds]
    if len(lower) != positions.shape[-1]:
        raise ValueError(f"pad_nodes: bounds {bounds!r} do not match {positions.shape[-1]}D "
                         "positions")
    park = np.stack([lower[0] + 1.5 * radius * np.arange(p),
                     np.full(p, lower[1] - 2.0 * radius),
                     *(np.full(p, lo) for lo in lower[2:])], -1)
    park = np.broadcast_to(park.astype(positions.dtype), (positions.shape[0], p, len(lower)))
    return (np.concatenate([positions, park], 1),
            np.concatenate([particle_type, np.full(p, KINEMATIC, particle_type.dtype)]),
            np.concatenate([material, np.zeros(p, material.dtype)]))


@dataclass
class FamilyWindowSampler(WindowSampler):
    """:class:`~diffgns.graph.data.WindowSampler` with a family per trajectory.

    Attributes:
        families: (len(trajs),) family name of each trajectory (e.g. from
            :func:`diffgns.io.families_data.read_families`).
        weights: family -> weight >= 0 (normalised here); default: equal weights for the
            families present. A family without trajectories or a weight for a family not
            present raises ValueError naming it.
        pad_to: group node counts rounded up to a multiple of this and pad the windows
            (:func:`pad_nodes`); 1 = no padding.
        bounds, radius: the box (m) and connectivity radius (m) of :func:`pad_nodes`
            (needed when ``pad_to > 1``).
    """

    families: list[str] = field(default_factory=list)
    weights: dict[str, float] | None = None
    pad_to: int = 1
    bounds: tuple | None = None
    radius: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        if not (isinstance(self.pad_to, int) and self.pad_to >= 1):
            raise ValueError(f"FamilyWindowSampler.pad_to = {self.pad_to!r} must be an "
                             "integer >= 1 (nodes)")
        if self.pad_to > 1 and (self.bounds is None or not self.radius > 0):
            raise ValueError("FamilyWindowSampler.pad_to > 1 needs bounds (the box, m) and "
                             "radius > 0 (m) to park the padding nodes")
        if len(self.families) != len(self.trajs):
            raise ValueError(f"FamilyWindowSampler.families has {len(self.families)} names for "
                             f"{len(self.trajs)} trajectories; give one family per trajectory")
        present = list(dict.fromkeys(self.families))
        weights = dict.fromkeys(present, 1.0) if self.weights is None else dict(self.weights)
        unknown = sorted(set(weights) - set(present))
        bad = [f for f, w in weights.items() if not (np.isfinite(w) and w >= 0)]
        if unknown or bad or not sum(weights.values()) > 0:
            raise ValueError(f"FamilyWindowSampler.weights {weights}: families {unknown} have "
                             f"no trajectory, weights of {bad} are not finite numbers >= 0, or "
                             f"all are 0; weigh families among {present}")
        self._families = [f for f in present if weights.get(f, 0.0) > 0]
        w = np.array([weights[f] for f in self._families], float)
        self._family_p = w / w.sum()
        self._family_groups: dict[str, tuple[list[list[int]], np.ndarray]] = {}
        for f in self._families:
            groups: dict[int, list[int]] = {}
            for i, (t, g) in enumerate(zip(self.trajs, self.families)):
                if g == f:
                    groups.setdefault(self.padded(t.n_particles), []).append(i)
            members = list(groups.values())
            sizes = np.array([sum(self.trajs[i].n_frames - self.length + 1 for i in m)
                              for m in members], float)
            self._family_groups[f] = (members, sizes / sizes.sum())

    def padded(self, n: int) -> int:
        """Node count after padding: ``n`` rounded up to a multiple of ``pad_to``."""
        return -(-n // self.pad_to) * self.pad_to

    def window(self, t, start: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As :meth:`WindowSampler.window`, padded to :meth:`padded` nodes."""
        x, p, m = super().window(t, start)
        if self.pad_to == 1:
            return x, p, m
        return pad_nodes(x, p, m, self.padded(t.n_particles), self.bounds, self.radius)

    def family_probabilities(self) -> dict[str, float]:
        """Family -> probability that a batch is drawn from it."""
        return dict(zip(self._families, self._family_p.tolist()))

    def sample(self, rng: np.random.Generator, batch: int,
               group_rng: np.random.Generator | None = None) -> dict:
        """A batch of one family and one node count: positions (B, L, N, d), particle_type
        (B, N), material (B, N), walls, obstacles (see :meth:`WindowSampler.sample`; the
        family and node count come from ``group_rng`` when given)."""
        g = group_rng or rng
        f = self._families[g.choice(len(self._families), p=self._family_p)]
        members, p = self._family_groups[f]
        return self.windows(rng, members[g.choice(len(members), p=p)], batch)
