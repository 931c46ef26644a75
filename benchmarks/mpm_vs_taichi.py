"""diffgns' MPM kernels vs Taichi (CPU) on the physics of Taichi's ``mpm88`` demo.

    .venv/bin/python benchmarks/mpm_vs_taichi.py [--repeats 9] [--threads both]

The problem (both implementations written here, float32): 8192 particles of a weakly
compressible "J-fluid" (Kirchhoff stress E (J - 1) I with E = 400, p_rho = 1,
particle volume (dx/2)^2), a 128 x 128 node grid with dx = 1/128, dt = 2e-4, gravity
9.8, initial velocity (0, -1), and slab walls 3 nodes thick (nodes i < 3 and
i > 128 - 3, same along y) that zero the velocity component pointing into the wall.
Initial positions: numpy ``default_rng(0)`` uniform in [0.2, 0.6]^2, shared by both.

(a) Taichi: four parallel loops in one ``@ti.kernel`` (grid clear, P2G with atomic adds,
    grid update, G2P), one kernel launch per substep, ``ti.init(arch=ti.cpu,
    cpu_max_num_threads=<threads>)``.
(b) diffgns (:class:`DiffgnsJFluid`, shared with ``mpm3d_vs_taichi.py``): ``shape.stencil``
    -> ``transfer.p2g`` -> ``transfer.grid_velocity`` -> gravity -> ``boundaries.wall_slip``
    on the four slabs -> ``transfer.g2p``, in the
    component-major layout ((2, N) vectors, (2, 2, N) matrices), 50 substeps in a
    ``lax.scan`` under ``jax.jit``, the particles split over the process's host devices
    as ``MPM(scene)`` does by default (``jax.shard_map``, one ``psum`` of the grids per
    substep; two devices at 2 threads, one in the pinned 1-thread run).

Speed (``benchmarks/protocol.py``, ``benchmarks/timing.py``): after a first (compiling)
segment each, ``--repeats`` rounds; a round times one segment of ``--substeps-per-repeat``
substeps of each implementation, the order alternating round by round, so both see the same
machine load. The throughput ratio diffgns / Taichi is the median of the per-round ratios.
With ``--threads both`` (the default) it is measured with 2 threads (XLA's default, Taichi
``cpu_max_num_threads=2``), then again in a child process pinned to one core with one thread
on both sides; the report gives both ratios, wall and CPU time side by side.
(c) Independent driver: Taichi's own ``examples/simulation/mpm88.py`` from the installed
    package (its kernel unchanged, ``arch=ti.cpu``, no GUI), timed in the same rounds; its
    ratio is reported beside (b)/(a) so that a slip in (a)'s transcription would show.
Physics check: both are run 500 and 2000 substeps from the same start; mean particle
positions must agree within ``--tol`` (relative). Writes
``benchmarks/results/mpm_vs_taichi.json``.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from typing import Any

import numpy as np
import protocol
from protocol import fmt_rate

from diffgns.timing import interleave, measure, no_sync

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


class TaichiShippedExample:
    """Independent driver: Taichi's own ``examples/simulation/mpm88.py`` as installed with
    the ``taichi`` package, run unchanged except ``arch=ti.cpu`` with the thread setting
    and without its GUI loop (its ``substep`` kernel and ``init`` are what is called). Its
    initial positions come from ``ti.random``, so it is timed only, never compared."""

    def __init__(self, ti, threads: int, workdir: str):
        import importlib.util
        from pathlib import Path

        src = (Path(ti.__path__[0]) / "examples" / "simulation" / "mpm88.py").read_text()
        head, sep, _ = src.partition("init()\ngui")
        if not sep or "ti.init(arch=ti.gpu)" not in head:
            raise RuntimeError("Taichi's mpm88 example changed shape; cannot drive it")
        head = head.replace("ti.init(arch=ti.gpu)", "pass  # ti.init done by the benchmark")
        path = Path(workdir) / "taichi_mpm88_example.py"  # Taichi needs a real source file
        path.write_text(head)
        spec = importlib.util.spec_from_file_location("taichi_mpm88_example", path)
        self.module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(self.module)
        self.ti = ti

    def reset(self, x0=None):
        self.module.init()
        self.ti.sync()

    def run(self, n_substeps: int):
        for _ in range(n_substeps):
            self.module.substep()
        self.ti.sync()


# ============================================================================ diffgns
class DiffgnsJFluid:
    """The J-fluid physics of Taichi's mpm88/mpm3d from diffgns' transfer kernels, in ``dim``
    2 or 3, component-major, scanned + jitted (``n_grid`` nodes per axis, time step ``dt``,
    particle volume ``(dx/2)^2`` as both Taichi examples write it, in 3D too)."""

    def __init__(self, dim: int = 2, n_grid: int = N_GRID, dt: float = DT,
                 n_particles: int = N_PARTICLES):
        import jax
        import jax.numpy as jnp
        from jax.sharding import Mesh
        from jax.sharding import PartitionSpec as Spec

        from diffgns.mpm.boundaries import wall_slip
        from diffgns.mpm.shape import stencil
        from diffgns.mpm.transfer import g2p, grid_velocity, p2g

        self.jax, self.jnp, self.dim = jax, jnp, dim
        f32 = jnp.float32
        dx = 1.0 / n_grid
        p_vol = (0.5 * dx) ** 2
        p_mass = P_RHO * p_vol
        n_nodes = n_grid**dim
        stress_k = dt * 4.0 / dx**2 * p_vol
        # (slab of the node grid, outward normal of the wall surface): nodes i < BOUND and
        # i > n_grid - BOUND along each axis
        slabs = []
        for a in range(dim):
            for sl, side in ((slice(None, BOUND), 1.0), (slice(n_grid - BOUND + 1, None), -1.0)):
                idx = [slice(None)] * dim
                idx[a] = sl
                slabs.append((tuple(idx), tuple(side if b == a else 0.0 for b in range(dim))))

        def substep(state, _):
            x, v, C, J = state
            mass = jnp.full(x.shape[1:], p_mass, f32)
            idx, w, dpos = stencil(x / dx, (n_grid,) * dim)
            tau = E * (J - 1.0)  # Kirchhoff stress tau * I
            affine = p_mass * C
            for a in range(dim):
                affine = affine.at[a, a].add(-stress_k * tau)
            grid = p2g(idx, w, dpos, mass, mass * v, affine, n_nodes, dx)
            if axis is not None:  # sharded as MPM(scene) on two host devices: sum the grids
                grid = jax.lax.psum(grid, axis)
            gv = grid_velocity(grid)
            gv = gv.at[1].add(-dt * GRAVITY).reshape(dim, *(n_grid,) * dim)
            for sl, normal in slabs:
                comps = wall_slip(tuple(gv[c][sl] for c in range(dim)), normal)
                gv = gv.at[(slice(None), *sl)].set(jnp.stack(comps))
            v, C = g2p(idx, w, dpos, gv, dx)
            x = x + dt * v
            J = J * (1.0 + dt * sum(C[a, a] for a in range(dim)))
            return (x, v, C, J), None

        # the library's default: the devices MPM(scene) would pick for this many particles
        # (diffgns.hostdevices.mpm_devices: two on a 2-core CPU, one when pinned to a core),
        # one psum of the grids per substep as in MPM._substep
        from diffgns.hostdevices import mpm_devices

        self.devices = mpm_devices("auto", n_particles, dim) or jax.local_devices()[:1]
        axis = "p" if len(self.devices) > 1 else None

        def scan(state):
            return jax.lax.scan(substep, state, None, length=SCAN_LEN)[0]

        if axis is not None:
            spec = (Spec(None, axis), Spec(None, axis), Spec(None, None, axis), Spec(axis))
            scan = jax.shard_map(scan, mesh=Mesh(np.array(self.devices), (axis,)),
                                 in_specs=(spec,), out_specs=spec)
        self._run_scan = jax.jit(scan)
        self.state = None
        self.v0 = V0 if dim == 2 else (0.0,) * dim

    def reset(self, x0: np.ndarray):
        jnp, d = self.jnp, self.dim
        n = len(x0)
        if len(self.devices) > 1 and n % len(self.devices):
            raise ValueError(f"{n} particles do not split over {len(self.devices)} devices")
        x = jnp.asarray(x0.T, jnp.float32)
        v = jnp.broadcast_to(jnp.asarray(self.v0, jnp.float32)[:, None], (d, n))
        self.state = self.jax.block_until_ready(
            (x, v, jnp.zeros((d, d, n), jnp.float32), jnp.ones(n, jnp.float32)))

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


def first_calls(sims: dict, x0: np.ndarray) -> dict:
    """Wall and CPU seconds of each implementation's first segment (Taichi JIT / XLA
    compile + one scan of SCAN_LEN substeps), timed apart."""
    out = {}
    for name, sim in sims.items():
        sim.reset(x0)
        s = measure(lambda sim=sim: sim.run(SCAN_LEN), sync=no_sync)[0]
        out[name] = {"first_call_s": s.wall_s, "first_call_cpu_s": s.cpu_s}
    return out


def timing_rounds(sims: dict, x0: np.ndarray, seg: int, repeats: int,
                  n_particles: int = N_PARTICLES) -> dict:
    """Reset both to x0, then interleaved rounds of one ``seg``-substep segment each (the
    first segment of each, timed apart, compiles/warms up). Throughput ratio diffgns /
    Taichi = median over rounds of t_taichi / t_diffgns."""
    for sim in sims.values():
        sim.reset(x0)
    res = interleave({k: (lambda s=s: s.run(seg)) for k, s in sims.items()}, repeats,
                     sync=no_sync)
    work = n_particles * seg
    out = {"rounds": res.to_json()["rounds"], "timing": {}}
    for name in sims:
        t = res.summary(name)
        t.update(particle_substeps_per_s=work / t["median_s"],
                 particle_substeps_per_s_best=work / t["min_s"],
                 us_per_substep=1e6 * t["median_s"] / seg)
        out["timing"][name] = t
    out["ratio_diffgns_over_taichi"] = res.ratio("taichi", "diffgns")
    out["ratio_diffgns_over_taichi_cpu"] = res.ratio("taichi", "diffgns", cpu=True)
    if "taichi_example" in sims:
        out["ratio_diffgns_over_taichi_example"] = res.ratio("taichi_example", "diffgns")
    out["ratio_of_medians"] = (out["timing"]["diffgns"]["particle_substeps_per_s"]
                               / out["timing"]["taichi"]["particle_substeps_per_s"])
    return out


def report(run: protocol.Run, res: dict, repeats: int, seg: int) -> None:
    for name, t in res["timing"].items():
        run.print(f"{name:>8}: {fmt_rate(t['particle_substeps_per_s'])} "
                  f"particle-substeps/s (median of {repeats} x {seg} substeps; "
                  f"{t['us_per_substep']:.0f} us/substep; CPU/wall {t['cpu_over_wall']:.2f})")
    run.print("throughput ratio diffgns / taichi: "
              f"{res['ratio_diffgns_over_taichi']:.3f} (median of per-round ratios; "
              f"CPU-time ratio {res['ratio_diffgns_over_taichi_cpu']:.3f})")
    if "ratio_diffgns_over_taichi_example" in res:
        run.print("throughput ratio diffgns / Taichi's shipped mpm88 example (independent "
                  f"driver): {res['ratio_diffgns_over_taichi_example']:.3f}")


def skip(run: protocol.Run, reason: str, out: str):
    run.print(f"SKIPPED: {reason}")
    path = run.write(out, {"skipped": True, "reason": reason})
    run.print(f"wrote {path}")
    sys.exit(0)


def taichi_config(ti) -> dict:
    """Read now: the config object is freed by ti.reset()."""
    from taichi.lang import impl

    cfg = impl.current_cfg()
    return {"arch": str(cfg.arch), "cpu_max_num_threads": cfg.cpu_max_num_threads,
            "default_fp": str(cfg.default_fp), "offline_cache": bool(cfg.offline_cache),
            "launch": "one @ti.kernel (4 parallel loops) per substep"}


def add_options(ap: argparse.ArgumentParser, out: str) -> None:
    """The options of both Taichi comparisons (this one and ``mpm3d_vs_taichi.py``), beside
    the protocol's (``protocol.add_arguments(ap, threads="both")``)."""
    ap.add_argument("--repeats", type=int, default=9, help="timed rounds (>= 5)")
    ap.add_argument("--substeps-per-repeat", type=int, default=100,
                    help=f"substeps per timed segment (a multiple of {SCAN_LEN})")
    ap.add_argument("--tol", type=float, default=0.03,
                    help="relative tolerance on mean particle x and y")
    ap.add_argument("--out", default=out)


