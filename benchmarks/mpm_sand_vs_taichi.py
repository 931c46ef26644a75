"""diffgns' MPM vs Taichi (CPU) on the project's sand column (issue 22).

    .venv/bin/python benchmarks/mpm_sand_vs_taichi.py [--cells 45 [90]] [--repeats 9]
                                                      [--threads both]

The scene is ``column_collapse(cells_across=c)`` (width 0.1 m, aspect ratio 1, friction angle
30 deg, E = 2 MPa, nu = 0.3, rho = 1800 kg/m^3, 4 particles per cell; c = 45 gives 8,100
particles on a 194 x 59 node grid, c = 90 gives 32,400 on 377 x 109), float32, substep dt
from the scene's CFL rule (``scene.substep_dt``).

(a) diffgns: the library's public path, ``MPM(scene, dtype=float32)`` and
    ``rollout_jit(sim, params, state, n_frames=k)`` (a ``lax.scan`` of
    ``k * scene.substeps`` substeps under ``jax.jit``), as ``mpm_throughput.py`` runs it.
(b) Taichi: :meth:`diffgns.mpm.MPM.substep` transcribed into one ``@ti.kernel`` (four
    parallel loops: grid clear; per particle the trial F = F + dt C F, the Drucker-Prager
    return map on the Hencky strain through the same closed-form 2 x 2 SVD, and the MLS P2G
    with atomic adds; per node momentum -> velocity, gravity and the four box walls in the
    solver's order (slip left/right/top, Coulomb floor mu = 0.5); per particle the G2P with
    the APIC velocity gradient, advection and the clip to the domain), one kernel launch per
    substep, ``ti.init(arch=ti.cpu, default_fp=ti.f32, cpu_max_num_threads=<threads>)``. The
    material constants (Lame, DP alpha = sin(phi)/sqrt(2), apex) are computed in float32 as
    diffgns computes them from its float32 parameters; positions, volumes and masses are the
    scene's.

Physics check (before any timing): both run from the scene's initial state to each of
``--check-frames`` frames; the mean height, the runout (max x), the mean x and the mean speed
of the particles must agree within ``--tol`` (relative; float32 atomics reorder sums, so the
runs are not bitwise equal). A disagreement prints why and exits 1 without a ratio.

Speed (``benchmarks/protocol.py``, :mod:`diffgns.timing`): after a first (compiling) segment
each, ``--repeats`` interleaved rounds of one segment of ``--frames-per-repeat`` frames each;
throughput ratio diffgns / Taichi = median of the per-round ratios (wall and CPU time). With
``--threads both`` (the default) measured with 2 threads, then in a child pinned to one core
with one thread on both sides. Writes ``benchmarks/results/mpm_sand_vs_taichi.json``.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np
import protocol
from mpm_vs_taichi import taichi_config  # the same Taichi set-up record
from protocol import fmt_rate, warm_up_jax

from diffgns.timing import interleave, measure, no_sync

CHECK_FRAMES = (10, 40)
STAT_KEYS = ("mean_y", "max_x", "mean_x", "mean_speed")
F32 = np.float32


def sand_scene(cells: int):
    from diffgns.scene.builders import column_collapse

    return column_collapse(width=0.1, aspect_ratio=1.0, friction_angle=30.0,
                           cells_across=cells)


def material_constants(sim) -> dict:
    """The sand's constants in float32, computed as ``constitutive.drucker_prager`` computes
    them from diffgns' float32 parameters (one body: scalars)."""
    from diffgns.scene.materials import Sand

    bodies = sim.scene.bodies
    if len(bodies) != 1 or not isinstance(bodies[0].material, Sand):
        raise ValueError("the Taichi transcription covers one sand body")
    m = bodies[0].material
    E, nu = F32(m.E), F32(m.nu)
    one, two = F32(1.0), F32(2.0)
    mu = E / (two * (one + nu))
    lam = E * nu / ((one + nu) * (one - two * nu))
    phi = np.deg2rad(F32(m.friction_angle)).astype(F32)
    alpha = np.sin(phi) / np.sqrt(F32(2.0))
    k = two * lam + two * mu
    apex = two * F32(m.cohesion) * np.cos(phi) / (np.sin(phi) * k)
    return {"lam": float(lam), "mu": float(mu), "alpha": float(alpha), "k": float(k),
            "k_over_2mu": float(k / (two * mu)), "apex": float(apex), "rho": float(F32(m.rho)),
            "E": float(E), "nu": float(nu), "friction_angle_deg": float(m.friction_angle),
            "cohesion": float(m.cohesion)}


