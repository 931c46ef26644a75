"""Scenes from and to TOML files (and plain dicts).

Layout (a complete, valid scene file; ``tests/test_scene.py`` loads it)::

    [scene]            # domain, dx, gravity, frame_dt, padding, cfl, dt, max_speed, damping,
                       # flip
    domain = [[0.0, 1.0], [0.0, 0.5]]      # [[xmin, xmax], [ymin, ymax]], m
    dx = 0.01                              # grid cell size, m
    [walls]            # left/right/bottom/top = {kind = "slip"|"sticky"|"friction", mu}
    bottom = {kind = "friction", mu = 0.5}
    [[bodies]]         # one table per body: shape, material, velocity, particles_per_cell, name
    shape = {type = "rectangle", x0 = 0.0, y0 = 0.0, x1 = 0.2, y1 = 0.2}
    material = {type = "sand", friction_angle = 30.0}
    [[obstacles]]      # one table per box obstacle: corners (m) and surface
    x0 = 0.5
    y0 = 0.0
    x1 = 0.6
    y1 = 0.05
    surface = {kind = "sticky"}

A polygon body is ``shape = {type = "polygon", vertices = [[x, y], ...]}``; the material
tables take the fields of :mod:`diffgns.scene.materials` (``type = "sand"|"elastic"|"fluid"``).

A 3D scene has three domain axes (y vertical, z depth), three gravity components, walls
``back``/``front`` (z min/max; slip if not given), 3D shapes
``{type = "box", x0, y0, z0, x1, y1, z1}`` and ``{type = "cylinder", cx, cz, radius, y0,
y1}`` (upright, axis along y), three velocity components, particles_per_cell a perfect cube
(default 8) and obstacles with ``z0``/``z1``::

    [scene]
    domain = [[0.0, 0.4], [0.0, 0.2], [0.0, 0.4]]
    dx = 0.02
    [walls]
    bottom = {kind = "friction", mu = 0.5}
    [[bodies]]
    shape = {type = "cylinder", cx = 0.2, cz = 0.2, radius = 0.05, y0 = 0.0, y1 = 0.1}
    material = {type = "sand", friction_angle = 30.0}
"""
from __future__ import annotations

import sys
from pathlib import Path

from diffgns.errors import SceneError
from diffgns.scene.core import WALL_NAMES_3D, Body, BoxObstacle, Scene, Wall, Walls
from diffgns.scene.materials import material_from_dict, material_to_dict
from diffgns.scene.shapes import Box, Cylinder, Polygon, Rectangle

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

SCENE_KEYS = {"domain", "dx", "gravity", "frame_dt", "padding", "cfl", "dt", "max_speed",
              "damping", "flip"}


def _check_keys(d: dict, allowed: set, where: str) -> None:
    if not isinstance(d, dict):
        raise SceneError(f"{where} must be a table, got {type(d).__name__}")
    extra = set(d) - allowed
    if extra:
        raise SceneError(
            f"{where} has unknown field(s) {sorted(extra)}; allowed: {sorted(allowed)}"
        )


def _wall(d: dict, where: str) -> Wall:
    _check_keys(d, {"kind", "mu"}, where)
    return Wall(kind=d.get("kind", "slip"), mu=d.get("mu", 0.0))


def _shape(d: dict, where: str):
    d = dict(d)
    kind = d.pop("type", None)
    if kind == "rectangle":
        _check_keys(d, {"x0", "y0", "x1", "y1"}, where)
        missing = {"x0", "y0", "x1", "y1"} - set(d)
        if missing:
            raise SceneError(f"{where} is missing {sorted(missing)}")
        return Rectangle(**d)
    if kind == "polygon":
        _check_keys(d, {"vertices"}, where)
        return Polygon(_numbers(d.get("vertices", ()), 0, 2, f"{where}.vertices",
                                "a list of [x, y] vertices in m"))
    fields = {"box": (Box, ("x0", "y0", "z0", "x1", "y1", "z1")),
              "cylinder": (Cylinder, ("cx", "cz", "radius", "y0", "y1"))}
    if kind in fields:
        cls, names = fields[kind]
        _check_keys(d, set(names), where)
        missing = set(names) - set(d)
        if missing:
            raise SceneError(f"{where} is missing {sorted(missing)}")
        return cls(**d)
    raise SceneError(f"{where}.type = {kind!r} is unknown; use 'rectangle' or 'polygon' (2D), "
                     "'box' or 'cylinder' (3D)")


def _numbers(value, rows: int | None, cols: int, where: str, hint: str) -> tuple:
    """``value`` as a tuple of ``cols`` numbers (``rows`` is None) or of ``rows`` such tuples
    (``rows`` 0: any count); anything else is a SceneError naming ``where`` and ``hint``."""
    def row(v):
        if not (isinstance(v, list | tuple) and len(v) == cols
                and all(isinstance(x, int | float) and not isinstance(x, bool) for x in v)):
            raise SceneError(f"{where} = {value!r} is malformed; give {hint}")
        return tuple(v)

    if rows is None:
        return row(value)
    if not (isinstance(value, list | tuple) and (rows == 0 or len(value) == rows)):
        raise SceneError(f"{where} = {value!r} is malformed; give {hint}")
    return tuple(row(v) for v in value)


