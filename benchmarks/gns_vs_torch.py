"""Inference cost of one GNS step: diffgns (JAX) vs a PyTorch/PyG GNS written here.

    .venv/bin/python benchmarks/gns_vs_torch.py [--repeats 12] [--sides 22 32 45]
        [--threads both]

Problem (shared by both sides, float32): a side x side block of particles (``--sides``;
45 x 45 = 2025 by default, 22 and 32 give N = 484 and 1024) on a
square lattice of spacing h = R / 2.5 with R = 0.015 m, slightly jittered, in the
reference sand box ``[0.1, 0.9]^2``; a 6-frame position history (5 velocities) from a
small random walk; particle type 6 except the bottom row (type 3, kinematic); material
tan(30 deg). With R = 2.5 h an interior particle has 21 neighbours including itself
(|i|^2 + |j|^2 < 6.25); the block's border brings the mean to ~20 (the actual edge
count is measured and reported).

Architecture (both sides, the reference GNS): 16-wide type embedding over 9 types; node
features = 5 normalised velocities + 4 clipped wall distances / R + raw tan(phi); edge
features = (x_s - x_r) / R and its norm, self-edges included; encoder MLPs, ``mp_steps``
interaction steps with separate weights (edge MLP on [e, v_r, v_s], sum at the receiver,
node MLP on [v, agg], residual node and edge updates), decoder; every MLP has 2 hidden
layers of ``latent`` with ReLU and a LayerNorm after it except the decoder; identity
normalisers; semi-implicit Euler in frame units, kinematic particles held.

(a) diffgns: ``GNS(GNSConfig(latent, mp_steps, mlp_layers=2, radius=R, bounds),
    ParticleStats.identity())``.  *step* = jitted ``gns.advance`` (jax-md cell-list neighbour
    update at the current positions + features + network + Euler), *network* = jitted
    ``gns.acceleration`` on precomputed (capacity-padded) edges.
(b) torch: ``torch_geometric.nn.MessagePassing(aggr="add")`` interaction networks in the
    computation pattern of the reference PyTorch GNS (the first edge-MLP layer acts on the
    concatenation [e, x_i, x_j], no split), ``torch.no_grad()``, ``set_num_threads(2)``.
    *step* = radius graph + features + network + Euler, *forward* = features + network on a
    precomputed ``edge_index``. The radius graph: torch_geometric's ``radius_graph`` needs
    pyg-lib or torch_cluster; when neither is importable (the case on the development
    machine) it is built with ``torch.cdist`` (exact, non-matmul mode) + ``< R`` threshold
    + ``nonzero``, and the JSON says which was used.

*train* (both sides): one training step on the precomputed graph -- features + network +
mean squared error of the normalised acceleration over the non-kinematic particles +
backward + Adam (lr 1e-4); diffgns: ``jax.value_and_grad`` + ``optax.adam`` under one
``jax.jit``; torch: ``loss.backward()`` + ``torch.optim.Adam.step()``.
*train_k*: the same, ``k = TrainConfig().steps_per_call`` steps in one jitted call looped
inside the program (``lax.fori_loop``), as ``diffgns train`` runs them by default, against
``k`` torch steps; the ratio is per step either way.

Both models are checked to compute the same function: the flax parameters are copied into
the torch model and the accelerations compared (they agree to float32 round-off).

Timing (``benchmarks/protocol.py``, ``benchmarks/timing.py``): the first call of each
function timed apart (JAX compile = first call - median steady call), then ``--repeats``
interleaved rounds: each round times one call of diffgns and of torch, the order alternating
round by round, so both see the same background load. Ratio = diffgns time / torch time,
median of the per-round ratios; every round, wall and CPU time, is stored. With
``--threads both`` (the default) the whole comparison runs with 2 threads (XLA's default,
``torch.set_num_threads(2)``), then in a child process pinned to one core with one thread on
both sides, and the report gives both ratios.
If diffgns misses the target (step <= 0.5 x torch step at the reference config), or with
``--profile always``, the reference config is profiled: neighbour update, features, encoder,
processor steps, decoder, single-kernel timings of one interaction step (matmuls, gathers,
LayerNorm, segment_sum, masking), and whole-network variants (same weights, same result)
on receiver-sorted, mask-free and compact (unpadded) edge lists, timed interleaved.
Writes ``benchmarks/results/gns_vs_torch.json``.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import protocol
from protocol import warm_up_jax

from diffgns.graph.fit import TrainConfig  # noqa: E402
from diffgns.scene.materials import friction_feature  # noqa: E402
from diffgns.timing import block, interleave, measure, no_sync, time_call

RADIUS = 0.015
SPACING = RADIUS / 2.5
SIDE = 45  # default: N = 2025
BOUNDS = ((0.1, 0.9), (0.1, 0.9))
HISTORY = 5
N_TYPES = 9
TYPE_EMBED = 16
MLP_LAYERS = 2
SAND, KINEMATIC = 6, 3
TAN_PHI = float(friction_feature(30.0))
LN_EPS = 1e-6  # flax LayerNorm default; used on the torch side too so outputs match
CONFIGS = {"reference": (128, 10), "small": (64, 5)}
TARGET_RATIO = 0.5
STEPS_PER_CALL = TrainConfig().steps_per_call  # diffgns train's default
TRAIN_K = f"train_{STEPS_PER_CALL}"


# ============================================================================ scene
def make_scene(side: int = SIDE, seed: int = 0):
    """(history (N, 6, 2) float32, particle_type (N,) int32, material (N,) float32), N = side^2."""
    rng = np.random.default_rng(seed)
    g = np.arange(side) * SPACING
    gx, gy = np.meshgrid(g, g, indexing="ij")
    x0 = np.stack([gx.ravel(), gy.ravel()], axis=1) + BOUNDS[0][0] + 0.5 * SPACING
    x0 = x0 + rng.uniform(-0.02, 0.02, x0.shape) * SPACING  # far from the R thresholds
    steps = rng.normal(0.0, 2e-5, (x0.shape[0], HISTORY, 2))  # ~h / 300 per frame
    walk = np.concatenate([np.zeros((x0.shape[0], 1, 2)), np.cumsum(steps, axis=1)], axis=1)
    history = (x0[:, None, :] + walk - walk[:, -1:]).astype(np.float32)  # current = x0
    ptype = np.full(x0.shape[0], SAND, np.int32)
    ptype[np.isclose(gy.ravel(), 0.0)] = KINEMATIC
    material = np.full(x0.shape[0], TAN_PHI, np.float32)
    return history, ptype, material


# ============================================================================ torch
def torch_radius_graph(torch, x, radius: float):
    """(2, E) ``edge_index`` (row 0 = source/sender, row 1 = target/receiver) of all pairs
    with ``|x_s - x_r| < radius``, self-loops included, and the method used."""
    try:
        from torch_geometric.nn import radius_graph

        ei = radius_graph(x, r=radius, loop=True, max_num_neighbors=128)
        return ei, "torch_geometric.radius_graph"
    except ImportError:
        pass
    d = torch.cdist(x, x, compute_mode="donot_use_mm_for_euclid_dist")
    recv, send = torch.nonzero(d < radius, as_tuple=True)
    return torch.stack([send, recv]), "torch.cdist + threshold (no pyg-lib / torch_cluster)"


def build_torch_gns(latent: int, mp_steps: int):
    """A PyG GNS with the reference PyTorch GNS's computation pattern (random init)."""
    import torch
    from torch import nn
    from torch_geometric.nn import MessagePassing

    def mlp(n_in: int, n_out: int, layer_norm: bool = True) -> nn.Sequential:
        layers: list[nn.Module] = []
        width = n_in
        for _ in range(MLP_LAYERS):
            layers += [nn.Linear(width, latent), nn.ReLU()]
            width = latent
        layers.append(nn.Linear(width, n_out))
        if layer_norm:
            layers.append(nn.LayerNorm(n_out, eps=LN_EPS))
        return nn.Sequential(*layers)

    class Interaction(MessagePassing):
        """Edge MLP on cat[e, x_i, x_j] -> summed at the receiver -> node MLP on
        cat[x, agg]; returns the residual-updated node *and* edge latents."""

        def __init__(self):
            super().__init__(aggr="add")
            self.edge_fn = mlp(3 * latent, latent)
            self.node_fn = mlp(2 * latent, latent)

        def forward(self, x, edge_index, e):
            dx, de = self.propagate(edge_index, x=x, e=e)
            return x + dx, e + de

        def message(self, x_i, x_j, e):
            return self.edge_fn(torch.cat([e, x_i, x_j], dim=-1))

        def aggregate(self, inputs, index, ptr=None, dim_size=None):
            # keep the messages: they are the new edge latents (the reference GNS bug
            # returned the *input* edge features here instead)
            return super().aggregate(inputs, index, ptr=ptr, dim_size=dim_size), inputs

        def update(self, aggr_out, x):
            agg, msg = aggr_out
            return self.node_fn(torch.cat([x, agg], dim=-1)), msg

    n_node_features = 2 * HISTORY + 4 + 1

    class TorchGNS(nn.Module):
        def __init__(self):
            super().__init__()
            self.embed = nn.Embedding(N_TYPES, TYPE_EMBED)
            self.node_encoder = mlp(n_node_features + TYPE_EMBED, latent)
            self.edge_encoder = mlp(3, latent)
            self.processor = nn.ModuleList(Interaction() for _ in range(mp_steps))
            self.decoder = mlp(latent, 2, layer_norm=False)
            self.register_buffer("lower", torch.tensor([b[0] for b in BOUNDS]))
            self.register_buffer("upper", torch.tensor([b[1] for b in BOUNDS]))
            for name in ("vel", "acc"):  # identity normalisers, applied all the same
                self.register_buffer(f"{name}_mean", torch.zeros(2))
                self.register_buffer(f"{name}_std", torch.ones(2))

        def features(self, history, material, edge_index):
            n = history.shape[0]
            x = history[:, -1]
            vel = (history[:, 1:] - history[:, :-1] - self.vel_mean) / self.vel_std
            walls = torch.clamp(torch.cat([x - self.lower, self.upper - x], -1) / RADIUS,
                                -1.0, 1.0)
            nf = torch.cat([vel.reshape(n, -1), walls, material[:, None]], dim=-1)
            d = (x[edge_index[0]] - x[edge_index[1]]) / RADIUS
            ef = torch.cat([d, torch.linalg.vector_norm(d, dim=-1, keepdim=True)], dim=-1)
            return nf, ef

        def forward(self, history, particle_type, material, edge_index):
            """(N, 2) acceleration in m/frame^2 (features + network + denormalise)."""
            nf, ef = self.features(history, material, edge_index)
            v = self.node_encoder(torch.cat([nf, self.embed(particle_type)], dim=-1))
            e = self.edge_encoder(ef)
            for layer in self.processor:
                v, e = layer(v, edge_index, e)
            return self.decoder(v) * self.acc_std + self.acc_mean

        def step(self, history, particle_type, material):
            """Radius graph at the current positions + forward + semi-implicit Euler."""
            x = history[:, -1]
            edge_index, _ = torch_radius_graph(torch, x, RADIUS)
            acc = self.forward(history, particle_type, material, edge_index)
            x_next = x + (x - history[:, -2]) + acc
            x_next = torch.where((particle_type == KINEMATIC)[:, None], x, x_next)
            return x_next, edge_index

    return TorchGNS().eval()


