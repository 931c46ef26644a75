"""Training, saving and loading of MeshGraphNet models on cylinder-flow datasets.

Trained by the loop every network shares, :func:`diffgns.graph.fit.fit` (checkpoints,
exact resume, logs, SIGTERM, Adam with exponential learning-rate decay to a floor); the
batch and noise of a step are a function of (seed, step) (:func:`~diffgns.graph.fit.step_rng`).

One sample is one (trajectory, frame) pair: input velocity ``v_t`` with Gaussian noise
(``noise_std``, m/s) on fluid nodes, target ``[v_{t+1} - v_noisy, p_{t+1}]`` normalised;
the loss is the mean squared error of the velocity over fluid and outflow nodes and of the
pressure over every mesh vertex (:func:`~diffgns.mesh.meshnet.loss_weights`).

With ``TrainConfig.push_forward = K > 0`` each sample first rolls the model forward
``k ~ U{0..K}`` frames from the data without gradient (the push-forward trick of
Brandstetter et al. 2022): the network then learns to correct the input distribution its
own rollouts produce, the main cure for drift in long rollouts besides input noise.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization

from diffgns.graph.features import Normalizer, combine_std
from diffgns.graph.fit import TrainConfig, average_params, fit, make_optimizer, step_rng
from diffgns.io.dataset import read_metadata
from diffgns.mesh.dataset import iter_cylinder_dataset
from diffgns.mesh.meshnet import (
    FLUID,
    MeshGraph,
    MeshNet,
    MeshNetConfig,
    MeshStats,
    mesh_edges,
    node_loss,
    pad_mesh,
)
from diffgns.models import model_dir as _model_folder


def load_cylinder(path: str | Path) -> list[dict]:
    """Trajectories of a cylinder dataset as dicts of numpy arrays plus ``attrs``."""
    out = []
    for key, arrays, attrs in iter_cylinder_dataset(path):
        out.append(dict(arrays, key=key, attrs=attrs))
    if not out:
        raise ValueError(f"{path}: no trajectories")
    return out


def padding_for(trajs: list[dict], multiple: int = 64) -> tuple[int, int]:
    """(n_nodes, n_edges) padding that fits every mesh, rounded up to ``multiple``."""
    n = max(len(t["mesh_pos"]) for t in trajs)
    e = max(len(mesh_edges(t["cells"])[0]) for t in trajs)
    up = lambda x: int(-(-(x + 1) // multiple) * multiple)
    return up(n), up(e)


def viscosity_stats(trajs: list[dict]) -> Normalizer:
    """Normalizer of ln(nu) (nu in m^2/s, from each trajectory's ``attrs["nu"]``); a std
    below 1e-6 (one viscosity) is replaced by 1."""
    log_nu = np.log([float(t["attrs"]["nu"]) for t in trajs])
    std = float(np.std(log_nu))
    f = jnp.result_type(float)
    return Normalizer(jnp.asarray(np.mean(log_nu), f), jnp.asarray(std if std > 1e-6 else 1.0, f))


def stats_from_metadata(meta: dict, trajs: list[dict], noise_std: float,
                        viscosity_feature: bool = True) -> MeshStats:
    """Normalisers from the dataset metadata (noise folded into the stds), the mean mesh
    edge length of ``trajs`` as the edge scale and, if asked, the ln(nu) normaliser."""
    f = jnp.result_type(float)
    vel = Normalizer(jnp.asarray(meta["velocity_mean"], f),
                     combine_std(meta["velocity_std"], noise_std))
    t_mean = [*meta["velocity_change_mean"], meta["pressure_mean"]]
    t_std = [*np.asarray(combine_std(meta["velocity_change_std"], noise_std)).tolist(),
             meta["pressure_std"]]
    lengths = []
    for t in trajs:
        s, r = mesh_edges(t["cells"])
        lengths.append(np.linalg.norm(t["mesh_pos"][s] - t["mesh_pos"][r], axis=1))
    scale = float(np.mean(np.concatenate(lengths)))
    return MeshStats(vel, Normalizer(jnp.asarray(t_mean, f), jnp.asarray(t_std, f)), scale,
                     viscosity_stats(trajs) if viscosity_feature else None)


def graph_of(traj: dict, padding: tuple[int, int]) -> MeshGraph:
    """The padded graph of one trajectory, with its viscosity ``attrs["nu"]`` (m^2/s)."""
    nu = traj["attrs"].get("nu")
    return pad_mesh(traj["mesh_pos"], traj["cells"], traj["node_type"], *padding,
                    viscosity=None if nu is None else float(nu))


def graphs_of(trajs: list[dict], padding: tuple[int, int]) -> MeshGraph:
    """Stacked padded graphs (leading axis = trajectory)."""
    gs = [graph_of(t, padding) for t in trajs]
    return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *gs)


def padded_fields(trajs: list[dict], n_nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """velocity (B, F, n_nodes, 2) and pressure (B, F, n_nodes), zero-padded, float32;
    all trajectories must have the same number of frames."""
    F = {len(t["velocity"]) for t in trajs}
    if len(F) != 1:
        raise ValueError(f"trajectories differ in length {sorted(F)}")
    (F,) = F
    v = np.zeros((len(trajs), F, n_nodes, 2), np.float32)
    p = np.zeros((len(trajs), F, n_nodes), np.float32)
    for i, t in enumerate(trajs):
        v[i, :, : len(t["mesh_pos"])] = t["velocity"]
        p[i, :, : len(t["mesh_pos"])] = t["pressure"]
    return v, p


def save_model(out: Path, model: MeshNet, params, padding, info: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "params.msgpack").write_bytes(serialization.to_bytes(params))
    st = model.stats
    (out / "model.json").write_text(json.dumps(dict(
        kind="meshgraphnet", config=dataclasses.asdict(model.config), padding=list(padding),
        stats=dict(velocity_mean=np.asarray(st.velocity.mean).tolist(),
                   velocity_std=np.asarray(st.velocity.std).tolist(),
                   target_mean=np.asarray(st.target.mean).tolist(),
                   target_std=np.asarray(st.target.std).tolist(), edge_scale=st.edge_scale,
                   **({} if st.viscosity is None else dict(
                       log_viscosity_mean=float(st.viscosity.mean),
                       log_viscosity_std=float(st.viscosity.std)))),
        **info), indent=2, default=str))


def load_model(path: str | Path):
    """(model, params, info) from a folder written by :func:`save_model`, a training run
    folder holding one in ``model/``, or a shipped model's name
    (:func:`diffgns.models.model_dir`; a wrong path raises its ``ModelFolderError``)."""
    path = _model_folder(path, "model.json")
    info = json.loads((path / "model.json").read_text())
    s = info["stats"]
    f = jnp.result_type(float)
    nu = None
    if "log_viscosity_mean" in s:
        nu = Normalizer(jnp.asarray(s["log_viscosity_mean"], f),
                        jnp.asarray(s["log_viscosity_std"], f))
    stats = MeshStats(Normalizer(jnp.asarray(s["velocity_mean"], f),
                                 jnp.asarray(s["velocity_std"], f)),
                      Normalizer(jnp.asarray(s["target_mean"], f),
                                 jnp.asarray(s["target_std"], f)), float(s["edge_scale"]), nu)
    model = MeshNet(MeshNetConfig(**{"viscosity_feature": False, **info["config"]}), stats,
                    frame_dt=float(info.get("frame_dt", 0.01)))
    n, e = info["padding"]
    dummy = MeshGraph(jnp.zeros((n, 2)), jnp.zeros(n, jnp.int32), jnp.zeros(e, jnp.int32),
                      jnp.zeros(e, jnp.int32), jnp.zeros(e, bool), jnp.ones(()))
    params = serialization.from_bytes(model.init_network(jax.random.PRNGKey(0), dummy),
                                      (path / "params.msgpack").read_bytes())
    return model, params, info


def average_models(paths, out: str | Path) -> Path:
    """Write to ``out`` the uniform average of the parameters of MeshGraphNet folders
    ``paths`` (a "model soup" of fine-tunes of one parent). Their network configuration
    (all but the training noise), padding and normalisers must be identical (ValueError
    naming the difference); the first model's ``model.json`` is kept, with
    ``averaged_from``. Returns ``out``."""
    if len(paths) < 2:
        raise ValueError("averaging needs at least two models")
    models = [load_model(p) for p in paths]
    m0, _, info0 = models[0]
    net = lambda info: {k: v for k, v in info["config"].items() if k != "noise_std"}  # noqa: E731
    for p, (_, _, info) in zip(paths[1:], models[1:]):
        for what, a, b in (("configuration", net(info0), net(info)),
                           ("padding", info0["padding"], info["padding"]),
                           ("normaliser", info0["stats"], info["stats"])):
            if a != b:
                raise ValueError(f"cannot average {p} with {paths[0]}: different {what} "
                                 f"(first, this) = ({a}, {b})")
    avg = average_params([m[1] for m in models])
    keep = {k: v for k, v in info0.items() if k not in ("kind", "config", "padding", "stats")}
    save_model(Path(out), m0, avg, info0["padding"],
               dict(keep, averaged_from=[str(p) for p in paths]))
    return Path(out)


def pushed(model: MeshNet, params, graph: MeshGraph, v, n_push):
    """``v`` (N, 2) advanced ``n_push`` (traced int) model frames with stopped gradients;
    non-predicted nodes keep their values in ``v`` (steady boundary conditions)."""
    frozen = jax.lax.stop_gradient(params)
    body = lambda _, u: model.advance(frozen, graph, u, v)[0]
    return jax.lax.stop_gradient(jax.lax.fori_loop(0, n_push, body, v))


def _loss(model: MeshNet, params, graph: MeshGraph, v, v_next, p_next, key, n_push=0):
    v = pushed(model, params, graph, v, n_push)
    noise = model.config.noise_std * jax.random.normal(key, v.shape, v.dtype)
    v_in = v + jnp.where((graph.node_type == FLUID)[:, None], noise, 0.0)
    target = jnp.concatenate([v_next - v_in, p_next[:, None]], axis=-1)
    err = model.normalized_output(params, graph, v_in) - model.stats.target.normalize(target)
    return node_loss(graph, err[:, :2], err[:, 2])


def _grow_node_inputs(path, old: jax.Array, new: jax.Array) -> jax.Array:
    """``old`` param, or for the node encoder's first kernel one zero row inserted after the
    two velocity inputs (the viscosity input), so the grown network computes the same."""
    if old.shape == new.shape:
        return old
    name = jax.tree_util.keystr(path)
    if ("node_encoder" in name and "hidden_0" in name and "kernel" in name
            and new.shape == (old.shape[0] + 1, *old.shape[1:])):
        return jnp.concatenate([old[:2], jnp.zeros_like(old[:1]), old[2:]])
    raise ValueError(f"init_from: parameter {name} has shape {old.shape}, expected {new.shape}")


def fine_tune_start(model_dir, cfg: MeshNetConfig, template, data_stats: MeshStats):
    """(params, stats) to fine-tune from the model in ``model_dir``.

    Its configuration must equal ``cfg`` except the training noise and, going from a model
    without the viscosity input to one with it, ``viscosity_feature`` (the new input's weights
    start at zero, so the start computes what the old model did). The old normalisers are
    kept; the ln(nu) one comes from the data. ``template``: params of the new network."""
    old, old_params, _ = load_model(model_dir)
    a, b = dataclasses.asdict(old.config), dataclasses.asdict(cfg)
    grow = b["viscosity_feature"] and not a["viscosity_feature"]
    for k in ("noise_std", "viscosity_feature") if grow else ("noise_std",):
        a.pop(k), b.pop(k)
    if a != b:
        raise ValueError(f"init_from {model_dir}: its configuration {a} differs from {b} "
                         "beyond the training noise (and adding the viscosity input)")
    nu = old.stats.viscosity if old.config.viscosity_feature else data_stats.viscosity
    stats = MeshStats(old.stats.velocity, old.stats.target, old.stats.edge_scale, nu)
    return jax.tree_util.tree_map_with_path(_grow_node_inputs, old_params, template), stats


def train(train_path, out_dir, cfg: MeshNetConfig, tcfg: TrainConfig, padding=None,
          progress: bool = True, init_from=None):
    """Train (or resume) a MeshGraphNet; writes checkpoints, ``train_log.csv`` and
    ``out_dir/model``. ``init_from``: a model folder to fine-tune from
    (:func:`fine_tune_start`). Returns (model, params)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    trajs = load_cylinder(train_path)
    padding = tuple(padding or padding_for(trajs))
    model = MeshNet(cfg, stats_from_metadata(read_metadata(train_path), trajs, cfg.noise_std))
    graphs = graphs_of(trajs, padding)
    vel, pres = padded_fields(trajs, padding[0])
    opt = make_optimizer(tcfg)
    model.check_graph(graphs)
    params = model.init_network(jax.random.PRNGKey(tcfg.seed),
                                jax.tree_util.tree_map(lambda a: a[0], graphs))
    if init_from is not None:
        params, stats = fine_tune_start(init_from, cfg, params, model.stats)
        model = MeshNet(cfg, stats)

    def batch_loss(params, g, v, vn, pn, key, push):
        keys = jax.random.split(key, v.shape[0])
        f = lambda *a: _loss(model, params, *a)
        return jax.vmap(f)(g, v, vn, pn, keys, push).mean()

    @jax.jit
    def update(params, opt_state, g, v, vn, pn, key, push):
        loss, grads = jax.value_and_grad(batch_loss)(params, g, v, vn, pn, key, push)
        updates, opt_state = opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    info = dict(train=dataclasses.asdict(tcfg), data=str(train_path), init_from=init_from,
                n_trajectories=len(trajs), frame_dt=float(trajs[0]["attrs"]["frame_dt"]))
    B, F, K = tcfg.batch_size, vel.shape[1], tcfg.push_forward
    if not 0 <= K < F - 1:
        raise ValueError(f"push_forward must be in [0, {F - 2}] for {F}-frame trajectories, "
                         f"got {K}")

    def one_step(params, opt_state, step):
        rng, key = step_rng(tcfg.seed, step)
        ti, k = rng.integers(0, len(trajs), B), rng.integers(0, K + 1, B)
        fi = rng.integers(0, F - 1 - k)
        g = jax.tree_util.tree_map(lambda a: a[ti], graphs)
        params, opt_state, loss = update(params, opt_state, g, vel[ti, fi], vel[ti, fi + k + 1],
                                         pres[ti, fi + k + 1], key, jnp.asarray(k, jnp.int32))
        return params, opt_state, (loss,)

    params, opt_state, step = fit(one_step, params, opt.init(params), tcfg, out, info,
                                  ["loss"], desc="meshgraphnet", progress=progress)
    save_model(out / "model", model, params, padding, dict(info, steps=step))
    return model, params
