"""The simulator interface: a pair of pure functions, one rollout, one re-allocation loop.

Every simulator in diffgns (:class:`~diffgns.mpm.MPM`, :class:`~diffgns.graph.gns.GNS`,
:class:`~diffgns.hybrid.Hybrid`, :class:`~diffgns.mesh.meshnet.MeshNet`) has the shape of
jax-md's ``(init_fn, apply_fn)`` pair::

    state  = sim.init(...)               # outside jit: allocates (neighbour lists, ...)
    state  = sim.step(params, state)     # one frame; pure, jit/grad/vmap friendly
    frame  = sim.observe(state)          # what a trajectory records at a frame (a pytree)

and every rollout goes through :func:`rollout`::

    frames, final = rollout(sim, params, state, n_frames, checkpoint_block=None)

``frames`` is ``sim.observe`` stacked over ``n_frames + 1`` frames (frame 0 is ``state``);
``params`` holds what a user may vary or fit (friction angle, wall friction, network
weights), ``state`` what evolves. Simulators whose state holds something allocated outside
``jit`` (a neighbour list) report an overflow flag per frame (``frame.overflow``); the caller
re-allocates outside ``jit`` and redoes the rollout with :func:`retry_on_overflow`, or
simply calls :func:`rollout_safe`.

Particle simulators also count every position clamp per frame (``frame.clamp``, a
:class:`~diffgns.clamp.ClampCount`), so a clamp never hides an escape.

Time is in frames of ``sim.frame_dt`` seconds. Nothing here knows which simulator it holds.
"""
from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any, Generic, NamedTuple, Protocol, TypeVar, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from diffgns import hostdevices
from diffgns.clamp import ClampCount

hostdevices.request()  # two host devices for the sharded MPM, if JAX has not started yet

__all__ = [
    "Simulator", "ParticleFrame", "rollout", "rollout_jit", "rollout_safe", "scan_frames",
    "retry_on_overflow", "overflow_flags", "NeighborOverflowError",
]

P = TypeVar("P")
P_contra = TypeVar("P_contra", contravariant=True)
S = TypeVar("S")
F_co = TypeVar("F_co", covariant=True)
Carry = TypeVar("Carry")
R = TypeVar("R")


@runtime_checkable
class Simulator(Protocol, Generic[P_contra, S, F_co]):
    """What every simulator provides (besides its own ``init``, which allocates).

    Attributes:
        frame_dt: seconds between frames.
    """

    frame_dt: float

    def step(self, params: P_contra, state: S) -> S:
        """Advance ``state`` by one frame (pure)."""
        ...

    def observe(self, state: S) -> F_co:
        """The pytree a trajectory records at a frame."""
        ...


class ParticleFrame(NamedTuple):
    """What a particle simulator observes at a frame.

    Attributes:
        positions: (N, d) m.
        velocities: (N, d) m/s.
        overflow: bool scalar, True if a neighbour list overflowed at or before this frame
            (the frame and all later ones are then invalid; always False for the MPM).
        clamp: :class:`~diffgns.clamp.ClampCount` of the frame: positions a domain clamp
            moved while computing it, and the largest move (m). Never silent: every
            simulator counts its clamps here (:mod:`diffgns.clamp`).
    """

    positions: jax.Array
    velocities: jax.Array
    overflow: jax.Array
    clamp: ClampCount


class NeighborOverflowError(RuntimeError):
    """A neighbour list kept overflowing after every allowed re-allocation."""


def scan_frames(body: Callable[[Carry, Any], tuple[Carry, Any]], carry: Carry, xs: Any = None,
                length: int | None = None, checkpoint_block: int | None = None
                ) -> tuple[Carry, Any]:
    """``lax.scan(body, carry, xs, length)`` with ``jax.checkpoint`` on blocks of frames.

    With ``checkpoint_block = B`` the scan runs over ``length // B`` checkpointed blocks of
    ``B`` frames (plus a checkpointed remainder), so reverse mode stores only block
    boundaries and recomputes one block at a time: memory ~ (length / B + B) carries instead
    of ``length``. The values are those of the plain scan. ``None``, 0 or ``B >= length``
    give the plain scan (a single checkpointed block when ``B == length``).

    Args:
        body: ``(carry, x) -> (carry, y)``.
        xs: per-frame inputs with leading axis ``length`` (or None).
        length: number of frames (required when ``xs`` is None).
    Returns:
        ``(carry, ys)`` with ``ys`` stacked over the ``length`` frames.
    """
    n = length if length is not None else jax.tree.leaves(xs)[0].shape[0]
    if n == 0:
        raise ValueError("scan_frames: length must be >= 1")
    if not checkpoint_block or checkpoint_block > n:
        return jax.lax.scan(body, carry, xs, length=n)
    B = int(checkpoint_block)
    nb, rem = divmod(n, B)
    head = None if xs is None else jax.tree.map(lambda a: a[: nb * B].reshape(
        (nb, B) + a.shape[1:]), xs)
    block = jax.checkpoint(lambda c, x: jax.lax.scan(body, c, x, length=B), prevent_cse=False)
    carry, ys = jax.lax.scan(block, carry, head, length=nb)
    ys = jax.tree.map(lambda a: a.reshape((nb * B,) + a.shape[2:]), ys)
    if rem:
        tail = None if xs is None else jax.tree.map(lambda a: a[nb * B:], xs)
        last = jax.checkpoint(lambda c, x: jax.lax.scan(body, c, x, length=rem),
                              prevent_cse=False)
        carry, ys2 = last(carry, tail)
        ys = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), ys, ys2)
    return carry, ys


