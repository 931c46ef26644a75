"""Which scenes a trained particle GNS supports, read from its model folder.

A particle GNS emulates one MPM: the scenes of its training data, seen as **nodes** (means
of ``factor`` particles of the initial configuration) every ``frame_stride`` MPM frames. A
model folder's ``config.json`` records all of it: ``gns.bounds`` (the box), ``factor``,
``frame_stride`` and ``source`` (``kind``, ``width`` and ``cells_across`` of the training
columns, hence the MPM cell size ``dx = width / cells_across``, and ``dt``, the MPM frame).
Nothing here knows a scene family: :func:`check_scene` compares any :class:`Scene` with
that record and refuses, naming the mismatch, a scene the network has never seen an input
for:

* a scene of another dimension than the model's (2D or 3D: ``len(gns.bounds)``);

* a box other than the training box, for a model whose folder does not list its training
  boxes (``source.boxes``: written since the walls became a per-trajectory input of the
  network, :mod:`diffgns.graph.geometry`). A model that lists them runs in any box (the
  network sees a wall only within R); a box larger or smaller than every training box is a
  warning;
* a body that is not sand, or sand with an E, nu, rho or cohesion other than the training
  material's (the network's only material input is tan(friction angle));
* an MPM resolution (cell size dx, particles per cell) other than the one it emulates;
* an MPM frame (``Scene.frame_dt``) other than the training one, so that ``frame_dt *
  frame_stride`` (the GNS step) would differ.

What the network has no feature for but can still run on (obstacles, other wall friction,
other gravity, moving initial bodies when no training family had them, a body away from the
left wall for a model trained on left-wall columns only, a friction angle outside the
training data's range, ``source.friction_angle``) is returned as warnings: such runs are out
of the training distribution, not impossible. :func:`friction_warnings` gives the same
warning for parameter values an inversion reaches. :func:`diffgns.inverse.simulators.
default_model` prefers a model that has no warning for the scene.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from diffgns.errors import SceneError
from diffgns.scene.core import Scene
from diffgns.scene.materials import Sand

__all__ = ["ModelSource", "SceneSupport", "UnsupportedSceneError", "check_scene",
           "friction_warnings", "node_factor", "particle_spacing"]

#: particles per cell of the training data when the model folder does not record it
#: (every dataset builder of :mod:`diffgns.io.datagen` uses 4)
DEFAULT_PARTICLES_PER_CELL = 4
_SAND_FIELDS = ("E", "nu", "rho", "cohesion")


class UnsupportedSceneError(SceneError):
    """A scene a trained model cannot simulate; the message names the mismatch."""


@dataclass(frozen=True)
class ModelSource:
    """What a particle GNS model was trained on (lengths m, times s).

    Attributes:
        bounds: ``((xmin, xmax), (ymin, ymax)(, (zmin, zmax)))`` of the training box.
        dx: MPM cell size of the training data (None if the folder does not record it).
        particles_per_cell: MPM particles per cell of the training data.
        frame_dt: MPM frame of the training data (the GNS step is ``frame_dt * frame_stride``).
        factor: MPM particles per GNS node.
        frame_stride: MPM frames per GNS frame.
        material: the training sand's ``E`` (Pa), ``nu``, ``rho`` (kg/m^3), ``cohesion`` (Pa).
        kind: the scene family of the training data (e.g. "column"), for messages.
        flip: the training MPM's ``Scene.flip`` (0: APIC alone, every model made before it
            was recorded).
        friction_angle: ``(lo, hi)`` degrees, the range of the training data's friction
            angles (the network's material input is their tangent); None when the folder
            does not record it.
    """

    bounds: tuple
    dx: float | None
    particles_per_cell: int
    frame_dt: float
    factor: int
    frame_stride: int
    material: dict = field(default_factory=dict)
    kind: str = "?"
    flip: float = 0.0
    friction_angle: tuple[float, float] | None = None

    @classmethod
    def from_info(cls, info: dict) -> ModelSource:
        """Read a model folder's ``config.json`` (the ``info`` of ``load_model``)."""
        src = info.get("source") or {}
        bounds = src.get("bounds") or info["gns"]["bounds"]
        dx = src.get("dx")
        if dx is None and src.get("width") and src.get("cells_across"):
            dx = float(src["width"]) / int(src["cells_across"])
        sand = Sand()
        material = {k: float(src.get("material", {}).get(k, getattr(sand, k)))
                    for k in _SAND_FIELDS}
        return cls(bounds=tuple((float(lo), float(hi)) for lo, hi in bounds),
                   dx=None if dx is None else float(dx),
                   particles_per_cell=int(src.get("particles_per_cell",
                                                  DEFAULT_PARTICLES_PER_CELL)),
                   frame_dt=float(src.get("dt", 2.5e-3)), factor=int(info.get("factor", 1)),
                   frame_stride=int(info.get("frame_stride", 1)), material=material,
                   kind=str(src.get("kind", "?")), flip=float(src.get("flip", 0.0)),
                   friction_angle=_pair(src.get("friction_angle")))

    @property
    def dim(self) -> int:
        """Spatial dimension of the model, 2 or 3 (the axes of its box)."""
        return len(self.bounds)

    @property
    def particle_spacing(self) -> float | None:
        """Spacing of the training MPM particles, m (``dx / (particles per cell)^(1/d)``)."""
        return None if self.dx is None else particle_spacing(self.dx, self.particles_per_cell,
                                                             self.dim)


@dataclass(frozen=True)
class SceneSupport:
    """A scene a model can run on: the observation operator it implies, and warnings.

    Attributes:
        factor: MPM particles of the scene per GNS node.
        frame_stride: MPM frames per GNS frame.
        warnings: what the scene has that the training data had not (runs, untrained).
    """

    factor: int
    frame_stride: int
    warnings: tuple[str, ...] = ()


def particle_spacing(dx: float, particles_per_cell: int, dim: int = 2) -> float:
    """Spacing of MPM particles seeded ``particles_per_cell`` to a cell of side ``dx`` (m) in
    ``dim`` dimensions: ``dx / ppc^(1/d)``."""
    return dx / (math.sqrt(particles_per_cell) if dim == 2 else float(np.cbrt(particles_per_cell)))


def node_factor(factor: int, trained_spacing: float, spacing: float, dim: int = 2) -> int:
    """MPM particles per node that keep the trained node spacing when the MPM particles are
    ``spacing`` apart instead of ``trained_spacing`` (m): ``factor * (trained / spacing)^d``;
    refuses when that is not a whole number of particles."""
    f = factor * (trained_spacing / spacing) ** dim
    if abs(f - round(f)) > 1e-6 or round(f) < 1:
        raise UnsupportedSceneError(
            f"the model groups {factor} particles per node at particle spacing "
            f"{trained_spacing:g} m; at {spacing:g} m that is {f:g} particles per node, not a "
            "whole number: choose a resolution with an integer ratio")
    return int(round(f))


def _pair(v) -> tuple[float, float] | None:
    return None if v is None else (float(v[0]), float(v[1]))


def friction_warnings(values: dict, info: dict, what: str = "") -> list[str]:
    """Warnings for friction angles outside the model's training range.

    Args:
        values: ``{name: degrees}``; names whose base is ``friction_angle`` (``friction_angle``
            or ``friction_angle[body]``, :mod:`diffgns.inverse.parameters`) are checked,
            others ignored.
        info: the model folder's ``config.json``; a folder without ``source.friction_angle``
            (made before it was recorded) gives no warning.
        what: how the values arose, for the message (e.g. "the recovered").
    Returns:
        one message per value outside ``[lo, hi]`` (with 1e-4 degrees of tolerance: the
        float32 round trip of the stored tangents).
    """
    rng = ModelSource.from_info(info).friction_angle
    if rng is None:
        return []
    lo, hi = rng
    out = []
    for name, v in values.items():
        if name.split("[")[0] != "friction_angle":
            continue
        v = float(v)
        if not lo - 1e-4 <= v <= hi + 1e-4:
            out.append(f"{(what + ' ') if what else ''}{name} = {v:.2f} deg is outside the "
                       f"{lo:.1f}-{hi:.1f} deg of the model's training data: the network's "
                       "material input tan(friction_angle) is extrapolated there, and the "
                       "result is not one the model was trained to give")
    return out


def _close(a: float, b: float) -> bool:
    return abs(a - b) <= 1e-9 * max(1.0, abs(a), abs(b))


def check_scene(scene: Scene, info: dict, resolution: str = "exact",
                model: str = "the model") -> SceneSupport:
    """Refuse a scene ``model`` (its ``config.json`` as ``info``) does not support.

    Args:
        scene: the scene to simulate.
        info: the model folder's ``config.json`` (third item of ``load_model``).
        resolution: "exact": the scene's MPM cell size and particles per cell must be the
            training ones (a GNS emulating that MPM); "node-spacing": any MPM resolution whose
            particles group into nodes at the trained spacing (a hybrid on a finer MPM).
        model: the model's name, for messages.
    Returns:
        :class:`SceneSupport` (particles per node, frame stride, warnings).
    Raises:
        UnsupportedSceneError naming every mismatch.
    """
    if resolution not in ("exact", "node-spacing"):
        raise ValueError(f"resolution must be 'exact' or 'node-spacing', got {resolution!r}")
    src = ModelSource.from_info(info)
    if scene.dim != src.dim:
        raise UnsupportedSceneError(
            f"{model} cannot simulate this scene: it is {scene.dim}D but the model is "
            f"{src.dim}D (a GNS runs only in the dimension it was trained in); use a model "
            f"trained on {scene.dim}D data")
    why = []
    box = tuple(tuple(ax) for ax in scene.domain)
    boxes = (info.get("source") or {}).get("boxes")
    if not boxes and not np.allclose(np.asarray(box), np.asarray(src.bounds), rtol=0,
                                     atol=1e-9):
        why.append(f"its box {_fmt_box(box)} m is not the training box {_fmt_box(src.bounds)} m")
    for i, b in enumerate(scene.bodies):
        name = f"body {b.name or i}"
        if not isinstance(b.material, Sand):
            why.append(f"{name} is {b.material.kind}, but the model was trained on sand only")
            continue
        diff = {k: (getattr(b.material, k), v) for k, v in src.material.items()
                if not _close(float(getattr(b.material, k)), v)}
        if diff:
            why.append(f"{name}'s sand has " + ", ".join(
                f"{k} = {got:g} (trained on {want:g})" for k, (got, want) in diff.items())
                + "; the network's only material input is tan(friction_angle)")
    # Body fills particles_per_cell and velocity per dimension at construction (never None)
    ppcs = sorted({int(b.particles_per_cell or 0) for b in scene.bodies})
    if resolution == "exact" and src.dx is not None:
        if not _close(scene.dx, src.dx):
            why.append(f"its MPM cell size dx = {scene.dx:g} m is not the {src.dx:g} m the model "
                       f"emulates ({info.get('source', {}).get('cells_across', '?')} cells "
                       f"across the {info.get('source', {}).get('width', '?')} m training "
                       "column)")
        if ppcs != [src.particles_per_cell]:
            why.append(f"its particles per cell {ppcs} are not the {src.particles_per_cell} "
                       "of the training data")
    elif len(ppcs) > 1:
        why.append(f"its bodies have different particles per cell {ppcs}")
    if not _close(scene.flip, src.flip):
        why.append(f"its MPM transfer has flip = {scene.flip:g}, but the model emulates the "
                   f"MPM with flip = {src.flip:g} (Scene.flip; the answer depends on it)")
    if not _close(scene.frame_dt, src.frame_dt):
        why.append(f"its frame_dt = {scene.frame_dt:g} s gives GNS frames of "
                   f"{scene.frame_dt * src.frame_stride:g} s (frame_dt x frame_stride "
                   f"{src.frame_stride}); the model steps {src.frame_dt * src.frame_stride:g} "
                   f"s (frame_dt = {src.frame_dt:g} s)")
    factor = src.factor
    if not why and resolution == "node-spacing":
        try:
            if src.particle_spacing is not None:
                factor = node_factor(src.factor, src.particle_spacing,
                                     particle_spacing(scene.dx, ppcs[0], src.dim), src.dim)
        except UnsupportedSceneError as e:
            why.append(str(e))
    if why:
        raise UnsupportedSceneError(f"{model} cannot simulate this scene: " + "; ".join(why))
    return SceneSupport(factor, src.frame_stride, tuple(_warnings(scene, info)))


#: scene families (:mod:`diffgns.scene.families`) whose training scenes have moving bodies
MOVING_FAMILIES = frozenset({"squares", "obstacles", "collision"})


def _warnings(scene: Scene, info: dict) -> list[str]:
    out = []
    boxes = np.asarray((info.get("source") or {}).get("boxes") or [], float)
    if len(boxes):
        ext = np.diff(np.asarray(scene.domain, float), axis=-1)[:, 0]
        trained = boxes[..., 1] - boxes[..., 0]  # (n_boxes, d) extents
        if np.any(ext > trained.max(0) + 1e-9) or np.any(ext < trained.min(0) - 1e-9):
            out.append(f"its box {_fmt_box(scene.domain)} m is outside the range of the "
                       "training boxes' sizes (" + ", ".join(_fmt_box(b) for b in boxes)
                       + " m); the network sees walls only within its radius, but flows "
                       "this long or short were not in training")
    if scene.obstacles and not info.get("gns", {}).get("use_obstacles", False):
        out.append(f"the scene has {len(scene.obstacles)} obstacle(s); the network has no "
                   "obstacle input (trained without obstacles)")
    families = set(info.get("families") or ())
    if (any(any(v != 0 for v in (b.velocity or ())) for b in scene.bodies)
            and not families & MOVING_FAMILIES):
        out.append("bodies start moving; the training scenes started at rest")
    if (info.get("source") or {}).get("kind") == "column" and not info.get("mirror"):
        x_left = float(scene.domain[0][0])
        off = [b.name or str(i) for i, b in enumerate(scene.bodies)
               if float(b.shape.lower[0]) - x_left > scene.dx]
        if off:
            out.append(f"body {', '.join(off)} does not rest against the left wall (x = "
                       f"{x_left:g} m); the model was trained on columns against the left wall "
                       "only, and a column against the right wall is 64-87% off in runout "
                       "(gns_cg16_pfn on the validation scenes; GNS guide)")
    out += friction_warnings(
        {f"friction_angle[{b.name or i}]": b.material.friction_angle
         for i, b in enumerate(scene.bodies) if isinstance(b.material, Sand)}, info, "body")
    trained_g = (0.0, -9.81) + (0.0,) * (scene.dim - 2)
    if tuple(scene.gravity or ()) != trained_g:
        out.append(f"gravity {scene.gravity} m/s^2 differs from the training ("
                   + ", ".join(f"{g:g}" for g in trained_g) + ")")
    return out


def _fmt_box(box) -> str:
    return " x ".join(f"[{lo:g}, {hi:g}]" for lo, hi in box)
