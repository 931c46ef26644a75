"""The trained models shipped with diffgns, and the one way to find a model folder.

Each shipped model is a folder inside this package (``diffgns/models/<name>/``) with a
``MODEL_CARD.md`` and its weights: ``config.json`` + ``params.msgpack`` for a particle GNS, or a
``model/`` sub-folder (``model.json`` + ``params.msgpack``) for the MeshGraphNet and the message
networks. They are package data, found through :mod:`importlib.resources`, so they load the
same from a source checkout, an editable install or a wheel, whatever the working directory.

>>> from diffgns.models import model_path, shipped_models
>>> model_path("gns_columns")                  # a shipped name   -> .../diffgns/models/gns_columns
>>> model_path("meshnet_cylinder/model")       # a path inside a shipped model
>>> model_path("runs/gns/model")               # an existing folder wins over a shipped name
"""
from __future__ import annotations

import importlib.resources
import os
from pathlib import Path

__all__ = ["model_path", "models_root", "shipped_models"]


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


def model_path(name_or_path: str | os.PathLike[str]) -> Path:
    """The folder of a model: an existing path as given, otherwise a shipped model.

    ``name_or_path`` is tried, in order, as

    1. an existing file-system path (absolute, or relative to the working directory);
    2. a shipped model ``<name>`` or a path inside one, ``<name>/<sub>`` (for example
       ``"meshnet_cylinder/model"``); the repository-relative spelling of earlier versions,
       ``"models/<name>[/<sub>]"``, means the same.

    Raises ``FileNotFoundError`` naming the shipped models when neither exists.
    """
    given = Path(name_or_path).expanduser()
    if given.exists():
        return given
    parts = given.parts
    if parts[:1] == ("models",):
        parts = parts[1:]
    names = shipped_models()
    if parts and parts[0] in names:
        shipped = models_root().joinpath(*parts)
        if shipped.exists():
            return shipped
        raise FileNotFoundError(
            f"shipped model {parts[0]!r} has no {Path(*parts[1:])}; it contains: "
            + ", ".join(sorted(p.name for p in models_root().joinpath(parts[0]).iterdir())))
    raise FileNotFoundError(
        f"no model {str(name_or_path)!r}: not an existing path (working directory "
        f"{Path.cwd()}) and not a shipped model; shipped models: {', '.join(names)}")