def load_flax_params(model, params: dict) -> None:
    """Copy diffgns' flax params into :func:`build_torch_gns`'s model (same function).

    The split first edge layer (``edge``, ``sender``, ``receiver`` kernels) becomes one
    Linear on cat[e, x_i, x_j] = cat[e, v_receiver, v_sender].
    """
    import torch

    p = params["params"]

    def t(a):
        return torch.from_numpy(np.array(a, dtype=np.float32))

    def linear(layer, kernel, bias):
        layer.weight.copy_(t(kernel).T)
        layer.bias.copy_(t(bias))

    def norm(layer, q):
        layer.weight.copy_(t(q["scale"]))
        layer.bias.copy_(t(q["bias"]))

    def seq(module, q, first=0):
        linears = [m for m in module if isinstance(m, torch.nn.Linear)]
        names = [f"hidden_{i}" for i in range(MLP_LAYERS)] + ["out"]
        for lin, nm in zip(linears[first:], names[first:]):
            linear(lin, q[nm]["kernel"], q[nm]["bias"])
        if isinstance(module[-1], torch.nn.LayerNorm):
            norm(module[-1], q["norm"])

    with torch.no_grad():
        model.embed.weight.copy_(t(p["type_embed"]["embedding"]))
        seq(model.node_encoder, p["node_encoder"])
        seq(model.edge_encoder, p["edge_encoder"])
        seq(model.decoder, p["decoder"])
        for k, layer in enumerate(model.processor):
            q = p[f"processor_{k}"]
            split = q["edge_in"]
            kernel = np.concatenate([split[nm]["kernel"] for nm in
                                     ("edge", "receiver", "sender")], axis=0)
            linear(layer.edge_fn[0], kernel, split["edge"]["bias"])
            rest = q["edge_mlp"]  # hidden_0 .. out of the remaining MLP_LAYERS - 1 layers
            lins = [m for m in layer.edge_fn if isinstance(m, torch.nn.Linear)][1:]
            names = [f"hidden_{i}" for i in range(MLP_LAYERS - 1)] + ["out"]
            for lin, nm in zip(lins, names):
                linear(lin, rest[nm]["kernel"], rest[nm]["bias"])
            norm(layer.edge_fn[-1], rest["norm"])
            seq(layer.node_fn, q["node_mlp"])


