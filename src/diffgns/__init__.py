"""diffgns: differentiable particle and fluid simulation in JAX (MPM, GNS, hybrid).

The public names are imported on first use (PEP 562 ``__getattr__``), so importing a
submodule that needs no JAX (``diffgns.cli``, ``diffgns.errors``) stays fast:
``from diffgns import MPM`` imports JAX and the MPM, ``import diffgns.cli`` does not.
"""
from __future__ import annotations

import importlib
import sys
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the same names, for type checkers and IDEs
    from diffgns.errors import SceneError, UnstableError
    from diffgns.interface import ParticleFrame, Simulator, rollout, rollout_jit, rollout_safe
    from diffgns.mpm import MPM, MPMParams, MPMState
    from diffgns.scene import Body, BoxObstacle, Scene, Wall, Walls
    from diffgns.scene.materials import Elastic, Fluid, Sand
    from diffgns.scene.shapes import Polygon, Rectangle
    from diffgns.trajectory import Trajectory

__version__ = "0.1.0"

if "jax" in sys.modules:  # JAX already imported: ask for host devices before it starts
    from diffgns import hostdevices as _hostdevices

    _hostdevices.request()

__all__ = [
    "ParticleFrame", "Simulator", "rollout", "rollout_jit", "rollout_safe",
    "Body", "BoxObstacle", "Elastic", "Fluid", "MPM", "MPMParams", "MPMState", "Polygon",
    "Rectangle", "Sand", "Scene", "SceneError", "Trajectory", "UnstableError", "Wall", "Walls",
]

#: public name -> the module that defines it
_SOURCES = {
    **dict.fromkeys(("SceneError", "UnstableError"), "diffgns.errors"),
    **dict.fromkeys(("ParticleFrame", "Simulator", "rollout", "rollout_jit", "rollout_safe"),
                    "diffgns.interface"),
    **dict.fromkeys(("MPM", "MPMParams", "MPMState"), "diffgns.mpm"),
    **dict.fromkeys(("Body", "BoxObstacle", "Scene", "Wall", "Walls"), "diffgns.scene"),
    **dict.fromkeys(("Elastic", "Fluid", "Sand"), "diffgns.scene.materials"),
    **dict.fromkeys(("Polygon", "Rectangle"), "diffgns.scene.shapes"),
    "Trajectory": "diffgns.trajectory",
}
assert set(_SOURCES) == set(__all__)


def __getattr__(name: str) -> Any:
    """Import a public name on first access and cache it in the package namespace."""
    module = _SOURCES.get(name)
    if module is None:
        raise AttributeError(f"module 'diffgns' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
