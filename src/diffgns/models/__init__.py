"""The trained models shipped with diffgns, the one model-folder layout, and how a model is found.

**The layout.** A *model folder* holds a network's weights and everything needed to rebuild it:

``params.msgpack``
    the parameters (flax msgpack);
``config.json`` (particle GNS) or ``model.json`` (MeshGraphNet, message networks)
    the configuration, the normalisation statistics and what the model was trained on;
``MODEL_CARD.md``
    (shipped models) what it is for, how it was trained and how well it does.

A shipped model is such a folder inside this package (``diffgns/models/<name>/``), package data
found through :mod:`importlib.resources`, so it loads the same from a source checkout, an
editable install or a wheel, whatever the working directory. A training run folder
(``diffgns train --out RUN``) holds its checkpoint and logs, and its model folder as
``RUN/model/``.

**Finding a model** (:func:`model_dir`, used by every loader): the folder given, or its
``model/`` sub-folder (a training run folder; also the layout of earlier shipped models, still
used by the message networks), or, for a path ending in ``/model`` that does not exist, its
parent (e.g. ``models/gns_columns/model``). Anything else is refused with one
:class:`ModelFolderError` saying what the folder lacks and what it contains.

>>> from diffgns.models import model_dir, model_path, shipped_models
>>> model_path("gns_columns")                  # a shipped name   -> .../diffgns/models/gns_columns
>>> model_dir("meshnet_cylinder/model")        # one level too deep -> .../models/meshnet_cylinder
>>> model_dir("runs/gns")                      # a training run folder -> runs/gns/model
"""
from __future__ import annotations

import importlib.resources
import os
from pathlib import Path

from diffgns.errors import InputError

__all__ = ["CONFIG_FILES", "WEIGHTS", "ModelFolderError", "model_dir", "model_path",
           "models_root", "shipped_models"]

#: the weights file of every model folder
WEIGHTS = "params.msgpack"
#: the configuration file of each kind of model folder
CONFIG_FILES = {"config.json": "particle GNS", "model.json": "MeshGraphNet or message network"}


class ModelFolderError(InputError, FileNotFoundError):
    """A model name or folder that does not hold a model (exit status 2 on the command
    line). Both an :class:`~diffgns.errors.InputError` (a ``ValueError``) and a
    ``FileNotFoundError``; the message names what is missing and what exists."""


def models_root() -> Path:
    """The folder that holds the shipped models (this package's directory)."""
    root = importlib.resources.files(__name__)
    if not isinstance(root, Path):  # e.g. a zipped install: weights need a real folder
        raise RuntimeError(f"diffgns.models is not on the file system ({root!r}); install "
                           "diffgns as a regular (unzipped) package to use the shipped models")
    return root


def shipped_models() -> list[str]:
    """Names of the shipped models (folders with a ``MODEL_CARD.md``), sorted."""
    return sorted(p.name for p in models_root().iterdir() if (p / "MODEL_CARD.md").is_file())


def _is_model(folder: Path, config: str | None = None) -> bool:
    names = [config] if config else list(CONFIG_FILES)
    return (folder / WEIGHTS).is_file() and any((folder / c).is_file() for c in names)


def _contents(folder: Path) -> str:
    if not folder.is_dir():
        return "it does not exist"
    names = sorted(p.name + ("/" if p.is_dir() else "") for p in folder.iterdir())
    more = f" and {len(names) - 12} more" if len(names) > 12 else ""
    return "it contains " + (", ".join(names[:12]) + more if names else "nothing")


def model_path(name_or_path: str | os.PathLike[str]) -> Path:
    """The folder of a model as named: an existing path as given, otherwise a shipped model.

    ``name_or_path`` is tried, in order, as

    1. an existing file-system path (absolute, or relative to the working directory);
    2. a shipped model ``<name>`` or a path inside one, ``<name>/<sub>``; the
       repository-relative spelling ``"models/<name>[/<sub>]"`` means the same;
    3. a path ending in ``model`` that does not exist, inside a model folder: that folder
       (``"meshnet_cylinder/model"``, ``"models/gns_columns/model"``).

    The folder may be a training run folder holding ``model/``: :func:`model_dir` gives the
    folder with the weights. Raises :class:`ModelFolderError` naming the shipped models
    when none of these exists.
    """
    given = Path(name_or_path).expanduser()
    if given.exists():
        return given
    parts = given.parts
    if parts[:1] == ("models",):
        parts = parts[1:]
    names = shipped_models()
    if parts and parts[0] in names:
        candidate = models_root().joinpath(*parts)
    else:
        candidate = given
    if candidate.exists():
        return candidate
    if candidate.name == "model" and _is_model(candidate.parent):
        return candidate.parent  # one level too deep: the layout of earlier model folders
    if parts and parts[0] in names:
        base = models_root() / parts[0]
        raise ModelFolderError(
            "model", f"shipped model {parts[0]!r} has no {Path(*parts[1:])}; "
            f"{_contents(base)}", f"give {parts[0]!r} (its folder holds the weights)")
    raise ModelFolderError(
        "model", f"{str(name_or_path)!r} is not an existing path (working directory "
        f"{Path.cwd()}) nor a shipped model",
        f"give a model folder or one of the shipped models: {', '.join(names)}")


def model_dir(name_or_path: str | os.PathLike[str], config: str | None = None) -> Path:
    """The model folder with the weights of ``name_or_path`` (:func:`model_path`): the
    folder itself, or its ``model/`` sub-folder (a training run, earlier layouts).

    Args:
        config: the configuration file the caller needs (``"config.json"`` for a particle
            GNS, ``"model.json"`` for a MeshGraphNet); None accepts either.
    Raises:
        ModelFolderError: neither holds ``params.msgpack`` and the configuration; the
            message lists what the folder lacks and what it contains.
    """
    path = model_path(name_or_path)
    for folder in (path, path / "model"):
        if _is_model(folder, config):
            return folder
    needed = [config] if config else list(CONFIG_FILES)
    lacks = [] if (path / WEIGHTS).is_file() else [WEIGHTS]
    if not any((path / c).is_file() for c in needed):
        lacks.append(" or ".join(f"{c} ({CONFIG_FILES.get(c, 'model')})" for c in needed))
    other = [c for c in CONFIG_FILES if c not in needed and (path / c).is_file()]
    hint = f" (its {other[0]} is a {CONFIG_FILES[other[0]]})" if other else ""
    raise ModelFolderError(
        "model", f"{path} is not a model folder{hint}: it lacks {' and '.join(lacks)} (also "
        f"in model/); {_contents(path)}",
        "give the folder holding params.msgpack, a training run folder (with model/) or "
        "a shipped model name: " + ", ".join(shipped_models()))
