"""Cost of each physics effect: steady time per MPM substep of the same ~4k-particle body.

    .venv/bin/python benchmarks/mpm_effects.py [--repeats 7]

One 0.2 m x 0.2 m square (32 x 32 cells, 4 particles per cell = 4096 particles) in a
1.0 m x 0.5 m box (dx = 6.25 mm, 167 x 87 grid nodes), under gravity, in five variants:

    elastic_slip           Elastic corotated (E 2 MPa, nu 0.3, rho 1800) + slip walls
    sand_slip              Sand (Drucker-Prager, phi 30) + slip walls
    sand_friction          Sand + Coulomb friction walls (mu 0.3, all four)
    sand_friction_boxes    Sand + friction walls + 2 friction box obstacles
    fluid                  Fluid (Tait, K 0.2 MPa, viscosity 1e-3) + slip walls

All variants use the same substep dt (the smallest stable one of the five) and the jitted
MPM rollout for the same number of frames. Each variant is compiled first (compile = first
call - median steady call), then timed in interleaved rounds (one call of every variant per
round, the order alternating), so they share the machine's load; a variant's cost relative
to the baseline is also given as the median of its per-round ratios (``benchmarks/timing.py``,
under ``benchmarks/protocol.py``). Writes ``benchmarks/results/mpm_effects.json`` and
``mpm_effects.png``.
"""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import protocol
from protocol import warm_up_jax

from diffgns import MPM, rollout_jit
from diffgns.scene import Body, BoxObstacle, Scene, Wall, Walls
from diffgns.scene.materials import Elastic, Fluid, Sand
from diffgns.scene.shapes import Rectangle
from diffgns.timing import interleave, measure

DX = 0.2 / 32
DOMAIN = ((0.0, 1.0), (0.0, 0.5))
SQUARE = Rectangle(0.1, 0.05, 0.3, 0.25)
BOXES = (BoxObstacle(0.45, 0.0, 0.55, 0.05, Wall("friction", 0.3)),
         BoxObstacle(0.70, 0.0, 0.80, 0.10, Wall("friction", 0.3)))
BASELINE = "elastic_slip"


def variants(dt: float | None = None) -> dict[str, Scene]:
    sand = Sand(friction_angle=30.0, E=2.0e6, nu=0.3, rho=1800.0)
    elastic = Elastic(E=2.0e6, nu=0.3, rho=1800.0, model="corotated")
    fluid = Fluid(bulk_modulus=2.0e5, rho=1000.0, viscosity=1e-3, gamma=7.0)
    slip, fric = Walls.all("slip"), Walls.all("friction", 0.3)

    def scene(material, walls, obstacles=()):
        return Scene(domain=DOMAIN, dx=DX, bodies=(Body(SQUARE, material, particles_per_cell=4),),
                     walls=walls, obstacles=obstacles, dt=dt)

    return {
        "elastic_slip": scene(elastic, slip),
        "sand_slip": scene(sand, slip),
        "sand_friction": scene(sand, fric),
        "sand_friction_boxes": scene(sand, fric, BOXES),
        "fluid": scene(fluid, slip),
    }


def rollout_call(scene: Scene, n_frames: int):
    """Zero-argument call returning the (T, N, 2) positions of a jitted MPM rollout of
    ``scene``. The one place this benchmark calls the simulator."""
    sim = MPM(scene)
    params, state = sim.params(), sim.init()
    return lambda: rollout_jit(sim, params, state, n_frames=n_frames)[0].positions