def scene_from_dict(d: dict) -> Scene:
    """Build a validated Scene from a dict with the TOML layout above."""
    _check_keys(d, {"scene", "walls", "bodies", "obstacles"}, "scene file")
    sc = dict(d.get("scene", {}))
    _check_keys(sc, SCENE_KEYS, "[scene]")
    hint = "[[x0, x1], [y0, y1]] (2D) or [[x0, x1], [y0, y1], [z0, z1]] (3D) in m"
    dim = 2
    if "domain" in sc:
        sc["domain"] = _numbers(sc["domain"], 0, 2, "[scene].domain", hint)
        dim = len(sc["domain"])
        if dim not in (2, 3):
            raise SceneError(f"[scene].domain = {sc['domain']!r} is malformed; give {hint}")
    if "gravity" in sc:
        sc["gravity"] = _numbers(sc["gravity"], None, dim, "[scene].gravity",
                                 f"{'[gx, gy]' if dim == 2 else '[gx, gy, gz]'} in m/s^2, one "
                                 f"component per axis of the {dim}-axis domain")
    walls = d.get("walls", {})
    _check_keys(walls, set(WALL_NAMES_3D[: 2 * dim]), "[walls]")
    wall_objs = Walls(**{k: _wall(v, f"[walls].{k}") for k, v in walls.items()})
    bodies = []
    for i, b in enumerate(d.get("bodies", [])):
        where = f"[[bodies]][{i}]"
        _check_keys(b, {"shape", "material", "velocity", "particles_per_cell", "name"}, where)
        if "shape" not in b or "material" not in b:
            raise SceneError(f"{where} needs both 'shape' and 'material'")
        if not isinstance(b["material"], dict):
            raise SceneError(f"{where}.material must be a table like {{type = \"sand\", ...}}")
        velocity = b.get("velocity")  # default: at rest, filled by Body for its shape
        if velocity is not None and not (isinstance(velocity, list | tuple)
                                         and len(velocity) == dim):
            raise SceneError(f"{where}.velocity = {velocity!r} must be "
                             f"{'[vx, vy]' if dim == 2 else '[vx, vy, vz]'} in m/s "
                             f"(the domain has {dim} axes)")
        bodies.append(Body(
            shape=_shape(b["shape"], f"{where}.shape"),
            material=material_from_dict(b["material"], where),
            velocity=None if velocity is None else tuple(velocity),
            particles_per_cell=b.get("particles_per_cell"), name=b.get("name", ""),
        ))
    obstacles = []
    for i, o in enumerate(d.get("obstacles", [])):
        where = f"[[obstacles]][{i}]"
        corners = {"x0", "y0", "x1", "y1"} | ({"z0", "z1"} if dim == 3 else set())
        _check_keys(o, corners | {"surface"}, where)
        missing = corners - set(o)
        if missing:
            raise SceneError(f"{where} is missing {sorted(missing)}")
        surface = _wall(o.get("surface", {"kind": "sticky"}), f"{where}.surface")
        obstacles.append(BoxObstacle(o["x0"], o["y0"], o["x1"], o["y1"], surface,
                                     z0=o.get("z0"), z1=o.get("z1")))
    return Scene(bodies=tuple(bodies), walls=wall_objs, obstacles=tuple(obstacles), **sc)


def load_scene(path: str | Path) -> Scene:
    """Load a scene from a TOML file; malformed files raise SceneError naming the problem."""
    path = Path(path)
    if not path.exists():
        raise SceneError(f"scene file {path} does not exist")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"scene file {path} is not valid TOML: {e}") from e
    return scene_from_dict(data)


def scene_to_dict(s: Scene) -> dict:
    def shape(sh):
        if isinstance(sh, Rectangle):
            return {"type": "rectangle", "x0": sh.x0, "y0": sh.y0, "x1": sh.x1, "y1": sh.y1}
        if isinstance(sh, Box):
            return {"type": "box", **{k: getattr(sh, k) for k in ("x0", "y0", "z0", "x1", "y1",
                                                                  "z1")}}
        if isinstance(sh, Cylinder):
            return {"type": "cylinder", **{k: getattr(sh, k) for k in ("cx", "cz", "radius",
                                                                       "y0", "y1")}}
        return {"type": "polygon", "vertices": [list(v) for v in sh.vertices]}

    sc = {"domain": [list(ax) for ax in s.domain], "dx": s.dx, "gravity": list(s.gravity or ()),
          "frame_dt": s.frame_dt, "padding": s.padding, "cfl": s.cfl, "damping": s.damping}
    if s.flip:
        sc["flip"] = s.flip
    if s.dt is not None:
        sc["dt"] = s.dt
    if s.max_speed is not None:
        sc["max_speed"] = s.max_speed
    return {
        "scene": sc,
        "walls": {n: {"kind": w.kind, "mu": w.mu} for n, w in zip(s.wall_names, s.wall_list)},
        "bodies": [{"shape": shape(b.shape), "material": material_to_dict(b.material),
                    "velocity": list(b.velocity or ()), "particles_per_cell": b.particles_per_cell,
                    "name": b.name} for b in s.bodies],
        "obstacles": [{"x0": o.x0, "y0": o.y0, "x1": o.x1, "y1": o.y1,
                       **({} if o.z0 is None else {"z0": o.z0, "z1": o.z1}),
                       "surface": {"kind": o.surface.kind, "mu": o.surface.mu}}
                      for o in s.obstacles],
    }


def save_scene(s: Scene, path: str | Path) -> None:
    import tomli_w

    Path(path).write_text(tomli_w.dumps(scene_to_dict(s)))
