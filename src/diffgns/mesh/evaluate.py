"""Held-out evaluation of a MeshGraphNet against the CFD: errors, shedding, stability, cost.

For one trajectory of F frames (:func:`evaluate_trajectory`):

* velocity RMSE (m/s, over fluid and outflow nodes) of the rollout from frame 0 at horizons
  1, 50 and F - 1 frames;
* the Strouhal number ``St = f D / Ubar`` of the lift from the pressure on the cylinder
  (:func:`pressure_force_coefficients`, the same integral for CFD and model fields), over
  the whole compared horizon, and its relative error;
* the lift amplitude: peak-to-peak pressure lift over the second half of the compared
  horizon, model against CFD, and its relative error;
* the pressure head alone: the lift amplitude of the model's pressure given the CFD's own
  velocity at every frame (``lift_pp_teacher_forced``), which separates a pressure that
  misses the lift from dynamics that damp the shedding;
* ``meets_targets`` (issue 23): St within 5%, lift amplitude within 20% and the long rollout
  stable as below;
* stability: a rollout ``long_factor`` times the horizon; its velocities stay finite and below
  twice the CFD's largest speed, and it stays periodic (St over its last third within 5% of
  St over its first third, peak-to-peak lift in the last third within a factor 2 of the
  CFD's);
* cost: steady-state rollout seconds (and CPU seconds) per simulated second (compile
  excluded, median of ``repeats``, :func:`diffgns.timing.time_call`) against the CFD's wall
  seconds per simulated second stored with the data.
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from diffgns.interface import rollout_jit
from diffgns.mesh.analysis import shedding_metrics
from diffgns.mesh.meshnet import MeshNet
from diffgns.mesh.train import graph_of
from diffgns.timing import time_call


def cylinder_sides(cells: np.ndarray, on_cylinder: np.ndarray) -> np.ndarray:
    """(S, 2) vertex pairs of the mesh sides that lie on the cylinder (boundary sides)."""
    sides = np.concatenate([cells[:, [0, 1]], cells[:, [1, 2]], cells[:, [2, 0]]])
    sides = np.sort(sides, axis=1)
    uniq, count = np.unique(sides, axis=0, return_counts=True)
    b = uniq[count == 1]
    return b[on_cylinder[b[:, 0]] & on_cylinder[b[:, 1]]]


def pressure_force_coefficients(traj: dict, pressure: np.ndarray) -> tuple[np.ndarray,
                                                                            np.ndarray]:
    """Pressure part of (cD, cL) per frame from vertex pressures (F, N) (kinematic, m^2/s^2).

    ``F = -sum_sides p_mid n ds`` with n the unit normal pointing out of the cylinder;
    ``c = 2 F / (Ubar^2 D)``.
    """
    a = traj["attrs"]
    sides = cylinder_sides(traj["cells"], traj["on_cylinder"].astype(bool))
    x = traj["mesh_pos"]
    mid = 0.5 * (x[sides[:, 0]] + x[sides[:, 1]])
    n = mid - np.asarray(a["center"])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ds = np.linalg.norm(x[sides[:, 0]] - x[sides[:, 1]], axis=1)
    p_mid = 0.5 * (pressure[:, sides[:, 0]] + pressure[:, sides[:, 1]])
    force = -np.einsum("fs,sd->fd", p_mid * ds, n)
    u_bar, diameter = 2.0 * a["u_max"] / 3.0, 2.0 * a["radius"]
    c = 2.0 * force / (u_bar**2 * diameter)
    return c[:, 0], c[:, 1]


def _shedding(traj: dict, pressure: np.ndarray, dt: float) -> dict:
    cd, cl = pressure_force_coefficients(traj, pressure)
    t = np.arange(len(cl)) * dt
    a = traj["attrs"]
    return shedding_metrics(t, cd, cl, 0.0, 2.0 * a["radius"], 2.0 * a["u_max"] / 3.0)


def teacher_forced_pressure(model: MeshNet, params, graph, velocities) -> np.ndarray:
    """(F, N) the model's next pressure (m^2/s^2) from each of ``velocities`` (F, N, 2) m/s,
    frame by frame (the data's velocities, not the model's own rollout), one compiled
    ``lax.map``."""
    return np.asarray(_pressures(model, params, graph, jnp.asarray(velocities)))


@functools.partial(jax.jit, static_argnums=0)
def _pressures(model: MeshNet, params, graph, velocities):
    """Compiled once per model and mesh shape (not once per trajectory)."""
    return jax.lax.map(lambda v: model.predict(params, graph, v)[1], velocities)


def evaluate_trajectory(model: MeshNet, params, traj: dict, padding, long_factor: int = 3,
                        repeats: int = 3) -> dict:
    """Metrics of one held-out trajectory (see the module docstring)."""
    n = len(traj["mesh_pos"])
    graph = graph_of(traj, padding)
    model.check_graph(graph)
    v0 = np.zeros((padding[0], 2), np.float32)
    v0[:n] = traj["velocity"][0]
    F = len(traj["velocity"])
    dt = float(traj["attrs"]["frame_dt"])
    state = model.init(graph, v0)

    def roll(n_frames):
        frames, _ = rollout_jit(model, params, state, n_frames=n_frames)
        return frames.velocity, frames.pressure[1:]

    timing, (vs, ps) = time_call(lambda: roll(F - 1), repeats)
    vs, ps = np.asarray(vs)[:, :n], np.asarray(ps)[:, :n]
    mask = np.asarray(graph.predicted)[:n]
    err = vs[:, mask] - traj["velocity"][:, mask]
    rmse = np.sqrt(np.mean(err**2, axis=(1, 2)))
    horizons = {h: float(rmse[h]) for h in (1, 50, F - 1) if h < F}
    cfd = _shedding(traj, traj["pressure"][1:], dt)
    gnn = _shedding(traj, ps, dt)
    long_v, long_p = roll(long_factor * (F - 1))
    long_v, long_p = np.asarray(long_v)[:, :n], np.asarray(long_p)[:, :n]
    third = len(long_p) // 3
    first = _shedding(traj, long_p[:third], dt)
    last = _shedding(traj, long_p[-third:], dt)
    cfd_speed = float(np.linalg.norm(traj["velocity"], axis=-1).max())
    long_speed = float(np.nanmax(np.linalg.norm(long_v, axis=-1)))
    cfd_pp = float(np.ptp(pressure_force_coefficients(traj, traj["pressure"])[1]))
    last_pp = float(np.ptp(pressure_force_coefficients(traj, long_p[-third:])[1]))
    # lift amplitude over the compared horizon, from the second half (past any transient)
    half = (F - 1) // 2
    amp_cfd = float(np.ptp(pressure_force_coefficients(traj, traj["pressure"][1 + half:])[1]))
    amp_model = float(np.ptp(pressure_force_coefficients(traj, ps[half:])[1]))
    v_cfd = np.zeros((F - 1,) + v0.shape, np.float32)
    v_cfd[:, :n] = traj["velocity"][:-1]
    p_tf = teacher_forced_pressure(model, params, graph, v_cfd)[:, :n]
    amp_tf = float(np.ptp(pressure_force_coefficients(traj, p_tf[half:])[1]))
    sim_seconds = (F - 1) * dt
    stable = bool(np.all(np.isfinite(long_v)) and long_speed < 2 * cfd_speed
                  and abs(last["strouhal"] / first["strouhal"] - 1) < 0.05
                  and 0.5 < last_pp / cfd_pp < 2.0)
    return dict(
        key=traj["key"], reynolds=float(traj["attrs"]["reynolds"]), frames=F,
        rmse=horizons, strouhal_cfd=cfd["strouhal"], strouhal_model=gnn["strouhal"],
        strouhal_rel_error=abs(gnn["strouhal"] - cfd["strouhal"]) / cfd["strouhal"],
        lift_pp_cfd=amp_cfd, lift_pp_model=amp_model,
        lift_pp_rel_error=abs(amp_model - amp_cfd) / amp_cfd,
        lift_pp_teacher_forced=amp_tf,
        lift_pp_teacher_forced_rel_error=abs(amp_tf - amp_cfd) / amp_cfd,
        long_frames=long_factor * (F - 1), long_finite=bool(np.all(np.isfinite(long_v))),
        long_max_speed=long_speed, cfd_max_speed=cfd_speed,
        long_strouhal_first_third=first["strouhal"], long_strouhal_last_third=last["strouhal"],
        long_lift_pp_last_third=last_pp, cfd_lift_pp=cfd_pp,
        stable=stable,
        meets_targets=bool(abs(gnn["strouhal"] - cfd["strouhal"]) <= 0.05 * cfd["strouhal"]
                           and abs(amp_model - amp_cfd) <= 0.2 * amp_cfd and stable),
        compile_s=timing["compile_s"], model_s_per_sim_s=timing["median_s"] / sim_seconds,
        model_cpu_s_per_sim_s=timing["cpu_median_s"] / sim_seconds, model_timing=timing,
        cfd_s_per_sim_s=float(traj["attrs"].get("cfd_wall_per_sim_second", np.nan)),
        velocity=vs, pressure=ps, long_pressure=long_p)


def targets_table(results: list[dict]) -> str:
    """Markdown table of :func:`evaluate_trajectory` results against issue 23's targets
    (St within 5%, lift amplitude within 20%, 3x rollout bounded and periodic; cost is the
    model's rollout seconds per simulated second against the CFD's recorded with the data)."""
    rows = ["| Re | St CFD | St model | St err | lift p-p CFD | lift p-p model | lift err "
            "| lift p-p, CFD velocities | 3x bounded+periodic | meets | model s/sim-s "
            "| CFD s/sim-s |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        rows.append(
            f"| {r['reynolds']:g} | {r['strouhal_cfd']:.4f} | {r['strouhal_model']:.4f} "
            f"| {r['strouhal_rel_error']:.1%} | {r['lift_pp_cfd']:.3f} | "
            f"{r['lift_pp_model']:.3f} | {r['lift_pp_rel_error']:.1%} | "
            f"{r['lift_pp_teacher_forced']:.3f} | "
            f"{'yes' if r['stable'] else 'no'} | {'yes' if r['meets_targets'] else 'no'} | "
            f"{r['model_s_per_sim_s']:.3g} | {r['cfd_s_per_sim_s']:.3g} |")
    return "\n".join(rows)


def main(argv=None) -> int:
    """``python -m diffgns.mesh.evaluate --model M --data D``: every trajectory of ``D``."""
    import argparse
    import json

    from diffgns.io.files import check_input_file
    from diffgns.mesh.train import load_cylinder, load_model

    p = argparse.ArgumentParser(prog="python -m diffgns.mesh.evaluate",
                                description="MeshGraphNet vs CFD on every trajectory of a "
                                "cylinder dataset (issue 23's targets)")
    p.add_argument("--model", required=True, help="model folder (or run folder)")
    p.add_argument("--data", required=True, help="held-out cylinder dataset (.h5)")
    p.add_argument("--repeats", type=int, default=1, help="timed rollouts per case")
    p.add_argument("--json", default=None, help="write the metrics here")
    a = p.parse_args(argv)
    check_input_file(a.data, "--data", metadata=True)
    model, params, info = load_model(a.model)
    res = []
    for traj in load_cylinder(a.data):
        r = evaluate_trajectory(model, params, traj, info["padding"], repeats=a.repeats)
        for k in ("velocity", "pressure", "long_pressure"):
            r.pop(k)
        res.append(r)
    print(targets_table(res))
    print("timings indicative only: taken on a shared, loaded machine")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(res, f, indent=2, default=float)
    return 0


if __name__ == "__main__":  # pragma: no cover
    from diffgns.errors import run_module

    run_module(main)
