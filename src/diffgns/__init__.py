"""diffgns: differentiable particle and fluid simulation in JAX (MPM, GNS, hybrid)."""
from .errors import SceneError, UnstableError
from .materials import Elastic, Fluid, Sand
from .mpm import MPM, MPMParams, MPMState
from .scene import Body, BoxObstacle, Scene, Wall, Walls
from .shapes import Polygon, Rectangle
from .trajectory import Trajectory

__version__ = "0.1.0"

__all__ = [
    "Body", "BoxObstacle", "Elastic", "Fluid", "MPM", "MPMParams", "MPMState", "Polygon",
    "Rectangle", "Sand", "Scene", "SceneError", "Trajectory", "UnstableError", "Wall", "Walls",
]
