"""Incompressible Navier-Stokes past a cylinder: P2/P1 incremental pressure correction.

Equations (per unit density, SI units): ``du/dt + (u.grad)u - nu lap u + grad p = 0``,
``div u = 0`` on a :class:`~diffgns.mesh.geometry.ChannelMesh`, with

* inflow ``x = 0``: ``u = (4 Um y (H - y) / H^2, 0)`` (mean speed ``Ubar = 2 Um / 3``),
  optionally ramped in smoothly over ``ramp_time`` s;
* no slip on the channel walls and the cylinder (which may spin briefly, see ``kick``);
* outflow ``x = L``: do-nothing, ``nu du/dn = 0`` with ``p = 0``.

**Scheme.** Incremental pressure correction in rotational form (Timmermans et al. 1996;
Guermond, Minev & Shen 2006) with second-order backward differences (BDF2) and the convection
term extrapolated (``2 N(u^n) - N(u^{n-1})``, the IMEX "SBDF2" scheme); the first step is
BDF1/explicit Euler. Per step:

1. ``(3 u~ - 4 u^n + u^{n-1}) / (2 dt) - nu lap u~ = -grad p^n - (2 N^n - N^{n-1})``,
   ``u~ = g`` on Dirichlet boundaries;
2. ``-lap phi = -(3 / 2dt) div u~``, ``phi = 0`` at the outflow, ``dphi/dn = 0`` elsewhere;
3. ``u^{n+1} = u~ - (2 dt / 3) grad phi`` (L2 projection onto P2),
   ``p^{n+1} = p^n + phi - nu div u~`` (P1 projection of the divergence; 0 at the outflow).

Why: with explicit convection every matrix is constant, so the four sparse matrices are
LU-factorised once (scipy ``splu``) and a step is four triangular solves plus one cached
quadrature of the convection term -- ~10 ms for a 2k-vertex mesh on one core, versus a new
factorisation per step for semi-implicit convection. BDF2 and the rotational correction keep
velocity second-order in time and avoid the artificial pressure boundary layer of the standard
form; BDF2's damping of high frequencies (unlike Crank-Nicolson) keeps the explicit convection
robust. The price is a convective CFL limit: runs blew up at ``max|u| dt / h_min`` ~ 0.5
and ran at <= 0.3 (``h_min`` the shortest mesh edge), so ``dt`` is set by the mesh
(``Um dt / h_min <= 0.15`` in the datasets). That ``dt`` (5e-4 s on the 2.1k-vertex
Schäfer-Turek mesh) is ~1/670 of the shedding period, and halving it changed cD,max by
0.001% and cL,max by 0.02% (benchmarks/results/cfd_schafer_turek*.json): the time error is
far below the mesh error, so a larger-step implicit scheme would not buy accuracy here.

**Forces.** Drag and lift are the weak-form residual of the momentum equation tested with a
P2 field equal to ``e_x`` (``e_y``) at the cylinder dofs and 0 at all others (the "reaction
force" / volume-integral method of Babuska & Miller; John 2004): it converges at the rate of
the energy norm, twice the order of a line integral of gradients on the surface, and uses only
matrices already assembled. ``cD = 2 F_x / (Ubar^2 D)``, ``cL = 2 F_y / (Ubar^2 D)``.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from diffgns.errors import UnstableError
from diffgns.mesh.fem import Operators, assemble
from diffgns.mesh.geometry import ChannelMesh


@dataclass(frozen=True)
class FlowParams:
    """Physical and numerical parameters of a run (SI units, unit density).

    Attributes:
        u_max: peak inflow speed ``Um``, m/s (mean ``Ubar = 2 Um / 3``).
        nu: kinematic viscosity, m^2/s.
        dt: time step, s.
        ramp_time: the inflow rises as ``sin^2(pi t / (2 ramp_time))``; 0 = impulsive start.
        initial: ``"stokes"`` (the steady Stokes flow with the full inflow: smooth, solenoidal,
            no start-up pressure spike), ``"poiseuille"`` (inflow profile everywhere except on
            the cylinder; the impulsive start briefly doubles the speed next to the cylinder)
            or ``"rest"``; with ``ramp_time > 0`` the flow always starts from rest.
        kick: peak cylinder surface speed of a symmetry-breaking spin pulse, in units of
            ``Ubar`` (0 = none). The pulse is ``kick Ubar sin(pi t / kick_time)`` for
            ``t < kick_time``; it makes vortex shedding start within a few periods.
        kick_time: duration of the spin pulse, s.
        rotational: rotational (True) or standard incremental pressure correction.
        blowup_speed: raise :class:`UnstableError` once ``|u|`` exceeds this multiple of Um.
    """

    u_max: float = 1.5
    nu: float = 1e-3
    dt: float = 5e-4
    ramp_time: float = 0.0
    initial: str = "stokes"
    kick: float = 0.0
    kick_time: float = 0.5
    rotational: bool = True
    blowup_speed: float = 10.0

    def __post_init__(self):
        for name in ("u_max", "nu", "dt", "blowup_speed"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"FlowParams.{name} must be a positive number, got {v!r}")
        for name in ("ramp_time", "kick", "kick_time"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"FlowParams.{name} must be a number >= 0, got {v!r}")
        if self.initial not in ("stokes", "poiseuille", "rest"):
            raise ValueError(f"FlowParams.initial must be 'stokes', 'poiseuille' or 'rest', "
                             f"got {self.initial!r}")
        if self.kick > 0 and self.kick_time <= 0:
            raise ValueError("FlowParams.kick_time must be > 0 when kick > 0")


def reynolds(u_max: float, nu: float, diameter: float) -> float:
    """Re = Ubar D / nu with the mean inflow speed Ubar = 2 Um / 3."""
    return 2.0 * u_max / 3.0 * diameter / nu


class ProjectionSolver:
    """Time stepper; state ``u`` (n_u, 2) m/s on P2 dofs and ``p`` (n_p,) m^2/s^2 on P1 dofs."""

    def __init__(self, mesh: ChannelMesh, params: FlowParams, ops: Operators | None = None):
        self.mesh, self.prm = mesh, params
        self.ops = ops if ops is not None else assemble(mesh)
        o, g = self.ops, mesh.geometry
        fu, du, fp = o.free_u, o.dir_u, o.free_p
        self._profile = 4.0 * o.doflocs[o.inflow_u, 1] * (g.height - o.doflocs[o.inflow_u, 1]) \
            / g.height**2
        self._inflow_pos = np.searchsorted(du, o.inflow_u)
        self._cyl_pos = np.searchsorted(du, o.cyl_u)
        self._A, self._A_fd = {}, {}
        for order in (1, 2):  # BDF1 for the first step, BDF2 after
            a = self._a0(order) * o.M + params.nu * o.K
            self._A[order] = splu(sp.csc_matrix(a[fu][:, fu]))
            self._A_fd[order] = a[fu][:, du].tocsr()
        self._Kp = splu(sp.csc_matrix(o.Kp[fp][:, fp]))
        self._M = splu(sp.csc_matrix(o.M[fu][:, fu]))
        self._Mp = splu(sp.csc_matrix(o.Mp))
        self._BxT, self._ByT = o.Bx.T.tocsr(), o.By.T.tocsr()
        # rows of the residual summed over the cylinder dofs (force evaluation)
        c = o.cyl_u
        self._m_row = np.asarray(o.M[c].sum(axis=0)).ravel()
        self._k_row = np.asarray(o.K[c].sum(axis=0)).ravel()
        self._bx_row = np.asarray(o.Bx[:, c].sum(axis=1)).ravel()
        self._by_row = np.asarray(o.By[:, c].sum(axis=1)).ravel()
        self.u_bar = 2.0 * params.u_max / 3.0
        e = mesh.edges()
        self.h_min = float(np.min(np.linalg.norm(mesh.nodes[e[:, 0]] - mesh.nodes[e[:, 1]],
                                                 axis=1)))
        self.reset()

    # ------------------------------------------------------------------ set-up
    def _a0(self, order: int) -> float:
        return (1.0 if order == 1 else 1.5) / self.prm.dt

    def dirichlet(self, t: float) -> np.ndarray:
        """(len(dir_u), 2) prescribed velocity at time ``t`` on the Dirichlet dofs."""
        p, o = self.prm, self.ops
        g = np.zeros((len(o.dir_u), 2))
        ramp = 1.0 if t >= p.ramp_time else math.sin(0.5 * math.pi * t / p.ramp_time) ** 2
        g[self._inflow_pos, 0] = p.u_max * ramp * self._profile
        if p.kick > 0 and 0 < t < p.kick_time and self.mesh.geometry.has_cylinder:
            cx, cy = self.mesh.geometry.center
            s = p.kick * self.u_bar * math.sin(math.pi * t / p.kick_time) / \
                self.mesh.geometry.radius
            x = o.doflocs[o.cyl_u]
            g[self._cyl_pos, 0] = -s * (x[:, 1] - cy)
            g[self._cyl_pos, 1] = s * (x[:, 0] - cx)
        return g

    def reset(self) -> None:
        """Initial state at t = 0 (see ``FlowParams.initial``)."""
        o, g = self.ops, self.mesh.geometry
        self.t, self.n_steps = 0.0, 0
        self.u = np.zeros((o.n_u, 2))
        self.p = np.zeros(o.n_p)
        if self.prm.ramp_time == 0 and self.prm.initial == "stokes":
            self.u, self.p = self._stokes()
        elif self.prm.ramp_time == 0 and self.prm.initial == "poiseuille":
            y = o.doflocs[:, 1]
            self.u[:, 0] = 4.0 * self.prm.u_max * y * (g.height - y) / g.height**2
        self.u[o.dir_u] = self.dirichlet(0.0)
        self.u_prev = self.u.copy()
        self.n_cur = o.convection(self.u)
        self.n_prev = self.n_cur

    def _stokes(self) -> tuple[np.ndarray, np.ndarray]:
        """Steady Stokes flow (u, p) with the t = 0 boundary values and a do-nothing outflow."""
        o, nu = self.ops, self.prm.nu
        n = o.n_u
        a = sp.bmat([[nu * o.K, None, -o.Bx.T], [None, nu * o.K, -o.By.T],
                     [-o.Bx, -o.By, None]]).tocsr()
        fixed = np.concatenate([o.dir_u, n + o.dir_u])
        free = np.setdiff1d(np.arange(a.shape[0]), fixed)
        g = self.dirichlet(0.0)
        x = np.zeros(a.shape[0])
        x[fixed] = np.concatenate([g[:, 0], g[:, 1]])
        x[free] = splu(sp.csc_matrix(a[free][:, free])).solve(-(a[free][:, fixed] @ x[fixed]))
        p = x[2 * n:]
        return np.stack([x[:n], x[n:2 * n]], axis=1), p - p[o.out_p].mean()

    # ---------------------------------------------------------------- stepping
    def step(self) -> None:
        """Advance one time step; raises :class:`UnstableError` on blow-up."""
        o, prm = self.ops, self.prm
        order = 1 if self.n_steps == 0 else 2
        a0, dt = self._a0(order), prm.dt
        fu, du, fp = o.free_u, o.dir_u, o.free_p
        t1 = self.t + dt
        g = self.dirichlet(t1)
        if order == 1:
            hist, conv = self.u / dt, self.n_cur
        else:
            hist = (4.0 * self.u - self.u_prev) / (2.0 * dt)
            conv = 2.0 * self.n_cur - self.n_prev
        rhs = o.M @ hist - conv
        rhs[:, 0] += self._BxT @ self.p
        rhs[:, 1] += self._ByT @ self.p
        ut = np.empty_like(self.u)
        ut[du] = g
        ut[fu] = self._A[order].solve(rhs[fu] - self._A_fd[order] @ g)
        div = o.Bx @ ut[:, 0] + o.By @ ut[:, 1]
        phi = np.zeros(o.n_p)
        phi[fp] = self._Kp.solve(-a0 * div[fp])
        corr = np.stack([self._BxT @ phi, self._ByT @ phi], axis=1)
        u_new = ut
        u_new[fu] += self._M.solve(corr[fu]) / a0
        p_new = self.p + phi
        if prm.rotational:
            p_new -= prm.nu * self._Mp.solve(div)
        p_new[o.out_p] = 0.0
        self.u_prev, self.u, self.p = self.u, u_new, p_new
        self.n_prev, self.n_cur = self.n_cur, o.convection(u_new)
        self._dudt = a0 * u_new - hist
        self.t, self.n_steps = t1, self.n_steps + 1
        speed = float(np.sqrt(np.max(np.sum(u_new**2, axis=1))))
        if not math.isfinite(speed) or speed > prm.blowup_speed * prm.u_max:
            raise UnstableError(
                f"CFD blow-up at t = {self.t:.4g} s (step {self.n_steps}): max |u| = {speed:.3g}"
                f" m/s > {prm.blowup_speed} x Um; reduce dt (now {dt:g} s, convective CFL "
                f"{self.cfl():.2f}) or refine the mesh")

    def cfl(self) -> float:
        """Convective CFL number ``max|u| dt / h_min`` of the current state."""
        return float(np.sqrt(np.max(np.sum(self.u**2, axis=1)))) * self.prm.dt / self.h_min

    def forces(self) -> tuple[float, float]:
        """(cD, cL) at the current time from the weak-form residual on the cylinder dofs."""
        if not self.mesh.geometry.has_cylinder or self.n_steps == 0:
            return float("nan"), float("nan")
        u, nu = self.u, self.prm.nu
        f = -(self._m_row @ self._dudt + nu * (self._k_row @ u) + self.n_cur[self.ops.cyl_u].sum(0))
        f[0] += self._bx_row @ self.p
        f[1] += self._by_row @ self.p
        scale = 2.0 / (self.u_bar**2 * 2.0 * self.mesh.geometry.radius)
        return float(scale * f[0]), float(scale * f[1])

    def vertex_fields(self) -> tuple[np.ndarray, np.ndarray]:
        """Velocity (N, 2) m/s and pressure (N,) m^2/s^2 at the mesh vertices (copies)."""
        n = self.mesh.n_nodes
        return self.u[:n].copy(), self.p[:n].copy()

    def divergence_l2(self) -> float:
        """L2 norm of the P1 projection of div u, 1/s (0 for an exactly solenoidal field)."""
        o = self.ops
        d = self._Mp.solve(o.Bx @ self.u[:, 0] + o.By @ self.u[:, 1])
        return float(np.sqrt(max(d @ (o.Mp @ d), 0.0)))


@dataclass
class CaseResult:
    """Output of :func:`run_case`.

    Attributes:
        frame_times: (F,) s.  velocity: (F, N, 2) m/s.  pressure: (F, N) m^2/s^2 (per unit
        density), both at mesh vertices.  times, cd, cl: (S,) force history at every step.
        wall_time_s: wall time of the time loop (assembly excluded), s.  setup_s: assembly
        and factorisation, s.  info: dt, dofs, Re, CFL, h_min.
    """

    frame_times: np.ndarray
    velocity: np.ndarray
    pressure: np.ndarray
    times: np.ndarray
    cd: np.ndarray
    cl: np.ndarray
    wall_time_s: float
    setup_s: float
    info: dict

    @property
    def wall_per_sim_second(self) -> float:
        return self.wall_time_s / float(self.times[-1]) if len(self.times) else float("nan")


def _n_steps(interval: float, dt: float, name: str) -> int:
    n = round(interval / dt)
    if abs(n * dt - interval) > 1e-6 * max(dt, interval):
        raise ValueError(f"run_case: {name} ({interval:g} s) must be a multiple of dt ({dt:g} s)")
    return int(n)


def run_case(mesh: ChannelMesh, params: FlowParams, t_end: float, frame_dt: float,
             record_start: float = 0.0, progress: bool = False) -> CaseResult:
    """Run ``params`` on ``mesh`` for ``t_end`` s; keep frames every ``frame_dt`` s from
    ``record_start`` (inclusive) to ``t_end`` and the drag/lift at every step.

    Raises:
        ValueError: non-positive ``t_end``/``frame_dt``, intervals not multiples of ``dt``,
            ``record_start`` outside ``[0, t_end]``.
        UnstableError: on blow-up (non-finite velocity or ``|u| > blowup_speed Um``).
    """
    if not (math.isfinite(t_end) and t_end > 0 and math.isfinite(frame_dt) and frame_dt > 0):
        raise ValueError(f"run_case: t_end and frame_dt must be > 0, got {t_end}, {frame_dt}")
    if not 0 <= record_start <= t_end:
        raise ValueError(f"run_case: record_start ({record_start}) must be in [0, t_end]")
    dt = params.dt
    n_total = _n_steps(t_end, dt, "t_end")
    every = _n_steps(frame_dt, dt, "frame_dt")
    first = _n_steps(record_start, dt, "record_start")
    t0 = time.perf_counter()
    s = ProjectionSolver(mesh, params)
    setup = time.perf_counter() - t0
    frames_u, frames_p, frame_t = [], [], []
    times, cd, cl = np.zeros(n_total), np.zeros(n_total), np.zeros(n_total)
    max_cfl = 0.0

    def keep():
        u, p = s.vertex_fields()
        frames_u.append(u)
        frames_p.append(p)
        frame_t.append(s.t)

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n_total, desc="CFD steps", leave=False)
    t0 = time.perf_counter()
    if first == 0:
        keep()
    for k in range(1, n_total + 1):
        s.step()
        times[k - 1] = s.t
        cd[k - 1], cl[k - 1] = s.forces()
        if k >= first and (k - first) % every == 0:
            keep()
        if k % 100 == 0:
            max_cfl = max(max_cfl, s.cfl())
            if bar is not None:
                bar.update(100)
    wall = time.perf_counter() - t0
    if bar is not None:
        bar.close()
    g = mesh.geometry
    info = dict(dt=dt, n_steps=n_total, n_vertices=mesh.n_nodes, n_velocity_dofs=int(s.ops.n_u),
                n_pressure_dofs=int(s.ops.n_p), h_min=s.h_min, max_cfl=max_cfl,
                reynolds=reynolds(params.u_max, params.nu, 2 * g.radius) if g.has_cylinder
                else None)
    return CaseResult(frame_times=np.asarray(frame_t), velocity=np.stack(frames_u),
                      pressure=np.stack(frames_p), times=times, cd=cd, cl=cl,
                      wall_time_s=wall, setup_s=setup, info=info)
