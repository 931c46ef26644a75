"""Where a MeshGraphNet's long rollout runs away: first frame and node past 2x the CFD's speed.

    python benchmarks/meshnet_runaway.py checkpoints/meshnet_unroll/model \
        [--data data/sweep_heldout.h5] [--frames 600]

For every trajectory of the held-out cylinder dataset, rolls the model out ``--frames`` frames
(3x the training horizon by default) from the first data frame and prints: the first frame
whose fastest node exceeds twice the CFD's largest speed on that trajectory, that node's
position (m), type and whether it is predicted; and at the last frame the fastest node and the
x-range of the nodes above twice the CFD's speed. Accuracy diagnostic only (no timing).
"""
from __future__ import annotations

import argparse

import numpy as np

from diffgns.interface import rollout_jit
from diffgns.mesh.train import graph_of, load_cylinder, load_model


def runaway(model, params, traj: dict, padding, frames: int) -> str:
    """One line describing where ``traj``'s rollout first exceeds twice the CFD's speed."""
    n = len(traj["mesh_pos"])
    graph = graph_of(traj, padding)
    v0 = np.zeros((padding[0], 2), np.float32)
    v0[:n] = traj["velocity"][0]
    out, _ = rollout_jit(model, params, model.init(graph, v0), n_frames=frames)
    speed = np.linalg.norm(np.asarray(out.velocity)[:, :n], axis=-1)  # (frames + 1, n) m/s
    limit = 2 * float(np.linalg.norm(traj["velocity"], axis=-1).max())
    pos, kind = traj["mesh_pos"], np.asarray(traj["node_type"])
    predicted = np.asarray(graph.predicted)[:n]
    line = f"Re {traj['attrs']['reynolds']:.0f}: "
    bad = np.nonzero(speed.max(axis=1) > limit)[0]
    if not len(bad):
        return line + f"bounded: max speed {speed.max():.2f} m/s <= {limit:.2f}"
    f = int(bad[0])
    i, j = int(np.argmax(speed[f])), int(np.argmax(speed[-1]))
    fast = speed[-1] > limit
    xs = np.percentile(pos[fast][:, 0], [0, 50, 100]).round(2) if fast.any() else "-"
    return (line + f"first frame above 2x the CFD's speed {f}: node {i} at {pos[i].round(3)} m, "
            f"type {kind[i]}, predicted {bool(predicted[i])}; frame {frames}: max "
            f"{speed[-1].max():.1f} m/s at {pos[j].round(3)} m (type {kind[j]}), "
            f"{int(fast.sum())} of {n} nodes above, x min/median/max {xs} m")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("model", help="model folder")
    p.add_argument("--data", default="data/sweep_heldout.h5")
    p.add_argument("--frames", type=int, default=600)
    a = p.parse_args(argv)
    model, params, info = load_model(a.model)
    for traj in load_cylinder(a.data):
        print(runaway(model, params, traj, info["padding"], a.frames), flush=True)


if __name__ == "__main__":
    main()
