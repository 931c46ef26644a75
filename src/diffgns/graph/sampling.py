"""Per-family sampling of training windows (issue 21): a general GNS trains on several scene
families (:mod:`diffgns.scene.families`) whose trajectories differ in number and length; drawn
in proportion to their windows, a family with many long trajectories would crowd out the
others. :class:`FamilyWindowSampler` draws the family of each batch with the given weights,
then a node-count group of that family in proportion to its windows, then windows, as
:class:`~diffgns.graph.data.WindowSampler` does.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from diffgns.graph.data import WindowSampler

__all__ = ["FamilyWindowSampler"]


@dataclass
class FamilyWindowSampler(WindowSampler):
    """:class:`~diffgns.graph.data.WindowSampler` with a family per trajectory.

    Attributes:
        families: (len(trajs),) family name of each trajectory (e.g. from
            :func:`diffgns.io.families_data.read_families`).
        weights: family -> weight >= 0 (normalised here); default: equal weights for the
            families present. A family without trajectories or a weight for a family not
            present raises ValueError naming it.
    """

    families: list[str] = field(default_factory=list)
    weights: dict[str, float] | None = None

    def __post_init__(self):
        super().__post_init__()
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
                    groups.setdefault(t.n_particles, []).append(i)
            members = list(groups.values())
            sizes = np.array([sum(self.trajs[i].n_frames - self.length + 1 for i in m)
                              for m in members], float)
            self._family_groups[f] = (members, sizes / sizes.sum())

    def family_probabilities(self) -> dict[str, float]:
        """Family -> probability that a batch is drawn from it."""
        return dict(zip(self._families, self._family_p.tolist()))

    def sample(self, rng: np.random.Generator, batch: int) -> dict:
        """A batch of one family and one node count: positions (B, L, N, 2), particle_type
        (B, N), material (B, N)."""
        f = self._families[rng.choice(len(self._families), p=self._family_p)]
        members, p = self._family_groups[f]
        return self.windows(rng, members[rng.choice(len(members), p=p)], batch)
