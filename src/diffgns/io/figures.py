"""Plots, animations and VTK output of trajectories.

All figures are drawn with matplotlib's Agg canvas through the object-oriented API (no
``pyplot``), so this module works headless, never changes the global backend and leaves no
figures behind. Animations are GIFs written by matplotlib's ``PillowWriter`` (ffmpeg is not
needed). VTK output uses ``pyevtk``: one ``.vtu`` per frame plus a ``.pvd`` collection that
ParaView opens as a time series.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.animation import PillowWriter
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from pyevtk.hl import pointsToVTK
from pyevtk.vtk import VtkGroup

from diffgns.trajectory import ELASTIC, FLUID, KINEMATIC, SAND, Trajectory

TYPE_COLORS = {SAND: "#c2a25a", FLUID: "#2f7fc1", ELASTIC: "#3a9a4a", KINEMATIC: "#444444"}
"""Colour of each particle type in :func:`animate` (other types are drawn grey)."""

_PANEL_INCHES = 4.0


def _new_figure(figsize: tuple[float, float]) -> Figure:
    fig = Figure(figsize=figsize, dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _union_bounds(bounds_list: Sequence) -> tuple[tuple[float, float], ...]:
    """((min, max), ...) per axis over bounds of one dimension (2 or 3 axes)."""
    b = np.asarray([np.asarray(bd, dtype=float).reshape(-1, 2) for bd in bounds_list])
    return tuple((float(b[:, d, 0].min()), float(b[:, d, 1].max())) for d in range(b.shape[1]))


def _default_marker_size(n_particles: int) -> float:
    """Marker area in points^2 so that a few thousand particles stay readable."""
    return float(np.clip(2.0e4 / max(n_particles, 1), 0.3, 20.0))


def _type_colors(particle_type: np.ndarray) -> list[str]:
    return [TYPE_COLORS.get(int(t), "#999999") for t in particle_type]


class _PalettePillowWriter(PillowWriter):
    """``PillowWriter`` that keeps each grabbed frame as an 8-bit palette image.

    The stock writer holds every frame as RGB until :meth:`finish`; palette frames need a third
    of the memory and GIF stores them as palette images anyway.
    """

    def grab_frame(self, **savefig_kwargs) -> None:
        super().grab_frame(**savefig_kwargs)
        frame = self._frames[-1]
        self._frames[-1] = frame.convert("RGB").quantize(colors=256)


def _animation_frames(trajs: Trajectory | Sequence[Trajectory],
                      titles: Sequence[str] | None, color: str, every: int
                      ) -> tuple[list[Trajectory], float, list[np.ndarray],
                                 list[np.ndarray] | None, Normalize | None]:
    """The checked inputs of an animation: (trajectories, frame dt, the drawn positions per
    trajectory, their speeds or None, the shared speed Normalize or None). Only the frames
    that are drawn (0, every, 2 every, ...) are copied to the host."""
    runs = [trajs] if isinstance(trajs, Trajectory) else list(trajs)
    if not runs:
        raise ValueError("animate needs at least one trajectory")
    if titles is not None and len(titles) != len(runs):
        raise ValueError(f"got {len(titles)} titles for {len(runs)} trajectories")
    if color not in ("type", "speed"):
        raise ValueError(f"color must be 'type' or 'speed', got {color!r}")
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    dims = {int(t.positions.shape[-1]) for t in runs}
    if len(dims) > 1:
        raise ValueError(f"trajectories mix dimensions {sorted(dims)}; animate 2D and 3D "
                         "trajectories separately")
    dt = float(runs[0].frame_dt)
    if any(not np.isclose(float(t.frame_dt), dt, rtol=1e-6, atol=0) for t in runs):
        raise ValueError(f"trajectories have different frame_dt: {[t.frame_dt for t in runs]}")
    pos = [np.asarray(t.positions[::every]) for t in runs]
    speed, norm = None, None
    if color == "speed":
        speed = [np.linalg.norm(np.asarray(t.velocities[::every]), axis=-1) for t in runs]
        norm = Normalize(vmin=0.0, vmax=max(float(sp.max()) for sp in speed) or 1.0)
    return runs, dt, pos, speed, norm


def _record(fig: Figure, path: str | Path, fps: int, n_draw: int, seconds_per_draw: float,
            draw) -> Path:
    """Write the GIF ``path``: for k = 0 .. n_draw - 1, ``draw(k)`` updates the artists, the
    figure title shows ``t = k * seconds_per_draw`` and the frame is grabbed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    label = fig.suptitle("", fontsize=10)
    writer = _PalettePillowWriter(fps=fps)
    with writer.saving(fig, str(path), dpi=fig.dpi):
        for k in range(n_draw):
            draw(k)
            label.set_text(f"t = {k * seconds_per_draw:.3f} s")
            writer.grab_frame()
    return path


