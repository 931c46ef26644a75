"""Conditioning of runout measures for gradients: d(runout)/d(phi) from AD along a sweep of
friction angles, for the hard maximum, a percentile and the soft maximum, against central
finite differences (float64). Writes benchmarks/results/runout_gradients.json and a plot.

    python benchmarks/runout_gradients.py
"""
import json
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from diffgns import MPM  # noqa: E402
from diffgns.metrics import runout  # noqa: E402
from diffgns.scene.builders import column_collapse  # noqa: E402

OUT = Path(__file__).parent / "results"
METHODS = {"max": {"method": "max"}, "percentile99": {"method": "percentile", "q": 99.0},
           "softmax": {"method": "softmax"}}


def main():
    t0 = time.perf_counter()
    scene = column_collapse(width=0.1, aspect_ratio=1.0, cells_across=6)
    sim = MPM(scene, dtype="float64")
    base, state = sim.params(), sim.init_state()
    n_frames = 100

    def final(phi):
        p = base.replace(friction_angle=jnp.reshape(phi, (1,)))
        return sim.rollout_full(p, state, n_frames=n_frames, checkpoint=True, block=25)[0][-1]

    final_j = jax.jit(final)
    vjp = jax.jit(lambda phi: jax.vjp(final, phi))
    phis = np.linspace(32.0, 38.0, 13)
    res = {m: dict(ad=[], fd=[]) for m in METHODS}
    h = 0.05
    for phi in phis:
        x, pullback = vjp(jnp.asarray(phi))
        xp, xm = final_j(jnp.asarray(phi + h)), final_j(jnp.asarray(phi - h))
        for m, kw in METHODS.items():
            ct = jax.grad(lambda x, kw=kw: runout(x, **kw))(x)
            res[m]["ad"].append(float(pullback(ct)[0]))
            res[m]["fd"].append(float((runout(xp, **kw) - runout(xm, **kw)) / (2 * h)))
    summary = {}
    for m, r in res.items():
        ad, fd = np.array(r["ad"]), np.array(r["fd"])
        summary[m] = dict(
            ad_mean=float(ad.mean()), ad_rel_std=float(ad.std() / abs(ad.mean())),
            fd_rel_std=float(fd.std() / abs(fd.mean())),
            median_rel_err_ad_vs_fd=float(np.median(np.abs(ad - fd) / np.abs(fd))))
        print(f"{m:13s} mean dR/dphi {ad.mean():+.3e} m/deg  "
              f"AD spread {summary[m]['ad_rel_std']:.2f}"
              f"  FD spread {summary[m]['fd_rel_std']:.2f}  median |AD-FD|/|FD| "
              f"{summary[m]['median_rel_err_ad_vs_fd']:.3f}")
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "runout_gradients.json").write_text(json.dumps(dict(
        command=" ".join(sys.argv), particles=scene.n_particles, frames=n_frames,
        fd_step_deg=h, phis=phis.tolist(), results=res, summary=summary,
        wall_s=time.perf_counter() - t0), indent=2))
    fig = Figure(figsize=(6, 4))
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    for i, (m, r) in enumerate(res.items()):
        ax.plot(phis, r["ad"], "o-", color=f"C{i}", label=f"{m} (AD)")
        ax.plot(phis, r["fd"], "x--", color=f"C{i}", alpha=0.6, label=f"{m} (FD)")
    ax.set_xlabel("friction angle (deg)")
    ax.set_ylabel("d runout / d phi (m/deg)")
    ax.legend(fontsize=7)
    fig.savefig(OUT / "runout_gradients.png", dpi=100)
    print(f"total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
