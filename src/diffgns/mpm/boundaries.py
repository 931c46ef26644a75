"""Grid boundary conditions: box walls and static rigid obstacles.

Conditions act on grid node velocities (2, nx, ny) after the gravity update. A node
moving *into* a boundary (v . n < 0, n the outward normal of the boundary surface)
loses its normal velocity; a frictional boundary also reduces the tangential speed by
mu |v_n| (Coulomb), never reversing it; a sticky boundary stops the node.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.mpm import linalg as la


def _normal_bc(vx, vy, nx, ny, kind: str, mu=None):
    """Apply a boundary condition with outward normal (nx, ny) to velocities vx, vy."""
    if kind == "sticky":
        return jnp.zeros_like(vx), jnp.zeros_like(vy)
    vn = vx * nx + vy * ny
    into = vn < 0
    tx, ty = vx - vn * nx, vy - vn * ny
    if kind == "slip":
        return jnp.where(into, tx, vx), jnp.where(into, ty, vy)
    tn = la.safe_norm(jnp.stack([tx, ty]))
    scale = jnp.maximum(0.0, 1.0 + mu * vn / tn)  # vn < 0: 1 - mu |vn| / |vt|
    return jnp.where(into, tx * scale, vx), jnp.where(into, ty * scale, vy)


def _named_condition(name: str, kind: str):
    """A jitted boundary condition named ``name``: it appears as ``name=...`` in the jaxpr, so
    tests can check which conditions a scene traces."""
    def condition(vx, vy, nx, ny, mu=None):
        return _normal_bc(vx, vy, nx, ny, kind, mu)

    condition.__name__ = condition.__qualname__ = name
    return jax.jit(condition)


WALL = {k: _named_condition(f"wall_{k}", k) for k in ("sticky", "slip", "friction")}
OBSTACLE = {k: _named_condition(f"obstacle_{k}", k) for k in ("sticky", "slip", "friction")}
wall_sticky, wall_slip, wall_friction = WALL["sticky"], WALL["slip"], WALL["friction"]


def apply_walls(gv, walls, wall_mu, padding: int, n_cells: tuple[int, int]):
    """Apply the four box walls.

    Args:
        gv: (2, nx, ny) grid velocities, m/s.
        walls: static Walls (kinds).
        wall_mu: (4,) friction coefficients (left, right, bottom, top); leaves.
        padding: grid cells outside the domain.
        n_cells: domain cells (cx, cy).
    """
    p = padding
    cx, cy = n_cells
    slabs = (
        (np.s_[:, : p + 1, :], (1.0, 0.0)),
        (np.s_[:, p + cx:, :], (-1.0, 0.0)),
        (np.s_[:, :, : p + 1], (0.0, 1.0)),
        (np.s_[:, :, p + cy:], (0.0, -1.0)),
    )
    for k, (wall, (sl, (nx, ny))) in enumerate(zip(walls, slabs)):
        vx, vy = gv[sl][0], gv[sl][1]
        mu = wall_mu[k] if wall.kind == "friction" else None
        vx, vy = WALL[wall.kind](vx, vy, nx, ny, mu)
        gv = gv.at[sl].set(jnp.stack([vx, vy]))
    return gv


def obstacle_nodes(obstacles, grid_shape, origin, dx):
    """Static description of the grid nodes inside obstacles.

    Returns a dict kind -> (flat node indices (K,), normals (2, K), obstacle index (K,)),
    with the outward normal of the nearest face of each node's obstacle.
    """
    nx, ny = grid_shape
    I, J = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    X, Y = origin[0] + I * dx, origin[1] + J * dx
    out: dict[str, list] = {}
    taken = np.zeros(grid_shape, bool)
    for k, o in enumerate(obstacles):
        tol = 1e-9 * dx
        inside = (X >= o.x0 - tol) & (X <= o.x1 + tol) & (Y >= o.y0 - tol) & (Y <= o.y1 + tol)
        inside &= ~taken
        taken |= inside
        d = np.stack([X - o.x0, o.x1 - X, Y - o.y0, o.y1 - Y])  # left, right, bottom, top
        face = np.argmin(d, axis=0)
        normals = np.array([[-1.0, 0.0], [1.0, 0.0], [0.0, -1.0], [0.0, 1.0]])[face]
        flat = np.flatnonzero(inside.ravel())
        entry = out.setdefault(o.surface.kind, [[], [], []])
        entry[0].append(flat)
        entry[1].append(normals.reshape(-1, 2)[flat].T)
        entry[2].append(np.full(len(flat), k, np.int32))
    return {kind: (np.concatenate(e[0]), np.concatenate(e[1], 1), np.concatenate(e[2]))
            for kind, e in out.items()}


def apply_obstacles(gv, nodes, obstacle_mu):
    """Apply obstacle conditions to flat grid velocities (2, n_nodes)."""
    for kind, (idx, normals, owner) in nodes.items():
        vx, vy = gv[0, idx], gv[1, idx]
        mu = obstacle_mu[owner] if kind == "friction" else None
        vx, vy = OBSTACLE[kind](vx, vy, normals[0], normals[1], mu)
        gv = gv.at[:, idx].set(jnp.stack([vx, vy]))
    return gv