# ============================================================================ Taichi
class TaichiSand:
    """``MPM.substep`` of a one-body sand scene as a Taichi CPU program (one kernel launch
    per substep)."""

    def __init__(self, ti, sim):
        self.ti, self.sim = ti, sim
        parts = sim.scene.particles()
        self.x0 = np.asarray(parts["x"], F32)
        self.v0 = np.asarray(parts["v"], F32)
        self.vol = np.asarray(parts["vol"], F32)
        self.n = n = len(self.x0)
        self.mat = material_constants(sim)
        self.mass = (F32(self.mat["rho"]) * self.vol).astype(F32)  # rho[body] * vol
        f32 = ti.f32
        self.x = ti.Vector.field(2, f32, n)
        self.v = ti.Vector.field(2, f32, n)
        self.C = ti.Matrix.field(2, 2, f32, n)
        self.F = ti.Matrix.field(2, 2, f32, n)
        self.p_vol = ti.field(f32, n)
        self.p_mass = ti.field(f32, n)
        self.grid_mv = ti.Vector.field(2, f32, sim.grid_shape)
        self.grid_m = ti.field(f32, sim.grid_shape)
        self._substep = self._build()

    def _build(self):
        ti, sim, mat = self.ti, self.sim, self.mat
        x, v, C, F = self.x, self.v, self.C, self.F
        p_vol, p_mass, grid_mv, grid_m = self.p_vol, self.p_mass, self.grid_mv, self.grid_m
        scene = sim.scene
        dt, dx = sim.dt, sim.dx
        ox, oy = (float(F32(o)) for o in sim.origin)
        lox, loy = (float(F32(v_)) for v_ in sim.lo)
        hix, hiy = (float(F32(v_)) for v_ in sim.hi)
        gx, gy = (float(F32(g)) for g in scene.gravity)
        stress_k = dt * 4.0 / dx**2
        c_k = 4.0 / dx
        lam, mu = mat["lam"], mat["mu"]
        alpha, k_2mu, apex = mat["alpha"], mat["k_over_2mu"], mat["apex"]
        tiny = 1e-30  # linalg.tiny(float32)
        pad = scene.padding
        cx, cy = scene.n_cells

        @ti.func
        def quad_weights(fx):
            return ti.Matrix.rows([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2,
                                   0.5 * (fx - 0.5) ** 2])

        def make_wall(nx: float, ny: float, kind: str, mu_w: float):
            """boundaries._normal_bc for one wall (outward normal (nx, ny))."""
            @ti.func
            def wall(vel):
                out = vel
                if ti.static(kind == "sticky"):
                    out = ti.Vector.zero(ti.f32, 2)
                else:
                    vn = vel[0] * nx + vel[1] * ny
                    if vn < 0:
                        tx, ty = vel[0] - vn * nx, vel[1] - vn * ny
                        if ti.static(kind == "slip"):
                            out = ti.Vector([tx, ty])
                        else:
                            tn = ti.sqrt(tx * tx + ty * ty + tiny)
                            scale = ti.max(0.0, 1.0 + mu_w * vn / tn)
                            out = ti.Vector([tx * scale, ty * scale])
                return out

            return wall

        w_left, w_right, w_bottom, w_top = (
            make_wall(nx, ny, w.kind, float(F32(w.mu)))
            for (nx, ny), w in zip(((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)),
                                   scene.walls))

        @ti.func
        def drucker_prager(Ft):
            # linalg._svd_fwd_closed: F = U diag(s) V^T, U and V rotations
            a, b, c, d = Ft[0, 0], Ft[0, 1], Ft[1, 0], Ft[1, 1]
            e_, f_ = (a + d) / 2, (a - d) / 2
            g_, h_ = (c + b) / 2, (c - b) / 2
            q = ti.sqrt(e_ * e_ + h_ * h_)
            r = ti.sqrt(f_ * f_ + g_ * g_)
            a1 = ti.atan2(g_, f_)
            a2 = ti.atan2(h_, e_)
            theta = (a2 - a1) / 2
            ph = (a2 + a1) / 2
            cp, sp = ti.cos(ph), ti.sin(ph)
            ct, st = ti.cos(theta), -ti.sin(theta)
            U = ti.Matrix([[cp, -sp], [sp, cp]])
            V = ti.Matrix([[ct, -st], [st, ct]])
            e0 = ti.log(ti.max(q + r, 1e-4))
            e1 = ti.log(ti.max(q - r, 1e-4))
            # constitutive.drucker_prager (Klar et al. 2016)
            tr = e0 + e1
            tr_s = tr - apex
            h0, h1 = e0 - 0.5 * tr, e1 - 0.5 * tr
            hn = ti.sqrt(h0 * h0 + h1 * h1 + tiny)
            dgamma = hn + k_2mu * tr_s * alpha
            n0, n1 = e0, e1
            if tr_s >= 0:
                n0, n1 = 0.5 * apex, 0.5 * apex
            elif dgamma > 0:
                n0, n1 = e0 - dgamma * h0 / hn, e1 - dgamma * h1 / hn
            Fn = U @ ti.Matrix([[ti.exp(n0), 0.0], [0.0, ti.exp(n1)]]) @ V.transpose()
            trn = n0 + n1
            tau = U @ ti.Matrix([[2 * mu * n0 + lam * trn, 0.0],
                                 [0.0, 2 * mu * n1 + lam * trn]]) @ U.transpose()
            return tau, Fn

        @ti.kernel
        def substep():
            for I in ti.grouped(grid_m):
                grid_mv[I] = ti.Vector.zero(ti.f32, 2)
                grid_m[I] = 0.0
            # stress + particle -> grid (MLS)
            for p in x:
                Fp = F[p]
                tau, Fn = drucker_prager(Fp + dt * (C[p] @ Fp))
                F[p] = Fn
                mass = p_mass[p]
                X = ti.Vector([(x[p][0] - ox) / dx, (x[p][1] - oy) / dx])
                base = ti.cast(ti.floor(X - 0.5), ti.i32)
                fx = X - ti.cast(base, ti.f32)
                w = quad_weights(fx)
                affine = mass * C[p] - (stress_k * p_vol[p]) * tau
                mom = mass * v[p]
                for a, b in ti.static(ti.ndrange(3, 3)):
                    off = ti.Vector([a, b])
                    dpos = (ti.cast(off, ti.f32) - fx) * dx
                    wt = w[a, 0] * w[b, 1]
                    grid_mv[base + off] += wt * (mom + affine @ dpos)
                    grid_m[base + off] += wt * mass
            # grid update: velocity, gravity, walls (left, right, bottom, top)
            for i, j in grid_m:
                m = grid_m[i, j]
                inv = 0.0
                if m != 0:
                    inv = 1.0 / m
                vel = grid_mv[i, j] * inv
                vel += dt * ti.Vector([gx, gy])
                if i < pad + 1:
                    vel = w_left(vel)
                if i >= pad + cx:
                    vel = w_right(vel)
                if j < pad + 1:
                    vel = w_bottom(vel)
                if j >= pad + cy:
                    vel = w_top(vel)
                grid_mv[i, j] = vel
            # grid -> particle (APIC), advection, clip to the domain
            for p in x:
                X = ti.Vector([(x[p][0] - ox) / dx, (x[p][1] - oy) / dx])
                base = ti.cast(ti.floor(X - 0.5), ti.i32)
                fx = X - ti.cast(base, ti.f32)
                w = quad_weights(fx)
                nv = ti.Vector.zero(ti.f32, 2)
                nC = ti.Matrix.zero(ti.f32, 2, 2)
                for a, b in ti.static(ti.ndrange(3, 3)):
                    off = ti.Vector([a, b])
                    dcell = ti.cast(off, ti.f32) - fx
                    g = w[a, 0] * w[b, 1] * grid_mv[base + off]
                    nv += g
                    nC += g.outer_product(dcell)
                v[p] = nv
                C[p] = c_k * nC
                nx_ = x[p] + dt * nv
                x[p] = ti.Vector([ti.min(ti.max(nx_[0], lox), hix),
                                  ti.min(ti.max(nx_[1], loy), hiy)])

        return substep

    def reset(self):
        n = self.n
        eye = np.zeros((n, 2, 2), F32)
        eye[:, 0, 0] = eye[:, 1, 1] = 1.0
        self.x.from_numpy(self.x0)
        self.v.from_numpy(self.v0)
        self.C.from_numpy(np.zeros((n, 2, 2), F32))
        self.F.from_numpy(eye)
        self.p_vol.from_numpy(self.vol)
        self.p_mass.from_numpy(self.mass)
        self.ti.sync()

    def run(self, n_frames: int):
        for _ in range(n_frames * self.sim.n_sub):
            self._substep()
        self.ti.sync()

    def particles(self) -> tuple[np.ndarray, np.ndarray]:
        return self.x.to_numpy(), self.v.to_numpy()


