"""Pure-JAX explicit MLS-MPM."""
from .solver import MPM
from .state import MPMParams, MPMState

__all__ = ["MPM", "MPMParams", "MPMState"]
