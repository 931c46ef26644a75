"""The command line's validation layer: argument types, one-line errors, recipe checks,
interruptions and output clean-up. Imports no JAX (the scene checks import it when a command
runs).

Every refusal is one line on stderr, ``diffgns: error: <field>: <what is wrong>; <fix>``, with
exit status 2, before anything is written. Dataset recipes are checked by building their
scenes with :mod:`diffgns.scene.builders` (so :mod:`diffgns.scene.checks` and the material
checks apply, the same rules as scene files); this module adds only what a scene cannot
know: counts are whole numbers >= 1 and numbers are finite.
"""
from __future__ import annotations

import argparse
import math
import re
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from diffgns.errors import InputError, Interrupted, SceneError


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line: ``diffgns: error: ...`` (exit 2),
    and which reads every negative number (``-1e3``, ``-inf``, not only ``-5`` and ``-0.5``)
    as a value, not as an option."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(
            r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|infinity|nan)$", re.IGNORECASE)

    def error(self, message: str):
        if message.startswith("argument "):
            message = message[len("argument "):]
        if ";" not in message:
            message += f"; see `{self.prog} --help`"
        self.exit(2, f"diffgns: error: {message}\n")


def count(text: str) -> int:
    """argparse type: a whole number >= 1 (frames, trajectories, steps, ...)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number; give a count "
                                         ">= 1") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} is not a count >= 1; give at least 1")
    return value


def frames(text: str) -> int:
    """argparse type: frames of a stored trajectory, >= 2 (3 positions give the one
    acceleration the dataset statistics need)."""
    value = count(text)
    if value < 2:
        raise argparse.ArgumentTypeError(f"{value} frame is too short for a dataset (its "
                                         "acceleration statistics need 3 positions); give "
                                         "at least 2")
    return value


def finite(text: str) -> float:
    """argparse type: a finite number (no nan or inf)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number; give a finite "
                                         "number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text} is not a finite number; give a finite "
                                         "number")
    return value


#: words of scene/builder messages -> the dataset option that sets them, with its fix
_OPTIONS = {
    "friction_angle": ("--friction-angles", "give friction angles in degrees in (0, 90)"),
    "aspect_ratio": ("--aspect-ratios", "give column height / width ratios > 0, whole "
                     "multiples of 1 / --cells-across"),
    "width": ("--width", "give the column width in m, > 0"),
    "domain_height": ("--domain-height", "give a box height in m above the tallest column"),
    "domain_length": ("--domain-length", "give a box length in m"),
    "Scene.dx": ("--dx", "give a cell size in m that divides the 1 m box"),
    "size": ("--size", "give a square side in m, a multiple of --dx that fits the box"),
    "Rectangle": ("--size", "give a square side in m, a multiple of --dx that fits the box"),
}


#: the same for ``diffgns simulate --column``
_SIMULATE_OPTIONS = {
    "friction_angle": ("--friction-angle", "give a friction angle in degrees in (0, 90)"),
    "aspect_ratio": ("--aspect-ratio", "give a column height / width ratio > 0, a whole "
                     "multiple of 1 / --cells-across"),
    "width": ("--width", "give the column width in m, > 0"),
}



def positive(text: str) -> float:
    """argparse type: a finite number > 0 (learning rates, radii, tolerances)."""
    value = finite(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text} is not > 0; give a positive number")
    return value


def probability(text: str) -> float:
    """argparse type: a number in [0, 1]."""
    value = finite(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"{text} is not a probability; give 0 to 1")
    return value


def fraction(text: str) -> float:
    """argparse type: a number strictly between 0 and 1."""
    value = finite(text)
    if not 0 < value < 1:
        raise argparse.ArgumentTypeError(f"{text} is not in (0, 1); give a fraction "
                                         "strictly between 0 and 1")
    return value


