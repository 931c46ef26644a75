"""The examples in the ``diffgns`` command's module docstring are commands it accepts."""
import shlex

import pytest

from diffgns import cli


def _examples() -> list[str]:
    """The docstring's ``diffgns ...`` lines, backslash continuations joined."""
    out, cur = [], ""
    for line in cli.__doc__.splitlines():
        s = line.strip()
        if not (s.startswith("diffgns ") or cur):
            continue
        cur = f"{cur} {s.rstrip(chr(92)).strip()}".strip()
        if not s.endswith("\\"):
            out.append(cur)
            cur = ""
    return out


def test_docstring_shows_every_subcommand():
    shown = {shlex.split(e)[1] for e in _examples()}
    sub = next(a for a in cli.build_parser([])._actions if a.dest == "command")
    assert shown == set(sub.choices)


@pytest.mark.parametrize("example", _examples())
def test_docstring_example_parses(example):
    argv = shlex.split(example)[1:]
    args = cli.build_parser(argv).parse_args(argv)
    assert args.command == argv[0] and callable(args.func)