# ============================================================================ diffgns
class DiffgnsSand:
    """The library's MPM: jitted rollout of ``seg_frames`` frames per call."""

    def __init__(self, sim, seg_frames: int):
        import jax

        from diffgns import rollout_jit

        self.jax, self.sim, self.seg = jax, sim, seg_frames
        self.params, self.state0 = sim.params(), sim.init()
        self._rollout = rollout_jit
        self.state = None

    def reset(self):
        self.state = self.jax.block_until_ready(self.state0)

    def run(self, n_frames: int):
        if n_frames % self.seg:
            raise ValueError(f"diffgns runs whole segments of {self.seg} frames")
        for _ in range(n_frames // self.seg):
            _, self.state = self._rollout(self.sim, self.params, self.state, n_frames=self.seg)
        self.jax.block_until_ready(self.state)

    def particles(self) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.state.x).T, np.asarray(self.state.v).T


# ============================================================================ driver
def stats_of(x: np.ndarray, v: np.ndarray) -> dict:
    return {"finite": bool(np.all(np.isfinite(x)) and np.all(np.isfinite(v))),
            "mean_y": float(np.mean(x[:, 1])), "max_x": float(np.max(x[:, 0])),
            "mean_x": float(np.mean(x[:, 0])),
            "mean_speed": float(np.mean(np.linalg.norm(v, axis=1)))}


