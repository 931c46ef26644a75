"""Training-set generation with the MPM: column collapses and granular square flows.

Sample ``i`` is always stored under key ``f"{i:05d}"``, so an interrupted run resumes by
skipping the keys already in the file. Column collapses of one aspect ratio share their
particle layout, so their friction angles are rolled out together under ``jax.vmap``.

A new file is built as ``<path>.partial`` and renamed to ``path`` when complete; the file
carries its recipe (:func:`column_recipe`, :func:`squares_recipe`: every argument that shapes
the trajectories), and resuming with another recipe is refused before anything is written
(:class:`~diffgns.io.dataset.H5TrajectoryFile`).

``shard`` (:class:`~diffgns.distributed.Shard`) makes only every n-th unit of work into its
own file (:mod:`diffgns.io.shards`; merged with :func:`~diffgns.io.shards.merge_shards`):
for squares a flow, for columns a vmap batch of friction angles of one aspect ratio (the
batches a single process would roll out, so the merged file holds the same bytes).
"""
from __future__ import annotations

from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from diffgns.interface import rollout
from diffgns.io.shards import shard_writer
from diffgns.mpm import MPM
from diffgns.mpm.solver import max_speed
from diffgns.scene.recipes import column_samples, column_scene, square_scenes
from diffgns.shard import Shard
from diffgns.trajectory import Trajectory


def column_recipe(aspect_ratios, friction_angles, n_frames: int, width: float = 0.1,
                  cells_across: int = 10, dim: int = 2, **scene_kw) -> dict:
    """The fingerprint of a column-collapse dataset (JSON-serialisable). ``dim`` is recorded
    only for 3D, so the fingerprints of 2D files made before it existed still match."""
    extra = dict(dim=3) if dim == 3 else {}
    return dict(kind="column", aspect_ratios=[float(a) for a in aspect_ratios],
                friction_angles=[float(p) for p in friction_angles], n_frames=int(n_frames),
                width=float(width), cells_across=int(cells_across), dtype=_float_dtype(),
                **extra, **scene_kw)


def squares_recipe(n_frames: int, seed: int = 0, **scene_kw) -> dict:
    """The fingerprint of a granular-squares dataset (JSON-serialisable); not the number of
    flows: flow i depends on the seed and i alone, so a resume may add more."""
    return dict(kind="squares", n_frames=int(n_frames), seed=int(seed), dtype=_float_dtype(),
                **scene_kw)


def _float_dtype() -> str:
    return str(jnp.zeros(()).dtype)


def _traj(sim, params, pos, vel) -> Trajectory:
    return Trajectory(positions=np.asarray(pos), velocities=np.asarray(vel),
                      particle_type=np.asarray(sim.particle_type()),
                      material=np.asarray(sim.material_feature(params)),
                      frame_dt=sim.scene.frame_dt, bounds=sim.scene.domain)


def _rollout(sim, state, n_frames, params):
    frames, _ = rollout(sim, params, state, n_frames)
    return frames.positions, frames.velocities, max_speed(frames.velocities)


def _tile(n, leaf):
    return jnp.broadcast_to(leaf, (n, *leaf.shape))


def column_jobs(samples: list[dict], aspect_ratios, batch: int) -> list[list[int]]:
    """The units of work of a column dataset: for each aspect ratio in turn, its sample
    indices in chunks of ``batch`` (one vmapped rollout each)."""
    jobs = []
    for a in aspect_ratios:
        ids = [i for i, s in enumerate(samples) if s["aspect_ratio"] == float(a)]
        jobs += [ids[k:k + batch] for k in range(0, len(ids), batch)]
    return jobs


def generate_columns(path, aspect_ratios, friction_angles, n_frames: int, width: float = 0.1,
                     cells_across: int = 10, batch: int = 4, progress: bool = True,
                     shard: Shard | None = None, dim: int = 2, **scene_kw) -> Path:
    """Write column collapses over the (aspect ratio x friction angle) grid to ``path``
    (shard ``shard`` of them to :func:`~diffgns.io.shards.shard_path`); returns the file.
    ``dim = 3``: axisymmetric columns of radius ``width``
    (:func:`~diffgns.scene.recipes.column_scene`), trajectories (T, N, 3)."""
    shard = shard or Shard()
    samples = column_samples(aspect_ratios, friction_angles)
    extra = dict(kind="column", width=width, cells_across=cells_across, n_frames=n_frames)
    if dim == 3:  # (the file's metadata records the dimension itself)
        scene_kw = {k: v for k, v in scene_kw.items()
                    if not (k in ("domain_length", "domain_height") and v is None)}
    recipe = column_recipe(aspect_ratios, friction_angles, n_frames, width, cells_across,
                           dim, **scene_kw)
    jobs = shard.select(column_jobs(samples, aspect_ratios, batch))
    mine = [i for job in jobs for i in job]
    sims: dict[float, tuple] = {}
    with shard_writer(path, shard, extra, recipe, dict(batch=batch)) as w, \
            tqdm(total=len(mine), desc="column collapses", disable=not progress) as bar:
        bar.update(sum(w.has(f"{i:05d}") for i in mine))
        for job in jobs:
            ids = [i for i in job if not w.has(f"{i:05d}")]
            if not ids:
                continue
            a = samples[ids[0]]["aspect_ratio"]
            if a not in sims:
                scene = column_scene(a, width, cells_across, dim, **scene_kw)
                sim = MPM(scene)
                sims[a] = (sim, sim.params(), jax.jit(jax.vmap(partial(
                    _rollout, sim, sim.init(), n_frames))))
            sim, base, run = sims[a]
            phis = jnp.asarray([samples[i]["friction_angle"] for i in ids], base.E.dtype)
            ps = jax.tree.map(partial(_tile, len(ids)), base)
            ps = ps.replace(friction_angle=phis[:, None])
            pos, vel, speed = run(ps)
            for j, i in enumerate(ids):
                p = jax.tree.map(lambda leaf, j=j: leaf[j], ps)
                sim.check_stability(p, speed[j], pos[j])
                w.write(f"{i:05d}", _traj(sim, p, pos[j], vel[j]), attrs=samples[i])
                bar.update(1)
        w.finalize(connectivity_radius=2.0 * width / cells_across)
    return Path(w.final_path)


def generate_squares(path, n: int, n_frames: int, seed: int = 0, progress: bool = True,
                     shard: Shard | None = None, **scene_kw) -> Path:
    """Write ``n`` granular-square flows (random 1-2 masses and velocities) to ``path``
    (every ``shard.count``-th of them to :func:`~diffgns.io.shards.shard_path`); returns the
    file."""
    shard = shard or Shard()
    extra = dict(kind="squares", n_frames=n_frames, seed=seed)
    dx = scene_kw.get("dx", 0.02)
    recipe = squares_recipe(n_frames, seed, **scene_kw)
    with shard_writer(path, shard, extra, recipe) as w:
        scenes = square_scenes(n, seed, **scene_kw)
        for i in tqdm(range(n), desc="square flows", disable=not progress):
            scene = next(scenes)  # flow i depends on (seed, i): every shard draws them all
            if not shard.owns(i) or w.has(f"{i:05d}"):
                continue
            sim = MPM(scene)
            traj, _ = sim.run(sim.params(), sim.init(), n_frames)
            w.write(f"{i:05d}", traj, attrs=dict(seed=seed * 100003 + i,
                                                 n_masses=len(scene.bodies)))
        w.finalize(connectivity_radius=2.0 * dx)
    return Path(w.final_path)
