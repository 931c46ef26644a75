"""Pure-JAX explicit MLS-MPM."""
from diffgns.mpm.solver import MPM
from diffgns.mpm.state import MPMParams, MPMState

__all__ = ["MPM", "MPMParams", "MPMState"]
