"""Which friction angle can an inversion through the GNS recover? (its bias against the MPM)

    .venv/bin/python benchmarks/inverse_gns_bias.py [--aspect-ratios 1 1.5 1.75 2 2.5 3]
        [--phis 24 25 ... 36] [--target-phi 30]

For each column (``ColumnCase(aspect_ratio=a)``, width 0.1 m, 8 cells across, the 0.8 x 0.35
m box of ``models/gns_columns``) the observation is the MPM at phi = 30 deg seen as GNS nodes;
the GNS (first 6 frames = the observed ones) is rolled out over a grid of friction angles and
its final runout, for each definition (farthest node "max", soft maximum "softmax", 99th
percentile), is interpolated linearly to the phi where it equals the observed runout: the
value a converged runout inversion through the GNS returns (the optimiser only finds the
root). Also, for the default column, the same with other initial histories: the column at
rest repeated 6 times, and a differentiable MPM start-up at the trial phi.

No speed figure: the protocol (``benchmarks/protocol.py``) records the load, commit and
machine without refusing a loaded machine. Writes ``benchmarks/results/inverse_gns_bias.json``.
"""
from __future__ import annotations

import argparse

import numpy as np
import protocol

from diffgns.timing import measure, no_sync

METHODS = ("max", "softmax", "percentile")


def root(phis, values, target) -> float | None:
    d = np.asarray(values) - target
    i = np.flatnonzero(np.sign(d[:-1]) != np.sign(d[1:]))
    if not len(i):
        return None
    k = int(i[0])
    return float(phis[k] + d[k] / (d[k] - d[k + 1]) * (phis[k + 1] - phis[k]))


def final_positions(col, observed, loaded, phis, history: str, target_phi: float) -> list:
    """The GNS's last frame at every friction angle of ``phis``. The one place this benchmark
    calls the simulator."""
    import jax
    import jax.numpy as jnp

    from diffgns.inverse.simulators import gns_simulator

    obs = observed
    if history == "rest":
        obs = np.repeat(observed[:1], len(observed), axis=0)
    sim = gns_simulator(col, observed=obs, loaded=loaded, checkpoint_block=None,
                        history="mpm" if history == "mpm" else "observed")
    if history == "mpm":
        sim.allocate({"friction_angle": target_phi})
    f = jax.jit(lambda phi: sim({"friction_angle": phi})[-1])
    return [f(jnp.float32(p)) for p in phis]


def scan(col, observed, loaded, phis, history: str, target_phi: float) -> dict:
    import jax.numpy as jnp

    from diffgns.metrics import runout

    finals = final_positions(col, observed, loaded, phis, history, target_phi)
    out = {}
    for m in METHODS:
        tgt = float(runout(jnp.asarray(observed[-1]), method=m))
        vals = [float(runout(x, method=m)) for x in finals]
        i30 = int(np.argmin(np.abs(np.asarray(phis) - target_phi)))
        r = root(phis, vals, tgt)
        out[m] = dict(observed_runout_m=tgt, gns_runout_m=vals,
                      gns_error_at_target_phi=(vals[i30] - tgt) / tgt, recovered_phi=r,
                      bias_deg=None if r is None else r - target_phi)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--aspect-ratios", type=float, nargs="+",
                    default=[1.0, 1.5, 1.75, 2.0, 2.5, 3.0])
    ap.add_argument("--phis", type=float, nargs="+", default=list(range(22, 39)))
    ap.add_argument("--target-phi", type=float, default=30.0)
    ap.add_argument("--default-aspect-ratio", type=float, default=1.75)
    ap.add_argument("--out", default="inverse_gns_bias.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "inverse_gns_bias", timed=False)
    from diffgns.inverse.simulators import Column, ColumnCase, load_gns

    loaded = load_gns("gns_columns")  # the 8-cell ColumnCase default is its resolution
    rows = []

    def body():
        for a in args.aspect_ratios:
            col = Column(ColumnCase(aspect_ratio=a))
            observed = col.observation({"friction_angle": args.target_phi})
            hists = ["observed", "rest", "mpm"] if a == args.default_aspect_ratio \
                else ["observed"]
            for h in hists:
                res = scan(col, observed, loaded, args.phis, h, args.target_phi)
                rows.append(dict(aspect_ratio=a, nodes=col.n_nodes, history=h, **res))
                run.print(f"a={a:g} ({col.n_nodes} nodes), history {h}: " + "; ".join(
                    f"{m} {res[m]['gns_error_at_target_phi']:+.1%} -> phi "
                    + ("none" if res[m]["recovered_phi"] is None else
                       f"{res[m]['recovered_phi']:.2f}") for m in METHODS))

    total = measure(body, sync=no_sync)[0]
    path = run.finish(args.out, {
        "description": "friction angle at which the GNS's final runout equals the MPM's "
                       f"(phi = {args.target_phi:g}) runout, by linear interpolation over "
                       "a grid of phi; gns_error_at_target_phi = relative runout error of the "
                       "GNS at the true phi; history: the GNS's 6 initial frames (observed MPM "
                       "frames, the column at rest repeated, or an MPM start-up at the trial "
                       "phi)", "settings": vars(args), "total_wall_s": total.wall_s,
        "total_cpu_s": total.cpu_s, "results": rows})
    run.print(f"wrote {path}")


if __name__ == "__main__":
    main()
