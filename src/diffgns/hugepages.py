"""Transparent huge pages for XLA's CPU buffers: the ``diffgns`` command turns them on.

XLA's CPU runtime allocates an executable's whole temporary buffer at every call and frees
it after (3.5 GB for a reference GNS training call at N = 2,025); glibc serves allocations
that large with a fresh ``mmap``, so every call faults in and zeroes them again, 4 KiB at a
time: ~857,000 minor page faults and ~2.1 s of system CPU time per 4-step training call
(docs/performance.md, "Where a training step's time goes"). glibc's tunable
``glibc.malloc.hugetlb=1`` (glibc >= 2.35) makes malloc advise transparent huge pages for its
mappings, so those faults come 2 MiB at a time. The tunable is read once, when the process
starts: no library call can set it for a running interpreter. So the ``diffgns`` command
re-executes itself with it (:func:`reexec`) before it imports JAX, when all of these hold:

* Linux with glibc >= 2.35 and transparent huge pages ``always`` or ``madvise``
  (``/sys/kernel/mm/transparent_hugepage/enabled``);
* ``DIFFGNS_HUGEPAGES`` is not ``0`` (``0`` keeps glibc's defaults; any other value, or
  unset, allows the re-execution);
* ``GLIBC_TUNABLES`` does not already set ``glibc.malloc.hugetlb`` (the user's choice wins,
  and the re-executed process finds it set, so it never loops).

A Python program that imports diffgns gets the same by starting its interpreter with
``GLIBC_TUNABLES=glibc.malloc.hugetlb=1`` (or calling :func:`reexec` first thing). On a GPU
the tunable only concerns host allocations; nothing else changes.
"""
from __future__ import annotations

import os
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

#: environment variable: ``0`` keeps glibc's default allocation (no re-execution)
ENV = "DIFFGNS_HUGEPAGES"
#: the glibc tunable set by :func:`reexec`
TUNABLE = "glibc.malloc.hugetlb"
#: the first glibc with ``glibc.malloc.hugetlb``
MIN_GLIBC = (2, 35)
#: where Linux says whether transparent huge pages are available
THP_SETTING = Path("/sys/kernel/mm/transparent_hugepage/enabled")


def glibc_version() -> tuple[int, int] | None:
    """The C library's version as ``(major, minor)`` if it is glibc, else ``None``."""
    try:
        text = os.confstr("CS_GNU_LIBC_VERSION") or ""
    except (AttributeError, ValueError, OSError):
        return None
    name, _, version = text.partition(" ")
    parts = version.split(".")
    if name != "glibc" or len(parts) < 2 or not all(p.isdigit() for p in parts[:2]):
        return None
    return int(parts[0]), int(parts[1])


def thp_mode(setting: Path = THP_SETTING) -> str | None:
    """The kernel's transparent-huge-page mode (``always``, ``madvise`` or ``never``: the
    bracketed word of ``setting``), or ``None`` when the file is missing or unreadable."""
    try:
        text = setting.read_text()
    except OSError:
        return None
    start, end = text.find("["), text.find("]")
    return text[start + 1:end] if 0 <= start < end else None


def with_tunable(existing: str | None) -> str:
    """``GLIBC_TUNABLES`` with ``glibc.malloc.hugetlb=1`` appended to ``existing`` (a
    colon-separated list of ``name=value``)."""
    return f"{existing}:{TUNABLE}=1" if existing else f"{TUNABLE}=1"


def wanted(environ: Mapping[str, str] | None = None,
           glibc: tuple[int, int] | None | bool = True,
           mode: str | None | bool = True) -> bool:
    """Whether :func:`reexec` should re-execute this process (the rules of the module
    docstring). ``glibc`` and ``mode`` default to this machine's (:func:`glibc_version`,
    :func:`thp_mode`); tests pass them."""
    env = os.environ if environ is None else environ
    if env.get(ENV, "").strip() == "0":
        return False
    if f"{TUNABLE}=" in env.get("GLIBC_TUNABLES", ""):
        return False
    version = glibc_version() if glibc is True else glibc
    if not isinstance(version, tuple) or version < MIN_GLIBC:
        return False
    kernel = thp_mode() if mode is True else mode
    return kernel in ("always", "madvise")


def reexec(argv: Sequence[str] | None = None) -> None:
    """Replace this process by itself with ``GLIBC_TUNABLES=...glibc.malloc.hugetlb=1`` when
    :func:`wanted`; otherwise return. Call it before JAX starts (the new process starts
    from scratch, so anything computed before is lost). ``argv``: the command line to run
    again (default ``sys.orig_argv``, the interpreter's own, so ``diffgns ...`` and
    ``python -m diffgns.cli ...`` both come back as they were started)."""
    if not wanted():
        return
    args = list(sys.orig_argv if argv is None else argv)
    if not args:
        return
    env = dict(os.environ)
    env["GLIBC_TUNABLES"] = with_tunable(env.get("GLIBC_TUNABLES"))
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *args[1:]], env)
