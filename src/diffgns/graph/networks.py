"""Flax (linen) encode-process-decode graph network of the particle GNS.

Shapes: N nodes, E edges (fixed size, with a validity mask), L = ``latent``.

* Encoder: node MLP on ``[node_features, embed(particle_type)]`` and edge MLP on the edge
  features, each to L with a LayerNorm.
* Processor: ``mp_steps`` interaction networks with **separate weights**. Step k updates
  edges then nodes, both with residuals::

      e'  = LN(MLP_e([e, v_s, v_r]))          (first layer split, see below)
      agg = sum_{edges into r} w * e'          (w = mask, or mask * attention weight)
      v'  = LN(MLP_v([v, agg]))
      e <- e + e',  v <- v + v'

  Messages are summed at the receiver with ``jax.ops.segment_sum``; masked (padded) edges
  contribute zero and their latents are kept at zero.
* Decoder: MLP to the output (d = 2 or 3: the normalised acceleration), no LayerNorm.

The first layer of the edge MLP, ``W [e, v_s, v_r] + b``, is computed as
``W_e e + (W_s v)[s] + (W_r v)[r] + b`` (:class:`SplitEdgeDense`): the node projections
cost O(N L^2) instead of O(E L^2). It is mathematically identical to a Dense layer on the
concatenation whose kernel stacks ``W_e, W_s, W_r`` in that order.

Attention variant (``attention=True``): each message is weighted by a softmax, over the
receiver's incoming valid edges, of a learned scalar score of ``[e', v_r]`` (segment max
subtracted for stability); the aggregation becomes a weighted mean.
"""
from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "MLP", "EncodeProcessDecode", "InteractionStep", "SplitEdgeDense", "concat_dense_params",
    "init_params", "segment_softmax",
]


def _gather(a: jax.Array, idx: jax.Array) -> jax.Array:
    """Rows ``a[idx]`` with out-of-range (padding) indices clipped to a valid row."""
    return jnp.take(a, idx, axis=0, mode="clip")


class MLP(nn.Module):
    """``n_hidden_layers`` x (Dense(hidden) + ReLU), then Dense(out), optional LayerNorm.

    Input (..., F) -> output (..., out).
    """

    hidden: int
    n_hidden_layers: int
    out: int
    layer_norm: bool = True

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for i in range(self.n_hidden_layers):
            x = nn.relu(nn.Dense(self.hidden, name=f"hidden_{i}")(x))
        x = nn.Dense(self.out, name="out")(x)
        if self.layer_norm:
            x = nn.LayerNorm(name="norm")(x)
        return x


class SplitEdgeDense(nn.Module):
    """First edge-MLP layer ``Dense([e, v[s], v[r]])`` computed with per-node projections.

    Inputs: edge latents (E, Le), node latents (N, Lv), senders/receivers (E,).
    Output: (E, features) pre-activation. Parameters: ``edge`` (kernel (Le, F), bias),
    ``sender`` and ``receiver`` (kernels (Lv, F), no bias).
    """

    features: int

    @nn.compact
    def __call__(self, e: jax.Array, v: jax.Array, senders: jax.Array,
                 receivers: jax.Array) -> jax.Array:
        pe = nn.Dense(self.features, name="edge")(e)
        ps = nn.Dense(self.features, use_bias=False, name="sender")(v)
        pr = nn.Dense(self.features, use_bias=False, name="receiver")(v)
        return pe + _gather(ps, senders) + _gather(pr, receivers)


def segment_softmax(scores: jax.Array, segment_ids: jax.Array, mask: jax.Array,
                    num_segments: int) -> jax.Array:
    """Softmax of (E,) ``scores`` within each segment, over entries where ``mask`` is True.

    Masked entries get weight 0; a segment with no valid entry has no weights. Stable: the
    (gradient-stopped) per-segment max is subtracted before exponentiating.
    """
    neg = jnp.where(mask, scores, -jnp.inf)
    smax = jax.ops.segment_max(neg, segment_ids, num_segments)
    smax = jax.lax.stop_gradient(jnp.where(jnp.isfinite(smax), smax, 0.0))
    # Double where: masked entries never reach exp, so their gradient cannot be 0 * inf.
    z = jnp.where(mask, scores - _gather(smax, segment_ids), 0.0)
    ex = jnp.where(mask, jnp.exp(z), 0.0)
    denom = jax.ops.segment_sum(ex, segment_ids, num_segments)
    denom = jnp.where(denom > 0, denom, 1.0)
    return ex / _gather(denom, segment_ids)


