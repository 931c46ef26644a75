"""The ``diffgns`` command's re-execution with glibc's huge-page tunable (diffgns.hugepages)."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from diffgns import cli, hugepages

ON = {"PATH": "/usr/bin"}


@pytest.mark.parametrize("existing, expected", [
    (None, "glibc.malloc.hugetlb=1"),
    ("", "glibc.malloc.hugetlb=1"),
    ("glibc.malloc.arena_max=2", "glibc.malloc.arena_max=2:glibc.malloc.hugetlb=1"),
])
def test_tunable_is_appended_to_the_users(existing, expected):
    assert hugepages.with_tunable(existing) == expected


@pytest.mark.parametrize("environ, glibc, mode, expected", [
    (ON, (2, 36), "madvise", True),
    (ON, (2, 35), "always", True),
    (ON, (2, 34), "madvise", False),  # glibc without the tunable
    (ON, None, "madvise", False),  # not glibc (musl, macOS)
    (ON, (2, 36), "never", False),  # huge pages off in the kernel
    (ON, (2, 36), None, False),  # no THP setting (not Linux)
    ({**ON, "DIFFGNS_HUGEPAGES": "0"}, (2, 36), "madvise", False),  # the user's opt-out
    ({**ON, "DIFFGNS_HUGEPAGES": "1"}, (2, 36), "madvise", True),
    ({**ON, "GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"}, (2, 36), "madvise", False),
    ({**ON, "GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}, (2, 36), "madvise", False),  # no loop
    ({**ON, "GLIBC_TUNABLES": "glibc.malloc.arena_max=2"}, (2, 36), "madvise", True),
])
def test_wanted_follows_the_rules(environ, glibc, mode, expected):
    assert hugepages.wanted(environ, glibc=glibc, mode=mode) is expected


def test_thp_mode_reads_the_bracketed_word(tmp_path):
    f = tmp_path / "enabled"
    f.write_text("always [madvise] never\n")
    assert hugepages.thp_mode(f) == "madvise"
    f.write_text("[always] madvise never\n")
    assert hugepages.thp_mode(f) == "always"
    assert hugepages.thp_mode(tmp_path / "missing") is None


def test_glibc_version_parses_this_machine():
    version = hugepages.glibc_version()
    if sys.platform.startswith("linux") and "glibc" in (os.confstr("CS_GNU_LIBC_VERSION") or ""):
        assert isinstance(version, tuple) and version >= (2, 0)


def _child(env_extra):
    code = ("import os; from diffgns import hugepages; hugepages.reexec(); "
            "print(repr(os.environ.get('GLIBC_TUNABLES')))")
    env = {k: v for k, v in os.environ.items()
           if k not in ("GLIBC_TUNABLES", hugepages.ENV)}
    env.update(env_extra)
    return subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, timeout=120, check=True).stdout.splitlines()


def test_reexec_replaces_the_process_once_with_the_tunable():
    clean = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", hugepages.ENV)}
    if not hugepages.wanted(clean):
        pytest.skip("no glibc >= 2.35 or no transparent huge pages on this machine")
    # one line: the first process never reached its print, the re-executed one did not loop
    assert _child({}) == ["'glibc.malloc.hugetlb=1'"]
    assert _child({"GLIBC_TUNABLES": "glibc.malloc.arena_max=4"}) == [
        "'glibc.malloc.arena_max=4:glibc.malloc.hugetlb=1'"]
    assert _child({hugepages.ENV: "0"}) == ["None"]


def test_the_command_reexecutes_before_it_runs_but_not_when_called(monkeypatch):
    calls = []

    def fake():
        calls.append(True)
        raise RuntimeError("re-executed")

    monkeypatch.setattr(hugepages, "reexec", fake)
    monkeypatch.setattr(sys, "argv", ["diffgns", "simulate", "--column", "--aspect-ratio",
                                      "-1", "--out", "/nonexistent/x"])
    with pytest.raises(RuntimeError, match="re-executed"):
        cli.main()
    assert calls == [True]
    # called with an argv (tests, other programs) it never replaces the caller's process
    assert cli.main(["simulate", "--column", "--aspect-ratio", "-1",
                     "--out", "/nonexistent/x"]) == 2
    assert calls == [True]
    # --help exits in the parser, before any re-execution
    monkeypatch.setattr(sys, "argv", ["diffgns", "--help"])
    assert cli.main() == 0
    assert calls == [True]
