"""Builders for the scene families the learned simulators train on."""
from __future__ import annotations

import math

import numpy as np

from diffgns.errors import SceneError
from diffgns.scene.core import Body, Scene, Wall, Walls
from diffgns.scene.materials import Sand
from diffgns.scene.shapes import Rectangle


def column_collapse(
    width: float = 0.1,
    aspect_ratio: float = 1.0,
    friction_angle: float = 30.0,
    dx: float | None = None,
    cells_across: int = 10,
    particles_per_cell: int = 4,
    E: float = 2.0e6,
    nu: float = 0.3,
    rho: float = 1800.0,
    cohesion: float = 0.0,
    floor_mu: float = 0.5,
    domain_length: float | None = None,
    domain_height: float | None = None,
    frame_dt: float = 2.5e-3,
    **scene_kw,
) -> Scene:
    """A granular column of ``width`` (m) and height ``aspect_ratio * width`` against the
    left wall of a box, released at rest under gravity.

    The floor is Coulomb-frictional (``floor_mu``), the left wall is slip (the symmetry
    plane of a symmetric collapse), the others slip. The domain is long enough for the
    runout of Lube et al. (2005) plus a margin, unless ``domain_length`` is given (a fixed
    ``domain_length`` and ``domain_height`` give every aspect ratio the same box).
    ``dx`` defaults to ``width / cells_across``.
    """
    if not (width > 0 and aspect_ratio > 0):
        raise SceneError(f"column_collapse: width ({width}) and aspect_ratio ({aspect_ratio}) "
                         "must be > 0")
    dx = width / cells_across if dx is None else dx
    height = aspect_ratio * width
    if domain_length is None:
        a = aspect_ratio
        runout = width * (1 + max(1.2 * a, 1.9 * a ** (2 / 3)))
        domain_length = 1.4 * runout + 4 * dx
    nx = math.ceil(domain_length / dx)
    ny = math.ceil(((height * 1.1 + 2 * dx) if domain_height is None else domain_height) / dx)
    if ny * dx < height:
        raise SceneError(f"column_collapse: domain_height {domain_height} is below the column "
                         f"height {height}")
    # put the column on the lattice of the grid
    w_cells, h_cells = round(width / dx), round(height / dx)
    if abs(w_cells * dx - width) > 1e-9 or abs(h_cells * dx - height) > 1e-9:
        raise SceneError(f"column_collapse: width {width} and height {height} must be whole "
                         f"multiples of dx = {dx}; adjust cells_across or aspect_ratio")
    sand = Sand(friction_angle=friction_angle, E=E, nu=nu, rho=rho, cohesion=cohesion)
    body = Body(Rectangle(0.0, 0.0, width, height), sand, particles_per_cell=particles_per_cell,
                name="column")
    return Scene(
        domain=((0.0, nx * dx), (0.0, ny * dx)), dx=dx, bodies=(body,),
        walls=Walls(left=Wall("slip"), right=Wall("slip"), bottom=Wall("friction", floor_mu),
                    top=Wall("slip")),
        frame_dt=frame_dt, **scene_kw,
    )


def granular_squares(
    seed: int = 0,
    n_masses: int | None = None,
    size: float = 0.2,
    dx: float = 0.02,
    domain: tuple = ((0.0, 1.0), (0.0, 1.0)),
    speed: float = 2.0,
    friction_angle: float | tuple[float, float] = 30.0,
    particles_per_cell: int = 4,
    wall_mu: float = 0.3,
    frame_dt: float = 2.5e-3,
    **scene_kw,
) -> Scene:
    """One or two square granular masses with random positions and initial velocities
    in a box (the family of the published GNS sand training set).

    Args:
        seed: random seed (positions, velocities, number of masses if not given).
        size: side of each square, m (a multiple of dx).
        speed: largest initial speed component, m/s (uniform in [-speed, speed]).
        friction_angle: a value or a (min, max) range, degrees.
    """
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 3)) if n_masses is None else n_masses
    if n not in (1, 2):
        raise SceneError(f"granular_squares: n_masses = {n} must be 1 or 2")
    phi = friction_angle if np.isscalar(friction_angle) else float(rng.uniform(*friction_angle))
    (x0, x1), (y0, y1) = domain
    cells = round(size / dx)
    nx, ny = round((x1 - x0) / dx), round((y1 - y0) / dx)
    bodies: list[Body] = []
    occupied = np.zeros((nx, ny), bool)
    for k in range(n):
        for _ in range(200):
            i = int(rng.integers(1, nx - cells - 1))
            j = int(rng.integers(1, ny - cells - 1))
            if not occupied[i - 1:i + cells + 1, j - 1:j + cells + 1].any():
                break
        else:
            raise SceneError("granular_squares: could not place the squares without overlap; "
                             "use a smaller size or a larger domain")
        occupied[i:i + cells, j:j + cells] = True
        v = tuple(float(c) for c in rng.uniform(-speed, speed, 2))
        rect = Rectangle(x0 + i * dx, y0 + j * dx, x0 + (i + cells) * dx, y0 + (j + cells) * dx)
        bodies.append(Body(rect, Sand(friction_angle=phi), velocity=v,
                           particles_per_cell=particles_per_cell, name=f"square{k}"))
    return Scene(domain=domain, dx=dx, bodies=tuple(bodies), walls=Walls.all("friction", wall_mu),
                 frame_dt=frame_dt, **scene_kw)