class InteractionStep(nn.Module):
    """One message-passing step with residual node and edge updates.

    ``(v (N, L), e (E, L), senders, receivers, mask) -> (v (N, L), e (E, L))``.
    """

    latent: int
    mlp_layers: int
    attention: bool = False

    @nn.compact
    def __call__(self, v, e, senders, receivers, mask):
        n = v.shape[0]
        # Edge MLP with a split first layer; as MLP(hidden=latent, mlp_layers) on the concat.
        h = nn.relu(SplitEdgeDense(self.latent, name="edge_in")(e, v, senders, receivers))
        if self.mlp_layers > 1:
            h = MLP(self.latent, self.mlp_layers - 1, self.latent, name="edge_mlp")(h)
        else:
            h = nn.LayerNorm(name="edge_norm")(nn.Dense(self.latent, name="edge_out")(h))
        msg = h
        if self.attention:
            msg = jnp.where(mask[:, None], h, 0.0)
            feats = jnp.concatenate([msg, _gather(v, receivers)], axis=-1)
            score = nn.Dense(1, name="score")(feats)[:, 0]
            w = segment_softmax(score, receivers, mask, n)
            msg = msg * w[:, None]
        # Masked edges carry the receiver index n (see EncodeProcessDecode): segment_sum
        # drops them, so no (E, L) masking pass is needed here.
        agg = jax.ops.segment_sum(msg, receivers, num_segments=n)
        dv = MLP(self.latent, self.mlp_layers, self.latent, name="node_mlp")(
            jnp.concatenate([v, agg], axis=-1))
        return v + dv, e + h


class EncodeProcessDecode(nn.Module):
    """Encode-process-decode GNS network.

    Attributes:
        latent: latent width L (also the MLP hidden width).
        mp_steps: number of message-passing steps (separate weights each).
        mlp_layers: hidden layers per MLP (2 in the reference GNS).
        n_types: number of particle types for the embedding (9).
        type_embed: width of the particle-type embedding (16).
        attention: softmax attention over incoming edges instead of a plain sum.
        out: output width (the dimension d, 2 or 3: the normalised acceleration).
    """

    latent: int = 128
    mp_steps: int = 10
    mlp_layers: int = 2
    n_types: int = 9
    type_embed: int = 16
    attention: bool = False
    out: int = 2

    @nn.compact
    def __call__(self, node_features: jax.Array, particle_type: jax.Array,
                 edge_features: jax.Array, senders: jax.Array, receivers: jax.Array,
                 edge_mask: jax.Array, return_edge_latents: bool = False):
        """Apply the network.

        Args:
            node_features: (N, F) float.
            particle_type: (N,) int in ``[0, n_types)``.
            edge_features: (E, 3) float.
            senders, receivers: (E,) int (padding index N allowed where masked).
            edge_mask: (E,) bool, True for valid edges.
            return_edge_latents: also return the edge latents after each processor step.

        Returns:
            (N, out) output, or ``(output, edge_latents)`` with edge_latents of shape
            (mp_steps + 1, E, L): the encoded edges followed by each step's result
            (zero on masked edges).
        """
        emb = nn.Embed(self.n_types, self.type_embed, name="type_embed")(particle_type)
        v = MLP(self.latent, self.mlp_layers, self.latent, name="node_encoder")(
            jnp.concatenate([node_features, emb.astype(node_features.dtype)], axis=-1))
        e = MLP(self.latent, self.mlp_layers, self.latent, name="edge_encoder")(edge_features)
        # Padded edges get the out-of-range receiver N: every segment_sum drops them, so
        # their (finite) latents never reach a node and the processor needs no masking pass.
        receivers = jnp.where(edge_mask, receivers, v.shape[0])
        history: list[jax.Array] = [e]
        for k in range(self.mp_steps):
            v, e = InteractionStep(self.latent, self.mlp_layers, self.attention,
                                   name=f"processor_{k}")(v, e, senders, receivers, edge_mask)
            history.append(e)
        out = MLP(self.latent, self.mlp_layers, self.out, layer_norm=False, name="decoder")(v)
        if return_edge_latents:
            return out, jnp.where(edge_mask[None, :, None], jnp.stack(history), 0.0)
        return out


