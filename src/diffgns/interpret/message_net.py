"""A graph network whose edge messages are meant to be read: Cranmer et al. (2020) style.

    message_e = phi_e(edge features e)                       (E, msg_dim)
    a_i       = phi_v([node_i, sum_{e -> i} message_e])      (N, 2)

``phi_e`` and ``phi_v`` are :class:`diffgns.graph.networks.MLP` (no LayerNorm: the L1 penalty
must be able to switch message components off). Training minimises the mean squared (or
absolute) error of the normalised accelerations, plus ``l1_weight`` times the mean over edges
of the L1 norm of the messages, so that only as many components stay active as the physics
needs (two, in 2D), plus ``node_l2`` times the squared first-layer kernel of the node model.

Training runs in the loop every network shares, :func:`diffgns.graph.fit.fit` (Adam with
exponential decay to a floor, checkpoints with exact resume, logs, SIGTERM); the batch of a
step is a function of (seed, step) (:func:`~diffgns.graph.fit.step_rng`).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization, struct

from diffgns.graph.features import Normalizer
from diffgns.graph.fit import TrainConfig, fit, make_optimizer, step_rng
from diffgns.graph.networks import MLP
from diffgns.models import model_path


@dataclasses.dataclass(frozen=True)
class MessageNetConfig:
    """Network sizes (reference: messages 100, hidden 300, 3 hidden layers), L1 weight, loss.

    ``loss="mse"`` by default: contact forces act on a few percent of the edges, and a mean
    absolute error is minimised by predicting the median (zero) acceleration everywhere; the
    squared error is not (measured: MAE training stalled at the all-zero prediction).

    ``node_l2``: weight of an L2 penalty on the node model's first-layer kernel. Messages and
    that layer can trade scale freely, so without it the L1 penalty shrinks all message
    components together instead of selecting a few (measured: after 5000 steps without it,
    99 of 100 components had a std above 10% of the largest).

    ``l1_warmup``: the L1 weight ramps linearly from 0 to ``l1_weight`` over this many steps.
    Contacts touch few edges, so at initialisation the fit gradient is weak and a full L1
    weight switches every message off for good (measured: l1_weight 3e-2 from step 0 ended
    at the all-zero prediction); learning the physics first avoids that.
    """

    msg_dim: int = 100
    hidden: int = 300
    layers: int = 3
    l1_weight: float = 1e-2
    loss: str = "mse"
    node_l2: float = 1e-4
    l1_warmup: int = 0

    def __post_init__(self):
        if self.node_l2 < 0 or self.l1_weight < 0:
            raise ValueError("MessageNetConfig: l1_weight and node_l2 must be >= 0")
        if self.loss not in ("mse", "mae"):
            raise ValueError(f"MessageNetConfig.loss must be 'mse' or 'mae', got {self.loss!r}")


class MessageNet(nn.Module):
    """Edge model + sum aggregation + node model on one graph (see the module docstring).

    Call with normalised ``edges`` (E, F_e), ``nodes`` (N, F_n) and ``receivers`` (E,) int;
    returns (normalised accelerations (N, 2), messages (E, msg_dim)).
    """

    cfg: MessageNetConfig

    @nn.compact
    def __call__(self, edges, nodes, receivers):
        c = self.cfg
        msg = MLP(c.hidden, c.layers, c.msg_dim, layer_norm=False, name="edge_model")(edges)
        agg = jax.ops.segment_sum(msg, receivers, nodes.shape[0])
        acc = MLP(c.hidden, c.layers, 2, layer_norm=False, name="node_model")(
            jnp.concatenate([nodes, agg], axis=-1))
        return acc, msg


@struct.dataclass
class MessageStats:
    """Normalisation statistics of a message network (fitted on the training samples):
    :class:`~diffgns.graph.features.Normalizer` of the edge features (F_e,), the node
    features (F_n,) and the accelerations (a scale only: ``mean = 0``, ``std`` a scalar,
    m/s^2). Stds are floored at 1e-8."""

    edge: Normalizer
    node: Normalizer
    acceleration: Normalizer

    @classmethod
    def fit(cls, samples: dict) -> MessageStats:
        return cls(Normalizer.fit(samples["edges"], 1e-8), Normalizer.fit(samples["node"], 1e-8),
                   Normalizer.fit(np.ravel(samples["acc"]), 1e-8, center=False))

    def to_dict(self) -> dict:
        """The ``model.json`` form: edge_mean, edge_std, node_mean, node_std, acc_std."""
        return dict(edge_mean=np.asarray(self.edge.mean).tolist(),
                    edge_std=np.asarray(self.edge.std).tolist(),
                    node_mean=np.asarray(self.node.mean).tolist(),
                    node_std=np.asarray(self.node.std).tolist(),
                    acc_std=float(self.acceleration.std))

    @classmethod
    def from_dict(cls, d: dict) -> MessageStats:
        f = jnp.result_type(float)
        arr = lambda k: jnp.asarray(d[k], f)
        return cls(Normalizer(arr("edge_mean"), arr("edge_std")),
                   Normalizer(arr("node_mean"), arr("node_std")),
                   Normalizer(jnp.zeros((), f), arr("acc_std")))


def forward(net: MessageNet, norm: MessageStats, params, edges, nodes, receivers):
    """Physical-unit forward pass on a batch of graphs.

    edges (G, E, F_e) and nodes (G, N, F_n) in physical units -> (accelerations (G, N, 2)
    in m/s^2, messages (G, E, msg_dim)).
    """
    e, n = norm.edge.normalize(edges), norm.node.normalize(nodes)
    acc, msg = jax.vmap(lambda a, b: net.apply(params, a, b, receivers))(e, n)
    return norm.acceleration.denormalize(acc), msg


def make_loss(net: MessageNet, norm: MessageStats, receivers):
    def loss_fn(params, edges, nodes, acc, l1_scale=1.0):
        pred, msg = forward(net, norm, params, edges, nodes, receivers)
        err = (pred - acc) / norm.acceleration.std
        fit = jnp.mean(err**2) if net.cfg.loss == "mse" else jnp.mean(jnp.abs(err))
        l1 = jnp.mean(jnp.sum(jnp.abs(msg), axis=-1))
        l2 = jnp.sum(params["params"]["node_model"]["hidden_0"]["kernel"] ** 2)
        return fit + l1_scale * net.cfg.l1_weight * l1 + net.cfg.node_l2 * l2, (fit, l1)
    return loss_fn


def save(out: Path, cfg: MessageNetConfig, norm: MessageStats, params, info: dict) -> None:
    """Write ``params.msgpack`` and ``model.json`` (config, normaliser, info) to ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "params.msgpack").write_bytes(serialization.to_bytes(params))
    (out / "model.json").write_text(json.dumps(dict(
        net=dataclasses.asdict(cfg), normaliser=norm.to_dict(), **info), indent=2))