# ============================================================================ helpers
def mac_counts(latent: int, mp_steps: int, n: int, e_torch: int, e_jax: int) -> dict:
    """Multiply-accumulates of the dense layers (dominant cost) of each implementation."""
    L, h = latent, MLP_LAYERS - 1
    f_node = 2 * HISTORY + 4 + 1 + TYPE_EMBED
    node_enc = n * (f_node * L + h * L * L + L * L)
    edge_enc = 3 * L + h * L * L + L * L  # per edge
    enc_t, enc_j = node_enc + e_torch * edge_enc, node_enc + e_jax * edge_enc
    node_mlp = n * (2 * L * L + h * L * L + L * L)
    dec = n * (L * L + h * L * L + 2 * L)
    torch_proc = mp_steps * (e_torch * (3 * L * L + h * L * L + L * L) + node_mlp)
    jax_proc = mp_steps * (e_jax * (L * L + h * L * L + L * L) + 2 * n * L * L + node_mlp)
    return {"torch_gmac": (enc_t + torch_proc + dec) / 1e9,
            "diffgns_gmac": (enc_j + jax_proc + dec) / 1e9}


# ============================================================================ main
def diffgns_gns(latent: int, mp_steps: int, scene, jax, jnp) -> dict:
    """The diffgns side: GNS, parameters, neighbour list, edges and the two jitted calls
    (*step*: neighbour update + features + network + Euler; *network*: features + network
    on precomputed edges). The one place this benchmark calls the simulator's API."""
    from diffgns.graph.features import ParticleStats
    from diffgns.graph.gns import GNS, GNSConfig
    from diffgns.graph.neighbors import capacity, did_overflow, edges

    n = scene[0].shape[0]
    gns = GNS(GNSConfig(latent=latent, mp_steps=mp_steps, mlp_layers=MLP_LAYERS,
                        radius=RADIUS, bounds=BOUNDS), ParticleStats.identity())
    history, ptype, material = (jnp.asarray(a) for a in scene)
    params = gns.init_network(jax.random.PRNGKey(0), (history, ptype, material))
    nbrs = gns.allocate(history[:, -1])
    senders, receivers, mask = edges(nbrs, n)
    step_jit, net_jit = jax.jit(gns.advance), jax.jit(gns.acceleration)
    train_jit, many_jit, opt_state, target = train_step(
        gns, params, history, ptype, material, senders, receivers, mask, jax, jnp)
    k = jnp.int32(STEPS_PER_CALL)
    return dict(
        train=lambda: train_jit(params, opt_state, target), target=target,
        train_per_call=lambda: many_jit(params, opt_state, target, k),
        gns=gns, params=params, history=history, ptype=ptype, material=material, nbrs=nbrs,
        senders=senders, receivers=receivers, mask=mask, capacity=capacity(nbrs),
        overflowed=lambda out: bool(did_overflow(out[1])),
        step=lambda: step_jit(params, history, ptype, material, nbrs),
        network=lambda: net_jit(params, history, ptype, material, senders, receivers, mask))