def concat_dense_params(split_params: dict) -> dict:
    """Params of an ``nn.Dense`` on ``[e, v_s, v_r]`` equal to a :class:`SplitEdgeDense`.

    ``split_params`` is the ``SplitEdgeDense`` param dict (``edge``, ``sender``,
    ``receiver``); the kernel rows are stacked in the concatenation order.
    """
    kernels: Sequence[jax.Array] = [split_params[k]["kernel"]
                                    for k in ("edge", "sender", "receiver")]
    return {"kernel": jnp.concatenate(kernels, axis=0), "bias": split_params["edge"]["bias"]}


_TRUNC = 0.87962566103423978  # std of a standard normal truncated to [-2, 2]


def _host_rng(key: jax.Array) -> np.random.Generator:
    """A numpy generator seeded by the bits of a JAX key (typed or legacy uint32)."""
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.key_data(key)
    return np.random.default_rng(np.asarray(key, np.uint32).ravel().tolist())


def _truncated_normal(rng: np.random.Generator, size: int) -> np.ndarray:
    """``size`` standard normal samples restricted to [-2, 2] (rejection sampling)."""
    z = rng.standard_normal(size)
    bad = np.abs(z) > 2.0
    while bad.any():
        z[bad] = rng.standard_normal(int(bad.sum()))
        bad = np.abs(z) > 2.0
    return z


def init_params(module: nn.Module, key: jax.Array, *args, **kwargs) -> dict:
    """``module.init(key, *args)`` with flax's default distributions, drawn on the host.

    Dense kernels: LeCun truncated normal (std ``1/sqrt(fan_in)``, cut at 2 std), biases 0,
    LayerNorm scales 1 and biases 0, embeddings N(0, 1/features) -- the defaults of
    ``nn.Dense``, ``nn.LayerNorm`` and ``nn.Embed``. ``module.init`` draws every leaf with
    its own threefry call; under ``jit`` each costs ~0.1 s of XLA compile (over 10 s for the
    reference 10-step network), and eagerly each new shape does. Here the structure comes
    from ``jax.eval_shape`` (tracing only) and the values from numpy seeded by ``key``:
    deterministic in ``key``, nothing to compile, but not bit-identical to ``module.init``.
    Call outside ``jit`` (the key must be concrete).
    """
    shapes = jax.eval_shape(module.init, key, *args, **kwargs)
    leaves, treedef = jax.tree_util.tree_flatten_with_path(shapes)
    rng = _host_rng(key)
    out = []
    for path, sp in leaves:
        name = str(getattr(path[-1], "key", path[-1]))
        if name in ("bias", "scale"):
            z = np.full(sp.shape, 1.0 if name == "scale" else 0.0)
        elif name == "kernel":  # fan_in = all but the last axis
            fan_in = sp.size // sp.shape[-1]
            z = _truncated_normal(rng, sp.size).reshape(sp.shape) / (_TRUNC * np.sqrt(fan_in))
        elif name == "embedding":  # nn.Embed: variance_scaling(1, fan_in, normal, out_axis=0)
            z = rng.standard_normal(sp.shape) / np.sqrt(sp.shape[-1])
        else:
            raise ValueError(f"init_params: no default initialiser for parameter {name!r}")
        out.append(jnp.asarray(z, sp.dtype))
    return jax.tree_util.tree_unflatten(treedef, out)
