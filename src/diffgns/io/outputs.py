"""Run a scene with the MPM and write the usual outputs (I/O lives here, not in physics)."""
from __future__ import annotations

import json
import time
from functools import partial
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from diffgns import metrics
from diffgns.interface import rollout
from diffgns.io import figures as viz
from diffgns.io import figures3d as viz3d
from diffgns.io.dataset import DatasetWriter
from diffgns.io.files import staged_dir
from diffgns.memory import compile_ahead
from diffgns.mpm import MPM
from diffgns.mpm.solver import max_speed
from diffgns.scene.builders3d import cylinder_axis
from diffgns.scene.shapes import Cylinder
from diffgns.trajectory import Trajectory


def run_mpm(scene, n_frames: int, dtype=None, chunk: int = 50, progress: bool = True):
    """Roll ``scene`` out for ``n_frames`` frames in jitted chunks with a progress bar.

    Each distinct chunk length (``chunk``, and a shorter last one) is compiled ahead of time
    (:func:`diffgns.memory.compile_ahead`), so ``compile_s`` is the measured lowering and
    compilation time (also for a run of one chunk) and ``run_s`` the execution time alone.

    Returns (Trajectory with T = n_frames + 1, timing dict: compile_s, run_s (s),
    particles, substeps_per_frame, substep_dt (s), particle_substeps_per_s).
    Raises UnstableError if the run leaves its stability region.
    """
    sim = MPM(scene, dtype=dtype)
    params, state = sim.params(), sim.init()
    pos, vel = [np.asarray(state.x.T)[None]], [np.asarray(state.v.T)[None]]
    clamped, shift = [np.zeros(1, np.int32)], [np.zeros(1)]  # per frame (diffgns.clamp)
    done, t_compile, t_run = 0, 0.0, 0.0
    programs: dict[int, object] = {}
    with tqdm(total=n_frames, desc="MPM frames", disable=not progress, unit="frame") as bar:
        while done < n_frames:
            k = min(chunk, n_frames - done)
            if k not in programs:
                programs[k], info = compile_ahead(
                    jax.jit(partial(rollout, sim, n_frames=k)), params, state)
                t_compile += info["lower_s"] + info["compile_s"]
            t0 = time.perf_counter()
            frames, state = programs[k](params, state)  # type: ignore[operator]
            jax.block_until_ready(state)
            t_run += time.perf_counter() - t0
            sim.check_stability(params, max_speed(frames.velocities), frames.positions)
            traj = sim.trajectory(params, frames)
            pos.append(np.asarray(traj.positions[1:]))
            vel.append(np.asarray(traj.velocities[1:]))
            clamped.append(np.asarray(traj.clamped[1:]))
            shift.append(np.asarray(traj.clamp_shift[1:]))
            done += k
            bar.update(k)
    traj = Trajectory(positions=np.concatenate(pos), velocities=np.concatenate(vel),
                      particle_type=np.asarray(sim.particle_type()),
                      material=np.asarray(sim.material_feature(params)),
                      frame_dt=scene.frame_dt, bounds=scene.domain,
                      clamped=np.concatenate(clamped), clamp_shift=np.concatenate(shift))
    n_sub = scene.substeps
    timing = dict(compile_s=t_compile, run_s=t_run, particles=scene.n_particles,
                  substeps_per_frame=n_sub, substep_dt=scene.substep_dt,
                  particle_substeps_per_s=scene.n_particles * n_sub * n_frames / max(t_run, 1e-9))
    return traj, timing


RUNOUT_DEFINITIONS = {
    "final_runout_m": "farthest particle from the origin at the last frame (the runout plot's "
                      "curve)",
    "deposit_front_m": "far edge of the farthest one-cell bin whose deposit is at least one "
                       "cell high, at the last frame; stray particles ahead of it are ignored "
                       "(the plot's dashed line)",
}

RUNOUT_DEFINITIONS_3D = {
    "final_runout_radius_m": "farthest particle from the vertical axis through axis_xz_m "
                             "(horizontal distance) at the last frame (the runout plot's curve)",
    "deposit_front_radius_m": "outer edge of the farthest one-cell ring about the axis whose "
                              "deposit is at least one cell high, at the last frame; stray "
                              "particles beyond it are ignored (the plots' dashed lines)",
}