def start_taichi(ap: argparse.ArgumentParser, args, run: protocol.Run):
    """Check the options, import Taichi (or write a skipped record and exit); returns
    ``ti`` initialised on the CPU at the run's threads."""
    if args.substeps_per_repeat % SCAN_LEN or args.substeps_per_repeat < SCAN_LEN:
        ap.error(f"--substeps-per-repeat must be a positive multiple of {SCAN_LEN}")
    try:
        import taichi as ti
    except Exception as e:  # ImportError or a broken install
        skip(run, f"taichi is not importable ({e!r}); install it with `pip install taichi` "
             "(the `bench` extra)", args.out)
    ti.init(arch=ti.cpu, default_fp=ti.f32, random_seed=0, cpu_max_num_threads=run.threads)
    return ti


def compare(run: protocol.Run, args, sims: dict, timed: dict, x0: np.ndarray,
            n_particles: int = N_PARTICLES) -> tuple[dict, dict, dict, Any, bool]:
    """First calls, the physics check of ``sims`` ("taichi", "diffgns") from ``x0``, then
    interleaved timing rounds of ``timed``; printed as they come. Returns
    ``(first, check, res, total, agree)``."""
    seg, repeats = args.substeps_per_repeat, max(5, args.repeats)

    def body():
        first = first_calls(sims, x0)
        run.print(f"first {SCAN_LEN}-substep call (includes compilation): " + ", ".join(
            f"{k} {v['first_call_s']:.2f} s" for k, v in first.items()))
        check = physics_check(sims, x0, args.tol)
        for cp, row in check.items():
            r = row["rel_diff"]
            run.print(f"after {cp:>4} substeps: mean y diffgns {row['diffgns']['mean_y']:.5f} "
                      f"taichi {row['taichi']['mean_y']:.5f} (rel diff {r['mean_y']:.2e}); "
                      f"mean x rel diff {r['mean_x']:.2e}; std y rel diff {r['std_y']:.2e} -> "
                      f"{'agree' if row['agree'] else 'DISAGREE'}")
        return first, check, timing_rounds(timed, x0, seg, repeats, n_particles)

    total, (first, check, res) = measure(body, sync=lambda _: None)
    report(run, res, repeats, seg)
    agree = all(row["agree"] for row in check.values())
    run.print(f"physics agree within {args.tol:.0%}: {agree}; total {total.wall_s:.1f} s "
              f"(CPU {total.cpu_s:.1f} s)")
    return first, check, res, total, agree


