"""Learned simulators on graphs: neighbour lists, features, networks and the particle GNS."""
from diffgns.graph.features import (
    Normalizer,
    ParticleStats,
    edge_features,
    node_features,
    random_walk_noise,
    target_acceleration,
)
from diffgns.graph.gns import GNS, GNSConfig, GNSParams, GNSState
from diffgns.graph.neighbors import NeighborBuilder, did_overflow, edges
from diffgns.graph.networks import MLP, EncodeProcessDecode, init_params

__all__ = [
    "GNS", "GNSConfig", "GNSParams", "GNSState", "MLP", "EncodeProcessDecode", "NeighborBuilder",
    "Normalizer", "ParticleStats", "did_overflow", "edge_features", "edges", "init_params",
    "node_features", "random_walk_noise", "target_acceleration",
]