def train_step(gns, params, history, ptype, material, senders, receivers, mask, jax, jnp):
    """(jitted ``(params, opt_state, target) -> (params, opt_state, loss)``, Adam state,
    target): one training step on a fixed graph -- features + network + mean squared error
    of the normalised acceleration over non-kinematic particles + backward + Adam (lr 1e-4).
    """
    import optax

    opt = optax.adam(1e-4)
    weight = jnp.asarray(ptype != KINEMATIC, jnp.float32)

    def loss(p, target):
        out = gns.normalized_acceleration(p, history, ptype, material, senders, receivers,
                                          mask)
        return jnp.sum(weight[:, None] * (out - target) ** 2) / (2.0 * jnp.sum(weight))

    def step(p, state, target):
        value, grads = jax.value_and_grad(loss)(p, target)
        updates, state = opt.update(grads, state, p)
        return optax.apply_updates(p, updates), state, value

    def many(p, state, target, count):
        # ``count`` steps in one call, looped inside the program as the library's
        # Trainer.steps does (TrainConfig.steps_per_call): one temporary buffer for all
        def body(i, c):
            return step(c[0], c[1], target)
        return jax.lax.fori_loop(0, count, body, (p, state, jnp.zeros(())))

    target = jnp.asarray(np.random.default_rng(1).normal(size=(history.shape[0], 2)),
                         jnp.float32)
    return jax.jit(step), jax.jit(many), opt.init(params), target


def torch_train_step(torch, model, th, tp, tm, edge_index, target):
    """The same training step for the torch model (train mode, Adam lr 1e-4, same loss)."""
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    weight = (tp != KINEMATIC).to(torch.float32)
    tgt = torch.from_numpy(np.array(target))

    def step():
        opt.zero_grad(set_to_none=True)
        out = model(th, tp, tm, edge_index)
        value = (weight[:, None] * (out - tgt) ** 2).sum() / (2.0 * weight.sum())
        value.backward()
        opt.step()
        return value

    return step


def check_equivalence(model, params, th, tp, tm, edge_index, acc_jax, x_next_jax, torch):
    """Copy the flax weights into the torch model and compare accelerations."""
    try:
        load_flax_params(model, params)
        with torch.no_grad():
            acc_t = model(th, tp, tm, edge_index).numpy()
            x_next_t = model.step(th, tp, tm)[0].numpy()
    except (KeyError, IndexError, TypeError, ValueError, RuntimeError) as err:
        return {"params_copied": False, "reason": repr(err)}
    scale = float(np.abs(np.asarray(acc_jax)).max())
    eq = {"params_copied": True,
          "max_abs_diff_acceleration": float(np.abs(acc_t - np.asarray(acc_jax)).max()),
          "max_abs_acceleration": scale,
          "max_abs_diff_next_position": float(np.abs(x_next_t - np.asarray(x_next_jax)).max())}
    eq["same_function"] = eq["max_abs_diff_acceleration"] <= 1e-4 * max(scale, 1.0)
    return eq