def load(path: str | Path):
    """Read a model folder written by :func:`save` (or a shipped model's name):
    (net, norm, params, info)."""
    path = model_path(path)  # a folder, or the name of a shipped model
    meta = json.loads((path / "model.json").read_text())
    cfg = MessageNetConfig(**meta.pop("net"))
    norm = MessageStats.from_dict(meta.pop("normaliser"))
    net = MessageNet(cfg)
    n_edge, n_node = len(norm.edge.mean), len(norm.node.mean)
    template = net.init(jax.random.PRNGKey(0), jnp.zeros((2, n_edge)), jnp.zeros((2, n_node)),
                        jnp.zeros(2, jnp.int32))
    params = serialization.from_bytes(template, (path / "params.msgpack").read_bytes())
    return net, norm, params, meta


def train(samples: dict, out_dir: str | Path, cfg: MessageNetConfig, tcfg: TrainConfig,
          progress: bool = True):
    """Train (or resume from ``out_dir/checkpoint.msgpack``) on edge samples.

    ``samples`` is :func:`diffgns.interpret.nbody_data.edge_samples` output. Writes
    ``train_log.csv`` and, at the end, the model folder ``out_dir/model``. Returns
    (net, norm, params).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    net = MessageNet(cfg)
    norm = MessageStats.fit(samples)
    recv = jnp.asarray(samples["receivers"])
    params = net.init(jax.random.PRNGKey(tcfg.seed), jnp.zeros(samples["edges"].shape[1:]),
                      jnp.zeros(samples["node"].shape[1:]), recv)
    opt = make_optimizer(tcfg)
    loss_fn = make_loss(net, norm, recv)

    @jax.jit
    def update(params, opt_state, edges, nodes, acc, l1_scale):
        (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, edges, nodes,
                                                                        acc, l1_scale)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss, aux

    info = dict(train=dataclasses.asdict(tcfg), n_graphs=int(len(samples["edges"])))
    n_graphs = len(samples["edges"])

    def one_step(params, opt_state, step):
        rng, _ = step_rng(tcfg.seed, step)
        idx = rng.integers(0, n_graphs, tcfg.batch_size)
        params, opt_state, loss, (fit, l1) = update(
            params, opt_state, samples["edges"][idx], samples["node"][idx], samples["acc"][idx],
            min(1.0, step / cfg.l1_warmup) if cfg.l1_warmup else 1.0)
        return params, opt_state, (loss, fit, l1)

    params, opt_state, step = fit(one_step, params, opt.init(params), tcfg, out, info,
                                  ["loss", "fit", "message_l1"], desc="message net",
                                  progress=progress)
    save(out / "model", cfg, norm, params, dict(info, steps=step))
    return net, norm, params
