"""Hybrid GNS/MPM simulation: schedule, node/particle hand-off, the hybrid simulator."""
from diffgns.hybrid.simulator import (
    GNS_MODE,
    MPM_MODE,
    Hybrid,
    HybridFrame,
    HybridParams,
    HybridResult,
    HybridState,
    Schedule,
)

__all__ = ["GNS_MODE", "MPM_MODE", "Hybrid", "HybridFrame", "HybridParams", "HybridResult",
           "HybridState", "Schedule"]
