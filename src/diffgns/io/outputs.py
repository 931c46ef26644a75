"""Run a scene with the MPM and write the usual outputs (I/O lives here, not in physics)."""
from __future__ import annotations

import json
import time
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from diffgns import metrics
from diffgns.io import figures as viz
from diffgns.io.dataset import DatasetWriter
from diffgns.io.files import staged_dir
from diffgns.mpm import MPM
from diffgns.trajectory import Trajectory


def run_mpm(scene, n_frames: int, dtype=None, chunk: int = 50, progress: bool = True):
    """Roll ``scene`` out for ``n_frames`` frames in jitted chunks with a progress bar.

    Returns (Trajectory with T = n_frames + 1, timing dict with compile and run seconds).
    Raises UnstableError if the run leaves its stability region.
    """
    sim = MPM(scene, dtype=dtype)
    params, state = sim.params(), sim.init()
    pos, vel = [np.asarray(state.x.T)[None]], [np.asarray(state.v.T)[None]]
    clamped, shift = [np.zeros(1, np.int32)], [np.zeros(1)]  # per frame (diffgns.clamp)
    done, chunk_s = 0, []
    with tqdm(total=n_frames, desc="MPM frames", disable=not progress, unit="frame") as bar:
        while done < n_frames:
            k = min(chunk, n_frames - done)
            t0 = time.perf_counter()
            traj, state = sim.run(params, state, k)
            jax.block_until_ready(state)
            chunk_s.append((k, time.perf_counter() - t0))
            pos.append(np.asarray(traj.positions[1:]))
            vel.append(np.asarray(traj.velocities[1:]))
            clamped.append(np.asarray(traj.clamped[1:]))
            shift.append(np.asarray(traj.clamp_shift[1:]))
            done += k
            bar.update(k)
    # the first chunk compiles: its compile share is its time minus a steady chunk's
    steady = [t / k for k, t in chunk_s[1:]] or [chunk_s[0][1] / chunk_s[0][0]]
    per_frame = float(np.median(steady))
    t_compile = max(0.0, chunk_s[0][1] - chunk_s[0][0] * per_frame)
    t_run = sum(t for _, t in chunk_s) - t_compile
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


def write_outputs(traj: Trajectory, scene, out: str | Path, vtk_every: int = 10,
                  anim_every: int = 4, origin: float = 0.0, L0: float | None = None,
                  extra: dict | None = None) -> dict:
    """Write animation.gif, runout.png, deposit.png, vtk/ (ParaView), trajectory.h5 and
    summary.json to the folder ``out``.

    Everything is written to a temporary folder beside ``out`` and moved into ``out`` only
    when all of it is written (:func:`diffgns.io.files.staged_dir`), so a failed or
    interrupted call leaves ``out`` as it was. Returns the summary (runout and deposit front
    in m, both defined in its ``runout_definitions``; the run's position clamps,
    ``clamped_positions`` ..., when ``traj`` records them; ``files`` lists the paths in
    ``out``).
    """
    out = Path(out)
    x = np.asarray(traj.positions)
    run = np.asarray(metrics.runout(x, origin=origin))
    front = float(metrics.deposit_front(traj.positions[-1], scene.dx, scene.dx, origin=origin))
    with staged_dir(out) as tmp:
        files = {
            "animation": viz.animate(traj, tmp / "animation.gif", every=anim_every,
                                     color="speed"),
            "runout_plot": viz.plot_runout(
                np.asarray(traj.times), run, tmp / "runout.png", L0=L0,
                labels=["farthest particle"],
                references=[((front - L0) / L0 if L0 else front,
                             f"deposit front, last frame ({front:.3f} m)")]),
            "deposit_plot": viz.plot_deposits([(x[0], "initial"), (x[-1], "final")],
                                              tmp / "deposit.png", scene.domain),
        }
        vtk = viz.write_vtk(traj, tmp / "vtk", every=vtk_every)
        files["vtk_collection"] = vtk[-1]
        with DatasetWriter(tmp / "trajectory.h5") as w:
            w.write("00000", traj)
            w.finalize(connectivity_radius=2.0 * scene.dx)
        files = {k: out / Path(v).relative_to(tmp) for k, v in files.items()}
        summary = dict(final_runout_m=float(run[-1]), deposit_front_m=front,
                       runout_definitions=RUNOUT_DEFINITIONS,
                       frames=int(traj.n_frames), particles=int(traj.n_particles),
                       files={k: str(v) for k, v in files.items()},
                       **(traj.clamp_summary() or {}), **(extra or {}))
        if L0:
            summary["normalised_runout_front"] = (front - L0) / L0
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary
