"""Conditioning of runout measures for gradients: d(runout)/d(phi) from AD along a sweep of
friction angles, for the hard maximum, a percentile and the soft maximum, against central
finite differences (float64). Writes benchmarks/results/runout_gradients.json and a plot.

    .venv/bin/python benchmarks/runout_gradients.py [--phis 32 38 13] [--frames 100]

No speed figure: the protocol (``benchmarks/protocol.py``) records the load, commit and
machine in the JSON but does not refuse a loaded machine.
"""
from __future__ import annotations

import argparse

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import protocol  # noqa: E402

from diffgns import MPM, rollout  # noqa: E402
from diffgns.metrics import runout  # noqa: E402
from diffgns.scene.builders import column_collapse  # noqa: E402
from diffgns.timing import measure, no_sync  # noqa: E402

METHODS = {"max": {"method": "max"}, "percentile99": {"method": "percentile", "q": 99.0},
           "softmax": {"method": "softmax"}}


def final_positions_fn(n_frames: int):
    """(scene, final(phi) -> (N, 2) positions of the last frame). The one place this
    benchmark calls the simulator."""
    scene = column_collapse(width=0.1, aspect_ratio=1.0, cells_across=6)
    sim = MPM(scene, dtype="float64")
    base, state = sim.params(), sim.init()

    def final(phi):
        p = base.replace(friction_angle=jnp.reshape(phi, (1,)))
        return rollout(sim, p, state, n_frames, checkpoint_block=25)[0].positions[-1]

    return scene, final


def sweep(final, phis, h: float) -> dict:
    """AD (one VJP per angle) and central FD derivatives of every runout measure."""
    final_j = jax.jit(final)
    vjp = jax.jit(lambda phi: jax.vjp(final, phi))
    res = {m: dict(ad=[], fd=[]) for m in METHODS}
    for phi in phis:
        x, pullback = vjp(jnp.asarray(phi))
        xp, xm = final_j(jnp.asarray(phi + h)), final_j(jnp.asarray(phi - h))
        for m, kw in METHODS.items():
            ct = jax.grad(lambda x, kw=kw: runout(x, **kw))(x)
            res[m]["ad"].append(float(pullback(ct)[0]))
            res[m]["fd"].append(float((runout(xp, **kw) - runout(xm, **kw)) / (2 * h)))
    return res


def plot(phis, res, path) -> None:
    plt = protocol.use_agg()
    fig, ax = plt.subplots(figsize=(6, 4))
    for i, (m, r) in enumerate(res.items()):
        ax.plot(phis, r["ad"], "o-", color=f"C{i}", label=f"{m} (AD)")
        ax.plot(phis, r["fd"], "x--", color=f"C{i}", alpha=0.6, label=f"{m} (FD)")
    ax.set_xlabel("friction angle (deg)")
    ax.set_ylabel("d runout / d phi (m/deg)")
    ax.legend(fontsize=7)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--phis", type=float, nargs=3, default=[32.0, 38.0, 13],
                    metavar=("FROM", "TO", "N"), help="friction angles (deg), np.linspace")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--fd-step", type=float, default=0.05, help="FD step (deg)")
    ap.add_argument("--out", default="runout_gradients.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "runout_gradients", timed=False)
    phis = np.linspace(args.phis[0], args.phis[1], int(args.phis[2]))
    scene, final = final_positions_fn(args.frames)
    total, res = measure(lambda: sweep(final, phis, args.fd_step), sync=no_sync)
    summary = {}
    for m, r in res.items():
        ad, fd = np.array(r["ad"]), np.array(r["fd"])
        summary[m] = dict(
            ad_mean=float(ad.mean()), ad_rel_std=float(ad.std() / abs(ad.mean())),
            fd_rel_std=float(fd.std() / abs(fd.mean())),
            median_rel_err_ad_vs_fd=float(np.median(np.abs(ad - fd) / np.abs(fd))))
        run.print(f"{m:13s} mean dR/dphi {ad.mean():+.3e} m/deg  "
                  f"AD spread {summary[m]['ad_rel_std']:.2f}"
                  f"  FD spread {summary[m]['fd_rel_std']:.2f}  median |AD-FD|/|FD| "
                  f"{summary[m]['median_rel_err_ad_vs_fd']:.3f}")
    path = run.finish(args.out, dict(
        particles=scene.n_particles, frames=args.frames, fd_step_deg=args.fd_step,
        phis=phis.tolist(), results=res, summary=summary, total_wall_s=total.wall_s,
        total_cpu_s=total.cpu_s), lambda p: plot(phis, res, p.with_suffix(".png")))
    run.print(f"wrote {path}; total {total.wall_s:.0f} s")


if __name__ == "__main__":
    main()
