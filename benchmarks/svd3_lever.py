"""The 3D SVD lever: Jacobi rotations (the library's) against LAPACK's batched SVD, in a 3D
sand frame and alone.

    .venv/bin/python benchmarks/svd3_lever.py [--cells 8 12] [--repeats 7] [--threads both]
        [--out svd3_lever.json] [--wait-quiet 600]

Scene: ``column_scene(1.0, cells_across=c, dim=3)`` (an axisymmetric sand column, 8
particles per cell: 12,992 particles at c = 8, 43,904 at c = 12), one frame of
``MPM(scene, devices=1)`` from the state after 2 frames (moving, yielding sand). Contenders,
compiled ahead of time and timed in interleaved rounds (compile apart, medians of wall and
CPU time, ``block_until_ready``), under ``benchmarks/protocol.py``:

* ``jacobi``: the library (:func:`diffgns.mpm.linalg.svd3`: cyclic Jacobi rotations on
  F^T F, Gram-Schmidt for U; elementwise, fused by XLA);
* ``lapack``: the same frame with the SVD's forward pass replaced by LAPACK's batched SVD
  with the signs fixed (:func:`lapack_svd3_fwd`, the library's implementation before
  2026-12-03, kept here as the reference);
* ``jacobi_2dev``: the library on two host devices (``MPM(scene, devices=2)``), which the
  LAPACK SVD could not do (it deadlocked the sharded frame); skipped with one device.

Also the SVD alone on the 3 x 3 x N deformation gradients of the state (both forward
passes, interleaved). Positions after the frame are compared (float32 round-off expected).
Writes ``benchmarks/results/svd3_lever.json``.
"""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import protocol
from protocol import warm_up_jax

from diffgns import MPM, rollout_jit
from diffgns.mpm import linalg as la
from diffgns.scene.recipes import column_scene
from diffgns.timing import interleave

NAME = "svd3_lever"


def lapack_svd3_fwd(F: jax.Array):
    """LAPACK's batched SVD of (3,3,N) with U, V made rotations and the sign moved to s[2]
    (the library's forward pass before the Jacobi one)."""
    M = jnp.moveaxis(F, -1, 0)
    u, s, vt = jnp.linalg.svd(M)
    du, dv = jnp.sign(jnp.linalg.det(u)), jnp.sign(jnp.linalg.det(vt))
    one = jnp.ones_like(du)
    u = u * jnp.stack([one, one, du], -1)[:, None, :]
    vt = vt * jnp.stack([one, one, dv], -1)[:, :, None]
    s = s * jnp.stack([one, one, du * dv], -1)
    return jnp.moveaxis(u, 0, -1), s.T, jnp.moveaxis(jnp.swapaxes(vt, 1, 2), 0, -1)


def frame_call(sim: MPM, params, state):
    """Zero-argument call of one compiled frame of ``sim`` from ``state``. The one place this
    benchmark calls the simulator."""
    step = jax.jit(lambda p, s: rollout_jit(sim, p, s, n_frames=1)[1].x)
    compiled = step.lower(params, state).compile()
    return lambda: compiled(params, state)


def with_forward(fwd, build):
    """``build()`` traced and compiled with ``la._svd3_fwd = fwd`` (caches cleared so that
    no trace of the other forward pass is reused)."""
    saved = la._svd3_fwd
    la._svd3_fwd = fwd
    jax.clear_caches()
    try:
        return build()
    finally:
        la._svd3_fwd = saved
        jax.clear_caches()


def size_rows(run: protocol.Run, cells: int, repeats: int) -> dict:
    scene = column_scene(1.0, cells_across=cells, dim=3)
    one = MPM(scene, devices=1)
    params = one.params()
    state = jax.jit(lambda p, s: rollout_jit(one, p, s, n_frames=2)[1])(params, one.init())
    calls = {"jacobi": frame_call(one, params, state),
             "lapack": with_forward(lapack_svd3_fwd, lambda: frame_call(one, params, state))}
    if len(jax.local_devices()) >= 2:
        calls["jacobi_2dev"] = frame_call(MPM(scene, devices=2), params, state)
    res = interleave(calls, repeats)
    out = {k: jax.block_until_ready(v) for k, v in res.outputs.items()}
    diff = {k: float(jnp.max(jnp.abs(out[k] - out["jacobi"]))) for k in out}
    F = state.F  # each forward pass compiled once, outside the timed calls
    alone = {"jacobi": jax.jit(la._svd3_fwd).lower(F).compile(),
             "lapack": jax.jit(lapack_svd3_fwd).lower(F).compile()}
    svd = interleave({k: (lambda c=c: c(F)) for k, c in alone.items()}, repeats)
    row = dict(cells=cells, particles=scene.n_particles, substeps=scene.substeps,
               frame={k: res.summary(k) for k in calls}, max_abs_x_diff_m=diff,
               svd_only={k: svd.summary(k) for k in ("jacobi", "lapack")},
               rounds=res.to_json()["rounds"])
    for k in calls:
        t = row["frame"][k]
        run.print(f"{scene.n_particles:6d} particles  {k:12s} frame {1e3 * t['median_s']:8.1f} ms "
                  f"(CPU {1e3 * t['cpu_median_s']:.1f} ms; compile {t['compile_s']:.1f} s)  "
                  f"max |dx| vs jacobi {diff[k]:.1e} m")
    run.print(f"{scene.n_particles:6d} particles  frame lapack/jacobi "
              f"{res.ratio('lapack', 'jacobi'):.2f}x; SVD alone lapack/jacobi "
              f"{svd.ratio('lapack', 'jacobi'):.2f}x "
              f"({1e3 * svd.summary('jacobi')['median_s']:.2f} ms against "
              f"{1e3 * svd.summary('lapack')['median_s']:.2f} ms)")
    if "jacobi_2dev" in calls:
        run.print(f"{scene.n_particles:6d} particles  frame two devices: "
                  f"{res.ratio('jacobi', 'jacobi_2dev'):.2f}x faster than one")
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cells", type=int, nargs="+", default=[8, 12],
                    help="cells across the column's radius")
    ap.add_argument("--repeats", type=int, default=7, help="interleaved rounds")
    ap.add_argument("--out", default=f"{NAME}.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, NAME)
    warm_up_jax()
    rows = [size_rows(run, c, args.repeats) for c in args.cells]
    run.print(f"wrote {run.finish(args.out, dict(rows=rows, repeats=args.repeats))}")


if __name__ == "__main__":
    main()
