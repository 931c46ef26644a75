"""MeshGraphNet (Pfaff et al. 2021) for incompressible flow on a triangular mesh.

Reuses the particle GNS network (:class:`~diffgns.graph.networks.EncodeProcessDecode`) on the
mesh's edges instead of a radius graph:

* **graph**: every triangle side, de-duplicated, in both directions (:func:`mesh_edges`);
  meshes are padded to fixed sizes (:func:`pad_mesh`) so different meshes share one jitted
  step; padded edges are masked and padded nodes excluded from the loss.
* **node features**: the normalised velocity (m/s) at the vertex and, with
  ``MeshNetConfig.viscosity_feature``, the normalised log kinematic viscosity of the flow
  (one value per graph, broadcast to its nodes): our datasets draw the Reynolds number and
  the inflow speed independently, so the velocity field and the geometry alone do not fix
  the viscous term. The node type (fluid 0, wall 1, inflow 2, outflow 3, padding 4) enters
  through the network's type embedding, a linear layer on the one-hot type.
* **edge features**: :func:`~diffgns.graph.features.edge_features` of the mesh positions,
  ``[(x_s - x_r) / h, |x_s - x_r| / h]`` with ``h`` the mean edge length of the training
  meshes (m).
* **output**: the normalised velocity change over one frame (2) and the next frame's
  pressure (1, kinematic p/rho in m^2/s^2) at the vertex.
* **rollout**: ``v <- v + dv`` on fluid and outflow nodes; wall and inflow nodes are held at
  their prescribed values (from the initial frame: the inflow profile is steady).

Time is in frames (``frame_dt`` s). Everything here is pure and jit-friendly; the static
configuration is a frozen dataclass, the statistics a pytree.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from diffgns.graph.features import Normalizer, edge_features
from diffgns.graph.networks import EncodeProcessDecode

FLUID, WALL, INFLOW, OUTFLOW, PAD = 0, 1, 2, 3, 4


@dataclasses.dataclass(frozen=True)
class MeshNetConfig:
    """Static MeshGraphNet configuration (reference: latent 128, 15 steps, 2 layers).

    ``noise_std``: std (m/s) of the Gaussian noise added to fluid-node input velocities in
    training; the target is taken against the noisy input, so the model learns to undo it.
    ``viscosity_feature``: the graph's log kinematic viscosity is a node input (needs
    ``MeshStats.viscosity`` and ``MeshGraph.viscosity``). Models saved before it existed load
    with False.
    """

    latent: int = 64
    mp_steps: int = 8
    mlp_layers: int = 2
    noise_std: float = 0.02
    viscosity_feature: bool = True

    def __post_init__(self):
        if self.latent < 1 or self.mp_steps < 1 or self.mlp_layers < 1 or self.noise_std < 0:
            raise ValueError(f"MeshNetConfig: sizes must be >= 1 and noise_std >= 0, got "
                             f"{self}")


@struct.dataclass
class MeshStats:
    """Normalisation statistics: velocity (m/s), target [dv (m/s/frame), p (m^2/s^2)], the
    edge length scale (m) and, for models with the viscosity input, ln(nu) (nu in m^2/s)."""

    velocity: Normalizer
    target: Normalizer
    edge_scale: float = struct.field(pytree_node=False, default=1.0)
    viscosity: Normalizer | None = None


@struct.dataclass
class MeshGraph:
    """A padded mesh: positions (N, 2) m, node_type (N,) int, senders/receivers (E,) int,
    edge_mask (E,) bool, and the flow's kinematic viscosity () m^2/s (NaN when unknown).
    Padding nodes have type PAD and sit at the origin."""

    mesh_pos: jax.Array
    node_type: jax.Array
    senders: jax.Array
    receivers: jax.Array
    edge_mask: jax.Array
    viscosity: jax.Array = struct.field(default_factory=lambda: jnp.asarray(jnp.nan))

    @property
    def predicted(self) -> jax.Array:
        """(N,) bool: nodes whose velocity the model advances (fluid and outflow)."""
        return (self.node_type == FLUID) | (self.node_type == OUTFLOW)


def loss_weights(graph: MeshGraph, near_wall_weight: float = 1.0) -> tuple[jax.Array,
                                                                          jax.Array]:
    """(velocity, pressure) per-node loss weights, (N,) each.

    Velocity errors count on the nodes the model advances (fluid and outflow); pressure
    errors on every mesh vertex (not padding), walls and inflow included: the velocity there
    is held, but the pressure is the model's output, and on the cylinder it is what the lift
    and the Strouhal number are computed from. Until 2026-12-05 the pressure counted on the
    advanced nodes only, so the cylinder's pressure was never trained: given the CFD's own
    velocities, the latent-64 model's pressure lift had 0.36-0.48 of the CFD's amplitude at
    the five held-out Reynolds numbers while its rollouts' wake velocities oscillated at
    0.96-0.98 of the CFD's (Re 165-275) (issue 23). ``near_wall_weight`` multiplies both on
    the first fluid ring off the walls (:func:`near_wall`).
    """
    w_v = graph.predicted.astype(graph.mesh_pos.dtype)
    w_p = (graph.node_type != PAD).astype(graph.mesh_pos.dtype)
    if near_wall_weight != 1.0:
        ring = jnp.where(near_wall(graph), near_wall_weight, 1.0)
        w_v, w_p = w_v * ring, w_p * ring
    return w_v, w_p


def node_loss(graph: MeshGraph, err_v: jax.Array, err_p: jax.Array,
              near_wall_weight: float = 1.0) -> jax.Array:
    """Weighted mean squared normalised error over the velocity components (N, 2) and the
    pressure (N,) of one frame (:func:`loss_weights`); dimensionless."""
    w_v, w_p = loss_weights(graph, near_wall_weight)
    total = jnp.sum(w_v[:, None] * err_v**2) + jnp.sum(w_p * err_p**2)
    return total / jnp.maximum(2.0 * w_v.sum() + w_p.sum(), 1.0)


def divergence_loss(graph: MeshGraph, err_velocity: jax.Array, length: float) -> jax.Array:
    """Mean over the predicted nodes (fluid and outflow) of ``(length * div e)^2``, with
    ``div e`` the :func:`divergence` (1/s, here per unit of ``e``) of a dimensionless
    velocity error field ``e`` (N, 2) (e.g. model minus data over the velocity scale) and
    ``length`` (m) the mesh's edge scale; dimensionless. Zero for an error field without
    divergence, however large; so it weighs the part of an error that breaks continuity
    (flow into a wall, a jet from a stagnation point), which the node loss weighs like any
    other."""
    w = graph.predicted.astype(err_velocity.dtype)
    d = length * divergence(graph, err_velocity)
    return jnp.sum(w * d**2) / jnp.maximum(w.sum(), 1.0)


def near_wall(graph: MeshGraph) -> jax.Array:
    """(N,) bool: predicted (fluid or outflow) nodes joined by a mesh edge to a wall node,
    the first ring off the cylinder and the channel walls (padded edges ignored)."""
    from_wall = (graph.node_type[graph.senders] == WALL) & graph.edge_mask
    hit = jnp.zeros(graph.node_type.shape, bool).at[graph.receivers].max(from_wall)
    return hit & graph.predicted


def divergence(graph: MeshGraph, velocity: jax.Array) -> jax.Array:
    """(N,) discrete divergence (1/s) of nodal velocities (N, 2) m/s: the trace of each
    node's least-squares velocity gradient over its mesh edges,
    ``G_i = (sum_j d_ij d_ij^T)^-1 sum_j d_ij (u_j - u_i)^T`` with ``d_ij = x_j - x_i`` (m)
    (padded edges ignored; 0 on padding nodes and on nodes whose edges do not span the
    plane). Exact for linear fields; on a boundary node one-sided, so compare it between two
    fields on the same mesh (e.g. a model frame against the data frame) rather than against
    zero."""
    s, r, w = graph.senders, graph.receivers, graph.edge_mask.astype(velocity.dtype)
    d = (graph.mesh_pos[s] - graph.mesh_pos[r]).astype(velocity.dtype) * w[:, None]
    du = velocity[s] - velocity[r]
    n = graph.mesh_pos.shape[0]
    m = jax.ops.segment_sum(d[:, :, None] * d[:, None, :], r, n)        # (N, 2, 2) m^2
    b = jax.ops.segment_sum(d[:, :, None] * du[:, None, :], r, n)       # (N, 2, 2) m^2/s
    det = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
    ok = (det > 1e-12 * jnp.maximum(m[:, 0, 0] + m[:, 1, 1], 1e-30) ** 2) & (
        graph.node_type != PAD)
    safe = jnp.where(ok, det, 1.0)
    # trace(M^-1 B) with M^-1 = [[m11, -m01], [-m10, m00]] / det
    tr = (m[:, 1, 1] * b[:, 0, 0] - m[:, 0, 1] * b[:, 1, 0]
          - m[:, 1, 0] * b[:, 0, 1] + m[:, 0, 0] * b[:, 1, 1])
    return jnp.where(ok, tr / safe, 0.0)


def mesh_edges(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Directed edges (senders, receivers) of a triangle mesh: each side once per direction.

    cells (C, 3) int (C triangles) -> two (E,) int32 arrays, E = 2 x number of distinct sides.
    """
    cells = np.asarray(cells)
    if cells.ndim != 2 or cells.shape[1] != 3:
        raise ValueError(f"cells must be (n_cells, 3), got {cells.shape}")
    sides = np.concatenate([cells[:, [0, 1]], cells[:, [1, 2]], cells[:, [2, 0]]])
    sides = np.unique(np.sort(sides, axis=1), axis=0)
    s = np.concatenate([sides[:, 0], sides[:, 1]]).astype(np.int32)
    r = np.concatenate([sides[:, 1], sides[:, 0]]).astype(np.int32)
    return s, r


