"""Builders of 3D scene families: the axisymmetric granular column and the quasi-2D slab.

Axes as in every diffgns scene: y vertical, x the 2D horizontal axis, z the depth axis.
"""
from __future__ import annotations

import math

from diffgns.errors import SceneError
from diffgns.scene.core import Body, Scene, Wall, Walls
from diffgns.scene.materials import Sand
from diffgns.scene.shapes import Box, Cylinder, Rectangle

__all__ = ["axisymmetric_column", "axisymmetric_runout_estimate", "cylinder_axis",
           "slab_column"]


def axisymmetric_runout_estimate(aspect_ratio: float) -> float:
    """Normalised runout (R_inf - R0)/R0 of an axisymmetric dry granular column of aspect
    ratio a = H0/R0 by the experimental scaling of Lube et al. (2004): 1.24 a for a <= 1.7,
    1.6 a^(1/2) above (Lajeunesse et al. 2004 report the same two regimes)."""
    a = float(aspect_ratio)
    return 1.24 * a if a <= 1.7 else 1.6 * math.sqrt(a)


def cylinder_axis(scene: Scene) -> tuple[tuple[float, float], Cylinder] | None:
    """The vertical axis (cx, cz), m, of an axisymmetric 3D scene and its column (the widest
    cylinder): when every body is an upright :class:`Cylinder` on one axis; else None."""
    shapes = [b.shape for b in scene.bodies if isinstance(b.shape, Cylinder)]
    if scene.dim != 3 or not shapes or len(shapes) != len(scene.bodies):
        return None
    if len({(round(sh.cx, 12), round(sh.cz, 12)) for sh in shapes}) != 1:
        return None
    column = max(shapes, key=lambda sh: sh.radius)
    return (float(column.cx), float(column.cz)), column


def axisymmetric_column(
    radius: float = 0.05,
    aspect_ratio: float = 1.0,
    friction_angle: float = 30.0,
    cells_across: int = 5,
    particles_per_cell: int = 8,
    E: float = 2.0e6,
    nu: float = 0.3,
    rho: float = 1800.0,
    cohesion: float = 0.0,
    floor_mu: float = 0.5,
    margin: float = 1.3,
    frame_dt: float = 2.5e-3,
    **scene_kw,
) -> Scene:
    """A granular cylinder of ``radius`` R0 (m) and height ``aspect_ratio * radius`` standing
    on a Coulomb floor (``floor_mu``) in the middle of a square box, released at rest.

    ``dx = radius / cells_across``. The box half-width is ``margin`` times the runout of
    :func:`axisymmetric_runout_estimate` plus 3 cells; side and top walls are slip.
    """
    if not (radius > 0 and aspect_ratio > 0 and cells_across >= 1):
        raise SceneError(f"axisymmetric_column: radius ({radius}), aspect_ratio "
                         f"({aspect_ratio}) and cells_across ({cells_across}) must be > 0")
    dx = radius / cells_across
    height = aspect_ratio * radius
    if abs(round(height / dx) * dx - height) > 1e-9:
        raise SceneError(f"axisymmetric_column: height {height} m is not a whole number of "
                         f"cells dx = {dx} m; adjust aspect_ratio or cells_across")
    reach = radius * (1.0 + axisymmetric_runout_estimate(aspect_ratio))
    half = math.ceil((margin * reach) / dx + 3)
    ny = math.ceil((1.1 * height) / dx + 2)
    L = 2 * half * dx
    sand = Sand(friction_angle=friction_angle, E=E, nu=nu, rho=rho, cohesion=cohesion)
    body = Body(Cylinder(L / 2, L / 2, radius, 0.0, height), sand,
                particles_per_cell=particles_per_cell, name="column")
    slip = Wall("slip")
    return Scene(domain=((0.0, L), (0.0, ny * dx), (0.0, L)), dx=dx, bodies=(body,),
                 walls=Walls(slip, slip, Wall("friction", floor_mu), slip, slip, slip),
                 frame_dt=frame_dt, **scene_kw)


def slab_column(
    width: float = 0.1,
    aspect_ratio: float = 1.0,
    depth_cells: int = 2,
    friction_angle: float = 30.0,
    cells_across: int = 10,
    particles_per_cell: int = 8,
    floor_mu: float = 0.5,
    domain_length: float | None = None,
    frame_dt: float = 2.5e-3,
    **sand_kw,
) -> Scene:
    """The 2D column collapse of :func:`diffgns.scene.builders.column_collapse` as a thin 3D
    slab ``depth_cells`` cells deep between frictionless (slip) back and front walls: a
    plane-strain problem that must reproduce the 2D scene.

    The slab uses the 2D builder's box (same dx, length and height) extruded along z.
    """
    from diffgns.scene.builders import column_collapse

    two = column_collapse(width=width, aspect_ratio=aspect_ratio, friction_angle=friction_angle,
                          cells_across=cells_across, floor_mu=floor_mu,
                          domain_length=domain_length, frame_dt=frame_dt, **sand_kw)
    dx = two.dx
    depth = depth_cells * dx
    (x0, x1), (y0, y1) = two.domain
    body2 = two.bodies[0]
    sh = body2.shape
    assert isinstance(sh, Rectangle)  # column_collapse builds a rectangle
    body = Body(Box(sh.x0, sh.y0, 0.0, sh.x1, sh.y1, depth), body2.material,
                particles_per_cell=particles_per_cell, name=body2.name)
    w = two.walls
    return Scene(domain=((x0, x1), (y0, y1), (0.0, depth)), dx=dx, bodies=(body,),
                 walls=Walls(w.left, w.right, w.bottom, w.top, Wall("slip"), Wall("slip")),
                 frame_dt=frame_dt)