def fraction_or_none(text: str) -> float | str:
    """argparse type: :func:`fraction`, or ``"none"`` (an option switched off)."""
    return "none" if text.strip().lower() == "none" else fraction(text)


def box_size(text: str) -> tuple[float, float]:
    """argparse type: a 2D box ``LENGTHxHEIGHT`` in m, e.g. ``1.4x0.35``."""
    parts = text.lower().split("x")
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"{text!r} is not a box; give LENGTHxHEIGHT in m, "
                                         "e.g. 1.4x0.35")
    length, height = (finite(p) for p in parts)
    if length <= 0 or height <= 0:
        raise argparse.ArgumentTypeError(f"{text}: box sides must be > 0 m")
    return (length, height)


def granular_kw(args) -> dict:
    """Family ranges (:class:`~diffgns.scene.families.FamilyRanges` fields) of a granular
    dataset recipe from the ``dataset`` arguments (only those given)."""
    kw: dict = {}
    if getattr(args, "boxes", None):
        kw["boxes"] = tuple(args.boxes)
    if getattr(args, "young_modulus", None) is not None:
        kw["young_modulus"] = args.young_modulus
    if getattr(args, "flip", None) is not None:
        kw["flip"] = args.flip
    return kw


def non_negative(text: str) -> float:
    """argparse type: a finite number >= 0 (noise levels, loss weights)."""
    value = finite(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text} is negative; give 0 or more")
    return value

def _scene_refusal(e: Exception, default: str, fix: str,
                   options: dict | None = None) -> InputError:
    """An InputError naming the options (``options``: message word -> (option, fix)) a
    scene/builder error ``e`` is about."""
    msg = str(e) if not isinstance(e, ZeroDivisionError) else "0 leads to a division by zero"
    hits = [(opt, f) for word, (opt, f) in (options or _OPTIONS).items() if word in msg]
    field = ", ".join(dict.fromkeys(opt for opt, _ in hits)) or default
    if ";" in msg:
        return InputError(field, msg)
    return InputError(field, msg, hits[0][1] if hits else fix)


def check_dataset(args) -> None:
    """Build every scene of the ``diffgns dataset`` recipe (which validates it); raise an
    InputError naming the option at fault. Cylinder recipes are checked by their own
    dataclasses in :mod:`diffgns.mesh.datagen`."""
    from diffgns.io.files import check_h5_file, partial_path

    out = Path(args.out)
    if out.exists() and out.is_dir():
        raise InputError("--out", f"{out} is a folder", "give the path of an .h5 file")
    for path in (out, partial_path(out)):  # a file to resume must be readable
        if path.exists():
            check_h5_file(path, "--out")
    dim = getattr(args, "dim", 2)
    if dim == 3 and args.kind != "column":
        raise InputError("--dim", f"--dim 3 is for --kind column only, not --kind {args.kind}",
                         "drop --dim, or use --kind column")
    if args.kind == "column":
        from diffgns.scene.recipes import column_scenes

        if dim == 3:
            for opt in ("domain_length", "domain_height"):
                if getattr(args, opt) is not None:
                    flag = "--" + opt.replace("_", "-")
                    raise InputError(flag, f"{flag} is a 2D option: a 3D column's box follows "
                                     "from its runout estimate", f"drop {flag} with --dim 3")
        try:
            for _ in column_scenes(args.aspect_ratios, args.friction_angles, width=args.width,
                                   cells_across=args.cells_across, dim=dim,
                                   domain_length=args.domain_length,
                                   domain_height=args.domain_height):
                pass
        except (SceneError, ValueError, ArithmeticError) as e:
            raise _scene_refusal(e, "--aspect-ratios", "check the column options") from None
    elif args.kind == "granular":
        from diffgns.scene.recipes import family_scenes

        try:
            for _ in family_scenes(args.families, args.n, args.seed, **granular_kw(args)):
                pass
        except SceneError as e:
            field = "--families, --boxes" if args.boxes else "--families"
            raise _scene_refusal(e, field, "check --families, --boxes and --seed",
                                 {"FamilyRanges.boxes": ("--boxes", "")}) from None
    elif args.kind == "squares":
        from diffgns.scene.recipes import square_scenes

        try:
            for _ in square_scenes(args.n, args.seed, **squares_kw(args)):
                pass
        except ZeroDivisionError as e:
            raise _scene_refusal(e, "--dx", "give a cell size in m > 0") from None
        except SceneError as e:
            raise _scene_refusal(e, "--size", "check the square options") from None
        except ValueError as e:  # numpy: no room to place a square
            raise InputError("--size, --dx", f"squares of {args.size:g} m do not fit the box "
                             f"with cells of {args.dx:g} m ({e})",
                             "give a smaller --size") from None


