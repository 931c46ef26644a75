"""Files at the edge, without JAX: checks of input files and atomic or staged writes.

Imported by the command line before any heavy module (h5py is imported on use), so a
missing or truncated input file is refused in a fraction of a second.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from diffgns.errors import InputError

#: prefix of trajectory groups being written (removed when a file is reopened)
_TMP_PREFIX = "_incomplete_"


def partial_path(path: str | Path) -> Path:
    """Where a staged writer builds ``path`` until it is complete: ``<path>.partial``."""
    path = Path(path)
    return path.with_name(path.name + ".partial")


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to a temporary file beside ``path`` and rename it to ``path``."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _normalised(value):
    """``value`` as JSON would give it back (tuples -> lists), for comparisons."""
    return json.loads(json.dumps(value, default=str))


def _short(value) -> str:
    text = json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."


def check_h5_file(path: str | Path, field: str, trajectories: bool = False) -> None:
    """Raise :class:`~diffgns.errors.InputError` (``field``: what is wrong; the fix) unless
    ``path`` is a readable HDF5 file, holding at least one trajectory group if
    ``trajectories``. Reads only the file's index, not its data."""
    import h5py

    path = Path(path)
    if not path.exists():
        raise InputError(field, f"{path} does not exist", "check the path")
    if not path.is_file():
        raise InputError(field, f"{path} is not a file", "give an HDF5 (.h5) file")
    try:
        with h5py.File(path, "r") as f:
            groups = [k for k in f if not k.startswith(_TMP_PREFIX)
                      and isinstance(f[k], h5py.Group)]
    except OSError as e:
        reason = str(e).split("(", 1)[-1].rstrip(")") if "(" in str(e) else str(e)
        raise InputError(field, f"{path} is not a readable HDF5 file ({reason})",
                         "it is truncated or corrupt: regenerate it") from None
    if trajectories and not groups:
        raise InputError(field, f"{path} holds no trajectory",
                         "give a dataset written by diffgns dataset/simulate")


def check_input_file(path: str | Path, field: str, metadata: bool = False) -> None:
    """Refuse (:class:`~diffgns.errors.InputError`) a dataset file that is missing or
    unreadable: an HDF5 file must open and hold a trajectory (and, with ``metadata``, have
    its ``<stem>.metadata.json`` or a ``metadata.json`` beside it), an ``.npz`` must exist."""
    path = Path(path)
    if path.suffix == ".npz":
        if not path.is_file():
            raise InputError(field, f"{path} does not exist", "check the path")
        return
    check_h5_file(path, field, trajectories=True)
    candidates = [path.with_name(f"{path.stem}.metadata.json"), path.with_name("metadata.json")]
    if metadata and not any(c.is_file() for c in candidates):
        raise InputError(field, f"{path} has no metadata (looked for "
                         f"{', '.join(c.name for c in candidates)} beside it)",
                         "copy the dataset with its metadata file, or regenerate it with "
                         "diffgns dataset")


def new_dirs(path: str | Path) -> list[Path]:
    """The folders of ``path`` (itself included) that do not exist yet, outermost first."""
    path = Path(path).absolute()
    return [d for d in [*reversed(path.parents), path] if not d.exists()]


def remove_empty_dirs(dirs: list[Path]) -> None:
    """Remove those of ``dirs`` (outermost first, from :func:`new_dirs`) that are empty."""
    for d in reversed(dirs):
        if d.is_dir() and not any(d.iterdir()):
            d.rmdir()


@contextmanager
def staged_dir(out: str | Path) -> Iterator[Path]:
    """Yield a fresh temporary folder beside ``out``; when the block succeeds, move each of
    its entries into ``out`` (created if missing; same-named entries replaced), so ``out``
    never holds a half-written output. On an exception the temporary folder is removed and
    ``out`` is left as it was."""
    out = Path(out)
    created = new_dirs(out.parent)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
    try:
        yield tmp
        out.mkdir(exist_ok=True)
        for entry in sorted(tmp.iterdir()):
            dest = out / entry.name
            if dest.is_dir() and not dest.is_symlink():
                shutil.rmtree(dest)
            os.replace(entry, dest)
    except BaseException:
        remove_empty_dirs(created)
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        remove_empty_dirs(created)


def trajectory_count(path: str | Path) -> int:
    """Number of complete trajectory groups in the HDF5 file ``path``."""
    import h5py

    with h5py.File(path, "r") as f:
        return sum(1 for k in f if not k.startswith(_TMP_PREFIX))