def run_config(latent, mp_steps, scene, args, torch, jax, jnp):
    history_np, ptype_np, material_np = scene
    n = history_np.shape[0]
    d = diffgns_gns(latent, mp_steps, scene, jax, jnp)
    first_step, (x_next_jax, nbrs_out, _clamp) = measure(d["step"])
    first_net, acc_jax = measure(d["network"])
    if d["overflowed"]((x_next_jax, nbrs_out)):
        raise RuntimeError("neighbour list overflowed in the benchmark step")
    senders, mask = np.asarray(d["senders"]), np.asarray(d["mask"])
    receivers = np.asarray(d["receivers"])
    n_valid = int(mask.sum())

    model = build_torch_gns(latent, mp_steps)
    th, tp, tm = (torch.from_numpy(a) for a in (history_np, ptype_np.astype(np.int64),
                                                 material_np))
    edge_index, graph_method = torch_radius_graph(torch, th[:, -1], RADIUS)
    jax_set = set(zip(senders[mask].tolist(), receivers[mask].tolist()))
    torch_set = set(zip(edge_index[0].tolist(), edge_index[1].tolist()))
    equivalence = check_equivalence(model, d["params"], th, tp, tm, edge_index, acc_jax,
                                     x_next_jax, torch)

    def torch_step():
        with torch.no_grad():
            return model.step(th, tp, tm)

    def torch_fwd():
        with torch.no_grad():
            return model(th, tp, tm, edge_index)

    torch_train = torch_train_step(torch, model, th, tp, tm, edge_index, d["target"])

    def torch_train_k():
        for _ in range(STEPS_PER_CALL):
            out = torch_train()
        return out

    first_train = measure(d["train"])[0]
    first_train_k = measure(d["train_per_call"])[0]
    for _ in range(args.warmup):
        block(d["step"]())
        block(d["network"]())
        block(d["train"]())
        block(d["train_per_call"]())
        torch_step()
        torch_fwd()
        torch_train()
    timings, ratios, rounds = {}, {}, {}
    for part, (fj, ft) in {"step": (d["step"], torch_step),
                           "network": (d["network"], torch_fwd),
                           "train": (d["train"], torch_train),
                           TRAIN_K: (d["train_per_call"], torch_train_k)}.items():
        res = interleave({"diffgns": fj, "torch": ft}, args.repeats,
                         sync={"diffgns": block, "torch": no_sync}, warmup=False)
        timings[f"diffgns_{part}"] = res.summary("diffgns")
        timings[f"torch_{part}"] = res.summary("torch")
        ratios[part] = {"median_paired_ratio": res.ratio("diffgns", "torch"),
                        "median_paired_cpu_ratio": res.ratio("diffgns", "torch", cpu=True),
                        "ratio_of_medians": timings[f"diffgns_{part}"]["median_s"]
                        / timings[f"torch_{part}"]["median_s"]}
        rounds[part] = res.to_json()["rounds"]
    for part, first in (("step", first_step), ("network", first_net), ("train", first_train),
                        (TRAIN_K, first_train_k)):
        t = timings[f"diffgns_{part}"]
        t.update(first_call_s=first.wall_s, first_call_cpu_s=first.cpu_s,
                 compile_s=max(0.0, first.wall_s - t["median_s"]))
    return {
        "latent": latent, "mp_steps": mp_steps, "mlp_layers": MLP_LAYERS, "n_particles": n,
        "edges_incl_self": n_valid, "mean_neighbours_incl_self": n_valid / n,
        "diffgns_edge_slots_incl_self": int(senders.shape[0]),
        "diffgns_capacity_no_self": d["capacity"], "torch_edges": int(edge_index.shape[1]),
        "edge_sets_equal": jax_set == torch_set, "torch_graph_method": graph_method,
        "equivalence": equivalence,
        "macs": mac_counts(latent, mp_steps, n, int(edge_index.shape[1]), int(senders.shape[0])),
        "timings": timings, "ratios": ratios, "rounds": rounds,
        "_objects": (d["gns"], d["params"], d["history"], d["ptype"], d["material"], d["nbrs"],
                     model, th, tp, tm, edge_index),
        "_calls": {"step": d["step"], "network": d["network"], "train": d["train"],
                   "torch_train": torch_train, "target": d["target"],
                   "graph": (d["senders"], d["receivers"], d["mask"])},
    }