def physics_check(sims: dict, checkpoints, tol: float) -> dict:
    """Run both from the scene's initial state; compare statistics at the checkpoints
    (frames)."""
    for sim in sims.values():
        sim.reset()
    out, done = {}, 0
    for cp in checkpoints:
        row = {}
        for name, sim in sims.items():
            sim.run(cp - done)
            row[name] = stats_of(*sim.particles())
        done = cp
        a, b = row["diffgns"], row["taichi"]
        rel = {k: abs(a[k] - b[k]) / abs(b[k]) for k in STAT_KEYS}
        row["rel_diff"] = rel
        row["failed"] = ([k for k in STAT_KEYS if not rel[k] <= tol]
                         + [f"{n} not finite" for n in ("diffgns", "taichi")
                            if not row[n]["finite"]])
        row["agree"] = not row["failed"]
        out[str(cp)] = row
    return out


def first_calls(sims: dict, seg: int) -> dict:
    """Wall and CPU seconds of each side's first segment (Taichi JIT / XLA compile + run)."""
    out = {}
    for name, sim in sims.items():
        sim.reset()
        s = measure(lambda sim=sim: sim.run(seg), sync=no_sync)[0]
        out[name] = {"first_call_s": s.wall_s, "first_call_cpu_s": s.cpu_s}
    return out