def check_simulate(args):
    """The scene of ``diffgns simulate`` (built, so validated) and its reference length
    (the column width, m, or None); an InputError names the option at fault."""
    from diffgns.scene.builders import column_collapse
    from diffgns.scene.files import load_scene

    if args.scene:
        try:
            return load_scene(args.scene), None
        except SceneError as e:
            raise InputError(f"--scene {args.scene}", str(e)) from None
    try:
        scene = column_collapse(width=args.width, aspect_ratio=args.aspect_ratio,
                                friction_angle=args.friction_angle,
                                cells_across=args.cells_across)
    except (SceneError, ValueError, ArithmeticError) as e:
        raise _scene_refusal(e, "--aspect-ratio", "check the column options",
                             _SIMULATE_OPTIONS) from None
    return scene, args.width


def model_folder(name: str, field: str = "--model"):
    """The model folder of ``name`` (:func:`diffgns.models.model_dir`: the folder itself or
    a run's ``model/``), a missing or incomplete folder as an InputError on ``field``."""
    from diffgns.models import ModelFolderError, model_dir

    try:
        return model_dir(name)
    except ModelFolderError as e:
        raise InputError(field, e.problem, e.fix) from None
    except FileNotFoundError as e:
        raise InputError(field, str(e), "give a model folder (config.json, params.msgpack) "
                         "or a shipped model name (see models/)") from None


def is_mesh_model(folder) -> bool:
    """Whether the model folder ``folder`` (from :func:`model_folder`) holds a MeshGraphNet
    (its ``model.json`` says ``"kind": "meshgraphnet"``; a particle GNS has ``config.json``,
    a message network a ``model.json`` of another kind)."""
    import json

    meta = Path(folder) / "model.json"
    return meta.is_file() and json.loads(meta.read_text()).get("kind") == "meshgraphnet"


def squares_kw(args) -> dict:
    """Scene keywords of a squares recipe from the ``dataset`` arguments."""
    kw = dict(dx=args.dx, size=args.size,
              friction_angle=(min(args.friction_angles), max(args.friction_angles)))
    if args.domain_length and args.domain_height:
        kw["domain"] = ((0.0, args.domain_length), (0.0, args.domain_height))
    return kw


@contextmanager
def signals_as_exceptions() -> Iterator[None]:
    """Turn SIGTERM into :class:`Interrupted` while the block runs (SIGINT already raises
    KeyboardInterrupt), so clean-up and exit status 143 follow the same path as Ctrl-C."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Interrupted(signum)

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old if old is not None else signal.SIG_DFL)


def report_interrupt(e: BaseException, detail: str = "") -> int:
    """Print the one-line interruption message (unless the interrupted code already printed
    it: ``e.reported``); the exit status (130 SIGINT, 143 SIGTERM)."""
    signum = e.signum if isinstance(e, Interrupted) else int(signal.SIGINT)
    if getattr(e, "reported", False):
        return 128 + signum
    name = signal.Signals(signum).name
    print(f"diffgns: interrupted by {name}" + (f"; {detail}" if detail else ""),
          file=sys.stderr)
    return 128 + signum
