"""Unstructured triangular meshes of a channel with a circular cylinder, made with ``triangle``.

The domain is the rectangle ``[0, length] x [0, height]`` (m) minus an optional disc of radius
``radius`` centred at ``center``. Flow enters at ``x = 0`` and leaves at ``x = length``.

Mesh size is graded with the distance ``d`` (m) to the cylinder surface and, optionally, the
distance ``w`` (m) to a wake line running ``wake_length`` m downstream from the cylinder centre::

    h = min(size_far, size_cylinder + grading * d, size_wake + grading * w)

The boundary is first split into segments of the local size (the cylinder into a regular
polygon of side ~``size_cylinder``), triangulated with a minimum angle of 30 degrees and no
Steiner points on the boundary (so cylinder vertices lie exactly on the circle), then refined
with per-triangle area limits ``sqrt(3)/4 h(d_centroid)^2`` until every triangle meets its limit.

Node types (int32), the classes of the MeshGraphNet cylinder-flow data with our own compact
codes (the original MeshGraphNet enum used NORMAL=0, INFLOW=4, OUTFLOW=5, WALL_BOUNDARY=6;
:data:`MESHGRAPHNET_CODES` maps ours onto it):

=========  ====  ==============================================================
FLUID      0     interior nodes
WALL       1     no-slip: channel walls (y = 0, y = height) and cylinder surface
INFLOW     2     x = 0, parabolic inflow prescribed (corners excluded)
OUTFLOW    3     x = length, do-nothing / p = 0 (corners excluded)
=========  ====  ==============================================================

The four channel corners are WALL (the no-slip value also satisfies the inflow profile there).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from diffgns._extras import require

triangle = require("triangle", "cfd")

FLUID, WALL, INFLOW, OUTFLOW = 0, 1, 2, 3
NODE_TYPE_NAMES = {FLUID: "fluid", WALL: "wall", INFLOW: "inflow", OUTFLOW: "outflow"}
MESHGRAPHNET_CODES = {FLUID: 0, WALL: 6, INFLOW: 4, OUTFLOW: 5}

# segment markers used inside triangle (not exported)
_M_WALL, _M_INFLOW, _M_OUTFLOW, _M_CYL = 1, 2, 3, 4
_MAX_REFINE = 12


@dataclass(frozen=True)
class ChannelGeometry:
    """A channel ``[0, length] x [0, height]`` (m) with a cylinder (``radius = 0``: none).

    Raises:
        ValueError: non-positive channel sizes, negative radius, or a cylinder that does not
            lie strictly inside the channel.
    """

    length: float = 2.2
    height: float = 0.41
    center: tuple[float, float] = (0.2, 0.2)
    radius: float = 0.05

    def __post_init__(self):
        vals = dict(length=self.length, height=self.height, radius=self.radius)
        for name, v in vals.items():
            if not math.isfinite(float(v)):
                raise ValueError(f"channel geometry: {name} must be finite, got {v}")
        if self.length <= 0 or self.height <= 0:
            raise ValueError(f"channel geometry: length and height must be > 0, got "
                             f"{self.length} x {self.height}")
        if self.radius < 0:
            raise ValueError(f"channel geometry: radius must be >= 0, got {self.radius}")
        cx, cy = (float(c) for c in self.center)
        object.__setattr__(self, "center", (cx, cy))
        if self.radius > 0:
            gap = min(cx, self.length - cx, cy, self.height - cy) - self.radius
            if not gap > 0:
                raise ValueError(
                    f"channel geometry: the cylinder (centre {self.center}, radius "
                    f"{self.radius}) must lie strictly inside the channel [0, {self.length}] x "
                    f"[0, {self.height}]; move the centre or reduce the radius")

    @property
    def has_cylinder(self) -> bool:
        return self.radius > 0

    def distance_to_cylinder(self, x: np.ndarray) -> np.ndarray:
        """Distance (m) of points ``x`` (..., 2) to the cylinder surface (inf if none)."""
        if not self.has_cylinder:
            return np.full(np.shape(x)[:-1], np.inf)
        return np.hypot(x[..., 0] - self.center[0], x[..., 1] - self.center[1]) - self.radius


@dataclass(frozen=True)
class ChannelMesh:
    """A triangulated channel.

    Attributes:
        nodes: (N, 2) float64 vertex coordinates, m.
        cells: (C, 3) int32 vertex indices of the C triangles, counter-clockwise.
        node_type: (N,) int32 codes FLUID/WALL/INFLOW/OUTFLOW (module docstring).
        on_cylinder: (N,) bool, the WALL nodes on the cylinder surface.
        geometry: the :class:`ChannelGeometry` meshed.
        sizes: the size parameters used (m), for the record.
    """

    nodes: np.ndarray
    cells: np.ndarray
    node_type: np.ndarray
    on_cylinder: np.ndarray
    geometry: ChannelGeometry
    sizes: dict = field(default_factory=dict)

    @property
    def n_nodes(self) -> int:
        return int(self.nodes.shape[0])

    def cell_areas(self) -> np.ndarray:
        """(C,) triangle areas, m^2."""
        return _areas(self.nodes, self.cells)

    def edges(self) -> np.ndarray:
        """(E, 2) unique undirected mesh edges (i < j)."""
        e = np.concatenate([self.cells[:, [0, 1]], self.cells[:, [1, 2]], self.cells[:, [2, 0]]])
        return np.unique(np.sort(e, axis=1), axis=0)


def _areas(x: np.ndarray, tri: np.ndarray) -> np.ndarray:
    a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    return 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1])
                  - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))


def _graded_line(a, b, size_fn, samples: int = 2001) -> np.ndarray:
    """Points from ``a`` towards ``b`` (``b`` excluded) spaced by the local ``size_fn``.

    The number of intervals is ``ceil(int ds / h(s))``; points sit at equal increments of that
    integral, so the spacing follows ``h`` smoothly.
    """
    a, b = np.asarray(a, float), np.asarray(b, float)
    s = np.linspace(0.0, 1.0, samples)
    inv_h = 1.0 / size_fn(a + (b - a) * s[:, None])
    ds = np.linalg.norm(b - a) / (samples - 1)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (inv_h[1:] + inv_h[:-1]) * ds)])
    n = max(1, int(math.ceil(cum[-1] - 1e-9)))
    ts = np.interp(np.arange(n) * cum[-1] / n, cum, s)
    return a + (b - a) * ts[:, None]


def build_mesh(geometry: ChannelGeometry | None = None, size_cylinder: float = 0.01,
               size_far: float = 0.04, grading: float = 0.3, size_wake: float | None = None,
               wake_length: float = 1.0, min_angle: float = 30.0) -> ChannelMesh:
    """Mesh the channel of ``geometry`` (default: Schäfer-Turek 2D channel).

    Args:
        geometry: the channel and cylinder.
        size_cylinder: target edge length on the cylinder surface, m (> 0).
        size_far: largest edge length away from the cylinder, m (>= size_cylinder).
        grading: growth of the edge length with distance to the cylinder, m/m (> 0).
        size_wake: edge length along the wake line (None: no wake refinement), m.
        wake_length: length of the wake line behind the cylinder centre, m (> 0).
        min_angle: triangle's minimum angle in degrees (0 < angle <= 34).

    Returns:
        a :class:`ChannelMesh`. Without a cylinder the mesh is uniform with ``size_far``.

    Raises:
        ValueError: a non-positive or non-finite size, ``size_far < size_cylinder``, or a
            cylinder too small for ``size_cylinder`` (fewer than 8 segments) -- the message
            names the parameter.
    """
    g = geometry if geometry is not None else ChannelGeometry()
    size_wake = size_far if size_wake is None else size_wake
    for name, v in dict(size_cylinder=size_cylinder, size_far=size_far, grading=grading,
                        size_wake=size_wake, wake_length=wake_length).items():
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"build_mesh: {name} must be a positive number, got {v}")
    if size_far < size_cylinder:
        raise ValueError(f"build_mesh: size_far ({size_far}) must be >= size_cylinder "
                         f"({size_cylinder})")
    if not 0 < min_angle <= 34:
        raise ValueError(f"build_mesh: min_angle must be in (0, 34] degrees, got {min_angle}")
    if size_far > 0.5 * min(g.length, g.height):
        raise ValueError(f"build_mesh: size_far ({size_far}) must be at most half the channel "
                         f"height/length; reduce it")

    def size_fn(x):
        h = np.minimum(size_far, size_cylinder + grading * g.distance_to_cylinder(x))
        if size_wake < size_far and g.has_cylinder:
            cx, cy = g.center
            along = np.clip(x[..., 0] - cx, 0.0, wake_length)
            w = np.hypot(x[..., 0] - cx - along, x[..., 1] - cy)
            h = np.minimum(h, size_wake + grading * w)
        return h

    L, H = g.length, g.height
    corners = [(0.0, 0.0), (L, 0.0), (L, H), (0.0, H)]
    side_markers = [_M_WALL, _M_OUTFLOW, _M_WALL, _M_INFLOW]
    verts, vmark, smark = [], [], []
    for k in range(4):
        pts = _graded_line(corners[k], corners[(k + 1) % 4], size_fn)
        m = np.full(len(pts), side_markers[k])
        m[0] = _M_WALL  # corners are wall nodes
        verts.append(pts)
        vmark.append(m)
        smark.append(np.full(len(pts), side_markers[k]))
    verts, vmark, smark = np.concatenate(verts), np.concatenate(vmark), np.concatenate(smark)
    nb = len(verts)
    segs = np.stack([np.arange(nb), (np.arange(nb) + 1) % nb], axis=1)
    tri_in = dict(vertices=verts, vertex_markers=vmark, segments=segs, segment_markers=smark)
    if g.has_cylinder:
        n = int(math.ceil(2 * math.pi * g.radius / size_cylinder))
        if n < 8:
            raise ValueError(f"build_mesh: size_cylinder ({size_cylinder}) gives only {n} "
                             f"segments on the cylinder of radius {g.radius}; use <= "
                             f"{2 * math.pi * g.radius / 8:.3g}")
        th = 2 * math.pi * np.arange(n) / n
        circ = np.stack([g.center[0] + g.radius * np.cos(th),
                         g.center[1] + g.radius * np.sin(th)], axis=1)
        k = np.arange(n)
        tri_in["vertices"] = np.concatenate([verts, circ])
        tri_in["vertex_markers"] = np.concatenate([vmark, np.full(n, _M_CYL)])
        tri_in["segments"] = np.concatenate([segs, nb + np.stack([k, (k + 1) % n], axis=1)])
        tri_in["segment_markers"] = np.concatenate([smark, np.full(n, _M_CYL)])
        tri_in["holes"] = np.asarray([g.center])

    t = triangle.triangulate(tri_in, f"pq{min_angle:g}a{np.sqrt(3) / 4 * size_far**2:.6g}YQ")
    for _ in range(_MAX_REFINE):  # graded refinement until every area limit is met
        x, tri = t["vertices"], t["triangles"]
        target = np.sqrt(3) / 4 * size_fn(x[tri].mean(axis=1)) ** 2
        if np.all(np.abs(_areas(x, tri)) <= 1.05 * target):
            break
        t["triangle_max_area"] = target
        t = triangle.triangulate(t, f"rpq{min_angle:g}aYQ")

    nodes = np.asarray(t["vertices"], dtype=np.float64)
    cells = np.asarray(t["triangles"], dtype=np.int32)
    flip = _areas(nodes, cells) < 0
    cells[flip] = cells[flip][:, [0, 2, 1]]
    mark = np.asarray(t["vertex_markers"]).ravel()
    node_type = np.full(len(nodes), FLUID, np.int32)
    node_type[(mark == _M_WALL) | (mark == _M_CYL)] = WALL
    node_type[mark == _M_INFLOW] = INFLOW
    node_type[mark == _M_OUTFLOW] = OUTFLOW
    sizes = dict(size_cylinder=size_cylinder, size_far=size_far, grading=grading,
                 size_wake=size_wake, wake_length=wake_length, min_angle=min_angle)
    return ChannelMesh(nodes=nodes, cells=cells, node_type=node_type,
                       on_cylinder=mark == _M_CYL, geometry=g, sizes=sizes)
