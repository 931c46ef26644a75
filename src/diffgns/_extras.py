"""Optional dependencies: import one, or say which ``pip install diffgns[<extra>]`` brings it.

The core install (``pip install diffgns``) carries what the MPM, the particle GNS, the hybrid
and the inverse problems need. The rest comes in extras, declared in ``pyproject.toml``:

=========  ==========================================  =========================================
extra      packages                                    used by
=========  ==========================================  =========================================
cfd        scikit-fem, triangle, scipy                 :mod:`diffgns.mesh` CFD ground truth
symbolic   pyoperon, sympy, scipy                      :mod:`diffgns.interpret.symbolic`
                                                       (sympy and scipy also come with jax-md
                                                       and jax; they are listed for clarity)
bench      taichi, torch, torch-geometric              the peer benchmarks in ``benchmarks/``
docs       mkdocs, mkdocstrings[python], mkdocs-material   the docs site
test       test tools + cfd + symbolic                 ``make test``
=========  ==========================================  =========================================

Modules that need an extra import it through :func:`require` instead of a bare ``import``, so a
missing extra fails at once with the command that fixes it, for example::

    triangle = require("triangle", "cfd")
"""
from __future__ import annotations

import importlib
from types import ModuleType

#: extra -> the import names it provides (documentation; :func:`require` checks the extra name).
EXTRAS: dict[str, tuple[str, ...]] = {
    "cfd": ("skfem", "triangle", "scipy"),
    "symbolic": ("pyoperon", "sympy", "scipy"),
    "bench": ("taichi", "torch", "torch_geometric"),
    "docs": ("mkdocs", "mkdocstrings"),
}


class MissingExtraError(ModuleNotFoundError):
    """An optional dependency is not installed; the message names the extra that installs it.

    A ``ModuleNotFoundError`` (so an ``ImportError``): code that catches either still works."""


def require(module: str, extra: str) -> ModuleType:
    """Import ``module`` (a dotted import name such as ``"skfem"`` or ``"pyoperon.sklearn"``),
    or raise :class:`MissingExtraError` (a ``ModuleNotFoundError``) whose message names
    ``pip install diffgns[<extra>]``.

    Only a missing module is translated: an error raised while importing an installed module
    (a broken build, an incompatible version) propagates unchanged, because installing the
    extra again would not fix it.
    """
    if extra not in EXTRAS:
        raise ValueError(f"unknown extra {extra!r}; known extras: {', '.join(sorted(EXTRAS))}")
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        top = module.split(".")[0]
        # err.name is the module that failed; sys.modules[name] = None gives err.name = name
        if err.name is not None and err.name.split(".")[0] != top:
            raise
        raise MissingExtraError(
            f"{module!r} is not installed; it comes with the {extra!r} extra: "
            f"pip install diffgns[{extra}]  (quote it in zsh: pip install 'diffgns[{extra}]')"
        ) from err
