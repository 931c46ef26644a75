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


def _subparsers(parser):
    sub = next(a for a in parser._actions if a.dest == "command")
    return sub.choices


def test_every_option_of_every_subcommand_has_help():
    missing = [f"{name} {'/'.join(a.option_strings) or a.dest}"
               for name, p in _subparsers(cli.build_parser([])).items()
               for a in p._actions
               if a.help in (None, "") and a.dest != "help"]
    assert not missing, f"options without help: {missing}"


def test_description_lists_every_subcommand_and_no_none_choice():
    parser = cli.build_parser([])
    for name, p in _subparsers(parser).items():
        assert f"\n  {name} " in parser.description, name
        for a in p._actions:
            assert None not in (a.choices or []), f"{name} {a.option_strings} lists None"


STAGED = [("train_general_gns.sh", {}), ("train_general_radius.sh", {"RADIUS": "0.022"}),
          ("train_column3d_gns.sh", {}), ("train_column_unroll.sh", {"STAGE": "u8"}),
          ("train_column_unroll.sh", {"STAGE": "u16"})]


@pytest.mark.parametrize("script,env", STAGED, ids=[f"{s}-{e}" for s, e in STAGED])
def test_staged_training_scripts_print_commands_the_cli_accepts(script, env, tmp_path):
    """``DRY=1 examples/<script>`` prints its ``diffgns train`` stages; each parses, with
    every data file of the script as its own argument (``--data a.h5 b.h5``)."""
    import os
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    run = subprocess.run(["bash", str(root / "examples" / script)], cwd=tmp_path,
                         env={**os.environ, **env, "DRY": "1", "RUNS": str(tmp_path / "r")},
                         capture_output=True, text=True, check=True)
    cmds = [shlex.split(s) for s in run.stdout.splitlines() if s.startswith("diffgns train")]
    assert cmds, run.stdout
    for argv in cmds:
        args = cli.build_parser(argv[1:]).parse_args(argv[1:])
        assert args.command == "train" and all(" " not in d for d in args.data), argv
    if script == "train_column_unroll.sh":
        (argv,) = cmds
        args = cli.build_parser(argv[1:]).parse_args(argv[1:])
        assert args.data == ["data/columns16_train.h5", "data/columns16_tall.h5"]
        assert args.unroll == {"u8": 8, "u16": 16}[env["STAGE"]]