def animate(
    trajs: Trajectory | Sequence[Trajectory],
    path: str | Path,
    titles: Sequence[str] | None = None,
    fps: int = 20,
    every: int = 1,
    color: str = "type",
    s: float | None = None,
) -> Path:
    """Save a GIF with one panel per trajectory, side by side.

    Args:
        trajs: a trajectory or a list of them (same ``frame_dt``). Shorter trajectories hold
            their last frame.
        path: output ``.gif``.
        titles: one title per panel.
        fps: frames per second of the GIF.
        every: draw every ``every``-th frame (0, every, 2 every, ...).
        color: ``"type"`` (fixed colour per particle type, see :data:`TYPE_COLORS`) or
            ``"speed"`` (|v| in m/s, one colour scale shared by all panels).
        s: marker area in points^2; chosen from the particle count if ``None``.

    All panels share the axis limits (the union of the trajectories' bounds, m) with equal
    aspect; the figure title shows the time ``t = 0.125 s``. Returns the path written. (3D
    trajectories: :func:`diffgns.io.figures3d.animate3d`, the same machinery in a 3D view.)
    """
    runs, dt, pos, speed, norm = _animation_frames(trajs, titles, color, every)
    if pos[0].shape[-1] != 2:
        raise ValueError(f"animate draws 2D trajectories, positions (T, N, 2), got "
                         f"{pos[0].shape}; use diffgns.io.figures3d.animate3d in 3D")
    n_draw = max(p.shape[0] for p in pos)
    (xmin, xmax), (ymin, ymax) = _union_bounds([t.bounds for t in runs])
    aspect = (ymax - ymin) / (xmax - xmin)
    panel_h = float(np.clip(_PANEL_INCHES * aspect, 1.5, 2 * _PANEL_INCHES))
    fig = _new_figure((_PANEL_INCHES * len(runs) + (1.0 if speed else 0.0), panel_h + 0.6))
    axes = fig.subplots(1, len(runs), squeeze=False)[0]

    scatters = []
    for i, (ax, traj) in enumerate(zip(axes, runs, strict=True)):
        ax.set_xlim(xmin, xmax)
        ax.set_ylim(ymin, ymax)
        ax.set_aspect("equal")
        ax.tick_params(labelsize=7)
        if titles is not None:
            ax.set_title(titles[i], fontsize=9)
        size = _default_marker_size(traj.n_particles) if s is None else s
        if speed is None:
            sc = ax.scatter(*pos[i][0].T, s=size, c=_type_colors(np.asarray(traj.particle_type)),
                            linewidths=0)
        else:
            sc = ax.scatter(*pos[i][0].T, s=size, c=speed[i][0], cmap="viridis", norm=norm,
                            linewidths=0)
        scatters.append(sc)
    if speed is not None:
        fig.colorbar(scatters[0], ax=list(axes), label="speed (m/s)", shrink=0.8)

    def draw(k: int) -> None:
        for i, sc in enumerate(scatters):
            j = min(k, pos[i].shape[0] - 1)
            sc.set_offsets(pos[i][j])
            if speed is not None:
                sc.set_array(speed[i][j])

    return _record(fig, path, fps, n_draw, every * dt, draw)


