"""Exceptions raised at the edge of the package (scenes, files, CLI)."""
from __future__ import annotations


class SceneError(ValueError):
    """An invalid scene description; the message names the field and the fix."""


class UnstableError(RuntimeError):
    """A simulation left its stability region (CFL exceeded or non-finite state)."""


class InputError(ValueError):
    """Invalid input at the edge: a command-line argument, a file on disk, a dataset recipe.

    The message is one line, ``<field>: <what is wrong>; <fix>``, e.g.
    ``--frames: 0 is not a count >= 1; give the number of frames to simulate``.
    """

    def __init__(self, field: str, problem: str, fix: str = ""):
        self.field, self.problem, self.fix = field, problem, fix
        super().__init__(f"{field}: {problem}" + (f"; {fix}" if fix else ""))

    def __reduce__(self):  # picklable with its three arguments
        return (type(self), (self.field, self.problem, self.fix))


class Interrupted(BaseException):
    """SIGINT or SIGTERM arrived during a command; ``code`` is 128 + the signal number
    (130, 143). A BaseException like :class:`KeyboardInterrupt`, so ``except Exception``
    does not swallow it."""

    def __init__(self, signum: int):
        import signal

        self.signum, self.code = int(signum), 128 + int(signum)
        super().__init__(f"interrupted by {signal.Signals(signum).name}")


def run_module(main, interrupted_hint: str = "") -> None:  # pragma: no cover - exits
    """Entry point of a ``python -m diffgns.<module>`` command: exit with ``main()``'s status;
    an :class:`InputError` becomes one ``error: ...`` line (status 1), an interruption one
    line (plus ``interrupted_hint``) and its status (130 for Ctrl-C)."""
    import sys

    try:
        sys.exit(main())
    except InputError as e:
        sys.exit(f"error: {e}")
    except (Interrupted, KeyboardInterrupt) as e:
        print(f"{e}{interrupted_hint}", file=sys.stderr)
        sys.exit(getattr(e, "code", 130))
