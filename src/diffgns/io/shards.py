"""Dataset generation in shards: several processes or hosts, one HDF5 file each, then merged.

A generator that makes sample ``i`` from its spec alone (its key ``f"{i:05d}"``, its seed)
shards by running only the specs a :class:`~diffgns.distributed.Shard` owns (every n-th,
``shard.select(specs)`` or ``shard.owns(i)``) into the writer :func:`shard_writer` opens:

* ``Shard(0, 1)`` (one process): the dataset file itself, exactly as before;
* shard ``i/n``: ``<stem>.shard-<i>-of-<n>.h5`` beside it (:func:`shard_path`), with the
  dataset's recipe plus ``shard = "i/n"``, so a resume with another recipe or another shard
  is refused; finished trajectories are kept and skipped on resume as for any dataset.

:func:`merge_shards` then copies the trajectories of all ``n`` shards, unchanged (HDF5
copies of the same bytes), into one dataset with the recipe of a single-process run and
recomputes its metadata over the same trajectories in the same key order: the merged file
equals the one a single process would have written. A merge refuses shards of different
recipes, a missing, repeated or unfinished shard, and keys present in two shards.

Why a merge rather than a dataset that reads a list of shards: every reader of diffgns
(training, rollout, benchmarks, LagrangeBench-style tools) takes one HDF5 file and one
``metadata.json`` with statistics over the whole set; a merge keeps them all unchanged.
"""
from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import h5py

from diffgns.errors import InputError
from diffgns.io.dataset import DatasetWriter, read_metadata
from diffgns.io.files import _TMP_PREFIX, check_h5_file, partial_path
from diffgns.shard import Shard


def shard_path(path: str | Path, shard: Shard) -> Path:
    """Where shard ``shard`` of the dataset ``path`` is written: ``path`` itself for one
    shard, else ``<dir>/<stem>.shard-<i>-of-<n><suffix>``."""
    path = Path(path)
    if shard.count == 1:
        return path
    return path.with_name(f"{path.stem}.shard-{shard.index}-of-{shard.count}{path.suffix}")


def shard_recipe(recipe: dict, shard: Shard, layout: dict | None = None) -> dict:
    """The recipe stored in a shard's file: the dataset's plus ``shard = "i/n"`` and
    ``shard_layout``: whatever else decides which samples a shard owns (e.g. the column
    generator's vmap batch), which all shards of a merge must share."""
    if shard.count == 1:
        return recipe
    return dict(recipe, shard=str(shard), shard_layout=dict(layout or {}))


def shard_writer(path: str | Path, shard: Shard, metadata_extra: dict, recipe: dict,
                 layout: dict | None = None) -> DatasetWriter:
    """The staged, resumable :class:`DatasetWriter` of ``shard`` of dataset ``path``
    (:func:`shard_path`, :func:`shard_recipe`)."""
    return DatasetWriter(shard_path(path, shard), metadata_extra=metadata_extra,
                         recipe=shard_recipe(recipe, shard, layout), staged=True)


def _read_recipe(path: Path) -> tuple[dict, dict]:
    with h5py.File(path, "r") as f:
        recipe = json.loads(f.attrs.get("recipe", "null") or "null")
        extra = json.loads(f.attrs.get("metadata_extra", "{}"))
    if not isinstance(recipe, dict) or "shard" not in recipe:
        raise InputError(str(path), "is not a dataset shard (its recipe has no 'shard')",
                         "give the files written by diffgns dataset --shard i/n")
    return recipe, extra


def merge_shards(paths: Sequence[str | Path], out: str | Path) -> Path:
    """Merge the shard files ``paths`` (all ``n`` shards of one recipe, any order) into the
    dataset ``out`` (staged as ``<out>.partial``; metadata written beside it). Returns
    ``out``.

    Raises:
        InputError: naming the file at fault (missing, unreadable, not a shard, another
            recipe, a shard missing or given twice, a key in two shards) or ``--out`` when
            it exists already.
    """
    out = Path(out)
    if not paths:
        raise InputError("shards", "none given", "give the n files of --shard 0/n .. n-1/n")
    if out.exists():
        raise InputError("--out", f"{out} exists", "merge into a new file (or delete it)")
    shards: dict[int, Path] = {}
    base, extra0, count, keys_of = None, None, None, {}
    for p in map(Path, paths):
        if not p.exists() and partial_path(p).exists():
            raise InputError(str(p), "is unfinished (only its .partial exists)",
                             "run its diffgns dataset --shard command again to complete it")
        check_h5_file(p, str(p), trajectories=True)
        recipe, extra = _read_recipe(p)
        shard = Shard.parse(recipe.pop("shard"))
        if base is None:
            base, extra0, count = recipe, extra, shard.count
        elif recipe != base or shard.count != count:
            diff = sorted(k for k in set(recipe) | set(base) if recipe.get(k) != base.get(k))
            raise InputError(str(p), "was made by another recipe than "
                             f"{next(iter(shards.values()))} (differs in "
                             f"{', '.join(diff) or 'shard count'})",
                             "merge the shards of one dataset only")
        if shard.index in shards:
            raise InputError(str(p), f"is shard {shard} again (also {shards[shard.index]})",
                             "give each shard once")
        shards[shard.index] = p
        with h5py.File(p, "r") as f:
            keys_of[p] = sorted(k for k in f if not k.startswith(_TMP_PREFIX))
    assert base is not None and count is not None and extra0 is not None
    base.pop("shard_layout", None)
    missing = sorted(set(range(count)) - set(shards))
    if missing:
        raise InputError("shards", f"shard(s) {', '.join(f'{i}/{count}' for i in missing)} "
                         "missing", f"give all {count} shards")
    owner: dict[str, Path] = {}
    for p, keys in keys_of.items():
        for k in keys:
            if k in owner:
                raise InputError(str(p), f"holds trajectory {k!r}, as does {owner[k]}",
                                 "merge shards of one --shard i/n run")
            owner[k] = p
    gaps = sorted(set(f"{i:05d}" for i in range(len(owner))) - set(owner))
    if gaps:
        raise InputError("shards", f"trajectories {', '.join(gaps[:4])} are in no shard",
                         "run every shard with the same arguments (e.g. the same --n)")
    radius = read_metadata(next(iter(shards.values())))["default_connectivity_radius"]
    files = {p: h5py.File(p, "r") for p in shards.values()}
    try:
        with DatasetWriter(out, metadata_extra=extra0, recipe=base, staged=True) as w:
            for key in sorted(owner):
                w.copy_group(files[owner[key]][key], key)
            w.finalize(connectivity_radius=float(radius))
    finally:
        for f in files.values():
            f.close()
    return out


def shards_of(path: str | Path, count: int) -> list[Path]:
    """The ``count`` shard files of dataset ``path`` (:func:`shard_path`)."""
    return [shard_path(path, Shard(i, count)) for i in range(count)]