def profile_diffgns(res, repeats, torch, jax, jnp) -> dict:
    """Where diffgns' step time goes (reference config); every entry a median in ms."""
    import flax.linen as nn

    from diffgns.graph.neighbors import edges
    from diffgns.graph.networks import MLP, InteractionStep

    config_res = res
    gns, params, history, ptype, material, nbrs, model, th, tp, tm, edge_index = res["_objects"]
    cfg = gns.config
    n, L = history.shape[0], cfg.latent
    p = params["params"]
    s, r, m = edges(nbrs, n)
    out: dict = {"note": "medians in ms of separately jitted pieces; pieces fuse differently "
                         "inside the whole step, so they need not add up exactly"}

    def ms(fn):
        return 1e3 * time_call(fn, repeats)[0]["median_s"]

    # -- step decomposition
    nb_fn = jax.jit(lambda x, nb: edges(gns.neighbors.update(x, nb), n))
    out["neighbour_update_and_edges"] = ms(lambda: nb_fn(history[:, -1], nbrs))
    feat_fn = jax.jit(gns.features)
    out["features"] = ms(lambda: feat_fn(history, material, s, r, m))
    nf, ef = feat_fn(history, material, s, r, m)
    net_fn = jax.jit(gns.network.apply)
    out["network_apply"] = ms(lambda: net_fn(params, nf, ptype, ef, s, r, m))

    def enc(nf, ef):
        emb = jnp.take(p["type_embed"]["embedding"], ptype, axis=0)
        v = MLP(L, cfg.mlp_layers, L).apply({"params": p["node_encoder"]},
                                           jnp.concatenate([nf, emb], -1))
        e = MLP(L, cfg.mlp_layers, L).apply({"params": p["edge_encoder"]}, ef)
        return v, jnp.where(m[:, None], e, 0.0)

    enc_fn = jax.jit(enc)
    out["encoder"] = ms(lambda: enc_fn(nf, ef))
    v, e = enc_fn(nf, ef)
    ist = InteractionStep(L, cfg.mlp_layers, cfg.attention)
    proc_fn = jax.jit(lambda q, v, e, s, r, m: ist.apply({"params": q}, v, e, s, r, m))
    one = ms(lambda: proc_fn(p["processor_0"], v, e, s, r, m))
    out["one_interaction_step"] = one
    out["processor_estimate_mp_steps_x_one"] = one * cfg.mp_steps
    dec_fn = jax.jit(lambda v: MLP(L, cfg.mlp_layers, 2, layer_norm=False).apply(
        {"params": p["decoder"]}, v))
    out["decoder"] = ms(lambda: dec_fn(v))

    # -- kernels of one interaction step (padded edge count, as in the step)
    q = p["processor_0"]
    ein = q["edge_in"]
    h = jnp.ones_like(e)

    kern = {}
    f = jax.jit(lambda e: jax.nn.relu(e @ ein["edge"]["kernel"] + ein["edge"]["bias"]))
    kern["edge_dense_ExLxL_relu (x3 per step)"] = ms(lambda: f(e))
    f = jax.jit(lambda v: (v @ ein["sender"]["kernel"], v @ ein["receiver"]["kernel"]))
    kern["node_projections_2xNxLxL"] = ms(lambda: f(v))
    f = jax.jit(lambda a, b: jnp.take(a, s, axis=0, mode="clip")
                + jnp.take(b, r, axis=0, mode="clip"))
    kern["two_gathers_N_to_E_plus_add"] = ms(lambda: f(v, v))
    ln = nn.LayerNorm()
    lnp = ln.init(jax.random.PRNGKey(0), h[:2])
    f = jax.jit(lambda x: ln.apply(lnp, x))
    kern["layernorm_E"] = ms(lambda: f(h))
    f = jax.jit(lambda x: jax.ops.segment_sum(x, r, num_segments=n))
    kern["segment_sum_E_to_N"] = ms(lambda: f(h))
    f = jax.jit(lambda x, y: (jnp.where(m[:, None], x, 0.0), jnp.where(m[:, None], y + x, 0.0)))
    kern["masking_wheres_and_residual_E"] = ms(lambda: f(h, e))
    f = jax.jit(lambda v, a: MLP(L, cfg.mlp_layers, L).apply(
        {"params": q["node_mlp"]}, jnp.concatenate([v, a], -1)))
    kern["node_mlp_N"] = ms(lambda: f(v, v))
    order = np.argsort(np.asarray(r), kind="stable")
    r_sorted = jnp.asarray(np.asarray(r)[order])
    f = jax.jit(lambda x: jax.ops.segment_sum(x, r_sorted, num_segments=n,
                                              indices_are_sorted=True))
    kern["segment_sum_E_to_N_sorted_indices"] = ms(lambda: f(h))
    out["kernels_one_step_ms"] = kern

    # -- whole-network variants without touching src/ (same math, different edge layout),
    # graphs closed over as constants, timed interleaved round by round
    sn, rn, mn = (np.asarray(a) for a in (s, r, m))
    cs, cr = sn[mn], rn[mn]
    o_pad = np.argsort(rn, kind="stable")  # padding (index N) stays at the end
    o_cmp = np.lexsort((cs, cr))
    graphs = {
        "padded_as_in_step (capacity x1.25 + self)": (sn, rn, mn),
        "padded_sorted_by_receiver": (sn[o_pad], rn[o_pad], mn[o_pad]),
        "padded_mask_free (const all-true mask; padding dropped by segment_sum)":
            (sn, rn, np.ones_like(mn)),
        "compact_valid_edges_only": (cs, cr, np.ones(cs.shape[0], bool)),
        "compact_sorted_by_receiver": (cs[o_cmp], cr[o_cmp], np.ones(cs.shape[0], bool)),
    }

    def variant(g):
        gs, gr, gm = (jnp.asarray(a) for a in g)
        f = jax.jit(lambda prm, hist: gns.acceleration(prm, hist, ptype, material, gs, gr, gm))
        return lambda: f(params, history)

    fns = {k: variant(g) for k, g in graphs.items()}
    ref_out = np.asarray(next(iter(fns.values()))())
    dev = {k: float(np.abs(np.asarray(fn()) - ref_out).max()) for k, fn in fns.items()}
    res = interleave(fns, repeats, warmup=False)
    out["network_variants_ms"] = {k: 1e3 * res.summary(k)["median_s"] for k in fns}
    out["network_variants_max_abs_dev_from_padded"] = dev
    out["edge_slots"] = {"padded": int(s.shape[0]), "valid": int(cs.shape[0])}

    # -- torch side, for comparison
    def tgraph():
        return torch_radius_graph(torch, th[:, -1], RADIUS)[0]

    out["torch_radius_graph"] = ms_torch(tgraph, repeats)
    out["host"] = host_profile(config_res, repeats, torch, jax, jnp)
    return out


