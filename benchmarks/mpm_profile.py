"""Where an MPM substep's time goes (sand column), and the transfer levers measured.

    .venv/bin/python benchmarks/mpm_profile.py [--cells 45 90] [--repeats 7] [--threads both]

For each size (``column_collapse(cells_across=c)``: sand, 4 particles per cell, friction
floor, slip walls; N = 4 c^2) the pieces of :meth:`diffgns.mpm.MPM.substep` are jitted apart,
each inside a ``lax.scan`` of ``K`` repetitions (so dispatch is amortised; every repetition
feeds a tiny multiple of its output back so XLA cannot hoist it), on the state after a few
frames of the collapse:

* ``stress``: trial deformation gradient + Drucker-Prager return map (SVD, log/exp);
* ``stencil``: base nodes, B-spline weights and offsets of every particle;
* ``p2g``: MLS contributions + the one scatter-add to the grid;
* ``grid``: momentum -> velocity, gravity, Coulomb walls (and obstacles if any);
* ``g2p``: row gather + APIC velocity gradient;
* ``substep``: the whole substep as the solver runs it.

The pieces are timed in interleaved rounds; their sum need not equal the whole (XLA fuses
across piece boundaries inside the substep). The lever table times the transfers as they
were before issue 22's changes (P2G with the contributions fused into the scatter, G2P as
nine 2-wide gathers per particle) against the current ones, interleaved, and checks that
both give the same values. Writes ``benchmarks/results/mpm_profile.json``.
"""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np
import protocol
from protocol import warm_up_jax

from diffgns import MPM, rollout_jit
from diffgns.mpm import boundaries
from diffgns.mpm import linalg as la
from diffgns.mpm.shape import stencil
from diffgns.mpm.transfer import g2p, grid_velocity, p2g
from diffgns.scene.builders import column_collapse
from diffgns.timing import interleave

K = 20  # repetitions per jitted call


def _repeat(fn):
    """Jitted ``x -> K`` chained calls of ``fn(x)`` (first output leaf fed back x 1e-12)."""
    def body(x, _):
        out = fn(x)
        leaf = jax.tree_util.tree_leaves(out)[0]
        return x + 1e-12 * jnp.sum(leaf), None

    return jax.jit(lambda x: jax.lax.scan(body, x, None, length=K)[0])


def old_p2g(idx, w, dpos, mass, momentum, affine, n_nodes, dx):
    """P2G before issue 22: contributions fused into the scatter (no barrier)."""
    dx_, dy_ = dpos[0] * dx, dpos[1] * dx
    mvx = w * (momentum[0][None] + affine[0, 0][None] * dx_ + affine[0, 1][None] * dy_)
    mvy = w * (momentum[1][None] + affine[1, 0][None] * dx_ + affine[1, 1][None] * dy_)
    vals = jnp.stack([mvx, mvy, w * mass[None]], -1).reshape(-1, 3)
    return jnp.zeros((n_nodes, 3), vals.dtype).at[idx.reshape(-1)].add(
        vals, mode="promise_in_bounds")


def old_g2p(idx, w, dpos, gv, dx):
    """G2P before issue 22: nine 2-wide gathers per particle."""
    gv = gv.reshape(2, -1)
    g = jnp.stack([gv[0], gv[1]], -1).at[idx].get(mode="promise_in_bounds")  # (9, N, 2)
    gx, gy = w * g[..., 0], w * g[..., 1]
    v = jnp.stack([gx.sum(0), gy.sum(0)])
    C = (4.0 / dx) * jnp.stack([
        jnp.stack([(gx * dpos[0]).sum(0), (gx * dpos[1]).sum(0)]),
        jnp.stack([(gy * dpos[0]).sum(0), (gy * dpos[1]).sum(0)])])
    return v, C