def plot(rows: dict, path):
    plt = protocol.use_agg()
    names = list(rows)
    us = [rows[n]["us_per_substep"] for n in names]
    rel = [rows[n]["relative_to_baseline"] for n in names]
    err_lo = [rows[n]["us_per_substep"] - 1e6 * rows[n]["min_s"] / rows[n]["substeps_per_call"]
              for n in names]
    err_hi = [1e6 * rows[n]["max_s"] / rows[n]["substeps_per_call"] - rows[n]["us_per_substep"]
              for n in names]
    fig, ax = plt.subplots(figsize=(8, 4))
    bars = ax.bar(names, us, yerr=[err_lo, err_hi], capsize=4,
                  color=["tab:gray", "tab:olive", "tab:orange", "tab:red", "tab:blue"])
    for b, r, hi in zip(bars, rel, err_hi):
        ax.annotate(f"x{r:.2f}", (b.get_x() + b.get_width() / 2, b.get_height() + hi),
                    ha="center", va="bottom", fontsize=9, xytext=(0, 3),
                    textcoords="offset points")
    n = next(iter(rows.values()))["n_particles"]
    ax.set_ylabel("us per substep (median, min-max bars)")
    ax.set_title(f"MPM cost per effect, {n} particles (relative to {BASELINE})")
    ax.tick_params(axis="x", labelrotation=15)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def measure_variants(scenes: dict[str, Scene], frames: int, repeats: int) -> dict:
    """Interleaved rounds over the variants (first calls = compile, timed apart)."""
    res = interleave({k: rollout_call(sc, frames) for k, sc in scenes.items()}, repeats)
    rows = {}
    for name, scene in scenes.items():
        sub = scene.substeps * frames
        s = res.summary(name)
        rows[name] = {
            "effects": sorted(scene.effects), "n_particles": scene.n_particles,
            "grid_shape": list(scene.grid_shape), "substep_dt_s": scene.substep_dt,
            "substeps_per_call": sub,
            "finite": bool(jnp.all(jnp.isfinite(res.outputs[name]))), **s,
            "us_per_substep": 1e6 * s["median_s"] / sub,
            "particle_substeps_per_s": scene.n_particles * sub / s["median_s"],
        }
    base = rows[BASELINE]["us_per_substep"]
    for name, row in rows.items():
        row["relative_to_baseline"] = row["us_per_substep"] / base
        # median over rounds of the ratio against the baseline call of the same round
        row["relative_paired_median"] = res.ratio(name, BASELINE)
    return {"rows": rows, "rounds": res.to_json()["rounds"]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7, help="timed rounds (>= 3)")
    ap.add_argument("--frames", type=int, default=8, help="frames per timed call")
    ap.add_argument("--out", default="mpm_effects.json")
    protocol.add_arguments(ap)
    args = ap.parse_args(argv)
    run = protocol.start(args, "mpm_effects")
    repeats = max(3, args.repeats)
    dt = min(s.stable_dt() for s in variants().values())
    scenes = variants(dt)
    warm_up_jax()
    total, res = measure(lambda: measure_variants(scenes, args.frames, repeats),
                         sync=lambda _: None)
    rows = res["rows"]
    run.print(f"{'variant':<20} {'particles':>9} {'us/substep':>10} {'rel':>6} "
              f"{'rel(paired)':>11} {'compile s':>9} {'cpu/wall':>8} {'M p-substeps/s':>14}")
    for name, r in rows.items():
        run.print(f"{name:<20} {r['n_particles']:>9} {r['us_per_substep']:>10.1f} "
                  f"{r['relative_to_baseline']:>6.2f} {r['relative_paired_median']:>11.2f} "
                  f"{r['compile_s']:>9.2f} {r['cpu_over_wall']:>8.2f} "
                  f"{r['particle_substeps_per_s'] / 1e6:>14.3f}")
    run.print(f"median of {repeats} interleaved rounds x "
              f"{rows[BASELINE]['substeps_per_call']} substeps each; total {total.wall_s:.1f} s")
    payload = {
        "description": "same 4096-particle square, same dt, jitted MPM rollout; "
                       "relative_to_baseline = median us/substep / baseline median; "
                       "relative_paired_median = median over rounds of the per-round ratio",
        "baseline": BASELINE, "dtype": str(jnp.asarray(0.0).dtype), "jax": jax.__version__,
        "dt_s": dt, "frames_per_call": args.frames, "repeats": repeats,
        "total_wall_s": total.wall_s, "total_cpu_s": total.cpu_s, "results": rows,
        "rounds": res["rounds"],
    }
    path = run.finish(args.out, payload, lambda p: plot(rows, p.with_suffix(".png")))
    run.print(f"wrote {path} (and the plot beside it)")


if __name__ == "__main__":
    main()
