"""GNS training step: noisy one-step loss, push-forward, data-parallel optimiser step.

The loss is the MSE of the normalised acceleration over non-kinematic particles (or, with
``TrainConfig.huber_delta > 0``, its Huber version: quadratic up to ``delta`` standard
deviations per component, linear beyond), with random-walk input noise and the target
corrected for it. Batches are split over all
devices of the run with ``jax.sharding`` (parameters replicated, batch sharded); XLA inserts
the gradient all-reduce. The same code runs in one process and in several
(:mod:`diffgns.distributed`): every process draws the same global batch from (seed, step)
and places only its own rows on its own devices. The loop around the step (checkpoints,
exact resume, logs, SIGTERM, learning-rate schedule) is :func:`diffgns.graph.fit.fit`,
shared by every trained network; its configuration and checkpoint helpers are re-exported.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import NamedSharding, PartitionSpec
from jax_md import partition

from diffgns.distributed import data_mesh, replicate, shard_batch, to_host
from diffgns.graph.features import random_walk_noise, target_acceleration
from diffgns.graph.fit import (  # re-exported: the training API of every network
    TrainConfig,
    load_checkpoint,
    make_optimizer,
    save_checkpoint,
    step_rng,
)
from diffgns.graph.geometry import Geometry
from diffgns.graph.gns import GNS
from diffgns.graph.neighbors import capacity, did_overflow, edges
from diffgns.interface import retry_on_overflow
from diffgns.trajectory import KINEMATIC

__all__ = ["NeighborLists", "TrainConfig", "Trainer", "load_checkpoint", "make_optimizer",
           "pushed_target", "save_checkpoint", "step_rng", "step_with_reallocation",
           "steps_with_reallocation",
           "window_loss"]


def pushed_target(window, hist, unroll: int):
    """Target acceleration (N, d) for the input history ``hist``, in m/frame^2.

    ``window`` (L, N, d) is the data, ``hist`` (N, C+1, d) the input history: the noisy data
    (``unroll = 0``) or the model's own rollout from it after ``unroll`` push-forward steps,
    ending at data frame ``C + unroll``. Either way its offset from the data is treated as
    input noise (:func:`~diffgns.graph.features.target_acceleration`): the target corrects
    the *velocity* only, and the last frame's offset is carried to the target position.
    Asking the model to remove the whole position error in one step instead makes the target
    ~(position error)/frame^2, dozens of acceleration standard deviations, which swamps
    the loss (measured: normalised loss 1.46 against 0.0125 without pushing).
    """
    C = hist.shape[1] - 1
    # dynamic slices: ``unroll`` may be traced (the frame index of window_loss's scan)
    truth = jnp.swapaxes(jax.lax.dynamic_slice_in_dim(window, unroll, C + 1, 0), 0, 1)
    nxt = jax.lax.dynamic_index_in_dim(window, C + 1 + unroll, 0, keepdims=False)
    return target_acceleration(nxt, truth, hist - truth)


def window_loss(gns: GNS, params, window, particle_type, material, nbrs, key, unroll: int,
                momentum_weight: float, geometry: Geometry | None = None,
                huber_delta: float = 0.0, target_scale_floor: float = 0.0,
                loss_frames: int = 1):
    """Loss of one window (L, N, d) of positions, L = history + 1 + unroll + loss_frames,
    in the walls and obstacles ``geometry`` (default: the GNS's box, no obstacle).

    ``unroll`` push-forward frames first roll the model without gradient. Then
    ``loss_frames = K`` frames: the loss of each is the one-step loss below of the model's
    current history against :func:`pushed_target`, after which the model advances that
    history by its own prediction (:meth:`~diffgns.graph.gns.GNS.integrate`, walls and
    kinematic nodes included) *with* gradient, so the mean of the K losses is
    differentiated through the rollout: a prediction is also charged for the errors it
    causes in the frames after it. ``K = 1`` is the one-step loss.

    Per particle the squared error of the normalised acceleration summed over components,
    or with ``huber_delta > 0`` twice optax's Huber loss per component (equal to the squared
    error below ``huber_delta`` standard deviations, linear above): impacts against walls
    put accelerations of 20-50 standard deviations into <1% of the node-frames of the
    granular data, which then carry 77-90% of an MSE's weight (measured on
    data/granular_valid.h5), so a robust loss keeps slow frictional flow in the gradient.
    Averaged over non-kinematic particles. With ``target_scale_floor > 0`` the window's loss
    (momentum term included) is divided by its mean squared normalised target plus the
    floor: a relative error, so a batch of impacts no longer outweighs one of slow flow by
    ~500x (the losses of the two kinds of batch on the granular data, in
    ``gns_cg16_pfn``'s units), in the gradient or in Adam's second moments."""
    C = gns.config.history
    if window.shape[0] != C + 1 + unroll + loss_frames:  # static; jnp indexing would clip
        raise ValueError(f"window_loss: a window of {window.shape[0]} frames, but history "
                         f"{C}, push-forward {unroll} and {loss_frames} loss frames need "
                         f"{C + 1 + unroll + loss_frames}")
    clean = jnp.swapaxes(window[: C + 1], 0, 1)  # (N, C+1, d)
    noise = random_walk_noise(key, clean, gns.config.noise_std, particle_type)
    hist = clean + noise
    n = hist.shape[0]
    frozen = jax.lax.stop_gradient(params)

    def push(carry, k):  # push-forward: the model's own predictions, no gradient
        hist, over = carry
        kin = jax.lax.dynamic_index_in_dim(window, C + 1 + k, 0, keepdims=False)
        x_next, nb, _ = gns.advance(frozen, hist, particle_type, material, nbrs, kin,
                                    geometry)
        hist = jnp.concatenate([hist[:, 1:], x_next[:, None]], axis=1)  # no parameter in it
        return (hist, over | did_overflow(nb)), None

    # One traced frame for every push-forward count, as for the loss frames below (a Python
    # loop traced the model once per frame: 17-32 s per step compiling at 16 frames).
    (hist, over), _ = jax.lax.scan(push, (hist, jnp.zeros((), bool)), jnp.arange(unroll))
    w = (particle_type != KINEMATIC).astype(hist.dtype)

    def frame(carry, k):  # k > 0: the model's own frames, with gradient
        hist, total, over = carry
        target = pushed_target(window, hist, unroll + k)  # noise and drift alike
        nb = gns.neighbors.update(hist[:, -1], nbrs)
        s, r, m = edges(nb, n)
        pred = gns.normalized_acceleration(params, hist, particle_type, material, s, r, m,
                                           geometry)
        total = total + _frame_loss(pred, gns.normalizer.acceleration.normalize(target), w,
                                    momentum_weight, huber_delta, target_scale_floor)
        kin = jax.lax.dynamic_index_in_dim(window, C + 1 + unroll + k, 0, keepdims=False)
        x_next, _ = gns.integrate(hist, gns.normalizer.acceleration.denormalize(pred),
                                  particle_type, kin, geometry)
        hist = jnp.concatenate([hist[:, 1:], x_next[:, None]], axis=1)
        return (hist, total, over | did_overflow(nb)), None

    # One traced frame for every K (compile time independent of K; a Python loop took
    # minutes per node count at K = 8), rematerialised in the backward pass for K > 1:
    # memory independent of K (K = 16, 2 windows of 384 nodes: peak RSS 1.3 GB against
    # 4.0 GB stored, ~10% more time; measured beside two jobs). The last frame's integrate
    # feeds nothing: its output and gradient are dropped.
    body = jax.checkpoint(frame) if loss_frames > 1 else frame
    (_, total, over), _ = jax.lax.scan(body, (hist, jnp.zeros((), hist.dtype), over),
                                       jnp.arange(loss_frames))
    return total / loss_frames, over


def _frame_loss(pred, tgt, w, momentum_weight: float, huber_delta: float,
                target_scale_floor: float):
    """One frame's loss of :func:`window_loss`: normalised predicted against target
    accelerations (N, d), weights ``w`` (N,) (0 on kinematic nodes)."""
    per = (2.0 * optax.losses.huber_loss(pred, tgt, delta=huber_delta) if huber_delta
           else (pred - tgt) ** 2)
    loss = jnp.sum(w * jnp.sum(per, -1)) / jnp.maximum(w.sum(), 1.0)
    if momentum_weight:
        dmean = jnp.sum(w[:, None] * (pred - tgt), 0) / jnp.maximum(w.sum(), 1.0)
        loss = loss + momentum_weight * jnp.sum(dmean**2)
    if target_scale_floor:
        ms = jnp.sum(w * jnp.sum(tgt**2, -1)) / jnp.maximum(w.sum(), 1.0)
        loss = loss / (jax.lax.stop_gradient(ms) + target_scale_floor)
    return loss


class Trainer:
    """Owns the jitted, device-parallel training step for one GNS and optimiser."""

    def __init__(self, gns: GNS, cfg: TrainConfig, devices=None):
        """``devices``: the mesh (default one device per process,
        :func:`diffgns.distributed.process_devices`); ``cfg.batch_size`` must be a multiple
        of their number."""
        self.gns, self.cfg = gns, cfg
        self.opt = make_optimizer(cfg)
        self.mesh = data_mesh(devices)
        self.replicated = NamedSharding(self.mesh, PartitionSpec())
        self.batched = NamedSharding(self.mesh, PartitionSpec("data"))
        self.stacked = NamedSharding(self.mesh, PartitionSpec(None, "data"))
        rep = self.replicated
        self._step = jax.jit(self._step_impl, out_shardings=(rep, rep, rep, rep))
        self._steps = jax.jit(self._steps_impl, out_shardings=(rep, rep, rep, rep))

    def _batch_loss(self, params, batch, nbrs, key):
        B = batch["positions"].shape[0]
        keys = jax.random.split(key, B)
        f = lambda w, t, m, k, g: window_loss(self.gns, params, w, t, m, nbrs, k,
                                              self.cfg.push_forward, self.cfg.momentum_weight,
                                              g, self.cfg.huber_delta,
                                              self.cfg.target_scale_floor, self.cfg.unroll)
        geometry = None
        if "walls" in batch:  # per-window walls (B, d, 2) and obstacles (B, K, 2d)
            geometry = Geometry(batch["walls"], batch["obstacles"])
        losses, over = jax.vmap(f)(batch["positions"], batch["particle_type"],
                                   batch["material"], keys, geometry)
        return losses.mean(), jnp.any(over)

    def _step_impl(self, params, opt_state, batch, nbrs, key):
        (loss, over), grads = jax.value_and_grad(self._batch_loss, has_aux=True)(
            params, batch, nbrs, key)
        updates, new_opt = self.opt.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), new_opt, loss, over

    def _steps_impl(self, params, opt_state, batches, count, nbrs, keys):
        """``count`` (traced, <= K) optimiser steps on ``batches`` (leaves (K, B, ...)) and
        ``keys`` (K, 2) in one device call: one compiled program for every count, whose
        temporary buffer all the steps share. Returns (params, opt_state, losses (K,),
        overflowed (K,)); entries past ``count`` stay 0 / False."""
        K = keys.shape[0]

        def body(i, carry):
            p, s, losses, overs = carry
            b = jax.tree.map(lambda a: a[i], batches)
            p, s, loss, over = self._step_impl(p, s, b, nbrs, keys[i])
            return p, s, losses.at[i].set(loss), overs.at[i].set(over)

        zeros = (jnp.zeros(K, jnp.float32), jnp.zeros(K, bool))
        return jax.lax.fori_loop(0, count, body, (params, opt_state, *zeros))

    def steps(self, params, opt_state, batches: list[dict], nbrs, keys: list):
        """``len(batches)`` optimiser steps (at most ``cfg.steps_per_call``, one node count)
        in one device call; the same steps as :meth:`step` in turn, at float32 round-off.
        The list is padded to ``steps_per_call`` so that every count runs one compiled
        program. Returns (params, opt_state, losses (k,), overflowed (k,))."""
        k, K = len(batches), max(self.cfg.steps_per_call, len(batches))
        pad = [batches[-1]] * (K - k)
        stacked = {name: np.stack([np.asarray(b[name]) for b in batches + pad])
                   for name in batches[0]}
        key_stack = jnp.stack(list(keys) + [keys[-1]] * (K - k))
        params, opt_state, nbrs, key_stack = replicate((params, opt_state, nbrs, key_stack),
                                                       self.replicated)
        p, s, losses, over = self._steps(params, opt_state,
                                         shard_batch(stacked, self.stacked, axis=1),
                                         jnp.int32(k), nbrs, key_stack)
        return p, s, losses[:k], over[:k]

    def shard(self, batch: dict) -> dict:
        """Put the global host batch on the devices of the run, split along the batch axis
        (each process places its own rows)."""
        return shard_batch(batch, self.batched)

    def step(self, params, opt_state, batch, nbrs, key):
        """One optimiser step; returns (params, opt_state, loss, overflowed), all replicated
        over the mesh. On overflow the caller re-allocates ``nbrs`` and calls again with the
        same inputs (nothing applied)."""
        params, opt_state, nbrs, key = replicate((params, opt_state, nbrs, key),
                                                 self.replicated)
        return self._step(params, opt_state, self.shard(batch), nbrs, key)


class NeighborLists(dict):
    """The training run's neighbour lists, node count -> jax-md list, and their capacities
    as checkpointable host state (:class:`diffgns.graph.fit.HostState`).

    A list's capacity (edge slots ``K``, cell-list slots) is sized from the batch that first
    needs it or that overflowed it, and it changes the result of a step at float32 round-off
    (the edge arrays have ``K + N`` rows, which changes the summation order of the message
    aggregation and of the gradient; measured: 3.7e-9 to 3e-8 in the parameters after one
    step). So the capacities are saved with every checkpoint and a resumed run rebuilds each
    list with exactly the capacity the uninterrupted run had at that step.
    """

    def __init__(self) -> None:
        super().__init__()
        self.pending: dict[int, tuple[int, int | None]] = {}

    def state_dict(self) -> dict:
        """{str(node count): [edge slots, cell-list slots or -1]}."""
        out = {str(n): [capacity(nb), -1 if nb.cell_list_capacity is None
                        else int(nb.cell_list_capacity)] for n, nb in self.items()}
        out.update({str(n): [k, -1 if c is None else c] for n, (k, c) in self.pending.items()
                    if n not in self})
        return out

    def load_state_dict(self, state: dict) -> None:
        """Forget the lists; each is rebuilt with the saved capacity when next needed."""
        self.clear()
        self.pending = {int(n): (int(k), None if int(c) < 0 else int(c))
                        for n, (k, c) in state.items()}

    def get_or_allocate(self, gns: GNS, x: jax.Array) -> partition.NeighborList:
        """The list for the ``len(x)`` nodes: the existing one, one with the saved capacity
        (after a resume), or a new one sized for positions ``x`` (N, d)."""
        n = int(x.shape[0])
        if n not in self:
            nb = gns.allocate(x)
            if n in self.pending:
                nb = with_capacity(nb, *self.pending.pop(n), n)
            self[n] = nb
        return self[n]


def with_capacity(nbrs: partition.NeighborList, slots: int, cell_slots: int | None,
                  n: int) -> partition.NeighborList:
    """``nbrs`` with exactly ``slots`` edge slots and ``cell_slots`` cell-list slots: the
    list a run that allocated it from other positions would hold. The edges are recomputed
    by every update inside the step, so only the capacities (static) matter; the index
    buffer is cut or padded with the out-of-range index ``n`` as jax-md pads it."""
    idx = nbrs.idx[:, :slots]
    if idx.shape[1] < slots:
        idx = jnp.concatenate([idx, jnp.full((2, slots - idx.shape[1]), n, idx.dtype)], 1)
    return nbrs.set(idx=idx, max_occupancy=int(slots),
                    cell_list_capacity=nbrs.cell_list_capacity if cell_slots is None
                    else int(cell_slots))


def step_with_reallocation(trainer: Trainer, params, opt_state, batch: dict, nbrs: dict, key,
                           max_retries: int = 6):
    """:meth:`Trainer.step` that (re)allocates the neighbour list of the batch's node count
    outside jit and redoes the step on overflow, with growing head-room (edge slots and
    cell-list slots), so no edge is ever dropped. ``nbrs`` maps node count -> list and is
    updated in place; pass a :class:`NeighborLists` to have the capacities checkpointed
    (exact resume). Returns (params, opt_state, loss)."""
    return _with_reallocation(
        trainer, [batch], nbrs,
        lambda nb: trainer.step(params, opt_state, batch, nb, key), max_retries)


def steps_with_reallocation(trainer: Trainer, params, opt_state, batches: list[dict],
                            nbrs: dict, keys: list, max_retries: int = 6):
    """:meth:`Trainer.steps` (several steps, one node count, one device call) with the
    overflow rule of :func:`step_with_reallocation`: if any step of the call overflowed, the
    list is re-allocated for the positions of the first that did and the whole call is redone
    from the same inputs. Returns (params, opt_state, losses (k,))."""
    return _with_reallocation(
        trainer, batches, nbrs,
        lambda nb: trainer.steps(params, opt_state, batches, nb, keys), max_retries)


def _with_reallocation(trainer: Trainer, batches: list[dict], nbrs: dict, run,
                       max_retries: int):
    """The one overflow rule of training: the list of the batches' node count is allocated
    (or restored with its checkpointed capacity) from the first batch's current positions,
    ``run(list) -> (params, opt_state, loss(es), overflowed)`` is redone after re-allocating
    for the first batch whose step overflowed. Returns (params, opt_state, loss(es))."""
    C = trainer.gns.config.history
    sizes = {b["positions"].shape[2] for b in batches}
    if len(sizes) != 1:
        raise ValueError(f"steps_with_reallocation needs one node count, got {sorted(sizes)}")
    n = sizes.pop()
    xs = [jnp.asarray(b["positions"][0, C]) for b in batches]
    if isinstance(nbrs, NeighborLists):
        nbrs.get_or_allocate(trainer.gns, xs[0])
    elif n not in nbrs:
        nbrs[n] = trainer.gns.allocate(xs[0])

    def first_bad(out) -> int:  # index of the first overflowed step (0 for a single step)
        return int(np.argmax(np.atleast_1d(np.asarray(to_host(out[3])))))

    out, nbrs[n] = retry_on_overflow(
        run, nbrs[n], lambda out: bool(np.any(to_host(out[3]))),
        lambda nb, out, k: trainer.gns.neighbors.reallocate(xs[first_bad(out)], nb, k),
        max_retries)
    return out[0], out[1], out[2]
