"""The general granular dataset (issue 21): MPM trajectories of random scenes of every
family of :mod:`diffgns.scene.families`, for a GNS that generalises beyond column collapses.

``diffgns dataset --kind granular --families squares columns obstacles collision --n 200
--seed 0 --out data/granular.h5`` calls :func:`generate_families`. Sample ``i`` is stored
under key ``f"{i:05d}"`` and is the scene ``family_plan(families, n, seed)[i]``
(:func:`diffgns.scene.recipes.family_plan`: families round-robin, scene seed ``seed *
1_000_003 + i``), so a run resumes by key, a larger ``--n`` extends a file, and a held-out set
is the same command with another ``--seed``. The MPM is the one ``gns_cg16_pfn`` emulates
(``dx = 0.1 / 16`` m, 4 particles per cell, 2.5 ms frames), so coarse-graining 16 applies.

Each trajectory group carries, besides the datasets of :class:`~diffgns.io.dataset
.DatasetWriter`, the attributes ``family`` (str), ``scene_seed`` (int), ``obstacles``
((K, 4) float ``[x0, y0, x1, y1]`` in m, K = 0, 1 or 2: what the GNS needs to see them; read
back with :func:`read_obstacles`), ``description`` (JSON text of
:func:`~diffgns.scene.families.random_sample`'s description) and ``mpm_seconds`` (wall time
of the MPM rollout, s: indicative, it depends on the machine's load). The metadata file adds
``kind = "granular"``, ``families`` and the number of trajectories of each family.
"""
from __future__ import annotations

import json
import time
from collections import Counter
from pathlib import Path

import h5py
import numpy as np
from tqdm import tqdm

from diffgns.io.files import _TMP_PREFIX
from diffgns.io.shards import shard_writer
from diffgns.mpm import MPM
from diffgns.scene.families import ranges_dict
from diffgns.scene.recipes import family_plan, family_scenes
from diffgns.shard import Shard

__all__ = ["families_recipe", "generate_families", "read_families", "read_obstacles",
           "read_ranges"]


def families_recipe(families, n_frames: int, seed: int = 0, **ranges) -> dict:
    """The fingerprint of a granular-families dataset (JSON-serialisable): the family list,
    frames, seed, every range of :class:`~diffgns.scene.families.FamilyRanges` and the float
    dtype; not ``n`` (sample i depends on the seed and i alone, so a resume may add more)."""
    import jax.numpy as jnp

    return dict(kind="granular", families=list(families), n_frames=int(n_frames),
                seed=int(seed), ranges=ranges_dict(**ranges), dtype=str(jnp.zeros(()).dtype))


def generate_families(path, families, n: int, n_frames: int, seed: int = 0,
                      progress: bool = True, shard: Shard | None = None, **ranges) -> Path:
    """Write ``n`` MPM trajectories of ``n_frames`` frames of random family scenes to
    ``path`` (staged as ``<path>.partial``, resumable, refused if the file has another
    recipe); see the module docstring for the layout. With ``shard`` only every
    ``shard.count``-th sample, into :func:`~diffgns.io.shards.shard_path` (merge with
    :func:`~diffgns.io.shards.merge_shards`). Returns the file written."""
    shard = shard or Shard()
    recipe = families_recipe(families, n_frames, seed, **ranges)
    counts = Counter(f for f, _ in family_plan(families, n, seed))
    extra = dict(kind="granular", families=list(families), n_frames=int(n_frames),
                 seed=int(seed), family_counts=dict(counts))
    dx = recipe["ranges"]["dx"]
    with shard_writer(path, shard, extra, recipe) as w:
        for i, (family, s, scene, desc) in enumerate(tqdm(
                family_scenes(families, n, seed, **ranges), total=n, desc="granular scenes",
                disable=not progress)):
            key = f"{i:05d}"
            if not shard.owns(i) or w.has(key):
                continue
            sim = MPM(scene)
            t0 = time.perf_counter()
            traj, _ = sim.run(sim.params(), sim.init(), n_frames)
            np.asarray(traj.positions)  # wait for the rollout
            seconds = time.perf_counter() - t0
            obstacles = np.asarray(desc["obstacles"], float).reshape(-1, 4)
            w.write(key, traj, attrs=dict(family=family, scene_seed=s, obstacles=obstacles,
                                          description=json.dumps(desc), mpm_seconds=seconds,
                                          n_substeps=scene.substeps))
        w.finalize(connectivity_radius=2.0 * dx)
    return Path(w.final_path)


def read_obstacles(path: str | Path, key: str) -> np.ndarray:
    """(K, 4) obstacles ``[x0, y0, x1, y1]`` (m) of trajectory ``key`` of ``path``; (0, 4)
    for a trajectory stored without any (e.g. column or squares datasets)."""
    with h5py.File(path, "r") as f:
        obs = f[key].attrs.get("obstacles")
    return np.zeros((0, 4)) if obs is None else np.asarray(obs, float).reshape(-1, 4)


def read_families(path: str | Path) -> dict[str, str]:
    """Key -> family of every trajectory of ``path`` (``""`` where none is stored)."""
    with h5py.File(path, "r") as f:
        return {k: str(f[k].attrs.get("family", "")) for k in sorted(f)
                if isinstance(f[k], h5py.Group) and not k.startswith(_TMP_PREFIX)}


def read_ranges(path: str | Path) -> dict:
    """The :class:`~diffgns.scene.families.FamilyRanges` fields ``path`` was drawn with (from
    its recipe; tuples as the dataclass has them), so that ``random_sample(family,
    scene_seed, **read_ranges(path))`` redraws any of its scenes."""
    with h5py.File(path, "r") as f:
        ranges = json.loads(f.attrs["recipe"])["ranges"]

    def tup(v):
        return tuple(tup(x) for x in v) if isinstance(v, list) else v

    return {k: tup(v) for k, v in ranges.items()}