def fresh_pages(fn, sync, calls: int = 3) -> dict:
    """Per call of ``fn``: minor page faults (fresh pages the kernel maps and zeroes, in MB
    at 4 KiB a page), user and system CPU seconds, wall seconds (``getrusage``, whole
    process; two warm-up calls first)."""
    import resource

    for _ in range(2):
        sync(fn())
    r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    for _ in range(calls):
        sync(fn())
    r1, t1 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    return {"fresh_page_MB": (r1.ru_minflt - r0.ru_minflt) * 4096 / 1e6 / calls,
            "user_s": (r1.ru_utime - r0.ru_utime) / calls,
            "sys_s": (r1.ru_stime - r0.ru_stime) / calls, "wall_s": (t1 - t0) / calls}


def host_profile(res, repeats, torch, jax, jnp, k: int = 4) -> dict:
    """Host-side cost of a call: XLA's CPU runtime allocates an executable's temporary
    buffer at every call and frees it after; glibc maps a fresh zeroed region for it, so a
    call pays page faults in proportion to its temporaries (GBs for a training step).
    Measured for the step, the network and the training step on both sides, and for ``k``
    training steps in one ``lax.scan`` call (one temporary buffer for ``k`` steps), timed
    per step interleaved with the single-step call."""
    import optax

    gns, params, history, ptype, material, nbrs, model, th, tp, tm, edge_index = res["_objects"]
    d = res["_calls"]
    out: dict = {"note": "per call; fresh_page_MB = minor faults x 4 KiB"}
    for name in ("step", "network", "train"):
        out[f"diffgns_{name}"] = fresh_pages(d[name], block)
    out["torch_train"] = fresh_pages(d["torch_train"], no_sync)
    s, r, m = d["graph"]
    opt = optax.adam(1e-4)
    weight = jnp.asarray(ptype != KINEMATIC, jnp.float32)

    def loss(p, target):
        o = gns.normalized_acceleration(p, history, ptype, material, s, r, m)
        return jnp.sum(weight[:, None] * (o - target) ** 2) / (2.0 * jnp.sum(weight))

    def one(carry, target):
        p, st = carry
        value, grads = jax.value_and_grad(loss)(p, target)
        updates, st = opt.update(grads, st, p)
        return (optax.apply_updates(p, updates), st), value

    scan = jax.jit(lambda p, st, t: jax.lax.scan(one, (p, st), t))
    targets = jnp.stack([d["target"]] * k)
    st0 = opt.init(params)
    out[f"diffgns_train_scan_{k}_per_call"] = fresh_pages(
        lambda: scan(params, st0, targets), block)
    rr = interleave({"single": d["train"], "scan": lambda: scan(params, st0, targets)},
                    max(5, repeats // 2), sync={"single": block, "scan": block})
    out[f"train_ms_per_step_single_vs_scan_{k}"] = {
        "single": 1e3 * rr.summary("single")["median_s"],
        "scan": 1e3 * rr.summary("scan")["median_s"] / k}
    return out


def ms_torch(fn, repeats):
    return 1e3 * time_call(fn, repeats, sync=no_sync)[0]["median_s"]


def print_table(run: protocol.Run, results: dict) -> None:
    head = (f"{'config':<22} {'part':<8} {'diffgns ms':>11} {'torch ms':>9} "
            f"{'ratio':>6} {'cpu ratio':>9} {'JAX compile s':>14}")
    run.print(head)
    for name, res in results.items():
        for part in ("step", "network", "train", TRAIN_K):
            tj = res["timings"][f"diffgns_{part}"]
            tt = res["timings"][f"torch_{part}"]
            rr = res["ratios"][part]
            run.print(f"{name:<22} {part:<8} {1e3 * tj['median_s']:>11.1f} "
                      f"{1e3 * tt['median_s']:>9.1f} {rr['median_paired_ratio']:>6.2f} "
                      f"{rr['median_paired_cpu_ratio']:>9.2f} {tj['compile_s']:>14.2f}")
    run.print("ratio = diffgns time / torch time, median of the per-round ratios (wall; CPU)")
    for name, res in results.items():
        run.print(f"{name}: N={res['n_particles']}, edges incl. self={res['edges_incl_self']} "
                  f"(mean {res['mean_neighbours_incl_self']:.2f}/particle; diffgns slots "
                  f"{res['diffgns_edge_slots_incl_self']}), torch edges={res['torch_edges']}, "
                  f"same edge set={res['edge_sets_equal']}, same function="
                  f"{res['equivalence'].get('same_function')}")


def print_profile(run: protocol.Run, profile: dict) -> None:
    run.print(f"diffgns profile ({profile['config']} config, ms):")
    for k, val in profile.items():
        if isinstance(val, dict):
            for kk, vv in val.items():
                fmt = ".1e" if k.endswith("_from_padded") else ".1f"
                if isinstance(vv, dict):
                    vv = ", ".join(f"{a} {b:.3g}" for a, b in vv.items())
                run.print(f"  {k}: {kk}: {vv:{fmt}}" if isinstance(vv, float)
                          else f"  {k}: {kk}: {vv}")
        elif isinstance(val, float):
            run.print(f"  {k}: {val:.1f}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=12, help="timed rounds (>= 10)")
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--sides", type=int, nargs="+", default=[SIDE],
                    help="particles per side of the block (N = side^2)")
    ap.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    ap.add_argument("--profile", choices=("auto", "always", "never"), default="auto",
                    help="profile diffgns at the reference config (auto: if it misses)")
    ap.add_argument("--profile-repeats", type=int, default=7)
    ap.add_argument("--out", default="gns_vs_torch.json")
    protocol.add_arguments(ap, threads="both")
    args = ap.parse_args(argv)
    run = protocol.start(args, "gns_vs_torch")

    import jax
    import jax.numpy as jnp
    import torch

    torch.set_num_threads(run.threads)
    warm_up_jax()
    results = {}

    def body():
        for side in args.sides:
            scene = make_scene(side)
            for name in args.configs:
                latent, mp_steps = CONFIGS[name]
                results[f"{name}_N{side * side}"] = run_config(latent, mp_steps, scene, args,
                                                               torch, jax, jnp)

    total = measure(body, sync=no_sync)[0]
    ref_key = f"reference_N{max(args.sides) ** 2}"
    ref = results.get(ref_key)
    missed = ref is not None and ref["ratios"]["step"]["median_paired_ratio"] > TARGET_RATIO
    profile = None
    if args.profile == "always" or (args.profile == "auto" and missed):
        key = ref_key if ref is not None else next(iter(results))
        profile = {"config": key, **profile_diffgns(results[key], args.profile_repeats,
                                                     torch, jax, jnp)}
    for res in results.values():
        res.pop("_objects")
        res.pop("_calls")
    print_table(run, results)
    if ref is not None:
        run.print(f"target diffgns step <= {TARGET_RATIO} x torch step ({ref_key}): "
                  f"{'met' if not missed else 'MISSED'} "
                  f"({ref['ratios']['step']['median_paired_ratio']:.2f})")
        for part in ("train", TRAIN_K):
            tr = ref["ratios"][part]["median_paired_ratio"]
            run.print(f"target diffgns training step ({part}) <= {TARGET_RATIO} x torch's "
                      f"({ref_key}): {'met' if tr <= TARGET_RATIO else 'MISSED'} ({tr:.2f})")
    if profile is not None:
        print_profile(run, profile)
    payload = {
        "description": __doc__.split("\n\n")[2].strip(),
        "scene": {"radius_m": RADIUS, "lattice_spacing_m": SPACING, "sides": args.sides,
                  "bounds": BOUNDS, "history_velocities": HISTORY, "n_types": N_TYPES,
                  "type_embed": TYPE_EMBED, "material": "tan(30 deg)"},
        "torch_threads": torch.get_num_threads(),
        "repeats": args.repeats, "warmup": args.warmup, "target_ratio": TARGET_RATIO,
        "target_met": (not missed) if ref is not None else None,
        "configs": results, "profile": profile,
        "total_wall_s": total.wall_s, "total_cpu_s": total.cpu_s,
    }
    if run.mode == "both":
        one = payload["one_thread_pinned"] = run.pinned_child()
        for part in ("step", "train", TRAIN_K):
            payload[f"ratios_{part}"] = {
                k: {"2_threads": r["ratios"][part]["median_paired_ratio"],
                    "1_thread_pinned": one.get("configs", {}).get(k, {}).get("ratios", {})
                    .get(part, {}).get("median_paired_ratio")} for k, r in results.items()}
            for k, r in payload[f"ratios_{part}"].items():
                run.print(f"{k}: {part} time diffgns / torch: " + protocol.both_ratios(
                    r["2_threads"], r["1_thread_pinned"], one, digits=2), tag=False)
    path = run.finish(args.out, payload)
    run.print(f"wrote {path}")


if __name__ == "__main__":
    main()
