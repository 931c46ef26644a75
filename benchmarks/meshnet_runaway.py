"""Where a MeshGraphNet's long rollout runs away: first frame and node past 2x the CFD's speed.

    python benchmarks/meshnet_runaway.py checkpoints/meshnet_unroll/model \
        [--data data/sweep_heldout.h5] [--frames 600] [--out meshnet_runaway.json]

For every trajectory of the held-out cylinder dataset, rolls the model out ``--frames`` frames
(3x the training horizon by default) from the first data frame and prints: the first frame
whose fastest node exceeds twice the CFD's largest speed on that trajectory, that node's
position (m), type and whether it is predicted; and at the last frame the fastest node and the
x-range of the nodes above twice the CFD's speed. Accuracy only: the protocol records the load
and never refuses the run (``benchmarks/protocol.py``).
"""
from __future__ import annotations

import argparse

import numpy as np
import protocol

from diffgns.interface import rollout_jit
from diffgns.mesh.train import graph_of, load_cylinder, load_model


def runaway(model, params, traj: dict, padding, frames: int) -> dict:
    """Where ``traj``'s rollout of ``frames`` frames first exceeds twice the CFD's speed."""
    n = len(traj["mesh_pos"])
    graph = graph_of(traj, padding)
    v0 = np.zeros((padding[0], 2), np.float32)
    v0[:n] = traj["velocity"][0]
    out, _ = rollout_jit(model, params, model.init(graph, v0), n_frames=frames)
    speed = np.linalg.norm(np.asarray(out.velocity)[:, :n], axis=-1)  # (frames + 1, n) m/s
    limit = 2 * float(np.linalg.norm(traj["velocity"], axis=-1).max())
    pos, kind = traj["mesh_pos"], np.asarray(traj["node_type"])
    row = dict(reynolds=float(traj["attrs"]["reynolds"]), limit_m_s=limit,
               max_speed_m_s=float(speed.max()), first_frame=None)
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
    line = f"Re {r['reynolds']:.0f}: "
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
    p.add_argument("--out", default="meshnet_runaway.json")
    protocol.add_arguments(p)
    a = p.parse_args(argv)
    run = protocol.start(a, "meshnet_runaway", timed=False)
    model, params, info = load_model(a.model)
    rows = []
    for traj in load_cylinder(a.data):
        rows.append(runaway(model, params, traj, info["padding"], a.frames))
        run.print(describe(rows[-1], a.frames))
    out = run.finish(a.out, dict(model=a.model, data=a.data, frames=a.frames, rows=rows))
    run.print(f"wrote {out}")


if __name__ == "__main__":
    main()