def close(run: protocol.Run, args, payload: dict, first, check, res, total, agree) -> None:
    """Add the common record, run the pinned 1-thread variant (``--threads both``), write."""
    payload.update({
        "substeps_per_repeat": args.substeps_per_repeat, "repeats": max(5, args.repeats),
        "compile": first, **res,
        "physics_check": {"tolerance_rel": args.tol, "agree": agree, "checkpoints": check},
        "total_wall_s": total.wall_s, "total_cpu_s": total.cpu_s})
    if run.mode == "both":
        one = payload["one_thread_pinned"] = run.pinned_child()
        r2, r1 = res["ratio_diffgns_over_taichi"], one.get("ratio_diffgns_over_taichi")
        payload["ratios"] = {"2_threads": r2, "1_thread_pinned": r1}
        run.print("diffgns / taichi throughput: " + protocol.both_ratios(r2, r1, one),
                  tag=False)
    path = run.finish(args.out, payload)
    run.print(f"wrote {path}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_options(ap, "mpm_vs_taichi.json")
    protocol.add_arguments(ap, threads="both")
    args = ap.parse_args(argv)
    run = protocol.start(args, "mpm_vs_taichi")
    ti = start_taichi(ap, args, run)
    import jax

    ti_config = taichi_config(ti)
    x0 = initial_positions(0)
    sims = {"taichi": TaichiMPM88(ti), "diffgns": DiffgnsJFluid()}
    workdir = tempfile.mkdtemp(prefix="mpm88_")
    try:
        timed = {**sims, "taichi_example": TaichiShippedExample(ti, run.threads, workdir)}
    except (OSError, RuntimeError, AttributeError) as e:
        run.print(f"Taichi's shipped mpm88 example not driven: {e}")
        timed = sims
    first, check, res, total, agree = compare(run, args, sims, timed, x0)
    payload = {
        "problem": {
            "n_particles": N_PARTICLES, "n_grid": N_GRID, "dx": DX, "dt": DT, "p_rho": P_RHO,
            "p_vol": P_VOL, "E": E, "gravity": GRAVITY, "bound": BOUND, "v0": V0,
            "init": "numpy default_rng(0).uniform(0.2, 0.6, (8192, 2)), float32",
            "dtype": "float32",
        },
        "taichi_config": ti_config,
        "diffgns_config": {"jit": f"lax.scan of {SCAN_LEN} substeps", "jax": jax.__version__,
                           "devices": len(sims["diffgns"].devices),
                           "kernels": ["shape.stencil", "transfer.p2g",
                                       "transfer.grid_velocity", "boundaries.wall_slip",
                                       "transfer.g2p"]},
    }
    close(run, args, payload, first, check, res, total, agree)


if __name__ == "__main__":
    main()
