"""State hand-off between GNS nodes and MPM particles (used by :mod:`diffgns.hybrid.simulator`).

GNS nodes are cluster means of MPM particles (:func:`diffgns.graph.data.coarse_grain_map`).

* MPM -> GNS: node position = mean position of its particles (what the GNS was trained on).
* GNS -> MPM: every particle follows the affine field of its node: with ``r`` its offset
  from the node before the frame, it moves by ``u_k + (grad u)_k r``, so a cluster
  stretches and shears as the node field does and its mean stays the node ("affine", the
  default). Its velocity is its node's plus the deviation from its node's mean velocity
  that it had before the frame, ``v_k + (v_p - mean_k v)``: the sub-node velocity structure
  of the last MPM frame (a stretching front's leading particles faster than its trailing
  ones) is carried through the GNS segment, and each cluster's mean velocity is the node's.
  The GNS knows nothing below the node scale, and the node field's least-squares gradient,
  a fit over neighbours 2.5 node spacings around, flattened it: at a thin front whose
  particles spread from 0.72 to 1.13 m/s the extrapolated velocities spread from 0.88 to
  0.96 m/s, and each hand-off back to the MPM slowed the front (hybrid guide, "The
  particles' own velocity structure"). "rigid" moves every particle by its node's
  displacement and gives it the node's velocity (clusters keep their shape; what published
  research code did). The APIC matrix
  C of a particle is the velocity gradient of the node field at its node, and the deformation
  gradient F is either reset to I (stress-free, what published research code did), carried
  unchanged from the last MPM frame, or updated with the isochoric part of the displacement
  gradient of the node field, ``F <- (I + grad u) F / sqrt(det(I + grad u))``
  ("reconstruct"), after which the MPM's return mapping
  projects it back onto the yield surface. Where ``det(I + grad u)`` is outside
  :data:`RECONSTRUCT_JACOBIAN` the particle keeps its F, and the hybrid counts it
  (``HybridFrame.f_kept``).

Gradients of the node fields are ridge-regularised least-squares fits over the GNS graph's
edges: for node i with neighbours j, ``G_i = B_i (A_i + r tr(A_i) I)^-1`` with
``B_i = sum_j du_ij dX_ij^T``, ``A_i = sum_j dX_ij dX_ij^T`` and ``r`` = :data:`LSQ_RIDGE`.
Without the ridge, a node whose neighbours lie nearly on a line (a deposit spread one node
thick) divides the GNS's noise across the line by the neighbours' tiny spread across it;
the resulting steep gradients, extrapolated over the cluster as particle velocities, lifted
resting deposits in the MPM frames that followed (:data:`LSQ_RIDGE`).

**Each particle stays with its cluster, inside the box** (:func:`keep_inside`). The affine
map extrapolates the node's gradient to the whole cluster, and nothing in it knows about
walls. Measured (``gns_cg16_pfn``, column a = 2.5, phi = 24 deg, GNS-only map over 120
frames): frame after frame the least-squares gradient of a spreading flow stretched the
clusters (one grew from 1.6 to 6.2 cm across while its node sat 3 cm from the left wall),
and the particles on the wall side of a node were carried through the wall and clamped
onto it: 4 particles on a wall at frame 40, 47 at frame 90, on the left wall and the floor.
The map is therefore limited per cluster: the affine term is scaled by the largest factor
in [0, 1] that keeps all the cluster's particles inside (falling back towards the rigid map
only as far as needed); where even the rigid offsets would cross a wall (a node close to a
wall), the cluster's offsets are then contracted towards the node by the largest factor in
[0, 1] that fits. Both factors scale offsets about the node, so the cluster mean stays the
node. "Inside" is the box inset by half the MPM particle spacing (where the MPM's fill puts
the first particles; a particle already closer is not pushed further): with the box itself
as the limit, the stretched clusters still parked their wall-side particles 1 micrometre
from the walls (11-15 of them on that case), unclamped but on the wall. A clamp remains only
as a safety net for a node outside the box, and it is counted (:mod:`diffgns.clamp`).
Box obstacles limit the affine term the same way, and a particle whose own path then enters
one stops at its face, counted like a clamp (:func:`keep_inside`).

**Particles at a boundary move along it** (:func:`boundary_slip`): within
:data:`BOUNDARY_SLIP_CELLS` MPM cells of a wall or obstacle face, a mapped particle's
velocity into it is removed, as the MPM's grid removes it from its own particles; the mapped
velocity (measured with the node field's extrapolated one) otherwise drove a sliding front
into the frictional floor at every hand-off to the MPM.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from diffgns.clamp import ClampCount, clamp_positions
from diffgns.graph.features import obstacle_distances
from diffgns.mpm.boundaries import normal_condition

HANDOFFS = ("reset", "carry", "reconstruct")
# "reconstruct" trusts the node field's displacement gradient while it changes a cluster's
# area by at most this factor either way in one frame; outside (a folded or exploding
# node field) no isochoric part exists or means anything, so the particle keeps its F and is
# counted (never a silently clipped Jacobian, which compresses the skeleton instead)
RECONSTRUCT_JACOBIAN = (0.25, 4.0)
PARTICLE_MAPS = ("affine", "rigid")
# Ridge of the node-field gradients (:func:`lsq_gradient`), as a fraction of tr(A). Plain
# least squares (the map until 2026-12-07) divided by the spread of a node's neighbours in
# its thinnest direction: on a deposit spread one node thick, GNS noise across the layer
# became steep vertical gradients, and the affine map's particle velocities v + (grad v) r
# lifted resting deposits (hybrid K=8 M=2 on two held-out long-box squares: 0.131 and 0.239
# of the displacement against the GNS alone's 0.119 and 0.142; with this ridge 0.046 and
# 0.031, and K=8 M=2 never worse than the GNS alone on the 72 held-out cases: hybrid guide).
LSQ_RIDGE = 0.02
# How far from a wall or obstacle face (in MPM cells) the map removes a particle's velocity
# into it (:func:`boundary_slip`): the reach of the MPM's quadratic B-spline, so every
# particle that transfers momentum to a boundary grid node. The node field's velocity is a
# cluster mean, one node thick at a flow's front; extrapolated to the particles on the
# floor it left them moving into it, and the MPM's Coulomb floor took mu times that normal
# speed off their tangential speed in the first MPM frame: validation case 0 (a square mass
# sliding out), K2M8:W150, the front's 10 nodes lost 9.4 mm/s against the MPM's own
# deceleration in the first MPM frame, 3.8 mm/s with 1 cell, 0.1 mm/s with 1.5 (hybrid guide).
BOUNDARY_SLIP_CELLS = 1.5


def node_means(x: jax.Array, cluster: jax.Array, counts: jax.Array) -> jax.Array:
    """(M, 2) cluster means of particle positions ``x`` (2, N); ``cluster`` (N,) int in
    [0, M), ``counts`` (M,) particles per cluster."""
    s = jax.ops.segment_sum(x.T, cluster, num_segments=counts.shape[0])
    return s / counts[:, None].astype(x.dtype)


def lsq_gradient(u: jax.Array, x: jax.Array, senders, receivers, mask,
                 ridge: float = LSQ_RIDGE) -> jax.Array:
    """(M, 2, 2) ridge-regularised least-squares gradient ``G[i, a, b] = d u_a / d x_b`` of a
    node field: ``G_i = B_i (A_i + ridge tr(A_i) I)^-1`` with ``A_i = sum_j dX_ij dX_ij^T``
    and ``B_i = sum_j du_ij dX_ij^T`` over node i's edges (see :data:`LSQ_RIDGE`).

    Args:
        u: (M, 2) field values at the nodes (e.g. velocity, m/s, or displacement, m).
        x: (M, 2) node positions, m.
        senders, receivers, mask: (E,) graph edges (padding edges have mask False).
        ridge: the ridge as a fraction of ``tr(A_i)`` (>= 0; 0: plain least squares).

    A node with no edge to another node gets a zero gradient (self-edges carry no ``dX``).
    A well-spread neighbourhood's gradient is shrunk by about ``1 / (1 + 2 ridge)``; a
    direction its edges hardly sample (a layer one node thick, or a single neighbour) gets
    next to none, where plain least squares divides the noise across the layer by the
    layer's tiny spread (with ``ridge = 0`` such a node gets a zero gradient).
    """
    if not ridge >= 0:
        raise ValueError(f"ridge must be >= 0 (a fraction of tr A), got {ridge!r}")
    w = mask.astype(x.dtype)[:, None]
    dx = (x[senders] - x[receivers]) * w
    du = (u[senders] - u[receivers]) * w
    m = x.shape[0]
    A = jax.ops.segment_sum(dx[:, :, None] * dx[:, None, :], receivers, num_segments=m)
    B = jax.ops.segment_sum(du[:, :, None] * dx[:, None, :], receivers, num_segments=m)
    tr = A[:, 0, 0] + A[:, 1, 1]
    A = A + ridge * tr[:, None, None] * jnp.eye(2, dtype=A.dtype)
    det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
    ok = det > 1e-6 * tr ** 2  # false where A = 0 (no neighbour)
    safe_det = jnp.where(ok, det, 1.0)
    inv = jnp.stack([jnp.stack([A[:, 1, 1], -A[:, 0, 1]], -1),
                     jnp.stack([-A[:, 1, 0], A[:, 0, 0]], -1)], -2) / safe_det[:, None, None]
    G = jnp.einsum("mab,mbc->mac", B, inv)
    return jnp.where(ok[:, None, None], G, 0.0)


def segment_entry(base, d, boxes, exempt=None):
    """(N,) largest t in [0, 1] such that ``base + t d`` stays out of every box (2D).

    ``base``, ``d``: (2, N) start point and step of each particle's segment, m. ``boxes``:
    (K, 4) ``[x0, y0, x1, y1]`` (m; K may be 0, and boxes parked far away never bind).
    A segment that enters the open interior of a box stops at its entry point (on the face);
    a base already inside a box gives 0 (this limit cannot move it out). ``exempt``: (K, N)
    bool, boxes a particle is exempt from (it was already inside).
    """
    if boxes.shape[0] == 0:
        return jnp.ones(base.shape[1], base.dtype)
    lo, hi = boxes[:, :2, None], boxes[:, 2:, None]  # (K, 2, 1)
    b, dd = base[None], d[None]  # (1, 2, N)
    moving = dd != 0
    safe = jnp.where(moving, dd, 1.0)
    t1, t2 = (lo - b) / safe, (hi - b) / safe
    inside_slab = (b > lo) & (b < hi)
    near = jnp.where(moving, jnp.minimum(t1, t2), jnp.where(inside_slab, -jnp.inf, jnp.inf))
    far = jnp.where(moving, jnp.maximum(t1, t2), jnp.where(inside_slab, jnp.inf, -jnp.inf))
    t_in, t_out = near.max(axis=1), far.min(axis=1)  # (K, N)
    inside = jnp.all(inside_slab, axis=1)
    hits = (t_in < t_out) & (t_in < 1.0) & (t_out > 0.0)
    t = jnp.where(inside, 0.0, jnp.where(hits, jnp.clip(t_in, 0.0, 1.0), 1.0))
    if exempt is not None:
        t = jnp.where(exempt, 1.0, t)
    return jnp.min(t, axis=0)


def keep_inside(x_node, offset, step, cluster, n_nodes: int, lo, hi, x_old=None,
                margin: float = 0.0, obstacles=None):
    """Per-cluster limit of a particle map so that every particle stays inside the box.

    The map puts particle ``p`` of cluster ``k`` at ``x_node[k] + offset[p] + s_k step[p]``
    (``offset``: the rigid offset from the node, ``step``: the affine term). This returns the
    positions with the largest ``s_k`` in [0, 1] that keeps all of cluster ``k``'s particles
    inside their bounds (the affine term falls back towards rigid only as far as needed), and
    where even the rigid offsets would leave the box, the cluster's offsets are then scaled by
    the largest ``lam_k`` in [0, 1] that fits (the cluster contracts towards its node, which
    stays its mean). A cluster that fits is mapped unchanged (s = lam = 1).

    ``s_k`` and ``lam_k`` are chosen axis by axis (the box's bounds are separable, and each
    axis's offsets sum to zero over a cluster): a cluster resting on the floor keeps its
    stretch along the floor. One factor over all axes (the limiter of 2026-12-01 to 12-03)
    took the front clusters' horizontal stretch away whenever one particle touched the
    floor's margin, and the GNS's runout fell by 0.12 m on a = 2.75 (issue 21).

    A particle's bounds are the box inset by ``margin`` (a material point's centre stays half
    a particle spacing from a wall, as in the MPM's initial fill), widened to include where
    the particle already was (``x_old``) and its node, so the map never pushes a particle
    further into the margin than it is, and a node inside the margin stays feasible. The
    bounds are never closer to a wall than 1e-6 of the box size, so rounding can never put
    a limited particle outside.

    Box ``obstacles`` are walls too, handled in two ways. The affine term's ``s_k`` also keeps
    every particle's path from its rigid position out of them (grown by ``margin``;
    :func:`segment_entry`; one factor for both axes, as the region outside an obstacle is
    not a product of intervals). And after the box's limits, each particle whose own path
    from where it was (``x_old``; without it, from its node) enters a grown obstacle stops at
    the entry, and is counted like a clamp: the cluster then keeps its shape, and its mean is
    no longer exactly its node (the next MPM frame's nodes are the particle means again). A
    particle that was already inside a grown obstacle is exempt from it. Without any
    obstacle limit, GNS frames pushed particles into obstacles and the next MPM frames threw
    them out (a hybrid K=4 M=4 on a held-out obstacle scene: 5-14 particles inside, then
    clamps of up to 9 mm and a final error 12 times the GNS alone's, issue 21). Until
    2026-12-07 the obstacles also took part in ``lam``, contracting a cluster towards its
    node: that compressed clusters beside an obstacle (4x denser, they then sank through the
    sand in the MPM frames), and a node inside an obstacle (where the MPM's own cluster means
    often are: a cluster's particles on two faces of it) collapsed its 16 particles onto one
    point inside the solid, which sank through it (hybrid guide, "a node inside an
    obstacle").

    Args:
        x_node: (2, N) new position of each particle's node (inside the box), m.
        offset, step: (2, N) rigid offset and affine term of each particle, m.
        cluster: (N,) node index; n_nodes: M.
        lo, hi: (2,) box, m.
        x_old: (2, N) particle positions before the map, m (None: not used).
        margin: inset of the box and growth of the obstacles, m (>= 0).
        obstacles: (K, 4) box obstacles ``[x0, y0, x1, y1]``, m (None or K = 0: none).

    Returns:
        ``(positions, stops)``: (2, N) positions, m, and the
        :class:`~diffgns.clamp.ClampCount` of the particles stopped on an obstacle's face.
    """
    eps = 1e-6 * jnp.max(hi - lo)
    lo_p = jnp.broadcast_to((lo + margin)[:, None], x_node.shape)
    hi_p = jnp.broadcast_to((hi - margin)[:, None], x_node.shape)
    for y in (x_node,) if x_old is None else (x_node, x_old):
        lo_p, hi_p = jnp.minimum(lo_p, y), jnp.maximum(hi_p, y)
    lo_p = jax.lax.stop_gradient(jnp.maximum(lo_p, (lo + eps)[:, None]))
    hi_p = jax.lax.stop_gradient(jnp.minimum(hi_p, (hi - eps)[:, None]))

    def largest(base, d):
        """(d, N) largest t in [0, 1] with lo_p <= base + t d <= hi_p, axis by axis (0 where
        base itself is outside on that axis)."""
        room = jnp.where(d > 0, hi_p - base, lo_p - base)
        moving = d != 0
        t = jnp.where(moving, room / jnp.where(moving, d, 1.0), jnp.inf)
        inside = (base >= lo_p) & (base <= hi_p)
        return jnp.where(inside, jnp.clip(t, 0.0, 1.0), 0.0)

    def per_cluster(t):  # (d, N) -> (d, M): the smallest over each cluster, axis by axis
        return jax.vmap(lambda r: jax.ops.segment_min(r, cluster, num_segments=n_nodes))(t)

    if obstacles is None:
        obstacles = jnp.zeros((0, 4), x_node.dtype)
    grown = jax.lax.stop_gradient(obstacles + margin * jnp.asarray([-1.0, -1.0, 1.0, 1.0],
                                                                   obstacles.dtype))
    start = x_node if x_old is None else x_old
    exempt = jnp.all(  # (K, N): the particle (or its node) is already inside a grown obstacle
        (start[None] > grown[:, :2, None]) & (start[None] < grown[:, 2:, None]), axis=1)

    def clear(base, d):  # box limits axis by axis, then the obstacles' one factor
        return jnp.minimum(largest(base, d), segment_entry(base, d, grown, exempt)[None])

    rigid = x_node + offset
    s = per_cluster(clear(rigid, step))
    off = offset + s[:, cluster] * step
    lam = per_cluster(largest(x_node, off))
    x = x_node + lam[:, cluster] * off
    # obstacles: each particle stops where its own path from where it was enters one
    t = segment_entry(start, x - start, grown, exempt)
    stopped = jnp.where(t < 1.0, start + t * (x - start), x)  # exactly x where not stopped
    return stopped, ClampCount.between(x, stopped, axis=0)


def within_reach(r: jax.Array, cluster: jax.Array, counts: jax.Array, reach: float | None):
    """(2, N) particle offsets ``r`` from their node, each shortened to at most ``reach`` m
    (its direction kept), then re-centred so that they still sum to zero over each cluster
    (``cluster`` (N,) node index, ``counts`` (M,) particles per node).

    The affine map evaluates a node's linear field (gradients fitted over the node's graph
    edges, all shorter than the GNS radius) at each particle's offset. Clusters are fixed at
    the start, and a flow shears them apart: a particle can end up far beyond the reach of
    its node's fit (test2 case 20, two thrown masses: 26% of the particles more than one
    radius from their node at the last frame, up to 0.44 m), where the linear field is an
    extrapolation. There ``(grad u) r`` grows with ``|r|`` (as did ``(grad v) r`` when the
    map extrapolated velocities too), and through GNS frame after GNS frame they launched
    strings of particles across the box (hybrid guide, "Particles beyond their node's
    reach").
    ``reach = None``: no limit (the offsets unchanged).
    """
    if reach is None:
        return r
    if not reach > 0:
        raise ValueError(f"reach must be > 0 m (or None), got {reach!r}")
    sq = jnp.sum(r * r, axis=0)
    far = sq > reach * reach  # the square root only where it is taken (a finite gradient at r = 0)
    short = r * jnp.where(far, reach / jnp.sqrt(jnp.where(far, sq, 1.0)), 1.0)
    mean = jax.ops.segment_sum(short.T, cluster, num_segments=counts.shape[0])
    mean = mean / counts[:, None].astype(r.dtype)
    return short - mean[cluster].T


def boundary_slip(x, v, lo, hi, band: float, obstacles=None):
    """Particle velocities with the component into a nearby boundary removed (slip).

    A particle within ``band`` of a box wall, or outside a box obstacle within ``band`` of
    it, loses the component of its velocity into that wall or obstacle: along the normal
    from the obstacle's nearest surface point
    (:func:`diffgns.graph.features.obstacle_distances`), by the MPM's slip condition
    (:func:`diffgns.mpm.boundaries.normal_condition`). The tangential component and every
    velocity pointing away are unchanged.
    The MPM's own particles at a boundary carry no such component (its grid removes it
    every substep); a mapped velocity, its node's (a cluster mean) plus a deviation carried
    from an earlier frame, does, and a frictional boundary would take ``mu`` times it off
    the tangential speed.

    Args:
        x, v: (2, N) particle positions (m) and velocities (m/s).
        lo, hi: (2,) box bounds, m. band: distance, m (0: no change).
        obstacles: (K, 4) box obstacles ``[x0, y0, x1, y1]``, m (None or K = 0: none).
    Returns:
        (2, N) velocities, m/s.
    """
    if band <= 0:
        return v
    into = ((x - lo[:, None] < band) & (v < 0)) | ((hi[:, None] - x < band) & (v > 0))
    v = jnp.where(into, jnp.zeros_like(v), v)  # the box walls, axis by axis
    if obstacles is None or obstacles.shape[0] == 0:
        return v
    # the nearest obstacle's distance and outward normal (the GNS's obstacle features, with
    # the band as their radius), then the MPM's own slip condition along that normal
    feat = obstacle_distances(x.T, obstacles, band)  # (N, 3): [d / band, (1 - d / band) n]
    s, w = feat[:, 0], 1.0 - feat[:, 0]
    near = (s >= 0) & (s < 1)
    n = jnp.where(near, feat[:, 1:].T / jnp.where(near, w, 1.0), 0.0)  # (2, N)
    slid = jnp.stack(normal_condition(tuple(v), tuple(n), "slip"))
    return jnp.where(near, slid, v)


def particles_from_nodes(state, cluster, x_node, disp, vel, grad_v, grad_u, handoff: str,
                         lo, hi, particle_map: str = "affine", margin: float = 0.0,
                         obstacles=None, reach: float | None = None,
                         slip_band: float = 0.0):
    """MPM state after a GNS frame that moved node ``k`` from ``x_node[k]`` by ``disp[k]``.

    Args:
        state: the :class:`~diffgns.mpm.state.MPMState` before the frame.
        cluster: (N,) node index of every particle.
        x_node: (M, 2) node positions before the frame (the cluster means of ``state.x``), m.
        disp: (M, 2) node displacement over the frame, m. vel: (M, 2) node velocity, m/s.
        grad_v: (M, 2, 2) node velocity gradient, 1/s: every particle's APIC matrix C.
            grad_u: (M, 2, 2) displacement gradient over the frame.
        handoff: one of :data:`HANDOFFS`. lo, hi: (2,) domain bounds, m.
        particle_map: one of :data:`PARTICLE_MAPS`.
        margin: how far from the walls (m) the map keeps particles that were not closer
            already (:func:`keep_inside`; the hybrid uses half the MPM particle spacing).
        obstacles: (K, 4) box obstacles ``[x0, y0, x1, y1]`` the map keeps particles out
            of, m (None: none).
        reach: the affine map's reach, m: the offsets it applies the displacement
            gradient to are shortened to at most this (:func:`within_reach`; the hybrid
            passes the GNS radius). None: unlimited.
        slip_band: particles this close to a wall or obstacle face lose their velocity
            into it (:func:`boundary_slip`; the hybrid passes
            :data:`BOUNDARY_SLIP_CELLS` MPM cells), m. 0: none.

    Returns:
        ``(state, ClampCount, kept)``: the new particle state, every particle inside the box
        by :func:`keep_inside`; the count is of a final safety clamp, which moves a particle
        only if its node itself is outside the box (the GNS counts that clamp of the node),
        and of the particles :func:`keep_inside` stopped on an obstacle's face.
        ``kept``: int32, particles whose F "reconstruct" left unchanged because the node
        field's area change ``det(I + grad u)`` was outside :data:`RECONSTRUCT_JACOBIAN`
        (always 0 for the other hand-offs).
    """
    if particle_map not in PARTICLE_MAPS:
        raise ValueError(f"particle_map must be one of {PARTICLE_MAPS}, got {particle_map!r}")
    Gu = jnp.moveaxis(grad_u[cluster], 0, -1)  # (2, 2, N)
    Gv = jnp.moveaxis(grad_v[cluster], 0, -1)
    node_new = (x_node + disp)[cluster].T  # (2, N)
    r = state.x - x_node[cluster].T  # (2, N) offset from the node before the frame
    m = x_node.shape[0]
    counts = jax.ops.segment_sum(jnp.ones(cluster.shape, r.dtype), cluster, num_segments=m)
    step = jnp.einsum("abn,bn->an", Gu, within_reach(r, cluster, counts, reach)) \
        if particle_map == "affine" else jnp.zeros_like(r)
    x, stops = keep_inside(node_new, r, step, cluster, m, lo, hi, state.x, margin, obstacles)
    v = vel[cluster].T
    if particle_map == "affine":  # each particle keeps its deviation from its node's mean
        v = v + state.v - node_means(state.v, cluster, counts)[cluster].T
    x, clamp = clamp_positions(x, lo[:, None], hi[:, None], axis=0)
    v = boundary_slip(x, v, lo, hi, slip_band, obstacles)
    clamp = clamp.merge(stops)
    C = Gv
    kept = jnp.zeros((), jnp.int32)
    if handoff == "reset":
        F = jnp.broadcast_to(jnp.eye(2, dtype=state.F.dtype)[:, :, None], state.F.shape)
    elif handoff == "carry":
        F = state.F
    elif handoff == "reconstruct":
        L = jnp.eye(2, dtype=state.F.dtype)[:, :, None] + Gu
        # Isochoric part only: a 1% volumetric error of the coarse node field would load a
        # stiff granular skeleton with ~10x its lithostatic pressure.
        det = L[0, 0] * L[1, 1] - L[0, 1] * L[1, 0]
        lo_j, hi_j = RECONSTRUCT_JACOBIAN
        credible = (det >= lo_j) & (det <= hi_j)
        L = L / jnp.sqrt(jnp.where(credible, det, 1.0))
        F = jnp.where(credible, jnp.einsum("abn,bcn->acn", L, state.F), state.F)
        kept = jnp.sum(~credible, dtype=jnp.int32)
    else:
        raise ValueError(f"handoff must be one of {HANDOFFS}, got {handoff!r}")
    return state.replace(x=x.astype(state.x.dtype), v=v.astype(state.v.dtype),
                         C=C.astype(state.C.dtype), F=F.astype(state.F.dtype)), clamp, kept


def specific_energy(x_prev: jax.Array, x: jax.Array, weights: jax.Array, gravity: jax.Array,
                    frame_dt: float) -> jax.Array:
    """Mechanical energy per unit mass, J/kg: kinetic (from the backward difference of node
    positions (M, 2) over ``frame_dt`` s) plus gravitational potential ``-g . x``, weighted by
    ``weights`` (M,) (particles per node)."""
    v = (x - x_prev) / frame_dt
    e = 0.5 * jnp.sum(v * v, -1) - x @ gravity
    return jnp.sum(weights * e) / jnp.sum(weights)