def rollout(sim: Simulator[P, S, Any], params: P, state: S, n_frames: int, *,
            checkpoint_block: int | None = None) -> tuple[Any, S]:
    """Roll ``sim`` out for ``n_frames`` frames (traceable: use under jit and grad).

    Args:
        sim: a :class:`Simulator` (static).
        params: its parameters (pytree; differentiable leaves).
        state: initial state from ``sim.init(...)``.
        n_frames: frames to advance (static, >= 1).
        checkpoint_block: frames per ``jax.checkpoint`` block for reverse mode (None: none).

    Returns:
        ``(frames, final_state)``: ``frames`` is ``sim.observe`` stacked over
        ``n_frames + 1`` frames, frame 0 being ``state``.
    """
    if int(n_frames) < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")

    def body(s: S, _: None) -> tuple[S, Any]:
        s = sim.step(params, s)
        return s, sim.observe(s)

    final, ys = scan_frames(body, state, None, int(n_frames), checkpoint_block)
    first = sim.observe(state)
    frames = jax.tree.map(lambda a, b: jnp.concatenate([jnp.asarray(a)[None], b]), first, ys)
    return frames, final


_rollout_compiled = jax.jit(rollout, static_argnames=("sim", "n_frames", "checkpoint_block"))


def rollout_jit(sim: Simulator[P, S, Any], params: P, state: S, n_frames: int,
                checkpoint_block: int | None = None) -> tuple[Any, S]:
    """:func:`rollout` compiled once per (simulator, n_frames, block, shapes): new parameter
    values or states of the same shapes never recompile (the static arguments are normalised,
    so ``checkpoint_block`` given or left out is the same program)."""
    return _rollout_compiled(sim, params, state, n_frames=int(n_frames),  # type: ignore[no-any-return]
                             checkpoint_block=None if not checkpoint_block
                             else int(checkpoint_block))


rollout_jit._cache_size = _rollout_compiled._cache_size  # type: ignore[attr-defined]


def overflow_flags(frames: Any) -> np.ndarray:
    """(T,) host bool array of per-frame overflow flags (all False if frames have none)."""
    flag = getattr(frames, "overflow", None)
    if flag is None:
        leaves = jax.tree.leaves(frames)
        return np.zeros(leaves[0].shape[0] if leaves else 0, bool)
    return np.asarray(np.asarray(flag, bool).reshape(np.shape(flag)[0], -1).any(axis=1))


def retry_on_overflow(run: Callable[[S], R], state: S, overflowed: Callable[[R], bool],
                      reallocate: Callable[[S, R, int], S], max_retries: int = 5
                      ) -> tuple[R, S]:
    """THE allocate-outside-jit / detect-overflow / re-allocate-and-redo loop.

    Args:
        run: ``state -> result`` (usually jitted); may overflow.
        state: a state whose capacity was allocated outside jit.
        overflowed: ``result -> bool`` on the host.
        reallocate: ``(state, result, attempt) -> state`` with more capacity (outside jit;
            ``attempt`` = 0, 1, ... lets it grow the head-room on repeated failures).
        max_retries: re-allocations allowed before :class:`NeighborOverflowError`.

    Returns:
        ``(result, state)``: the first result that did not overflow and the state it ran from
        (its capacity fits this run, so a following ``jax.grad`` can reuse it).
    """
    for attempt in range(max_retries + 1):
        result = run(state)
        if not overflowed(result):
            return result, state
        if attempt == max_retries:
            break
        state = reallocate(state, result, attempt)
    raise NeighborOverflowError(f"neighbour list still overflowing after {max_retries} "
                         "re-allocations; raise the model's capacity_multiplier")


def rollout_safe(sim: Any, params: Any, state: Any, n_frames: int, *,
                 checkpoint_block: int | None = None, max_retries: int = 5
                 ) -> tuple[Any, Any, Any]:
    """Jitted :func:`rollout` with re-allocation on overflow (outside jit).

    The simulator must provide ``reallocate(state, frames, first_bad_frame, attempt) ->
    state``. Returns ``(frames, final_state, initial_state)``; ``initial_state`` is the
    (possibly re-allocated) state the valid rollout started from.
    """
    run = partial(rollout_jit, sim, params, n_frames=int(n_frames),
                  checkpoint_block=checkpoint_block)

    def realloc(s: Any, out: Any, attempt: int) -> Any:
        k = int(np.argmax(overflow_flags(out[0])))
        return sim.reallocate(s, out[0], k, attempt)

    (frames, final), start = retry_on_overflow(
        run, state, lambda out: bool(overflow_flags(out[0]).any()), realloc, max_retries)
    return frames, final, start
