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
from diffgns.scene.core import Scene
from diffgns.scene.families import FAMILIES, random_sample

__all__ = ["FAMILY_SEED_STRIDE", "column_samples", "column_scenes", "family_plan",
           "family_scenes", "square_scenes"]

FAMILY_SEED_STRIDE = 1_000_003  # seeds of different dataset seeds never meet below this n


def column_samples(aspect_ratios, friction_angles) -> list[dict]:
    """The grid of (aspect ratio, friction angle) samples, in storage order."""
    return [dict(aspect_ratio=float(a), friction_angle=float(p))
            for a, p in itertools.product(aspect_ratios, friction_angles)]


def column_scenes(aspect_ratios, friction_angles, width: float = 0.1, cells_across: int = 10,
                  **scene_kw) -> Iterator[tuple[dict, Scene]]:
    """(sample, scene) of every sample of :func:`column_samples`, built (so validated) with
    :func:`~diffgns.scene.builders.column_collapse`; raises its SceneError on the first bad
    one."""
    for sample in column_samples(aspect_ratios, friction_angles):
        yield sample, column_collapse(width=width, cells_across=cells_across, **sample,
                                      **scene_kw)


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
    bad = [f for f in families if f not in FAMILIES]
    if not families or bad:
        raise SceneError(f"families {bad or families} unknown or empty; use names of {FAMILIES}")
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