def pieces(cells: int):
    """(scene, {name: (jitted K-repeat call, argument)}, {lever: (old, new, arg)})."""
    scene = column_collapse(cells_across=cells)
    sim = MPM(scene)
    params, state = sim.params(), sim.init()
    state = rollout_jit(sim, params, state, n_frames=4)[1]  # a moving, yielding column
    dt, dx = sim.dt, sim.dx
    shape = sim.grid_shape
    n_nodes = shape[0] * shape[1]
    origin = jnp.asarray(sim.origin, state.x.dtype)[:, None]
    mass = sim.mass(params, state)

    def stn(x):
        return stencil((x - origin) / dx, shape)

    idx, w, dpos = stn(state.x)
    affine = mass * state.C
    grid = p2g(idx, w, dpos, mass, mass * state.v, affine, n_nodes, dx)

    def grid_update(g):
        gv = grid_velocity(g) + dt * params.gravity[:, None]
        gv = boundaries.apply_walls(gv.reshape(2, *shape), sim.scene.walls, params.wall_mu,
                                    sim.scene.padding, sim.scene.n_cells)
        return gv

    gv = grid_update(grid)
    calls = {
        "stress": (_repeat(lambda F: sim.stress(params, state,
                                                F + dt * la.matmul(state.C, F))[0]), state.F),
        "stencil": (_repeat(lambda x: stn(x)[1]), state.x),
        "p2g": (_repeat(lambda x: p2g(*stn(x), mass, mass * state.v, affine, n_nodes, dx)),
                state.x),
        "grid": (_repeat(grid_update), grid),
        "g2p": (_repeat(lambda x: g2p(*stn(x), gv, dx)), state.x),
        "substep": (_repeat(lambda x: sim.substep(params, state.replace(x=x)).x), state.x),
    }
    levers = {
        "p2g": (_repeat(lambda x: old_p2g(*stn(x), mass, mass * state.v, affine, n_nodes, dx)),
                calls["p2g"][0], state.x),
        "g2p": (_repeat(lambda x: old_g2p(*stn(x), gv, dx)), calls["g2p"][0], state.x),
    }
    same = {
        "p2g": float(jnp.max(jnp.abs(old_p2g(idx, w, dpos, mass, mass * state.v, affine,
                                              n_nodes, dx) - grid))),
        "g2p": float(max(jnp.max(jnp.abs(a - b)) for a, b in zip(old_g2p(idx, w, dpos, gv, dx),
                                                                  g2p(idx, w, dpos, gv, dx)))),
    }
    return scene, calls, levers, same


def profile_size(run: protocol.Run, cells: int, repeats: int) -> dict:
    scene, calls, levers, same = pieces(cells)
    n, sub = scene.n_particles, scene.substeps
    res = interleave({k: (lambda f=f, a=a: f(a)) for k, (f, a) in calls.items()}, repeats)
    rows = {k: {"us_per_substep": 1e6 * res.summary(k)["median_s"] / K,
                "cpu_us_per_substep": 1e6 * res.summary(k)["cpu_median_s"] / K}
            for k in calls}
    whole = rows["substep"]["us_per_substep"]
    run.print(f"N = {n} ({scene.grid_shape[0]}x{scene.grid_shape[1]} grid, {sub} substeps/frame):"
              f" substep {whole:.0f} us = {n / whole:.2f} M particle-substeps/s")
    for k, r in rows.items():
        share = 100 * r["us_per_substep"] / whole
        run.print(f"  {k:>8}: {r['us_per_substep']:8.0f} us  ({share:5.1f}% of the substep; "
                  f"CPU {r['cpu_us_per_substep']:.0f} us)")
    lever_rows = {}
    for k, (old, new, a) in levers.items():
        lr = interleave({"before": lambda old=old, a=a: old(a), "now": lambda new=new, a=a: new(a)},
                        repeats)
        lever_rows[k] = {"before_us": 1e6 * lr.summary("before")["median_s"] / K,
                         "now_us": 1e6 * lr.summary("now")["median_s"] / K,
                         "ratio_now_over_before": lr.ratio("now", "before"),
                         "max_abs_difference": same[k]}
        r = lever_rows[k]
        run.print(f"  lever {k}: before {r['before_us']:.0f} us, now {r['now_us']:.0f} us "
                  f"(now/before {r['ratio_now_over_before']:.2f}; max |diff| {same[k]:.1e})")
    return {"cells_across": cells, "n_particles": n, "grid_shape": list(scene.grid_shape),
            "substeps_per_frame": sub, "repetitions_per_call": K, "pieces": rows,
            "levers": lever_rows, "rounds": res.to_json()["rounds"]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, nargs="+", default=[45, 90],
                    help="cells across the column (N = 4 cells^2 particles)")
    ap.add_argument("--repeats", type=int, default=7, help="interleaved rounds (>= 3)")
    ap.add_argument("--out", default="mpm_profile.json")
    protocol.add_arguments(ap, threads="both")
    args = ap.parse_args(argv)
    run = protocol.start(args, "mpm_profile")
    warm_up_jax()
    sizes = [profile_size(run, c, max(3, args.repeats)) for c in args.cells]
    payload = {"description": __doc__.splitlines()[0], "jax": jax.__version__,
               "dtype": str(np.dtype(jnp.asarray(0.0).dtype)), "sizes": sizes}
    if run.mode == "both":
        payload["one_thread_pinned"] = run.pinned_child()
    path = run.finish(args.out, payload)
    run.print(f"wrote {path}")


if __name__ == "__main__":
    main()