def pad_mesh(mesh_pos, cells, node_type, n_nodes: int, n_edges: int,
             viscosity: float | None = None) -> MeshGraph:
    """Build the edges of a mesh and pad it to ``n_nodes`` nodes and ``n_edges`` edges;
    ``viscosity`` (m^2/s, > 0) is the flow's, needed by models with the viscosity input."""
    if viscosity is not None and not (np.isfinite(viscosity) and viscosity > 0):
        raise ValueError(f"viscosity must be a positive kinematic viscosity (m^2/s), got "
                         f"{viscosity}")
    mesh_pos, node_type = np.asarray(mesh_pos), np.asarray(node_type)
    s, r = mesh_edges(cells)
    n, e = len(mesh_pos), len(s)
    if n > n_nodes or e > n_edges:
        raise ValueError(f"mesh of {n} nodes / {e} edges exceeds the padding "
                         f"{n_nodes} / {n_edges}")
    pos = np.zeros((n_nodes, 2), mesh_pos.dtype)
    pos[:n] = mesh_pos
    types = np.full(n_nodes, PAD, np.int32)
    types[:n] = node_type
    pad = np.full(n_edges - e, n_nodes - 1 if n_nodes > n else 0, np.int32)
    mask = np.zeros(n_edges, bool)
    mask[:e] = True
    nu = jnp.asarray(np.nan if viscosity is None else viscosity, jnp.result_type(float))
    return MeshGraph(jnp.asarray(pos), jnp.asarray(types),
                     jnp.asarray(np.concatenate([s, pad])),
                     jnp.asarray(np.concatenate([r, pad])), jnp.asarray(mask), nu)


