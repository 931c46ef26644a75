"""Exceptions raised at the edge of the package (scenes, files, CLI)."""


class SceneError(ValueError):
    """An invalid scene description; the message names the field and the fix."""


class UnstableError(RuntimeError):
    """A simulation left its stability region (CFL exceeded or non-finite state)."""
