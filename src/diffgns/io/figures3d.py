"""3D views of trajectories: a GIF of the particles in a fixed 3D view (:func:`animate3d`) and
the final deposit (:func:`plot_deposit3d`: top view coloured by height, height against the
distance from the axis).

Axes as in every diffgns scene: y is vertical, z the depth axis. Matplotlib's 3D axes draw
their third axis upwards, so a scene point (x, y, z) is drawn at (x, z, y). Figures use the
Agg canvases and the GIF machinery of :mod:`diffgns.io.figures` (no ``pyplot``, no ffmpeg).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np
from matplotlib.cm import ScalarMappable
from matplotlib.lines import Line2D
from matplotlib.patches import Circle

from diffgns import metrics
from diffgns.io.figures import (
    _PANEL_INCHES,
    _animation_frames,
    _default_marker_size,
    _new_figure,
    _record,
    _type_colors,
    _union_bounds,
)
from diffgns.trajectory import Trajectory

__all__ = ["animate3d", "height_map", "plot_deposit3d"]


def _drawn(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scene coordinates (N, 3) as matplotlib's (X, Y, Z) with Z up: (x, z, y)."""
    return p[:, 0], p[:, 2], p[:, 1]


def _frame_axes(ax, bounds, elev: float, azim: float) -> None:
    """Fixed limits (the domain, m), equal scales on all axes and a fixed view."""
    (x0, x1), (y0, y1), (z0, z1) = bounds
    ax.set_xlim(x0, x1)
    ax.set_ylim(z0, z1)
    ax.set_zlim(y0, y1)
    ax.set_box_aspect((x1 - x0, z1 - z0, y1 - y0), zoom=1.2)
    ax.view_init(elev=elev, azim=azim)
    ax.set_xlabel("x (m)", fontsize=7, labelpad=-4)
    ax.set_ylabel("z (m)", fontsize=7, labelpad=-4)
    ax.set_zlabel("y (m)", fontsize=7, labelpad=4)
    ax.tick_params(labelsize=6, pad=0)


def animate3d(
    trajs: Trajectory | Sequence[Trajectory],
    path: str | Path,
    titles: Sequence[str] | None = None,
    fps: int = 20,
    every: int = 1,
    color: str = "type",
    s: float | None = None,
    elev: float = 25.0,
    azim: float = -60.0,
) -> Path:
    """Save a GIF of 3D trajectories, one 3D panel per trajectory, side by side.

    The arguments are those of :func:`diffgns.io.figures.animate` (``color`` ``"type"`` or
    ``"speed"``; shorter trajectories hold their last frame; frames 0, every, 2 every, ...),
    plus the fixed view: ``elev`` and ``azim`` in degrees (matplotlib's ``view_init``). Every
    panel shows the union of the trajectories' bounds (m) with equal scales on the three axes,
    y drawn upwards. Returns the path written.
    """
    runs, dt, pos, speed, norm = _animation_frames(trajs, titles, color, every)
    if pos[0].shape[-1] != 3:
        raise ValueError(f"animate3d needs 3D trajectories, positions (T, N, 3), got "
                         f"{pos[0].shape}; use diffgns.io.figures.animate")
    bounds = _union_bounds([t.bounds for t in runs])
    n_draw = max(p.shape[0] for p in pos)
    fig = _new_figure(((_PANEL_INCHES + 0.6) * len(runs) + (1.0 if speed else 0.0),
                       _PANEL_INCHES))
    axes = [fig.add_subplot(1, len(runs), i + 1, projection="3d") for i in range(len(runs))]
    for i, ax in enumerate(axes):
        _frame_axes(ax, bounds, elev, azim)
        if titles is not None:
            ax.set_title(titles[i], fontsize=9)
    sizes = [_default_marker_size(t.n_particles) if s is None else s for t in runs]
    style: list[dict[str, Any]]
    if speed is None:
        style = [dict(c=_type_colors(np.asarray(t.particle_type))) for t in runs]
    else:
        style = [dict(cmap="viridis", norm=norm)] * len(runs)
        fig.colorbar(ScalarMappable(norm, "viridis"), ax=axes, label="speed (m/s)", shrink=0.7)
    scatters: list = [None] * len(runs)

    def draw(k: int) -> None:  # a 3D scatter has no public set_offsets: redraw it
        for i, ax in enumerate(axes):
            j = min(k, pos[i].shape[0] - 1)
            if scatters[i] is not None:
                scatters[i].remove()
            kw = style[i] if speed is None else dict(style[i], c=speed[i][j])
            x, z, y = _drawn(pos[i][j])
            scatters[i] = ax.scatter(x, z, zs=y, s=sizes[i], linewidths=0, **kw)

    return _record(fig, path, fps, n_draw, every * dt, draw)


