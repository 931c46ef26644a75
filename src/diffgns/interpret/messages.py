"""Reading a trained message network: which components are active, and what they encode.

The premise (Cranmer et al. 2020): with an L1 penalty, a network that predicts accelerations as
a function of summed edge messages keeps only ``dim`` active message components, and these are
a linear combination of the true pair-force components. This module measures that:

* :func:`edge_messages` - messages, features and true forces on sampled edges;
* :func:`rank_components` - components ordered by their standard deviation over edges;
* :func:`linear_r2` - R^2 of each top component regressed (with intercept) on the true force;
* :func:`force_calibration` / :func:`radial_force` - the least-squares linear map from the top
  ``dim`` components to the force (fitted on training edges), and the resulting force read out
  of the messages projected on the line of centres (signed, N; positive = attraction), the
  scalar that symbolic regression then explains. The map fixes only the messages' arbitrary
  linear gauge (2 x 2 + 2 numbers); the functional form comes from the network.
"""
from __future__ import annotations

import jax
import numpy as np

from diffgns.interpret.message_net import forward
from diffgns.interpret.nbody_data import EDGE_FEATURES


def edge_messages(net, norm, params, samples: dict, max_edges: int | None = None,
                  seed: int = 0, contact_only: bool = False, chunk: int = 256) -> dict:
    """Messages on (a random subset of) the edges of ``samples`` (edge_samples output).

    Returns flat arrays over the chosen edges: ``messages`` (M, msg_dim), ``features``
    (M, 9), ``force`` (M, 2) in N. ``contact_only`` keeps edges with a non-zero true force.
    """
    fwd = jax.jit(lambda e, n: forward(net, norm, params, e, n, samples["receivers"])[1])
    msgs = []
    for i in range(0, len(samples["edges"]), chunk):
        msgs.append(np.asarray(fwd(samples["edges"][i:i + chunk], samples["node"][i:i + chunk])))
    msgs = np.concatenate(msgs).reshape(-1, net.cfg.msg_dim)
    feats = samples["edges"].reshape(-1, samples["edges"].shape[-1])
    force = samples["force"].reshape(-1, 2)
    keep = np.arange(len(msgs))
    if contact_only:
        keep = keep[np.linalg.norm(force, axis=-1) > 0]
    if max_edges is not None and len(keep) > max_edges:
        keep = np.sort(np.random.default_rng(seed).choice(keep, max_edges, replace=False))
    return dict(messages=msgs[keep], features=feats[keep], force=force[keep])


def rank_components(messages: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(order, std): component indices by decreasing standard deviation, and the stds."""
    std = messages.std(axis=0)
    order = np.argsort(-std)
    return order, std[order]


def _lstsq(A: np.ndarray, y: np.ndarray) -> np.ndarray:
    A1 = np.concatenate([A, np.ones((len(A), 1))], axis=1)
    return np.linalg.lstsq(A1, y, rcond=None)[0]


def linear_r2(component: np.ndarray, force: np.ndarray) -> float:
    """R^2 of ``component`` (M,) fitted as a F_x + b F_y + c from ``force`` (M, 2)."""
    coef = _lstsq(force, component)
    pred = force @ coef[:2] + coef[2]
    ss_res = np.sum((component - pred) ** 2)
    ss_tot = np.sum((component - component.mean()) ** 2)
    return float(1 - ss_res / max(ss_tot, 1e-300))


def force_calibration(top: np.ndarray, force: np.ndarray) -> np.ndarray:
    """Least-squares map (dim + 1, 2) with ``force ~ [top, 1] @ W``; ``top`` is (M, dim)."""
    return _lstsq(top, force)


def radial_force(top: np.ndarray, W: np.ndarray, features: np.ndarray) -> np.ndarray:
    """Force read out of the messages, projected on the line of centres: (M,) in N.

    ``features`` columns 0..2 are (dx, dy, d) with dx = x_j - x_i, so positive values pull
    the receiver towards the sender.
    """
    F = np.concatenate([top, np.ones((len(top), 1))], axis=1) @ W
    n_hat = features[:, :2] / features[:, 2:3]
    return np.sum(F * n_hat, axis=-1)


GAUGES = ("force", "acceleration")
_M_I = EDGE_FEATURES.index("m_i")  # column of the receiver mass in the edge features


def gauge_target(edges: dict, gauge: str) -> np.ndarray:
    """What the messages are compared with: the pair force F_ij (N), or, in the
    ``"acceleration"`` gauge, F_ij / m_i (m/s^2), the receiver's acceleration due to j.

    The edge model sees the receiver's mass, so it may carry either; the node model then
    divides by the mass or not.
    """
    if gauge == "force":
        return edges["force"]
    return edges["force"] / edges["features"][:, _M_I:_M_I + 1]


def summarise(train_edges: dict, test_edges: dict, dim: int = 2, n_report: int = 5) -> dict:
    """Premise figures: top component stds, R^2 of each top component, calibration quality.

    Both dicts are :func:`edge_messages` outputs (training edges fit the calibration, test
    edges are scored). Both gauges (:func:`gauge_target`) are scored; ``gauge`` is the one the
    top components fit better, and the reported R^2 and calibration are for it.
    """
    order, std = rank_components(test_edges["messages"])
    top = order[:dim]
    best = None
    for gauge in GAUGES:
        target = gauge_target(test_edges, gauge)
        r2 = [linear_r2(test_edges["messages"][:, k], target) for k in top]
        W = force_calibration(train_edges["messages"][:, top], gauge_target(train_edges, gauge))
        F_hat = np.concatenate([test_edges["messages"][:, top],
                                np.ones((len(test_edges["messages"]), 1))], axis=1) @ W
        resid = F_hat - target
        r2_force = 1 - resid.var(axis=0).sum() / target.var(axis=0).sum()
        if best is None or min(r2) > min(best[1]):
            best = (gauge, r2, W, r2_force)
    gauge, r2, W, r2_force = best
    return dict(gauge=gauge, top_components=[int(k) for k in order[:n_report]],
                top_std=[float(s) for s in std[:n_report]],
                std_ratio_dim_to_next=float(std[dim - 1] / max(std[dim], 1e-30))
                if len(std) > dim else float("inf"),
                r2_top=[float(r) for r in r2], r2_force_from_top=float(r2_force),
                calibration=W.tolist(), n_test_edges=int(len(test_edges["messages"])))