def write_outputs(traj: Trajectory, scene, out: str | Path, vtk_every: int = 10,
                  anim_every: int = 4, origin: float = 0.0, L0: float | None = None,
                  extra: dict | None = None) -> dict:
    """Write animation.gif, runout.png, deposit.png, vtk/ (ParaView), trajectory.h5 and
    summary.json to the folder ``out``.

    2D: the animation and deposit are side views, the runout is along x from ``origin`` (m),
    normalised by ``L0`` (the column width, m) when given. 3D (:func:`_figures_3d`): the
    animation is a fixed 3D view, the deposit a top view coloured by height and a profile
    against the radius, the runout a radius about the scene's vertical axis
    (:func:`vertical_axis`), normalised by the column radius in an axisymmetric scene.

    Everything is written to a temporary folder beside ``out`` and moved into ``out`` only
    when all of it is written (:func:`diffgns.io.files.staged_dir`), so a failed or
    interrupted call leaves ``out`` as it was. Returns the summary (runout and deposit front
    in m, both defined in its ``runout_definitions``; the run's position clamps,
    ``clamped_positions`` ..., when ``traj`` records them; ``files`` lists the paths in
    ``out``).
    """
    out = Path(out)
    with staged_dir(out) as tmp:
        if scene.dim == 3:
            files, measures = _figures_3d(traj, scene, tmp, anim_every)
        else:
            files, measures = _figures_2d(traj, scene, tmp, anim_every, origin, L0)
        vtk = viz.write_vtk(traj, tmp / "vtk", every=vtk_every)
        files["vtk_collection"] = vtk[-1]
        with DatasetWriter(tmp / "trajectory.h5") as w:
            w.write("00000", traj)
            w.finalize(connectivity_radius=2.0 * scene.dx)
        files = {k: out / Path(v).relative_to(tmp) for k, v in files.items()}
        summary = dict(**measures, frames=int(traj.n_frames), particles=int(traj.n_particles),
                       files={k: str(v) for k, v in files.items()},
                       **(traj.clamp_summary() or {}), **(extra or {}))
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary


def _figures_2d(traj, scene, tmp: Path, anim_every: int, origin: float, L0):
    x = np.asarray(traj.positions)
    run = np.asarray(metrics.runout(x, origin=origin))
    front = float(metrics.deposit_front(traj.positions[-1], scene.dx, scene.dx, origin=origin))
    files = {
        "animation": viz.animate(traj, tmp / "animation.gif", every=anim_every, color="speed"),
        "runout_plot": viz.plot_runout(
            np.asarray(traj.times), run, tmp / "runout.png", L0=L0,
            labels=["farthest particle"],
            references=[((front - L0) / L0 if L0 else front,
                         f"deposit front, last frame ({front:.3f} m)")]),
        "deposit_plot": viz.plot_deposits([(x[0], "initial"), (x[-1], "final")],
                                          tmp / "deposit.png", scene.domain),
    }
    measures = dict(final_runout_m=float(run[-1]), deposit_front_m=front,
                    runout_definitions=RUNOUT_DEFINITIONS)
    if L0:
        measures["normalised_runout_front"] = (front - L0) / L0
    return files, measures


def vertical_axis(scene) -> tuple[tuple[float, float], Cylinder | None]:
    """The vertical axis of a 3D scene, (x, z) in m, and its column: the axis of the bodies
    when every body is an upright :class:`~diffgns.scene.shapes.Cylinder` on one axis (an
    axisymmetric scene; the column is the widest), else the particles' initial centroid in
    the x–z plane and None."""
    axis = cylinder_axis(scene)
    if axis is not None:
        return axis
    x = np.asarray(scene.particles()["x"])
    return (float(x[:, 0].mean()), float(x[:, 2].mean())), None


def _figures_3d(traj, scene, tmp: Path, anim_every: int):
    x = np.asarray(traj.positions)
    floor = scene.domain[1][0]
    centre, column = vertical_axis(scene)
    r = np.asarray(metrics.radial_distance(x, centre))  # (T, N)
    run = r.max(-1)
    # the deposit front of the 2D runout, on (r, height) in place of (x, y)
    final_rh = np.stack([r[-1], x[-1, :, 1] - floor], 1)
    front = float(metrics.deposit_front(final_rh, scene.dx, scene.dx))
    R0 = float(column.radius) if column is not None else None
    ref = (front - R0) / R0 if R0 else front
    files = {
        "animation": viz3d.animate3d(traj, tmp / "animation.gif", every=anim_every,
                                     color="speed"),
        "runout_plot": viz.plot_runout(
            np.asarray(traj.times), run, tmp / "runout.png", L0=R0,
            labels=["farthest particle from the axis"],
            references=[(ref, f"deposit front, last frame ({front:.3f} m)")],
            ylabel="(R - R0) / R0" if R0 else "runout radius R (m)"),
        "deposit_plot": viz3d.plot_deposit3d(x[0], x[-1], tmp / "deposit.png", scene.domain,
                                             scene.dx, centre, front=front),
    }
    measures = dict(final_runout_radius_m=float(run[-1]), deposit_front_radius_m=front,
                    deposit_height_m=float(final_rh[:, 1].max()), axis_xz_m=list(centre),
                    axis_definition="the column's axis" if column is not None else
                    "the initial centroid of the particles in x-z (not an axisymmetric scene)",
                    runout_definitions=RUNOUT_DEFINITIONS_3D)
    if column is not None:  # axisymmetric: the scaling of Lube et al. (2004)
        from diffgns.scene.builders3d import axisymmetric_runout_estimate

        a = (column.y1 - column.y0) / R0
        measures.update(initial_radius_m=R0, aspect_ratio=a,
                        normalised_runout_front=(front - R0) / R0,
                        normalised_runout_lube2004=axisymmetric_runout_estimate(a))
    return files, measures
