"""Where a MeshGraphNet's long rollout runs away: first frame and node past 2x the CFD's speed.

    python benchmarks/meshnet_runaway.py checkpoints/meshnet_unroll/model \
        [--data data/sweep_heldout.h5] [--frames 600] [--out meshnet_runaway.json]

For every trajectory of the held-out cylinder dataset, rolls the model out ``--frames`` frames
(3x the training horizon by default) from the first data frame and prints: the first frame
whose fastest node exceeds twice the CFD's largest speed on that trajectory, that node's
position (m), type and whether it is predicted; and at the last frame the fastest node and the
x-range of the nodes above twice the CFD's speed. Also per trajectory the drift of a bounded
rollout: the lift peak-to-peak and mean drag coefficient per window of ``--window`` frames,
and the node whose time-mean velocity over the last window is farthest from the CFD's over
its last window (both flows are periodic, so their means compare). Accuracy only: the
protocol records the load and never refuses the run (``benchmarks/protocol.py``).
"""
from __future__ import annotations

import argparse

import numpy as np
import protocol

from diffgns.interface import rollout_jit
from diffgns.mesh.evaluate import pressure_force_coefficients
from diffgns.mesh.train import graph_of, load_cylinder, load_model


def drift(traj: dict, velocity: np.ndarray, pressure: np.ndarray, window: int) -> dict:
    """Lift p-p and mean drag per ``window`` frames of a rollout (``velocity`` (F + 1, n, 2)
    m/s, ``pressure`` (F, n) m^2/s^2), the CFD's over its frames, and the worst node of the
    last window's time-mean velocity against the CFD's last window."""
    cd, cl = pressure_force_coefficients(traj, pressure)[:2]
    cd_c, cl_c = pressure_force_coefficients(traj, traj["pressure"][1:])[:2]
    starts = range(0, len(cl) - window + 1, window)
    err = np.linalg.norm(velocity[-window:].mean(0) - traj["velocity"][-window:].mean(0), axis=-1)
    i = int(np.argmax(err))
    return dict(window=window, window_start=list(starts),
                lift_pp=[float(np.ptp(cl[s:s + window])) for s in starts],
                drag_mean=[float(cd[s:s + window].mean()) for s in starts],
                cfd_lift_pp=float(np.ptp(cl_c)), cfd_drag_mean=float(cd_c.mean()),
                worst_mean_node_m=traj["mesh_pos"][i].tolist(), worst_mean_error_m_s=float(err[i]),
                worst_mean_velocity_cfd=traj["velocity"][-window:, i].mean(0).tolist(),
                worst_mean_velocity_model=velocity[-window:, i].mean(0).tolist())


def runaway(model, params, traj: dict, padding, frames: int, window: int = 50) -> dict:
    """Where ``traj``'s rollout of ``frames`` frames first exceeds twice the CFD's speed, and
    its :func:`drift`."""
    n = len(traj["mesh_pos"])
    graph = graph_of(traj, padding)
    v0 = np.zeros((padding[0], 2), np.float32)
    v0[:n] = traj["velocity"][0]
    out, _ = rollout_jit(model, params, model.init(graph, v0), n_frames=frames)
    vel = np.asarray(out.velocity)[:, :n]
    speed = np.linalg.norm(vel, axis=-1)  # (frames + 1, n) m/s
    limit = 2 * float(np.linalg.norm(traj["velocity"], axis=-1).max())
    pos, kind = traj["mesh_pos"], np.asarray(traj["node_type"])
    row = dict(reynolds=float(traj["attrs"]["reynolds"]), limit_m_s=limit,
               max_speed_m_s=float(speed.max()), first_frame=None,
               drift=drift(traj, vel, np.asarray(out.pressure)[1:, :n], window))
    bad = np.nonzero(speed.max(axis=1) > limit)[0]
    if not len(bad):
        return row
    f = int(bad[0])
    i, j = int(np.argmax(speed[f])), int(np.argmax(speed[-1]))
    fast = speed[-1] > limit
    row.update(first_frame=f, first_node=i, first_node_m=pos[i].tolist(),
               first_node_type=int(kind[i]), first_node_predicted=bool(graph.predicted[i]),
               last_max_m_s=float(speed[-1].max()), last_max_node_m=pos[j].tolist(),
               last_max_node_type=int(kind[j]), last_nodes_above=int(fast.sum()), nodes=n,
               last_x_min_median_max_m=np.percentile(pos[fast][:, 0], [0, 50, 100]).tolist()
               if fast.any() else None)
    return row


def describe(r: dict, frames: int) -> str:
    """One line of :func:`runaway`'s row."""
    d = r["drift"]
    line = (f"Re {r['reynolds']:.0f}: lift p-p per {d['window']} frames "
            f"{' '.join(f'{x:.2f}' for x in d['lift_pp'])} (CFD {d['cfd_lift_pp']:.2f}), mean "
            f"drag {' '.join(f'{x:.2f}' for x in d['drag_mean'])} (CFD "
            f"{d['cfd_drag_mean']:.2f}); last window's worst mean velocity at "
            f"{np.round(d['worst_mean_node_m'], 3)} m: "
            f"{np.round(d['worst_mean_velocity_model'], 2)}"
            f" against the CFD's {np.round(d['worst_mean_velocity_cfd'], 2)} m/s\n  ")
    if r["first_frame"] is None:
        return line + f"bounded: max speed {r['max_speed_m_s']:.2f} <= {r['limit_m_s']:.2f} m/s"
    xs = r["last_x_min_median_max_m"]
    return (line + f"first frame above 2x the CFD's speed {r['first_frame']}: node "
            f"{r['first_node']} at {np.round(r['first_node_m'], 3)} m, type "
            f"{r['first_node_type']}, predicted {r['first_node_predicted']}; frame {frames}: "
            f"max {r['last_max_m_s']:.1f} m/s at {np.round(r['last_max_node_m'], 3)} m (type "
            f"{r['last_max_node_type']}), {r['last_nodes_above']} of {r['nodes']} nodes above, "
            f"x min/median/max {np.round(xs, 2) if xs else '-'} m")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("model", help="model folder")
    p.add_argument("--data", default="data/sweep_heldout.h5")
    p.add_argument("--frames", type=int, default=600)
    p.add_argument("--window", type=int, default=50, help="frames per drift window")
    p.add_argument("--out", default="meshnet_runaway.json")
    protocol.add_arguments(p)
    a = p.parse_args(argv)
    run = protocol.start(a, "meshnet_runaway", timed=False)
    model, params, info = load_model(a.model)
    rows = []
    for traj in load_cylinder(a.data):
        rows.append(runaway(model, params, traj, info["padding"], a.frames, a.window))
        run.print(describe(rows[-1], a.frames))
    out = run.finish(a.out, dict(model=a.model, data=a.data, frames=a.frames, rows=rows))
    run.print(f"wrote {out}")


if __name__ == "__main__":
    main()
