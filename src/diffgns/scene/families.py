"""Random scenes of the granular families a general GNS trains on (issue 21).

:func:`random_scene` draws one scene of a family from an integer seed; :func:`random_sample`
also returns what was drawn (JSON-serialisable), for the dataset's per-trajectory metadata.
The draw depends on ``(family, seed)`` and the ranges alone, so a held-out set is a disjoint
range of seeds (:mod:`diffgns.io.families_data` uses ``seed * 1_000_003 + i``).

Families (:data:`FAMILIES`):

* ``squares``: 1-2 square or rectangular masses of random size, position and initial
  velocity anywhere in the box (the setting of the reference GNS's sand data);
* ``columns``: one column of random width and aspect ratio at rest against the left or right
  wall, on the floor (today's column collapse, both ways round);
* ``obstacles``: a column collapse or a thrown mass running into one or two box obstacles
  standing on the floor;
* ``collision``: two masses thrown at each other.

Held-out compositions (:data:`HELDOUT_FAMILIES`), never in a training set, each a
composition of training families' physics that no training scene shows:

* ``column_pair``: a column at rest against each side wall, the gap between them at most
  the sum of their heights, so that the two collapses run toward each other and (at low
  and moderate friction) meet: the flows of ``columns``, met head-on as in ``collision``;
* ``column_hit``: a column at rest against a side wall struck by a mass thrown at it (a
  ``columns`` collapse set off by a ``squares`` impact).

One boundary convention for every family, so the network never sees two behaviours at a wall
it cannot tell apart: the floor and the obstacles are Coulomb-frictional (``floor_mu``,
``obstacle_mu``, default 0.5 as the shipped column data), the side walls and the ceiling slip.
One friction angle per scene, uniform in ``friction_angle`` (degrees, default 15-45).

Everything lies on a lattice of ``lattice`` grid cells (default 2 cells of
``dx = 0.1 / 16 = 0.00625`` m, the MPM of ``gns_cg16_pfn``): body and obstacle corners, box
sizes. With 4 particles per cell a 2 x 2-cell block holds 16 particles, so the coarse-graining
16 of the shipped models bins whole blocks in every family. Bodies start at least ``gap``
lattice units from each other and from the obstacles, inside the box (columns touch the wall
and the floor they stand on, thrown masses start ``gap`` units off every wall): valid by
construction, checked again by :class:`~diffgns.scene.core.Scene`.

Light: numpy and the scene package only (no JAX).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from diffgns.errors import SceneError
from diffgns.scene.core import Body, BoxObstacle, Scene, Wall, Walls
from diffgns.scene.materials import Sand
from diffgns.scene.shapes import Rectangle

__all__ = ["ALL_FAMILIES", "BOXES", "FAMILIES", "HELDOUT_FAMILIES", "FamilyRanges",
           "random_sample", "random_scene", "ranges_dict"]

FAMILIES = ("squares", "columns", "obstacles", "collision")  # the training families
HELDOUT_FAMILIES = ("column_pair", "column_hit")  # compositions for held-out sets only
ALL_FAMILIES = FAMILIES + HELDOUT_FAMILIES  # appended: a family's random stream never moves
_DRAWS = 1000  # attempts per scene (a family that fits early draws exactly as with fewer)
BOXES = ((0.8, 0.35), (0.6, 0.5))  # (length, height) m: today's box and a taller, shorter one


@dataclass(frozen=True)
class FamilyRanges:
    """The ranges scenes are drawn from; ``(lo, hi)`` pairs are closed intervals.

    Attributes:
        friction_angle: degrees, in (0, 90).
        boxes: the (length, height) boxes, m, one drawn uniformly; multiples of the lattice.
        size: side of a thrown mass, m (a rectangle draws each side from it).
        rectangle_fraction: probability that a thrown mass is a rectangle, not a square.
        column_width: m; aspect_ratio: column height / width (capped by the box height).
        speed: largest initial speed component (vx, vy) of a thrown mass, m/s.
        obstacle_width, obstacle_height: m.
        n_masses: (min, max) number of masses of the ``squares`` family.
        n_obstacles: (min, max) number of obstacles of the ``obstacles`` family.
        dx: MPM cell size, m; lattice: placement lattice in cells; gap: lattice units kept
            free between bodies, obstacles and (for thrown masses) the walls.
        particles_per_cell, floor_mu, obstacle_mu, frame_dt (s): passed to the scene.
        young_modulus: the sand's Young's modulus E, Pa (default 2 MPa, the reference GNS's
            column data; the MPM's stable substep shrinks as 1/sqrt(E)). Not a draw: every
            scene of a set has the same E, and the random stream does not depend on it.
        flip: the MPM's ``Scene.flip`` (0: APIC alone, the default); not a draw either.
    """

    friction_angle: tuple[float, float] = (15.0, 45.0)
    boxes: tuple[tuple[float, float], ...] = BOXES
    size: tuple[float, float] = (0.05, 0.15)
    rectangle_fraction: float = 0.5
    column_width: tuple[float, float] = (0.05, 0.15)
    aspect_ratio: tuple[float, float] = (0.5, 3.0)
    speed: tuple[float, float] = (2.0, 1.0)
    obstacle_width: tuple[float, float] = (0.025, 0.1)
    obstacle_height: tuple[float, float] = (0.025, 0.1)
    n_masses: tuple[int, int] = (1, 2)
    n_obstacles: tuple[int, int] = (1, 2)
    dx: float = 0.1 / 16
    lattice: int = 2
    gap: int = 2
    particles_per_cell: int = 4
    floor_mu: float = 0.5
    obstacle_mu: float = 0.5
    frame_dt: float = 2.5e-3
    young_modulus: float = 2.0e6
    flip: float = 0.0

    def __post_init__(self):
        if not (math.isfinite(self.young_modulus) and self.young_modulus > 0):
            raise SceneError(f"FamilyRanges.young_modulus = {self.young_modulus} must be a "
                             "finite stiffness > 0 Pa (e.g. 2e6 or 2e7)")
        for name in ("friction_angle", "size", "column_width", "aspect_ratio",
                     "obstacle_width", "obstacle_height", "n_masses", "n_obstacles"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
                raise SceneError(f"FamilyRanges.{name} = ({lo}, {hi}) must be 0 < min <= max")
        if not self.friction_angle[1] < 90:
            raise SceneError(f"FamilyRanges.friction_angle = {self.friction_angle} must lie "
                             "in (0, 90) degrees")
        if not all(s >= 0 and math.isfinite(s) for s in self.speed) or len(self.speed) != 2:
            raise SceneError(f"FamilyRanges.speed = {self.speed} must be two numbers >= 0 m/s")
        if not 0 <= self.rectangle_fraction <= 1:
            raise SceneError(f"FamilyRanges.rectangle_fraction = {self.rectangle_fraction} "
                             "must be a probability in [0, 1]")
        if not (isinstance(self.lattice, int) and self.lattice >= 1
                and isinstance(self.gap, int) and self.gap >= 1):
            raise SceneError("FamilyRanges.lattice and .gap must be integers >= 1 (cells, "
                             "lattice units)")
        if not self.boxes:
            raise SceneError("FamilyRanges.boxes is empty; give at least one (length, height)")
        for box in self.boxes:
            for side in box:
                n = side / self.unit
                if abs(n - round(n)) > 1e-6 or round(n) < 8:
                    raise SceneError(
                        f"FamilyRanges.boxes: side {side} m of box {box} is not a whole number "
                        f"(>= 8) of lattice units of {self.unit} m (lattice {self.lattice} x "
                        f"dx {self.dx}); choose sides that are multiples of it")

    @property
    def unit(self) -> float:
        """Lattice unit, m."""
        return self.lattice * self.dx


def random_scene(family: str, seed: int, **ranges) -> Scene:
    """A random scene of ``family`` (one of :data:`ALL_FAMILIES`) drawn from ``seed`` (int >= 0);
    ``ranges`` override fields of :class:`FamilyRanges`. See :func:`random_sample`."""
    return random_sample(family, seed, **ranges)[0]


def random_sample(family: str, seed: int, **ranges) -> tuple[Scene, dict]:
    """``(scene, description)`` of a random scene of ``family`` drawn from ``seed``.

    The description holds the family, seed, box (m), friction angle (degrees), every body's
    rectangle ``[x0, y0, x1, y1]`` (m) and velocity (m/s), every obstacle's rectangle, and
    family extras (a column's aspect ratio and side). Raises SceneError for an unknown
    family, a negative seed, bad ranges, or ranges too large for the box.
    """
    if family not in ALL_FAMILIES:
        raise SceneError(f"random_scene: family {family!r} is unknown; use one of "
                         f"{ALL_FAMILIES}")
    if not (isinstance(seed, (int, np.integer)) and seed >= 0):
        raise SceneError(f"random_scene: seed = {seed!r} must be an integer >= 0")
    unknown = sorted(set(ranges) - {f.name for f in fields(FamilyRanges)})
    if unknown:
        raise SceneError(f"random_scene: unknown range(s) {unknown}; use fields of FamilyRanges")
    r = replace(FamilyRanges(), **ranges)
    rng = np.random.default_rng([ALL_FAMILIES.index(family), int(seed)])
    box = r.boxes[int(rng.integers(len(r.boxes)))]
    phi = float(rng.uniform(*r.friction_angle))
    lay = _Layout(r, box)
    extra: dict = {}
    for _ in range(_DRAWS):  # a draw that does not fit is redrawn (same rng: deterministic)
        lay.clear()
        try:
            extra = _DRAW[family](lay, rng, r)
            break
        except _NoRoom:
            continue
    else:
        hint = ("two columns must stand near enough to meet: use a shorter box or taller "
                "columns" if family == "column_pair" else "use smaller sizes or a larger box")
        raise SceneError(f"random_scene: could not place a {family} scene in the box {box} in "
                         f"{_DRAWS} draws; {hint}")
    sand = Sand(friction_angle=phi, E=r.young_modulus)
    bodies = tuple(Body(Rectangle(*lay.metres(b)), sand, velocity=v,
                        particles_per_cell=r.particles_per_cell, name=f"mass{k}")
                   for k, (b, v) in enumerate(zip(lay.bodies, lay.velocities)))
    surface = Wall("friction", r.obstacle_mu)
    obstacles = tuple(BoxObstacle(x0, y0, x1, y1, surface=surface)
                      for x0, y0, x1, y1 in map(lay.metres, lay.obstacles))
    scene = Scene(domain=((0.0, box[0]), (0.0, box[1])), dx=r.dx, bodies=bodies,
                  walls=Walls(left=Wall("slip"), right=Wall("slip"),
                              bottom=Wall("friction", r.floor_mu), top=Wall("slip")),
                  obstacles=obstacles, frame_dt=r.frame_dt, flip=r.flip)
    desc = dict(family=family, seed=int(seed), box=list(box), friction_angle=phi,
                bodies=[lay.metres(b) for b in lay.bodies],
                velocities=[list(v) for v in lay.velocities],
                obstacles=[lay.metres(o) for o in lay.obstacles], **extra)
    return scene, desc


class _NoRoom(Exception):
    """A draw did not fit; the caller redraws."""


class _Layout:
    """Rectangles on the placement lattice, ``(i, j, w, h)`` in lattice units, with an
    occupancy grid that keeps ``gap`` units between everything placed."""

    def __init__(self, r: FamilyRanges, box: tuple[float, float]):
        self.r = r
        self.nx, self.ny = (round(s / r.unit) for s in box)
        self.clear()

    def clear(self) -> None:
        self.occ = np.zeros((self.nx, self.ny), bool)
        self.bodies: list[tuple[int, int, int, int]] = []
        self.velocities: list[tuple[float, float]] = []
        self.obstacles: list[tuple[int, int, int, int]] = []

    def units(self, rng, lo_hi: tuple[float, float], cap: int | None = None) -> int:
        """A length in lattice units drawn uniformly from ``lo_hi`` m (at least 1 unit)."""
        n = max(1, round(float(rng.uniform(*lo_hi)) / self.r.unit))
        return n if cap is None else min(n, cap)

    def free(self, i: int, j: int, w: int, h: int) -> bool:
        g = self.r.gap
        inside = 0 <= i and 0 <= j and i + w <= self.nx and j + h <= self.ny
        return inside and not self.occ[max(i - g, 0):i + w + g, max(j - g, 0):j + h + g].any()

    def put(self, rect, velocity=None) -> None:
        i, j, w, h = rect
        if not self.free(i, j, w, h):
            raise _NoRoom
        self.occ[i:i + w, j:j + h] = True
        if velocity is None:
            self.obstacles.append(rect)
        else:
            self.bodies.append(rect)
            self.velocities.append(velocity)

    def put_random(self, rng, w: int, h: int, i_range: tuple[int, int],
                   j_range: tuple[int, int], velocity=None) -> tuple[int, int, int, int]:
        """Place a w x h rectangle with its corner uniform in the ranges (inclusive)."""
        (i0, i1), (j0, j1) = i_range, j_range
        if i1 < i0 or j1 < j0:
            raise _NoRoom
        for _ in range(50):
            rect = (int(rng.integers(i0, i1 + 1)), int(rng.integers(j0, j1 + 1)), w, h)
            if self.free(*rect):
                self.put(rect, velocity)
                return rect
        raise _NoRoom

    def mirror(self) -> None:
        """Reflect everything about the box's vertical mid-line (velocities too)."""
        self.bodies = [(self.nx - i - w, j, w, h) for i, j, w, h in self.bodies]
        self.obstacles = [(self.nx - i - w, j, w, h) for i, j, w, h in self.obstacles]
        self.velocities = [(0.0 - vx, vy) for vx, vy in self.velocities]  # no -0.0
        self.occ = self.occ[::-1].copy()

    def metres(self, rect) -> list[float]:
        """``[x0, y0, x1, y1]`` in m of a lattice rectangle."""
        i, j, w, h = rect
        u = self.r.unit
        return [i * u, j * u, (i + w) * u, (j + h) * u]

    def mass_size(self, rng) -> tuple[int, int]:
        w = self.units(rng, self.r.size)
        h = self.units(rng, self.r.size) if rng.random() < self.r.rectangle_fraction else w
        return w, h

    def thrown(self, rng, w: int, h: int, i_range=None, vx_sign: float = 0.0):
        """Place a thrown mass ``gap`` units off every wall; vx toward ``vx_sign`` if given."""
        g = self.r.gap
        i_range = i_range or (g, self.nx - g - w)
        sx, sy = self.r.speed
        vx = float(rng.uniform(-sx, sx)) if not vx_sign else vx_sign * float(
            rng.uniform(0.25 * sx, sx))
        v = (vx, float(rng.uniform(-sy, sy)))
        return self.put_random(rng, w, h, i_range, (g, self.ny - g - h), v)

    def column(self, rng) -> dict:
        """A column at rest against the left wall on the floor; returns its aspect ratio."""
        w = self.units(rng, self.r.column_width, cap=self.nx // 3)
        a = float(rng.uniform(*self.r.aspect_ratio))
        h = min(max(1, round(a * w)), self.ny - self.r.gap)
        self.put((0, 0, w, h), (0.0, 0.0))
        return dict(aspect_ratio=h / w, column_width=w * self.r.unit)


def _squares(lay: _Layout, rng, r: FamilyRanges) -> dict:
    for _ in range(int(rng.integers(r.n_masses[0], r.n_masses[1] + 1))):
        lay.thrown(rng, *lay.mass_size(rng))
    return {}


def _columns(lay: _Layout, rng, r: FamilyRanges) -> dict:
    extra = lay.column(rng)
    side = "right" if rng.random() < 0.5 else "left"
    if side == "right":
        lay.mirror()
    return dict(extra, side=side)


def _obstacles(lay: _Layout, rng, r: FamilyRanges) -> dict:
    """Built with the mass on the left moving right, then mirrored half of the time."""
    if rng.random() < 0.5:
        extra = dict(lay.column(rng), mass="column")
        i, _, w, _ = lay.bodies[0]
    else:
        w, h = lay.mass_size(rng)
        i, _, w, _ = lay.thrown(rng, w, h, (r.gap, lay.nx // 3), vx_sign=1.0)
        extra = dict(mass="thrown")
    start = i + w + r.gap  # obstacles downstream of the mass
    for _ in range(int(rng.integers(r.n_obstacles[0], r.n_obstacles[1] + 1))):
        ow = lay.units(rng, r.obstacle_width)
        oh = lay.units(rng, r.obstacle_height, cap=lay.ny // 2)
        lay.put_random(rng, ow, oh, (start, lay.nx - r.gap - ow), (0, 0))
    side = "right" if rng.random() < 0.5 else "left"
    if side == "right":
        lay.mirror()
    return dict(extra, side=side)


def _collision(lay: _Layout, rng, r: FamilyRanges) -> dict:
    """One mass in the left half moving right, one in the right half moving left, at
    overlapping heights (the second's vertical range is drawn around the first's)."""
    half = lay.nx // 2
    w, h = lay.mass_size(rng)
    _, j, _, _ = lay.thrown(rng, w, h, (r.gap, half - w - r.gap), vx_sign=1.0)
    w2, h2 = lay.mass_size(rng)
    j_range = (max(r.gap, j - h2 + 1), min(lay.ny - r.gap - h2, j + h - 1))
    sx, sy = r.speed
    v = (-float(rng.uniform(0.25 * sx, sx)), float(rng.uniform(-sy, sy)))
    lay.put_random(rng, w2, h2, (half + r.gap, lay.nx - r.gap - w2), j_range, v)
    return {}


def _column_pair(lay: _Layout, rng, r: FamilyRanges) -> dict:
    """A column against each side wall, close enough that the flows meet: the gap between
    them is at most the sum of their heights (a collapse runs out 1-1.5 times its height
    beyond its base at low friction), else the draw is redone."""
    first = lay.column(rng)
    lay.mirror()  # the first column now stands against the right wall
    second = lay.column(rng)
    (i0, _, w0, h0), (i1, _, _, h1) = lay.bodies[1], lay.bodies[0]
    gap = i1 - (i0 + w0)
    if gap > h0 + h1 or gap < 2 * r.gap:
        raise _NoRoom
    return dict(aspect_ratio=[second["aspect_ratio"], first["aspect_ratio"]],
                column_width=[second["column_width"], first["column_width"]],
                gap=gap * r.unit)


def _column_hit(lay: _Layout, rng, r: FamilyRanges) -> dict:
    """A column against the left wall and a mass thrown at it from its right, moving left
    and down with its bottom below the column's top (so it strikes the column, not the
    wall behind it); mirrored half of the time."""
    extra = lay.column(rng)
    _, _, cw, ch = lay.bodies[0]
    w, h = lay.mass_size(rng)
    lo = cw + 2 * r.gap
    sx, sy = r.speed
    v = (-float(rng.uniform(0.25 * sx, sx)), -float(rng.uniform(0.0, sy)))
    lay.put_random(rng, w, h, (lo, min(lay.nx - r.gap - w, lo + lay.nx // 3)),
                   (r.gap, min(ch - 1, lay.ny - r.gap - h)), v)
    side = "right" if rng.random() < 0.5 else "left"
    if side == "right":
        lay.mirror()
    return dict(extra, side=side)


_DRAW = {"squares": _squares, "columns": _columns, "obstacles": _obstacles,
         "collision": _collision, "column_pair": _column_pair, "column_hit": _column_hit}


def ranges_dict(**ranges) -> dict:
    """The full, JSON-serialisable :class:`FamilyRanges` with ``ranges`` applied (for a
    dataset's recipe fingerprint)."""
    return {k: (list(v) if isinstance(v, tuple) else v)
            for k, v in asdict(replace(FamilyRanges(), **ranges)).items()}
