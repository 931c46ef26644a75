"""The scenes of a dataset recipe, built (so validated) without running anything.

Light (numpy and the scene package only, no JAX): the command line validates a
``diffgns dataset`` recipe with these before it imports the simulator
(:mod:`diffgns.io.datagen` generates the trajectories of the same scenes).
"""
from __future__ import annotations

import itertools
from collections.abc import Iterator

from diffgns.errors import SceneError
from diffgns.scene.builders import column_collapse, granular_squares
from diffgns.scene.builders3d import axisymmetric_column
from diffgns.scene.core import Scene
from diffgns.scene.families import ALL_FAMILIES, random_sample

__all__ = ["FAMILY_SEED_STRIDE", "column_samples", "column_scene", "column_scenes", "family_plan",
           "family_scenes", "square_scenes"]

FAMILY_SEED_STRIDE = 1_000_003  # seeds of different dataset seeds never meet below this n


def column_samples(aspect_ratios, friction_angles) -> list[dict]:
    """The grid of (aspect ratio, friction angle) samples, in storage order."""
    return [dict(aspect_ratio=float(a), friction_angle=float(p))
            for a, p in itertools.product(aspect_ratios, friction_angles)]


def column_scene(aspect_ratio: float, width: float = 0.1, cells_across: int = 10,
                 dim: int = 2, **scene_kw) -> Scene:
    """One column of a column dataset.

    2D: :func:`~diffgns.scene.builders.column_collapse` (a column of ``width`` L0, m,
    against the left wall). 3D: :func:`~diffgns.scene.builders3d.axisymmetric_column`, a
    cylinder of radius ``width`` (R0, m: the half-width of the symmetric collapse, as L0 is
    in 2D) in the middle of its box; its box follows from the runout estimate, so
    ``domain_length`` / ``domain_height`` (2D options) must be None.
    """
    if dim == 2:
        return column_collapse(width=width, aspect_ratio=aspect_ratio,
                               cells_across=cells_across, **scene_kw)
    if dim != 3:
        raise SceneError(f"column dataset: dim must be 2 or 3, got {dim}")
    for k in ("domain_length", "domain_height"):
        if scene_kw.pop(k, None) is not None:
            raise SceneError(f"column dataset: {k} is a 2D option; a 3D column's box follows "
                             "from its runout estimate (leave it unset)")
    return axisymmetric_column(radius=width, aspect_ratio=aspect_ratio,
                               cells_across=cells_across, **scene_kw)


def column_scenes(aspect_ratios, friction_angles, width: float = 0.1, cells_across: int = 10,
                  dim: int = 2, **scene_kw) -> Iterator[tuple[dict, Scene]]:
    """(sample, scene) of every sample of :func:`column_samples`, built (so validated) with
    :func:`column_scene`; raises its SceneError on the first bad one."""
    for sample in column_samples(aspect_ratios, friction_angles):
        yield sample, column_scene(sample["aspect_ratio"], width, cells_across, dim,
                                   friction_angle=sample["friction_angle"], **scene_kw)


def square_scenes(n: int, seed: int = 0, **scene_kw) -> Iterator[Scene]:
    """The ``n`` scenes of :func:`diffgns.io.datagen.generate_squares`, built (so
    validated) in order."""
    for i in range(n):
        yield granular_squares(seed=seed * 100003 + i, **scene_kw)


def family_plan(families, n: int, seed: int = 0) -> list[tuple[str, int]]:
    """``(family, scene seed)`` of the ``n`` samples of a granular-families dataset: sample
    ``i`` is of family ``families[i % len(families)]`` (repeat a name to weight it) with
    scene seed ``seed * FAMILY_SEED_STRIDE + i``, so sample i never changes when ``n``
    grows and datasets of different ``seed`` (held-out sets) draw disjoint scenes."""
    families = list(families)
    bad = [f for f in families if f not in ALL_FAMILIES]
    if not families or bad:
        raise SceneError(f"families {bad or families} unknown or empty; use names of "
                         f"{ALL_FAMILIES}")
    if not (isinstance(seed, int) and seed >= 0):
        raise SceneError(f"seed = {seed!r} must be an integer >= 0")
    return [(families[i % len(families)], seed * FAMILY_SEED_STRIDE + i) for i in range(n)]


def family_scenes(families, n: int, seed: int = 0, **ranges
                  ) -> Iterator[tuple[str, int, Scene, dict]]:
    """``(family, scene seed, scene, description)`` of every sample of :func:`family_plan`,
    drawn by :func:`~diffgns.scene.families.random_sample` (so validated)."""
    for family, s in family_plan(families, n, seed):
        scene, desc = random_sample(family, s, **ranges)
        yield family, s, scene, desc
