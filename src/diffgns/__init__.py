"""diffgns: differentiable particle and fluid simulation in JAX (MPM, GNS, hybrid)."""
from diffgns.errors import SceneError, UnstableError
from diffgns.interface import ParticleFrame, Simulator, rollout, rollout_jit, rollout_safe
from diffgns.mpm import MPM, MPMParams, MPMState
from diffgns.scene import Body, BoxObstacle, Scene, Wall, Walls
from diffgns.scene.materials import Elastic, Fluid, Sand
from diffgns.scene.shapes import Polygon, Rectangle
from diffgns.trajectory import Trajectory

__version__ = "0.1.0"

__all__ = [
    "ParticleFrame", "Simulator", "rollout", "rollout_jit", "rollout_safe",
    "Body", "BoxObstacle", "Elastic", "Fluid", "MPM", "MPMParams", "MPMState", "Polygon",
    "Rectangle", "Sand", "Scene", "SceneError", "Trajectory", "UnstableError", "Wall", "Walls",
]
