"""Grid boundary conditions: box walls and static rigid obstacles, 2D or 3D.

Conditions act on grid node velocities (d, nx, ny[, nz]) after the gravity update. A node
moving *into* a boundary (v . n < 0, n the outward normal of the boundary surface)
loses its normal velocity; a frictional boundary also reduces the tangential speed by
mu |v_n| (Coulomb), never reversing it; a sticky boundary stops the node.

Walls are ordered as :data:`diffgns.scene.elements.WALL_NAMES_3D`: left/right (x),
bottom/top (y), back/front (z, 3D only).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.mpm import linalg as la


def normal_condition(v, n, kind: str, mu=None):
    """Apply a boundary condition with outward normal ``n`` (d floats or (K,) arrays) to
    velocity components ``v`` (d arrays); returns the d new components."""
    if kind == "sticky":
        return tuple(jnp.zeros_like(c) for c in v)
    vn = la._sum([c * nc for c, nc in zip(v, n)])
    into = vn < 0
    t = tuple(c - vn * nc for c, nc in zip(v, n))
    if kind == "slip":
        return tuple(jnp.where(into, tc, c) for tc, c in zip(t, v))
    tn = la.safe_norm(jnp.stack(t))
    scale = jnp.maximum(0.0, 1.0 + mu * vn / tn)  # vn < 0: 1 - mu |vn| / |vt|
    return tuple(jnp.where(into, tc * scale, c) for tc, c in zip(t, v))


def _named_condition(name: str, kind: str):
    """A jitted boundary condition named ``name``: it appears as ``name=...`` in the jaxpr, so
    tests can check which conditions a scene traces."""
    def condition(v, n, mu=None):
        return normal_condition(v, n, kind, mu)

    condition.__name__ = condition.__qualname__ = name
    return jax.jit(condition)


WALL = {k: _named_condition(f"wall_{k}", k) for k in ("sticky", "slip", "friction")}
OBSTACLE = {k: _named_condition(f"obstacle_{k}", k) for k in ("sticky", "slip", "friction")}
wall_sticky, wall_slip, wall_friction = WALL["sticky"], WALL["slip"], WALL["friction"]


def wall_slabs(padding: int, n_cells: tuple[int, ...]) -> list[tuple[tuple, tuple]]:
    """(index expression into (d, *grid), outward normal of the wall face) of each wall, in
    wall order: for each axis the low then the high side. The low wall holds the nodes
    ``[:p + 1]`` along its axis, the high wall ``[p + n:]``."""
    d = len(n_cells)
    out = []
    for a, n in enumerate(n_cells):
        for side, sl in ((1.0, slice(None, padding + 1)), (-1.0, slice(padding + n, None))):
            idx = [slice(None)] * (d + 1)
            idx[a + 1] = sl
            normal = tuple(side if b == a else 0.0 for b in range(d))
            out.append((tuple(idx), normal))
    return out


def apply_walls(gv, walls, wall_mu, padding: int, n_cells: tuple[int, ...]):
    """Apply the 2d box walls.

    Args:
        gv: (d, nx, ny[, nz]) grid velocities, m/s.
        walls: static Wall kinds, 2d of them in wall order.
        wall_mu: (2d,) friction coefficients in wall order; leaves.
        padding: grid cells outside the domain.
        n_cells: domain cells (cx, cy[, cz]).
    """
    d = gv.shape[0]
    for k, (wall, (sl, normal)) in enumerate(zip(walls, wall_slabs(padding, n_cells))):
        part = gv[sl]
        mu = wall_mu[k] if wall.kind == "friction" else None
        v = WALL[wall.kind](tuple(part[c] for c in range(d)), normal, mu)
        gv = gv.at[sl].set(jnp.stack(v))
    return gv


def obstacle_nodes(obstacles, grid_shape, origin, dx):
    """Static description of the grid nodes inside obstacles.

    Returns a dict kind -> (flat node indices (K,), normals (d, K), obstacle index (K,)),
    with the outward normal of the nearest face of each node's obstacle.
    """
    d = len(grid_shape)
    grids = np.meshgrid(*[np.arange(n) for n in grid_shape], indexing="ij")
    X = [origin[a] + grids[a] * dx for a in range(d)]
    out: dict[str, list] = {}
    taken = np.zeros(grid_shape, bool)
    for k, o in enumerate(obstacles):
        lo, hi = o.lower, o.upper
        tol = 1e-9 * dx
        inside = np.ones(grid_shape, bool)
        for a in range(d):
            inside &= (X[a] >= lo[a] - tol) & (X[a] <= hi[a] + tol)
        inside &= ~taken
        taken |= inside
        dist = np.stack([q for a in range(d) for q in (X[a] - lo[a], hi[a] - X[a])])
        face = np.argmin(dist, axis=0)  # left, right, bottom, top[, back, front]
        table = np.array([[(-1.0 if f % 2 == 0 else 1.0) if f // 2 == a else 0.0
                           for a in range(d)] for f in range(2 * d)])
        normals = table[face]
        flat = np.flatnonzero(inside.ravel())
        entry = out.setdefault(o.surface.kind, [[], [], []])
        entry[0].append(flat)
        entry[1].append(normals.reshape(-1, d)[flat].T)
        entry[2].append(np.full(len(flat), k, np.int32))
    return {kind: (np.concatenate(e[0]), np.concatenate(e[1], 1), np.concatenate(e[2]))
            for kind, e in out.items()}


def apply_obstacles(gv, nodes, obstacle_mu):
    """Apply obstacle conditions to flat grid velocities (d, n_nodes)."""
    d = gv.shape[0]
    for kind, (idx, normals, owner) in nodes.items():
        v = tuple(gv[c, idx] for c in range(d))
        mu = obstacle_mu[owner] if kind == "friction" else None
        v = OBSTACLE[kind](v, tuple(normals[c] for c in range(d)), mu)
        gv = gv.at[:, idx].set(jnp.stack(v))
    return gv
