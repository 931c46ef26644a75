"""diffgns' MPM kernels vs Taichi (CPU) on the physics of Taichi's ``mpm88`` demo.

    PYTHONPATH=src .venv/bin/python benchmarks/mpm_vs_taichi.py [--repeats 7]

The problem (both implementations written here, float32): 8192 particles of a weakly
compressible "J-fluid" (Kirchhoff stress E (J - 1) I with E = 400, p_rho = 1,
particle volume (dx/2)^2), a 128 x 128 node grid with dx = 1/128, dt = 2e-4, gravity
9.8, initial velocity (0, -1), and slab walls 3 nodes thick (nodes i < 3 and
i > 128 - 3, same along y) that zero the velocity component pointing into the wall.
Initial positions: numpy ``default_rng(0)`` uniform in [0.2, 0.6]^2, shared by both.

(a) Taichi: four parallel loops in one ``@ti.kernel`` (grid clear, P2G with atomic adds,
    grid update, G2P), one kernel launch per substep, ``ti.init(arch=ti.cpu)`` with the
    default thread count.
(b) diffgns: ``shape.stencil`` -> ``transfer.p2g`` -> ``transfer.grid_velocity`` ->
    gravity -> ``boundaries.wall_slip`` on the four slabs -> ``transfer.g2p``, in the
    component-major layout ((2, N) vectors, (2, 2, N) matrices), 50 substeps in a
    ``lax.scan`` under ``jax.jit``.

Speed: after warm-up, ``--repeats`` timed segments of ``--substeps-per-repeat``
substeps for each implementation, interleaved (alternating which goes first) so both see
the same machine load; median particle-substeps/s and the ratio diffgns / Taichi.
Physics check: both are run 500 and 2000 substeps from the same start; mean particle
positions must agree within ``--tol`` (relative). Writes
``benchmarks/results/mpm_vs_taichi.json``.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
from _common import fmt_rate, machine_info, timed, write_json

N_PARTICLES = 8192
N_GRID = 128
DX = 1.0 / N_GRID
DT = 2e-4
P_RHO = 1.0
P_VOL = (0.5 * DX) ** 2
P_MASS = P_RHO * P_VOL
E = 400.0
GRAVITY = 9.8
BOUND = 3
V0 = (0.0, -1.0)
SCAN_LEN = 50  # substeps per jitted diffgns call
CHECKPOINTS = (500, 2000)


def initial_positions(seed: int = 0) -> np.ndarray:
    """(N, 2) float32 positions uniform in [0.2, 0.6]^2."""
    return np.random.default_rng(seed).uniform(0.2, 0.6, (N_PARTICLES, 2)).astype(np.float32)


# ============================================================================ Taichi
class TaichiMPM88:
    """The mpm88 physics as a Taichi CPU program (one kernel launch per substep)."""

    def __init__(self, ti):
        self.ti = ti
        f32 = ti.f32
        self.x = ti.Vector.field(2, f32, N_PARTICLES)
        self.v = ti.Vector.field(2, f32, N_PARTICLES)
        self.C = ti.Matrix.field(2, 2, f32, N_PARTICLES)
        self.J = ti.field(f32, N_PARTICLES)
        self.grid_mv = ti.Vector.field(2, f32, (N_GRID, N_GRID))
        self.grid_m = ti.field(f32, (N_GRID, N_GRID))
        self._substep = self._build()

    def _build(self):
        ti = self.ti
        x, v, C, J, grid_mv, grid_m = self.x, self.v, self.C, self.J, self.grid_mv, self.grid_m
        inv_dx = 1.0 / DX
        stress_k = -DT * 4.0 * P_VOL * inv_dx * inv_dx  # times E (J - 1) below

        @ti.func
        def quad_weights(fx):
            # rows: weights of the three stencil nodes, columns: axes
            return ti.Matrix.rows([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2,
                                   0.5 * (fx - 0.5) ** 2])

        @ti.kernel
        def substep():
            for I in ti.grouped(grid_m):
                grid_mv[I] = ti.Vector.zero(ti.f32, 2)
                grid_m[I] = 0.0
            # particle -> grid (MLS: affine momentum includes the stress term)
            for p in x:
                X = x[p] * inv_dx
                base = ti.cast(ti.floor(X - 0.5), ti.i32)
                fx = X - ti.cast(base, ti.f32)
                w = quad_weights(fx)
                s = stress_k * E * (J[p] - 1.0)
                affine = P_MASS * C[p] + ti.Matrix([[s, 0.0], [0.0, s]])
                mom = P_MASS * v[p]
                for a, b in ti.static(ti.ndrange(3, 3)):
                    off = ti.Vector([a, b])
                    d = (ti.cast(off, ti.f32) - fx) * DX
                    wt = w[a, 0] * w[b, 1]
                    grid_mv[base + off] += wt * (mom + affine @ d)
                    grid_m[base + off] += wt * P_MASS
            # grid update: momentum -> velocity, gravity, slab walls
            for i, j in grid_m:
                vel = grid_mv[i, j]
                m = grid_m[i, j]
                if m > 0:
                    vel = vel / m
                vel[1] -= DT * GRAVITY
                if i < BOUND and vel[0] < 0:
                    vel[0] = 0.0
                if i > N_GRID - BOUND and vel[0] > 0:
                    vel[0] = 0.0
                if j < BOUND and vel[1] < 0:
                    vel[1] = 0.0
                if j > N_GRID - BOUND and vel[1] > 0:
                    vel[1] = 0.0
                grid_mv[i, j] = vel
            # grid -> particle (APIC velocity gradient), advection, J update
            for p in x:
                X = x[p] * inv_dx
                base = ti.cast(ti.floor(X - 0.5), ti.i32)
                fx = X - ti.cast(base, ti.f32)
                w = quad_weights(fx)
                nv = ti.Vector.zero(ti.f32, 2)
                nC = ti.Matrix.zero(ti.f32, 2, 2)
                for a, b in ti.static(ti.ndrange(3, 3)):
                    off = ti.Vector([a, b])
                    d = (ti.cast(off, ti.f32) - fx) * DX
                    wt = w[a, 0] * w[b, 1]
                    gv = grid_mv[base + off]
                    nv += wt * gv
                    nC += (4.0 * inv_dx * inv_dx * wt) * gv.outer_product(d)
                v[p] = nv
                C[p] = nC
                x[p] += DT * nv
                J[p] *= 1.0 + DT * nC.trace()

        return substep

    def reset(self, x0: np.ndarray):
        n = len(x0)
        self.x.from_numpy(x0)
        self.v.from_numpy(np.tile(np.asarray(V0, np.float32), (n, 1)))
        self.C.from_numpy(np.zeros((n, 2, 2), np.float32))
        self.J.from_numpy(np.ones(n, np.float32))
        self.ti.sync()

    def run(self, n_substeps: int):
        for _ in range(n_substeps):
            self._substep()
        self.ti.sync()

    def positions(self) -> np.ndarray:
        return self.x.to_numpy()


# ============================================================================ diffgns
class DiffgnsMPM88:
    """The same physics from diffgns' transfer kernels, component-major, scanned + jitted."""

    def __init__(self):
        import jax
        import jax.numpy as jnp

        from diffgns.mpm.boundaries import wall_slip
        from diffgns.mpm.shape import stencil
        from diffgns.mpm.transfer import g2p, grid_velocity, p2g

        self.jax, self.jnp = jax, jnp
        f32 = jnp.float32
        n_nodes = N_GRID * N_GRID
        mass = jnp.full((N_PARTICLES,), P_MASS, f32)
        stress_k = DT * 4.0 / DX**2 * P_VOL
        # (slab of the (nx, ny) node grid, outward normal of the wall surface)
        slabs = (
            (np.s_[:BOUND, :], (1.0, 0.0)),
            (np.s_[N_GRID - BOUND + 1:, :], (-1.0, 0.0)),
            (np.s_[:, :BOUND], (0.0, 1.0)),
            (np.s_[:, N_GRID - BOUND + 1:], (0.0, -1.0)),
        )

        def substep(state, _):
            x, v, C, J = state
            idx, w, dpos = stencil(x / DX, (N_GRID, N_GRID))
            tau = E * (J - 1.0)  # Kirchhoff stress tau * I
            affine = P_MASS * C
            affine = affine.at[0, 0].add(-stress_k * tau).at[1, 1].add(-stress_k * tau)
            grid = p2g(idx, w, dpos, mass, mass * v, affine, n_nodes, DX)
            gv = grid_velocity(grid)
            gv = gv.at[1].add(-DT * GRAVITY).reshape(2, N_GRID, N_GRID)
            for sl, (nx, ny) in slabs:
                vx, vy = wall_slip(gv[0][sl], gv[1][sl], nx, ny)
                gv = gv.at[(slice(None), *sl)].set(jnp.stack([vx, vy]))
            v, C = g2p(idx, w, dpos, gv.reshape(2, n_nodes), DX)
            x = x + DT * v
            J = J * (1.0 + DT * (C[0, 0] + C[1, 1]))
            return (x, v, C, J), None

        @jax.jit
        def run_scan(state):
            return jax.lax.scan(substep, state, None, length=SCAN_LEN)[0]

        self._run_scan = run_scan
        self.state = None

    def reset(self, x0: np.ndarray):
        jnp = self.jnp
        n = len(x0)
        x = jnp.asarray(x0.T, jnp.float32)
        v = jnp.broadcast_to(jnp.asarray(V0, jnp.float32)[:, None], (2, n))
        self.state = self.jax.block_until_ready(
            (x, v, jnp.zeros((2, 2, n), jnp.float32), jnp.ones(n, jnp.float32)))

    def run(self, n_substeps: int):
        if n_substeps % SCAN_LEN:
            raise ValueError(f"diffgns runs whole scans of {SCAN_LEN} substeps")
        for _ in range(n_substeps // SCAN_LEN):
            self.state = self._run_scan(self.state)
        self.jax.block_until_ready(self.state)

    def positions(self) -> np.ndarray:
        return np.asarray(self.state[0]).T


# ============================================================================ driver
def stats_of(x: np.ndarray) -> dict:
    finite = bool(np.all(np.isfinite(x)))
    return {"finite": finite, "mean_x": float(np.mean(x[:, 0])), "mean_y": float(np.mean(x[:, 1])),
            "std_x": float(np.std(x[:, 0])), "std_y": float(np.std(x[:, 1])),
            "min_y": float(np.min(x[:, 1]))}


def physics_check(sims: dict, x0: np.ndarray, tol: float) -> dict:
    """Run both from x0 and compare particle statistics at the checkpoints."""
    out = {}
    for sim in sims.values():
        sim.reset(x0)
    done = 0
    for cp in CHECKPOINTS:
        row = {}
        for name, sim in sims.items():
            sim.run(cp - done)
            row[name] = stats_of(sim.positions())
        done = cp
        a, b = row["diffgns"], row["taichi"]
        rel = {k: abs(a[k] - b[k]) / abs(b[k]) for k in ("mean_x", "mean_y", "std_y")}
        row["rel_diff"] = rel
        row["agree"] = bool(a["finite"] and b["finite"] and rel["mean_y"] <= tol
                            and rel["mean_x"] <= tol)
        out[str(cp)] = row
    return out


def interleaved_timing(sims: dict, x0: np.ndarray, seg: int, repeats: int) -> dict:
    """Reset every sim to x0, run one warm-up segment each, then ``repeats`` timed
    segments of ``seg`` substeps, alternating which implementation goes first."""
    for sim in sims.values():
        sim.reset(x0)
        sim.run(seg)
    walls = {k: [] for k in sims}
    cpus = {k: [] for k in sims}
    order = list(sims)
    for r in range(repeats):
        for name in order if r % 2 == 0 else order[::-1]:
            w, c, _ = timed(lambda s=sims[name]: s.run(seg), sync=lambda _: None)
            walls[name].append(w)
            cpus[name].append(c)
    work = N_PARTICLES * seg
    out = {}
    for name in sims:
        med = statistics.median(walls[name])
        out[name] = {
            "median_s": med, "min_s": min(walls[name]), "max_s": max(walls[name]),
            "samples_s": walls[name], "cpu_median_s": statistics.median(cpus[name]),
            "cpu_samples_s": cpus[name],
            "particle_substeps_per_s": work / med,
            "particle_substeps_per_s_best": work / min(walls[name]),
            "us_per_substep": 1e6 * med / seg,
        }
    return out


def paired_ratio(timing: dict, ref: str) -> float:
    """Median over repeats of t_ref / t_diffgns for segments timed back to back."""
    pairs = zip(timing[ref]["samples_s"], timing["diffgns"]["samples_s"])
    return statistics.median(a / b for a, b in pairs)


def report(timing: dict, repeats: int, seg: int):
    for name, t in timing.items():
        print(f"{name:>14}: {fmt_rate(t['particle_substeps_per_s'])} particle-substeps/s "
              f"(median of {repeats} x {seg} substeps; {t['us_per_substep']:.0f} us/substep; "
              f"CPU/wall {t['cpu_median_s'] / t['median_s']:.2f})", flush=True)


def skip(reason: str, machine: dict):
    print(f"SKIPPED: {reason}")
    path = write_json("mpm_vs_taichi.json", {"benchmark": "mpm_vs_taichi", "skipped": True,
                                              "reason": reason}, machine)
    print(f"wrote {path}")
    sys.exit(0)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=9, help="timed segments each (>= 5)")
    ap.add_argument("--substeps-per-repeat", type=int, default=100,
                    help=f"substeps per timed segment (a multiple of {SCAN_LEN})")
    ap.add_argument("--no-single-thread", action="store_true",
                    help="skip the supplementary 1-thread Taichi measurement")
    ap.add_argument("--tol", type=float, default=0.03,
                    help="relative tolerance on mean particle x and y")
    args = ap.parse_args()
    machine = machine_info()
    try:
        import taichi as ti
    except Exception as e:  # ImportError or a broken install
        skip(f"taichi is not importable ({e!r}); install it with `pip install taichi` "
             "(the `bench` extra)", machine)
        return
    import jax

    seg = args.substeps_per_repeat
    if seg % SCAN_LEN or seg < SCAN_LEN:
        ap.error(f"--substeps-per-repeat must be a positive multiple of {SCAN_LEN}")
    repeats = max(5, args.repeats)
    ti.init(arch=ti.cpu, default_fp=ti.f32, random_seed=0)
    from taichi.lang import impl

    def taichi_config():  # read now: the config object is freed by ti.reset()
        cfg = impl.current_cfg()
        return {"arch": str(cfg.arch), "cpu_max_num_threads": cfg.cpu_max_num_threads,
                "default_fp": str(cfg.default_fp), "offline_cache": bool(cfg.offline_cache),
                "launch": "one @ti.kernel (4 parallel loops) per substep"}

    ti_config = taichi_config()
    x0 = initial_positions(0)
    t_start = time.perf_counter()

    sims = {"taichi": TaichiMPM88(ti), "diffgns": DiffgnsMPM88()}
    first_call = {}
    for name, sim in sims.items():  # compile (taichi JIT / XLA) + first segment
        sim.reset(x0)
        first_call[name] = timed(lambda s=sim: s.run(SCAN_LEN), sync=lambda _: None)[0]
    print(f"first {SCAN_LEN}-substep call (includes compilation): "
          + ", ".join(f"{k} {v:.2f} s" for k, v in first_call.items()), flush=True)

    check = physics_check(sims, x0, args.tol)
    for cp, row in check.items():
        r = row["rel_diff"]
        print(f"after {cp:>4} substeps: mean y diffgns {row['diffgns']['mean_y']:.5f} "
              f"taichi {row['taichi']['mean_y']:.5f} (rel diff {r['mean_y']:.2e}); "
              f"mean x rel diff {r['mean_x']:.2e}; std y rel diff {r['std_y']:.2e} -> "
              f"{'agree' if row['agree'] else 'DISAGREE'}", flush=True)

    # timing, from the common initial state, interleaved
    timing = interleaved_timing(sims, x0, seg, repeats)
    ratio = timing["diffgns"]["particle_substeps_per_s"] / timing["taichi"][
        "particle_substeps_per_s"]
    ratio_best = timing["diffgns"]["particle_substeps_per_s_best"] / timing["taichi"][
        "particle_substeps_per_s_best"]
    ratio_paired = paired_ratio(timing, "taichi")
    for name, t in timing.items():
        t["first_call_s"] = first_call[name]
    report(timing, repeats, seg)
    print(f"ratio diffgns / taichi throughput: {ratio:.3f} (ratio of medians), "
          f"{ratio_paired:.3f} (median of paired segments), {ratio_best:.3f} (best runs)",
          flush=True)

    single = None
    if not args.no_single_thread:
        # supplementary: Taichi restricted to one thread (XLA's scatter is serial, and on a
        # loaded 2-core machine a 2-thread parallel-for waits for its slowest thread)
        ti.reset()
        ti.init(arch=ti.cpu, default_fp=ti.f32, random_seed=0, cpu_max_num_threads=1)
        sims1 = {"taichi_1thread": TaichiMPM88(ti), "diffgns": sims["diffgns"]}
        t1 = interleaved_timing(sims1, x0, seg, repeats)
        r1 = t1["diffgns"]["particle_substeps_per_s"] / t1["taichi_1thread"][
            "particle_substeps_per_s"]
        print("supplementary run, Taichi with cpu_max_num_threads=1:")
        report(t1, repeats, seg)
        r1p = paired_ratio(t1, "taichi_1thread")
        print(f"ratio diffgns / taichi(1 thread) throughput: {r1:.3f} (ratio of medians), "
              f"{r1p:.3f} (median of paired segments)")
        single = {"timing": t1, "taichi_config": taichi_config(),
                  "ratio_diffgns_over_taichi_1thread": r1,
                  "ratio_diffgns_over_taichi_1thread_paired_median": r1p}
    total = time.perf_counter() - t_start
    agree = all(row["agree"] for row in check.values())
    print(f"physics agree within {args.tol:.0%}: {agree}; total {total:.1f} s")

    path = write_json("mpm_vs_taichi.json", {
        "benchmark": "mpm_vs_taichi",
        "skipped": False,
        "problem": {
            "n_particles": N_PARTICLES, "n_grid": N_GRID, "dx": DX, "dt": DT, "p_rho": P_RHO,
            "p_vol": P_VOL, "E": E, "gravity": GRAVITY, "bound": BOUND, "v0": V0,
            "init": "numpy default_rng(0).uniform(0.2, 0.6, (8192, 2)), float32",
            "dtype": "float32",
        },
        "taichi_config": ti_config,
        "diffgns_config": {"jit": f"lax.scan of {SCAN_LEN} substeps", "jax": jax.__version__,
                           "kernels": ["shape.stencil", "transfer.p2g",
                                       "transfer.grid_velocity", "boundaries.wall_slip",
                                       "transfer.g2p"]},
        "substeps_per_repeat": seg,
        "repeats": repeats,
        "timing": timing,
        "ratio_diffgns_over_taichi": ratio,
        "ratio_diffgns_over_taichi_best": ratio_best,
        "ratio_diffgns_over_taichi_paired_median": ratio_paired,
        "supplementary_taichi_single_thread": single,
        "physics_check": {"tolerance_rel": args.tol, "agree": agree, "checkpoints": check},
        "total_wall_s": total,
    }, machine)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