class MeshState(NamedTuple):
    """State of a MeshGraphNet rollout: the padded mesh (static during a rollout), the
    velocity (N, 2) m/s, the velocity held on non-predicted nodes (N, 2) m/s (inflow and
    walls) and the last predicted pressure (N,) m^2/s^2 (0 before the first step)."""

    graph: MeshGraph
    velocity: jax.Array
    held: jax.Array
    pressure: jax.Array


class MeshFrame(NamedTuple):
    """What a MeshGraphNet rollout records at a frame: velocity (N, 2) m/s and pressure
    (N,) m^2/s^2 (predicted with the step into this frame; 0 at frame 0)."""

    velocity: jax.Array
    pressure: jax.Array


class MeshNet:
    """MeshGraphNet: network and statistics; a :class:`diffgns.interface.Simulator`::

        state = model.init(graph, v0)                       # v0 (N, 2) m/s
        frames, final = rollout(model, params, state, n)     # frames.velocity (n+1, N, 2)

    Args:
        config: :class:`MeshNetConfig`.
        stats: :class:`MeshStats`.
        frame_dt: seconds per frame of the data the model learned (for reports).
    """

    def __init__(self, config: MeshNetConfig, stats: MeshStats, frame_dt: float = 0.01):
        if config.viscosity_feature and stats.viscosity is None:
            raise ValueError("MeshNet: viscosity_feature needs MeshStats.viscosity (the ln nu "
                             "normaliser)")
        self.config, self.stats = config, stats
        self.net = EncodeProcessDecode(latent=config.latent, mp_steps=config.mp_steps,
                                       mlp_layers=config.mlp_layers, n_types=PAD + 1, out=3)
        self.frame_dt = float(frame_dt)

    def check_graph(self, graph: MeshGraph) -> None:
        """Raise ValueError if ``graph`` lacks what this model reads (call outside jit)."""
        nu = np.asarray(graph.viscosity)
        if self.config.viscosity_feature and not (np.all(np.isfinite(nu)) and np.all(nu > 0)):
            raise ValueError("this MeshGraphNet reads the flow's viscosity: build the graph "
                             "with pad_mesh(..., viscosity=nu)")

    def _inputs(self, graph: MeshGraph, velocity):
        v = self.stats.velocity.normalize(velocity)
        if self.config.viscosity_feature:
            nu = self.stats.viscosity.normalize(jnp.log(graph.viscosity)).astype(v.dtype)
            v = jnp.concatenate([v, jnp.broadcast_to(nu, v.shape[:-1] + (1,))], axis=-1)
        e = edge_features(graph.mesh_pos, graph.senders, graph.receivers, graph.edge_mask,
                          self.stats.edge_scale)
        return (v, graph.node_type, e, graph.senders, graph.receivers, graph.edge_mask)

    def init_network(self, key: jax.Array, graph: MeshGraph) -> dict:
        return self.net.init(key, *self._inputs(graph, jnp.zeros_like(graph.mesh_pos)))

    def normalized_output(self, params, graph: MeshGraph, velocity) -> jax.Array:
        """(N, 3) normalised [dv_x, dv_y, p] for velocities (N, 2) in m/s."""
        return self.net.apply(params, *self._inputs(graph, velocity))

    def predict(self, params, graph: MeshGraph, velocity):
        """(dv (N, 2) m/s per frame, pressure (N,) m^2/s^2)."""
        out = self.stats.target.denormalize(self.normalized_output(params, graph, velocity))
        return out[:, :2], out[:, 2]

    def advance(self, params, graph: MeshGraph, velocity, held_velocity):
        """One frame: next (velocity (N, 2), pressure (N,)); non-predicted nodes get
        ``held_velocity`` (N, 2)."""
        dv, p = self.predict(params, graph, velocity)
        v = jnp.where(graph.predicted[:, None], velocity + dv, held_velocity)
        return v, p

    def init(self, graph: MeshGraph, v0) -> MeshState:
        """Initial state from the velocity ``v0`` (N, 2) m/s, held on the boundary nodes
        (checks outside jit that ``graph`` has what the model reads)."""
        if not isinstance(graph.viscosity, jax.core.Tracer):
            self.check_graph(graph)
        v0 = jnp.asarray(v0)
        return MeshState(graph, v0, v0, jnp.zeros(v0.shape[:-1], v0.dtype))

    def step(self, params, state: MeshState) -> MeshState:
        """Advance one frame (pure)."""
        v, p = self.advance(params, state.graph, state.velocity, state.held)
        return state._replace(velocity=v, pressure=p.astype(v.dtype))

    def observe(self, state: MeshState) -> MeshFrame:
        return MeshFrame(state.velocity, state.pressure)
