"""Figures for fields on triangular meshes: vorticity, side-by-side animation, lift history."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import FuncAnimation, PillowWriter  # noqa: E402
from matplotlib.tri import Triangulation  # noqa: E402


def vorticity(mesh_pos: np.ndarray, cells: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """Per-triangle vorticity dv/dx - du/dy (1/s) of P1 velocities.

    mesh_pos (N, 2) m, cells (C, 3) (C triangles), velocity (..., N, 2) m/s -> (..., C).
    """
    x = mesh_pos[cells]                                   # (C, 3, 2)
    d1, d2 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]
    det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    # gradients of the barycentric functions of vertices 1 and 2 (vertex 0: minus their sum)
    g1 = np.stack([d2[:, 1], -d2[:, 0]], -1) / det[:, None]
    g2 = np.stack([-d1[:, 1], d1[:, 0]], -1) / det[:, None]
    v = velocity[..., cells, :]                           # (..., C, 3, 2)
    dv1, dv2 = v[..., 1, :] - v[..., 0, :], v[..., 2, :] - v[..., 0, :]
    grad = dv1[..., :, None] * g1[:, None, :] + dv2[..., :, None] * g2[:, None, :]
    return grad[..., 1, 0] - grad[..., 0, 1]


def animate_vorticity(mesh_pos, cells, omega_a, omega_b, path: str | Path,
                      titles=("CFD", "MeshGraphNet"), frame_dt: float = 0.01, every: int = 2,
                      fps: int = 15, vmax: float | None = None) -> Path:
    """GIF of two per-triangle vorticity histories (T frames, C triangles) on one mesh, one
    above the other."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tri = Triangulation(mesh_pos[:, 0], mesh_pos[:, 1], cells)
    vmax = vmax or float(np.percentile(np.abs(omega_a), 99))
    fig, axes = plt.subplots(2, 1, figsize=(9, 4.2))
    arts = []
    for ax, om, title in zip(axes, (omega_a, omega_b), titles):
        arts.append(ax.tripcolor(tri, facecolors=om[0], cmap="RdBu_r", vmin=-vmax, vmax=vmax))
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    label = fig.suptitle("")
    frames = range(0, min(len(omega_a), len(omega_b)), every)

    def update(f):
        for art, om in zip(arts, (omega_a, omega_b)):
            art.set_array(om[f])
        label.set_text(f"vorticity (1/s), t = {f * frame_dt:.2f} s")
        return arts

    FuncAnimation(fig, update, frames=frames).save(path, writer=PillowWriter(fps=fps))
    plt.close(fig)
    return path


def plot_lift(times, series: dict, path: str | Path, ylabel: str = "pressure lift cL") -> Path:
    """Lift coefficient histories, one line per entry of ``series`` (name -> (F,) array)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(8, 3))
    for name, cl in series.items():
        ax.plot(times[: len(cl)], cl, label=name)
    ax.set(xlabel="time since the first frame (s)", ylabel=ylabel)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