def timing_rounds(sims: dict, seg: int, repeats: int, work: int) -> dict:
    for sim in sims.values():
        sim.reset()
    res = interleave({k: (lambda s=s: s.run(seg)) for k, s in sims.items()}, repeats,
                     sync=no_sync)
    out = {"rounds": res.to_json()["rounds"], "timing": {}}
    for name in sims:
        t = res.summary(name)
        t.update(particle_substeps_per_s=work / t["median_s"],
                 particle_substeps_per_s_best=work / t["min_s"])
        out["timing"][name] = t
    out["ratio_diffgns_over_taichi"] = res.ratio("taichi", "diffgns")
    out["ratio_diffgns_over_taichi_cpu"] = res.ratio("taichi", "diffgns", cpu=True)
    out["ratio_of_medians"] = (out["timing"]["diffgns"]["particle_substeps_per_s"]
                               / out["timing"]["taichi"]["particle_substeps_per_s"])
    return out


def build(ti, cells: int, seg: int):
    import jax.numpy as jnp

    from diffgns import MPM

    scene = sand_scene(cells)
    sim = MPM(scene, dtype=jnp.float32)
    return scene, {"taichi": TaichiSand(ti, sim), "diffgns": DiffgnsSand(sim, seg)}


def measure_size(run: protocol.Run, ti, cells: int, args) -> tuple[dict, bool]:
    seg = args.frames_per_repeat
    scene, sims = build(ti, cells, seg)
    n, n_sub = scene.n_particles, scene.substeps
    run.print(f"sand column, cells_across={cells}: {n} particles, grid "
              f"{scene.grid_shape[0]} x {scene.grid_shape[1]}, dx {scene.dx:.3e} m, "
              f"dt {scene.substep_dt:.3e} s, {n_sub} substeps/frame")
    first = first_calls(sims, seg)
    run.print(f"first {seg}-frame call (includes compilation): " + ", ".join(
        f"{k} {v['first_call_s']:.2f} s" for k, v in first.items()))
    check = physics_check(sims, args.check_frames, args.tol)
    for cp, row in check.items():
        a, b, r = row["diffgns"], row["taichi"], row["rel_diff"]
        run.print(f"after {cp} frames ({int(cp) * n_sub} substeps): " + "; ".join(
            f"{k} diffgns {a[k]:.5g} taichi {b[k]:.5g} (rel {r[k]:.1e})" for k in STAT_KEYS)
            + f" -> {'agree' if row['agree'] else 'DISAGREE: ' + ', '.join(row['failed'])}")
    row = {"cells_across": cells, "n_particles": n, "grid_shape": list(scene.grid_shape),
           "diffgns_devices": len(sims["diffgns"].sim.devices or [0]),
           "dx_m": scene.dx, "substep_dt_s": scene.substep_dt, "substeps_per_frame": n_sub,
           "material": sims["taichi"].mat, "compile": first,
           "physics_check": {"tolerance_rel": args.tol, "statistics": list(STAT_KEYS),
                             "checkpoints_frames": check,
                             "agree": all(r["agree"] for r in check.values())}}
    if not row["physics_check"]["agree"]:
        return row, False
    work = n * n_sub * seg
    res = timing_rounds(sims, seg, args.repeats, work)
    for name, t in res["timing"].items():
        run.print(f"{name:>8}: {fmt_rate(t['particle_substeps_per_s'])} particle-substeps/s "
                  f"(median of {args.repeats} x {seg * n_sub} substeps; "
                  f"{1e6 * t['median_s'] / (seg * n_sub):.0f} us/substep; "
                  f"CPU/wall {t['cpu_over_wall']:.2f})")
    run.print(f"throughput ratio diffgns / taichi ({n} particles): "
              f"{res['ratio_diffgns_over_taichi']:.3f} (median of per-round ratios; CPU-time "
              f"ratio {res['ratio_diffgns_over_taichi_cpu']:.3f})")
    row.update(frames_per_repeat=seg, substeps_per_repeat=seg * n_sub, repeats=args.repeats,
               **res)
    return row, True


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, nargs="+", default=[45],
                    help="cells across the column (N = 4 c^2; 45 -> 8,100, 90 -> 32,400)")
    ap.add_argument("--repeats", type=int, default=9, help="timed rounds (>= 5)")
    ap.add_argument("--frames-per-repeat", type=int, default=2,
                    help="frames per timed segment (and per jitted diffgns call)")
    ap.add_argument("--check-frames", type=int, nargs="+", default=list(CHECK_FRAMES),
                    help="frames at which the physics is compared (multiples of "
                         "--frames-per-repeat)")
    ap.add_argument("--tol", type=float, default=0.03,
                    help="relative tolerance on mean height, runout, mean x and mean speed")
    ap.add_argument("--out", default="mpm_sand_vs_taichi.json")
    protocol.add_arguments(ap, threads="both")
    args = ap.parse_args(argv)
    run = protocol.start(args, "mpm_sand_vs_taichi")
    args.repeats = max(5, args.repeats)
    seg = args.frames_per_repeat
    args.check_frames = sorted(set(args.check_frames))
    if seg < 1 or any(c % seg for c in args.check_frames):
        ap.error("--check-frames must be multiples of --frames-per-repeat")
    try:
        import taichi as ti
    except Exception as e:  # ImportError or a broken install
        run.print(f"SKIPPED: taichi is not importable ({e!r}); `pip install taichi`")
        run.write(args.out, {"skipped": True, "reason": f"taichi not importable: {e!r}"})
        sys.exit(0)
    import jax

    warm_up_jax()
    ti.init(arch=ti.cpu, default_fp=ti.f32, random_seed=0, cpu_max_num_threads=run.threads)
    ti_config = taichi_config(ti)
    rows = []
    total, _ = measure(lambda: rows.extend(
        measure_size(run, ti, c, args) for c in args.cells), sync=lambda _: None)
    failed = [r for r, ok in rows if not ok]
    if failed:
        run.print("physics check FAILED (no ratio reported): " + "; ".join(
            f"{r['n_particles']} particles: " + ", ".join(
                f"{cp} frames: {', '.join(c['failed'])}"
                for cp, c in r["physics_check"]["checkpoints_frames"].items() if c["failed"])
            for r in failed), file=sys.stderr)
        sys.exit(1)
    sizes = [r for r, _ in rows]
    payload = {
        "scene": "column_collapse(width=0.1, aspect_ratio=1.0, friction_angle=30.0, "
                 "cells_across=c): sand, 4 ppc, Coulomb floor mu 0.5, slip walls",
        "dtype": "float32",
        "taichi_config": ti_config,
        "diffgns_config": {"path": "MPM(scene, dtype=float32) + rollout_jit(n_frames="
                                   f"{seg}) (lax.scan of substeps under jax.jit)",
                           "jax": jax.__version__,
                           "devices": [r["diffgns_devices"] for r in sizes]},
        "sizes": sizes, "total_wall_s": total.wall_s, "total_cpu_s": total.cpu_s,
    }
    ratios = {str(r["n_particles"]): r["ratio_diffgns_over_taichi"] for r in sizes}
    if run.mode == "both":
        one = payload["one_thread_pinned"] = run.pinned_child()
        r1 = {str(r["n_particles"]): r["ratio_diffgns_over_taichi"]
              for r in one.get("sizes", [])}
        payload["ratios"] = {"2_threads": ratios, "1_thread_pinned": r1 or None}
        for n, r2 in ratios.items():
            run.print(f"diffgns / taichi throughput, {n} particles: "
                      + protocol.both_ratios(r2, r1.get(n), one), tag=False)
    path = run.finish(args.out, payload)
    run.print(f"wrote {path}")


if __name__ == "__main__":
    main()
