"""Validation of a whole scene at construction: every message names the field and the fix."""
from __future__ import annotations

import math

import numpy as np

from diffgns.errors import SceneError
from diffgns.scene.elements import Body, BoxObstacle, Walls


def validate_scene(s) -> None:
    dom = s.domain
    if len(dom) not in (2, 3) or any(len(ax) != 2 for ax in dom):
        raise SceneError("Scene.domain must be ((xmin, xmax), (ymin, ymax)) in 2D or "
                         "((xmin, xmax), (ymin, ymax), (zmin, zmax)) in 3D, in m")
    d = len(dom)
    for name, (lo, hi) in zip("xyz", dom):
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise SceneError(f"Scene.domain along {name} = ({lo}, {hi}) needs max > min")
    if not (isinstance(s.dx, (int, float)) and s.dx > 0 and math.isfinite(s.dx)):
        raise SceneError(f"Scene.dx = {s.dx!r} must be a positive cell size in m")
    for name, (lo, hi) in zip("xyz", dom):
        n = (hi - lo) / s.dx
        if abs(n - round(n)) > 1e-6 * max(1.0, n) or round(n) < 2:
            raise SceneError(
                f"Scene.domain extent along {name} ({hi - lo} m) is not a whole number (>= 2) of "
                f"cells of dx = {s.dx} m; choose dx that divides it"
            )
    if not (isinstance(s.padding, int) and s.padding >= 2):
        raise SceneError(f"Scene.padding = {s.padding!r} must be an integer >= 2 (grid cells)")
    if len(s.gravity) != d or not all(math.isfinite(g) for g in s.gravity):
        raise SceneError(f"Scene.gravity must be a vector of {d} finite numbers in m/s^2 "
                         f"(one per domain axis), got {s.gravity}")
    if not (0 < s.frame_dt and math.isfinite(s.frame_dt)):
        raise SceneError(f"Scene.frame_dt = {s.frame_dt!r} must be > 0 s")
    if not (0 < s.cfl <= 0.5):
        raise SceneError(f"Scene.cfl = {s.cfl!r} must be in (0, 0.5]; 0.4 is a safe default")
    if not (s.damping >= 0 and math.isfinite(s.damping)):
        raise SceneError(f"Scene.damping = {s.damping!r} must be >= 0 (1/s)")
    if not (isinstance(s.flip, (int, float)) and not isinstance(s.flip, bool)
            and 0.0 <= s.flip <= 1.0):
        raise SceneError(f"Scene.flip = {s.flip!r} must be a fraction in [0, 1] (0: APIC, "
                         "e.g. 0.99: mostly FLIP)")
    if s.max_speed is not None and not (s.max_speed >= 0 and math.isfinite(s.max_speed)):
        raise SceneError(f"Scene.max_speed = {s.max_speed!r} must be >= 0 m/s")
    if not s.bodies:
        raise SceneError("Scene.bodies is empty; add at least one Body")
    if not isinstance(s.walls, Walls):
        raise SceneError("Scene.walls must be a Walls(left, right, bottom, top[, back, front])")
    if d == 2 and s.walls.depth_walls_set:
        raise SceneError("Scene.walls.back/front are set but the scene is 2D (a 2D box has no "
                         "depth walls); remove them or give a 3D domain")
    for i, b in enumerate(s.bodies):
        if not isinstance(b, Body):
            raise SceneError(f"Scene.bodies[{i}] is a {type(b).__name__}, expected Body")
        if b.shape.dim != d:
            raise SceneError(
                f"Scene.bodies[{i}] has a {b.shape.dim}D shape ({type(b.shape).__name__}) in a "
                f"{d}D scene; use Rectangle/Polygon in 2D and Box/Cylinder in 3D")
    for i, o in enumerate(s.obstacles):
        if not isinstance(o, BoxObstacle):
            raise SceneError(f"Scene.obstacles[{i}] is a {type(o).__name__}, expected BoxObstacle")
        if o.dim != d:
            raise SceneError(f"Scene.obstacles[{i}] is {o.dim}D in a {d}D scene; give z0 and z1 "
                             "in 3D and neither in 2D")
    tol = 1e-9 * max(hi - lo for lo, hi in dom)
    for i, b in enumerate(s.bodies):
        blo, bhi = b.shape.lower, b.shape.upper
        if any(bl < lo - tol or bh > hi + tol for bl, bh, (lo, hi) in zip(blo, bhi, dom)):
            raise SceneError(
                f"Scene.bodies[{i}] ({b.name or type(b.shape).__name__}) with bounding box "
                f"{blo} to {bhi} lies outside the domain {dom} (the grid padding "
                "is reserved for boundary conditions); move or shrink the body"
            )
    # overlapping bodies: a particle of one body inside another body's shape
    pts = [b.shape.fill(s.dx, b.particles_per_cell)[0] for b in s.bodies]
    for i, bi in enumerate(s.bodies):
        for j in range(len(s.bodies)):
            if i != j and np.any(bi.shape.contains(pts[j])):
                raise SceneError(
                    f"Scene.bodies[{i}] and Scene.bodies[{j}] overlap; separate them so no "
                    "region is filled twice"
                )
        for k, o in enumerate(s.obstacles):
            if np.any(o.contains(pts[i])):
                raise SceneError(
                    f"Scene.bodies[{i}] overlaps Scene.obstacles[{k}]; bodies must start "
                    "outside obstacles"
                )
    if s.dt is not None:
        if not (s.dt > 0 and math.isfinite(s.dt)):
            raise SceneError(f"Scene.dt = {s.dt!r} must be a positive time step in s")
        limit = s.stable_dt()
        if s.dt > limit * (1 + 1e-9):
            raise SceneError(
                f"Scene.dt = {s.dt:.3e} s exceeds the stability limit {limit:.3e} s "
                f"(cfl={s.cfl} * dx / (c_p={s.wave_speed():.1f} m/s + v_max="
                f"{s.speed_bound():.1f} m/s)); use dt <= {limit:.3e} or leave dt unset"
            )
        if s.dt > s.frame_dt:
            raise SceneError(f"Scene.dt = {s.dt} s is longer than frame_dt = {s.frame_dt} s")
