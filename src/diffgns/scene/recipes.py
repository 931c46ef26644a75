"""The scenes of a dataset recipe, built (so validated) without running anything.

Light (numpy and the scene package only, no JAX): the command line validates a
``diffgns dataset`` recipe with these before it imports the simulator
(:mod:`diffgns.io.datagen` generates the trajectories of the same scenes).
"""
from __future__ import annotations

import itertools
from collections.abc import Iterator

from diffgns.scene.builders import column_collapse, granular_squares
from diffgns.scene.core import Scene

__all__ = ["column_samples", "column_scenes", "square_scenes"]


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