def plot_runout(
    times: np.ndarray | Sequence[np.ndarray],
    runouts: np.ndarray | Sequence[np.ndarray],
    path: str | Path,
    labels: Sequence[str] | None = None,
    L0: float | None = None,
    references: Sequence[tuple[float, str]] | None = None,
    ylabel: str | None = None,
    title: str | None = None,
) -> Path:
    """Plot runout versus time for one or more runs.

    Args:
        times: (T,) times in s shared by all curves, or one (T_i,) array per curve (a list or
            an (n_curves, T) array).
        runouts: (T,) runout in m, a list of (T_i,) arrays or a (n_curves, T) array.
        path: output image (format from the suffix, e.g. ``.png``).
        labels: legend entry per curve; say which runout each is (farthest particle, deposit
            front, ...).
        L0: initial length of the column in m; if given, the normalised runout
            ``(L - L0) / L0`` is plotted instead of ``L``.
        references: (value, label) horizontal reference lines (dashed, in the legend), in the
            plotted quantity: normalised if ``L0`` is given, else m. E.g. Lube et al.'s law.
        ylabel: y-axis label (default ``(L - L0) / L0`` or ``runout L (m)``).
        title: figure title.
    """
    runouts = np.asarray(runouts) if not isinstance(runouts, (list, tuple)) else runouts
    curves = [np.asarray(r) for r in ([runouts] if np.ndim(runouts[0]) == 0 else runouts)]
    if np.ndim(times[0]) == 1:  # one time array per curve (list or 2-D array)
        time_list = [np.asarray(t) for t in times]
    else:
        time_list = [np.asarray(times)] * len(curves)
    if len(time_list) != len(curves):
        raise ValueError(f"got {len(time_list)} time arrays for {len(curves)} runout curves")
    if labels is not None and len(labels) != len(curves):
        raise ValueError(f"got {len(labels)} labels for {len(curves)} runout curves")
    references = list(references or [])
    for value, label in references:
        if not np.isfinite(value) or not label:
            raise ValueError(f"reference lines need a finite value and a label, got "
                             f"({value!r}, {label!r})")
    fig = _new_figure((5.5, 3.8))
    ax = fig.subplots()
    for i, (t, r) in enumerate(zip(time_list, curves, strict=True)):
        if t.shape != r.shape:
            raise ValueError(f"curve {i}: times shape {t.shape} != runout shape {r.shape}")
        y = (r - L0) / L0 if L0 is not None else r
        ax.plot(t, y, label=labels[i] if labels is not None else None)
    for k, (value, label) in enumerate(references):
        ax.axhline(value, ls="--", lw=1.2, color=f"C{(len(curves) + k) % 10}", label=label)
    ax.set_xlabel("t (s)")
    ax.set_ylabel(ylabel or ("(L - L0) / L0" if L0 is not None else "runout L (m)"))
    if title:
        ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    if labels is not None or references:
        ax.legend(fontsize=7)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def plot_deposits(
    deposits: Sequence[tuple[np.ndarray, str]],
    path: str | Path,
    bounds: Sequence[Sequence[float]],
    s: float | None = None,
) -> Path:
    """Overlay final deposits, one colour per run (3D deposits: their side view, the x–y
    projection).

    Args:
        deposits: list of (positions (N_i, d) in m, label), d = 2 or 3 (all alike).
        path: output image.
        bounds: ((xmin, xmax), (ymin, ymax)[, (zmin, zmax)]) axis limits in m.
        s: marker area in points^2; chosen from the largest particle count if ``None``.
    """
    if not deposits:
        raise ValueError("plot_deposits needs at least one deposit")
    dim = len(bounds)
    (xmin, xmax), (ymin, ymax) = _union_bounds([bounds])[:2]
    aspect = (ymax - ymin) / (xmax - xmin)
    fig = _new_figure((6.0, float(np.clip(6.0 * aspect, 2.0, 8.0)) + 0.6))
    ax = fig.subplots()
    colors = [f"C{i % 10}" for i in range(len(deposits))]
    for (positions, label), col in zip(deposits, colors, strict=True):
        positions = np.asarray(positions)
        if positions.ndim != 2 or positions.shape[1] != dim:
            raise ValueError(f"deposit '{label}': positions must be (N, {dim}) for {dim}D "
                             f"bounds, got {positions.shape}")
        size = _default_marker_size(positions.shape[0]) if s is None else s
        ax.scatter(positions[:, 0], positions[:, 1], s=size, color=col, alpha=0.5,
                   linewidths=0, label=label)
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    legend = ax.legend(fontsize=8)
    for handle in legend.legend_handles:  # legible legend markers whatever the particle size
        handle.set_sizes([20.0])
        handle.set_alpha(1.0)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def write_vtk(
    traj: Trajectory, out_dir: str | Path, prefix: str = "particles", every: int = 1
) -> list[Path]:
    """Write frames of ``traj`` as VTK unstructured-grid point clouds.

    Frame ``t`` (for t = 0, every, 2 every, ...) goes to ``<out_dir>/<prefix>_<t:05d>.vtu`` with
    the points (m; z = 0 for a 2D trajectory) and point data ``velocity`` (3-vectors, m/s;
    z = 0 in 2D), ``speed`` (m/s),
    ``particle_type`` and ``material``. ``<out_dir>/<prefix>.pvd`` collects them with their
    times in s.

    Returns:
        The ``.vtu`` paths in frame order followed by the ``.pvd`` path (last element).
    """
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ptype = np.ascontiguousarray(np.asarray(traj.particle_type))
    material = np.ascontiguousarray(np.asarray(traj.material))
    group = VtkGroup(str(out_dir / prefix))
    paths = []
    for t in range(0, traj.n_frames, every):
        pos = np.asarray(traj.positions[t])
        vel = np.asarray(traj.velocities[t])
        x, y = np.ascontiguousarray(pos[:, 0]), np.ascontiguousarray(pos[:, 1])
        vx, vy = np.ascontiguousarray(vel[:, 0]), np.ascontiguousarray(vel[:, 1])
        three = pos.shape[1] == 3  # 3D trajectories keep their z; 2D ones lie in z = 0
        z = np.ascontiguousarray(pos[:, 2]) if three else np.zeros_like(x)
        vz = np.ascontiguousarray(vel[:, 2]) if three else np.zeros_like(vx)
        data = {
            "velocity": (vx, vy, vz),
            "speed": np.ascontiguousarray(np.sqrt(vx * vx + vy * vy + vz * vz) if three
                                          else np.hypot(vx, vy)),
            "particle_type": ptype,
            "material": material,
        }
        written = pointsToVTK(str(out_dir / f"{prefix}_{t:05d}"), x, y, z, data=data)
        paths.append(Path(written))
        group.addFile(filepath=written, sim_time=t * float(traj.frame_dt))
    group.save()
    return [*paths, out_dir / f"{prefix}.pvd"]


def plot_convergence(result, path: str | Path, truth: dict | None = None) -> Path:
    """Parameters and loss per iteration of an inverse run (``InverseResult``).

    One panel per parameter (with the true value dashed, if given) and a log-scale loss panel.
    """
    names = list(result.history[0]["theta"])
    fig = _new_figure((4.0 * (len(names) + 1), 3.2))
    axes = np.atleast_1d(fig.subplots(1, len(names) + 1))
    it = result.series("iteration")
    for ax, name in zip(axes, names):
        ax.plot(it, result.series("theta", name), "o-")
        if truth and name in truth:
            ax.axhline(truth[name], ls="--", color="k", label="target")
            ax.legend(fontsize=8)
        ax.set_xlabel("iteration")
        ax.set_ylabel(name)
    loss = np.maximum(result.series("loss"), 1e-30)
    axes[-1].semilogy(it, loss, "o-", color="C3")
    axes[-1].set_xlabel("iteration")
    axes[-1].set_ylabel("loss")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