def height_map(x: np.ndarray, bounds, dx: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Top view of a deposit: the highest particle above the floor (y - ymin of ``bounds``,
    m) in each ``dx`` x ``dx`` column of the x–z plane.

    Returns (x edges (nx + 1,), z edges (nz + 1,), heights (nx, nz) in m, NaN where a column
    holds no particle).
    """
    x = np.asarray(x, dtype=float)
    (x0, x1), (y0, _), (z0, z1) = _union_bounds([bounds])
    nx, nz = (max(1, math.ceil((hi - lo) / dx - 1e-9)) for lo, hi in ((x0, x1), (z0, z1)))
    ix = np.clip(np.floor((x[:, 0] - x0) / dx).astype(int), 0, nx - 1)
    iz = np.clip(np.floor((x[:, 2] - z0) / dx).astype(int), 0, nz - 1)
    h = np.full((nx, nz), np.nan)
    np.fmax.at(h, (ix, iz), x[:, 1] - y0)
    return x0 + dx * np.arange(nx + 1), z0 + dx * np.arange(nz + 1), h


def plot_deposit3d(
    initial: np.ndarray,
    final: np.ndarray,
    path: str | Path,
    bounds,
    dx: float,
    centre: Sequence[float],
    front: float | None = None,
    s: float | None = None,
) -> Path:
    """The final deposit of a 3D run in two panels.

    Left, the top view (x–z plane): the height of the final deposit above the floor in
    ``dx`` columns (:func:`height_map`), the initial footprint dashed and the deposit
    ``front`` radius (m) as a dashed circle about ``centre``. Right, the profile: height
    above the floor against the distance r from the vertical axis through ``centre`` (x, z),
    m (:func:`diffgns.metrics.radial_distance`) — every final particle (dots) and the highest
    particle per ``dx`` bin of r (:func:`diffgns.metrics.deposit_profile`), initial and final.

    Args:
        initial, final: (N, 3) positions, m.
        bounds: ((xmin, xmax), (ymin, ymax), (zmin, zmax)) of the domain, m; ymin is the floor.
        dx: bin width (the grid cell), m.
        centre: (x, z) of the axis, m (the column's axis, or the initial centroid).
        front: deposit front radius, m, or None.
        s: marker area of the profile dots, points^2 (from the particle count if None).
    """
    initial, final = np.asarray(initial, float), np.asarray(final, float)
    for name, x in (("initial", initial), ("final", final)):
        if x.ndim != 2 or x.shape[1] != 3:
            raise ValueError(f"plot_deposit3d: {name} positions must be (N, 3), got {x.shape}")
    b = _union_bounds([bounds])
    floor, top = b[1]
    fig = _new_figure((10.0, 4.4))
    top_ax, prof = fig.subplots(1, 2, gridspec_kw=dict(width_ratios=(1.0, 1.3)))

    xe, ze, h = height_map(final, bounds, dx)
    mesh = top_ax.pcolormesh(xe, ze, np.ma.masked_invalid(h).T, cmap="viridis", vmin=0.0)
    fig.colorbar(mesh, ax=top_ax, label="deposit height (m)", shrink=0.85)
    _, _, h0 = height_map(initial, bounds, dx)
    xc, zc = 0.5 * (xe[1:] + xe[:-1]), 0.5 * (ze[1:] + ze[:-1])
    handles = []
    if min(h0.shape) >= 2:
        top_ax.contour(xc, zc, np.isfinite(h0).T.astype(float), levels=[0.5], colors="k",
                       linestyles="--", linewidths=1.0)
        handles.append(Line2D([], [], color="k", ls="--", label="initial footprint"))
    if front is not None:
        top_ax.add_patch(Circle((float(centre[0]), float(centre[1])), front, fill=False,
                                ls="--", color="C3"))
        handles.append(Line2D([], [], color="C3", ls="--",
                              label=f"deposit front r = {front:.3f} m"))
    top_ax.plot(*centre, "+", color="C3")
    top_ax.set_xlim(b[0])
    top_ax.set_ylim(b[2])
    top_ax.set_aspect("equal")
    top_ax.set_xlabel("x (m)")
    top_ax.set_ylabel("z (m)")
    top_ax.set_title("final deposit, top view", fontsize=9)
    if handles:
        top_ax.legend(handles=handles, fontsize=7, loc="upper right")

    r0, r1 = (np.asarray(metrics.radial_distance(jnp.asarray(p), centre))
              for p in (initial, final))
    r_max = float(max(r0.max(), r1.max())) + dx
    edges = dx * np.arange(math.ceil(r_max / dx) + 1)
    size = _default_marker_size(final.shape[0]) if s is None else s
    prof.scatter(r1, final[:, 1] - floor, s=size, color="C0", alpha=0.25, linewidths=0)
    for x, r, col, label in ((initial, r0, "k", "initial"), (final, r1, "C0", "final")):
        rh = jnp.asarray(np.stack([r, x[:, 1] - floor], 1))
        prof_h = np.asarray(metrics.deposit_profile(rh, jnp.asarray(edges)))
        prof.stairs(prof_h, edges, color=col, lw=1.5, label=f"{label}, highest per bin")
    if front is not None:
        prof.axvline(front, ls="--", color="C3", lw=1.2, label=f"deposit front ({front:.3f} m)")
    prof.set_xlim(0.0, edges[-1])
    prof.set_ylim(0.0, top - floor)
    prof.set_aspect("equal")
    prof.set_xlabel("distance from the axis r (m)")
    prof.set_ylabel("height above the floor (m)")
    prof.set_title("profile against the radius", fontsize=9)
    prof.legend(fontsize=7)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
