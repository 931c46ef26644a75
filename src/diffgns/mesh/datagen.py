"""Cylinder-flow training sets: random Reynolds numbers and cylinder geometries, one CFD run
per trajectory, written with :class:`~diffgns.mesh.dataset.CylinderDatasetWriter`.

Each sample draws, from its own seeded generator (so sample ``i`` is the same whether or not
earlier samples were written, and interrupted runs resume by skipping stored keys):

* the Reynolds number ``Re = Ubar D / nu`` uniformly in ``re_range``;
* the peak inflow speed ``Um`` uniformly in ``u_max_range`` (``Ubar = 2 Um / 3``); the
  viscosity follows as ``nu = Ubar D / Re``, so speed and Re vary independently;
* the radius uniformly in ``radius_range`` and the centre uniformly in ``cx_range`` x
  ``cy_range`` (rejected and redrawn if closer than ``min_gap`` to a channel wall).

The time step is the largest divisor of ``frame_dt`` with convective CFL ``Um dt / h_min``
at most ``cfl``. The flow starts from the steady Stokes field and runs ``spinup`` convective
time units ``D / Ubar`` (rounded up to whole frames) before the first of the ``n_frames``
stored frames, ``frame_dt`` s apart. The default spin-up was chosen by measuring when the
peak-to-peak lift settles within 2% of its final value
(:func:`~diffgns.mesh.analysis.shedding_onset`) on the dataset mesh: 31 D/Ubar at Re = 80
(Um = 1, D = 0.1), 22 D/Ubar at Re = 160 (Um = 2, D = 0.08); 35 leaves a margin.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from diffgns.mesh.analysis import shedding_metrics
from diffgns.mesh.cfd import FlowParams, run_case
from diffgns.mesh.dataset import CylinderDatasetWriter
from diffgns.mesh.geometry import ChannelGeometry, ChannelMesh, build_mesh


@dataclass(frozen=True)
class CylinderSampling:
    """Ranges (min, max) of the random cases and the fixed channel (SI units)."""

    re_range: tuple[float, float] = (80.0, 160.0)
    u_max_range: tuple[float, float] = (1.0, 2.0)
    radius_range: tuple[float, float] = (0.04, 0.06)
    cx_range: tuple[float, float] = (0.15, 0.35)
    cy_range: tuple[float, float] = (0.16, 0.25)
    length: float = 2.2
    height: float = 0.41
    min_gap: float = 0.05

    def __post_init__(self):
        for name in ("re_range", "u_max_range", "radius_range", "cx_range", "cy_range"):
            lo, hi = (float(v) for v in getattr(self, name))
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
                raise ValueError(f"CylinderSampling.{name} must be (min, max) with "
                                 f"0 < min <= max, got {getattr(self, name)}")
            object.__setattr__(self, name, (lo, hi))
        r = self.radius_range[1] + self.min_gap
        if not (min(self.cy_range[1], self.height - r) >= max(self.cy_range[0], r)):
            raise ValueError(f"CylinderSampling: no centre height in cy_range {self.cy_range} "
                             f"keeps radius {self.radius_range[1]} + gap {self.min_gap} "
                             f"inside the channel of height {self.height}")
        if self.cx_range[0] - r < 0 or self.cx_range[1] + r > self.length:
            raise ValueError(f"CylinderSampling: cx_range {self.cx_range} puts the cylinder "
                             f"closer than {self.min_gap} m to the inflow/outflow")


def sample_case(sampling: CylinderSampling, seed: int, index: int) -> dict:
    """Parameters of sample ``index`` (Re, u_max, nu, radius, center) -- deterministic."""
    rng = np.random.default_rng([seed, index])
    s = sampling
    re = rng.uniform(*s.re_range)
    u_max = rng.uniform(*s.u_max_range)
    radius = rng.uniform(*s.radius_range)
    for _ in range(1000):
        cx, cy = rng.uniform(*s.cx_range), rng.uniform(*s.cy_range)
        if min(cy, s.height - cy) - radius >= s.min_gap:
            break
    else:  # pragma: no cover - excluded by CylinderSampling validation
        raise ValueError("could not place the cylinder; widen cy_range")
    nu = (2.0 * u_max / 3.0) * 2.0 * radius / re
    return dict(reynolds=float(re), u_max=float(u_max), nu=float(nu), radius=float(radius),
                center=[float(cx), float(cy)], length=s.length, height=s.height)


def choose_dt(mesh: ChannelMesh, u_max: float, frame_dt: float, cfl: float) -> float:
    """Largest ``frame_dt / k`` (k integer) with ``u_max dt / h_min <= cfl``."""
    e = mesh.edges()
    h_min = float(np.min(np.linalg.norm(mesh.nodes[e[:, 0]] - mesh.nodes[e[:, 1]], axis=1)))
    return frame_dt / math.ceil(frame_dt * u_max / (cfl * h_min) - 1e-9)


@dataclass(frozen=True)
class CylinderRun:
    """Numerical settings shared by all trajectories of a dataset (SI units; ``spinup`` in
    convective time units D / Ubar)."""

    n_frames: int = 300
    frame_dt: float = 0.01
    spinup: float = 35.0
    size_cylinder: float = 0.008
    size_far: float = 0.035
    grading: float = 0.25
    size_wake: float | None = 0.014
    wake_length: float = 1.0
    cfl: float = 0.15
    kick: float = 0.0
    kick_time: float = 0.5

    def __post_init__(self):
        if not (isinstance(self.n_frames, int) and self.n_frames >= 2):
            raise ValueError(f"CylinderRun.n_frames must be an integer >= 2, got {self.n_frames}")
        for name in ("frame_dt", "size_cylinder", "size_far", "grading", "cfl"):
            if not getattr(self, name) > 0:
                raise ValueError(f"CylinderRun.{name} must be > 0, got {getattr(self, name)}")
        if not self.spinup >= 0:
            raise ValueError(f"CylinderRun.spinup must be >= 0, got {self.spinup}")


def case_setup(case: dict, run: CylinderRun) -> tuple[ChannelMesh, FlowParams]:
    """The mesh and flow parameters (time step by :func:`choose_dt`) of one case."""
    geom = ChannelGeometry(length=case["length"], height=case["height"],
                           center=tuple(case["center"]), radius=case["radius"])
    mesh = build_mesh(geom, size_cylinder=run.size_cylinder, size_far=run.size_far,
                      grading=run.grading, size_wake=run.size_wake,
                      wake_length=run.wake_length)
    dt = choose_dt(mesh, case["u_max"], run.frame_dt, run.cfl)
    prm = FlowParams(u_max=case["u_max"], nu=case["nu"], dt=dt, kick=run.kick,
                     kick_time=run.kick_time)
    return mesh, prm


def simulate_case(case: dict, run: CylinderRun, progress: bool = False) -> tuple[dict, dict]:
    """Mesh and run one case; returns (arrays, attrs) for :class:`CylinderDatasetWriter`."""
    mesh, prm = case_setup(case, run)
    dt = prm.dt
    u_bar = 2.0 * case["u_max"] / 3.0
    spin = math.ceil(run.spinup * 2 * case["radius"] / u_bar / run.frame_dt - 1e-9) \
        * run.frame_dt
    t_end = spin + (run.n_frames - 1) * run.frame_dt
    res = run_case(mesh, prm, t_end, run.frame_dt, record_start=spin, progress=progress)
    idx = np.searchsorted(res.times, res.frame_times - 0.5 * dt)  # force samples at frames
    met = shedding_metrics(res.times, res.cd, res.cl, spin, 2 * case["radius"], u_bar)
    arrays = dict(mesh_pos=mesh.nodes, cells=mesh.cells, node_type=mesh.node_type,
                  on_cylinder=mesh.on_cylinder, velocity=res.velocity, pressure=res.pressure,
                  time=res.frame_times, cd=res.cd[idx], cl=res.cl[idx])
    attrs = dict(case, frame_dt=run.frame_dt, dt=dt, spinup=spin, n_vertices=mesh.n_nodes,
                 n_cells=len(mesh.cells), cfd_wall_time_s=res.wall_time_s,
                 cfd_setup_s=res.setup_s, cfd_wall_per_sim_second=res.wall_per_sim_second,
                 max_cfl=res.info["max_cfl"], strouhal=met["strouhal"],
                 cd_mean=met["cd_mean"], cl_max=met["cl_max"],
                 cl_amplitude_drift=met["cl_amplitude_drift"])
    return arrays, attrs


def time_case(case: dict, run: CylinderRun, n_frames: int = 50,
              repeats: int = 1) -> float:
    """CFD wall seconds per simulated second of ``case`` (a trajectory's attrs) on the mesh
    and time step :func:`simulate_case` uses, timed now (assembly excluded, median of
    ``repeats`` runs of ``n_frames`` frames from the Stokes start), so that a speed
    comparison can be made against the CFD in the same run."""
    if not (isinstance(n_frames, int) and n_frames >= 1 and repeats >= 1):
        raise ValueError(f"time_case: n_frames and repeats must be >= 1, got {n_frames}, "
                         f"{repeats}")
    mesh, prm = case_setup(case, run)
    walls = [run_case(mesh, prm, n_frames * run.frame_dt, run.frame_dt).wall_per_sim_second
             for _ in range(repeats)]
    return float(np.median(walls))


def generate_cylinder(path, n: int, seed: int = 0, sampling: CylinderSampling | None = None,
                      run: CylinderRun | None = None, progress: bool = True,
                      recipe: dict | None = None, staged: bool = False) -> Path:
    """Write ``n`` cylinder-flow trajectories to ``path`` (resumes; see module docstring).

    ``recipe`` and ``staged`` go to the writer
    (:class:`~diffgns.io.dataset.H5TrajectoryFile`): a resume with another recipe is refused
    before anything is written, and a staged new file is built as ``<path>.partial`` and
    renamed when all ``n`` trajectories are written."""
    if not (isinstance(n, int) and n >= 1):
        raise ValueError(f"generate_cylinder: n must be a positive integer, got {n}")
    sampling = sampling or CylinderSampling()
    run = run or CylinderRun()
    extra = dict(seed=seed, sampling=asdict(sampling), run=asdict(run))
    with CylinderDatasetWriter(path, metadata_extra=extra, recipe=recipe, staged=staged) as w:
        for i in tqdm(range(n), desc="cylinder flows", disable=not progress):
            key = f"{i:05d}"
            if w.has(key):
                continue
            arrays, attrs = simulate_case(sample_case(sampling, seed, i), run, progress)
            w.write(key, arrays, dict(attrs, seed=seed, index=i))
        w.finalize()
    return Path(path)
