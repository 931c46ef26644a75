"""diffgns' 3D MPM kernels vs Taichi's shipped ``mpm3d`` example (CPU), issue 24.

    .venv/bin/python benchmarks/mpm3d_vs_taichi.py [--n-grid 32] [--repeats 9] [--threads both]

The problem is Taichi's own ``examples/simulation/mpm3d.py`` as installed with the
``taichi`` package: a weakly compressible "J-fluid" (Kirchhoff stress E (J - 1) I, E = 400,
p_rho = 1, particle volume (dx/2)^2 as the example writes it), ``n_grid^3 / 4`` particles on
an ``n_grid^3`` node grid (the example's settings: n_grid 32 -> 8,192 particles, dt 4e-4;
64 -> 65,536, dt 2e-4), gravity 9.8, slab walls 3 nodes thick.

(a) Taichi: the example's ``substep`` kernel, unchanged (its source is read from the
    installed package; only ``ti.init(arch=ti.gpu)`` becomes the benchmark's
    ``ti.init(arch=ti.cpu, cpu_max_num_threads=<threads>)`` and its ``dim, n_grid, steps,
    dt`` line is set to the chosen row of the example's own table).
(b) diffgns: the same physics from its dimension-generic transfer kernels
    (:class:`mpm_vs_taichi.DiffgnsJFluid` with ``dim=3``: ``shape.stencil`` (27 nodes) ->
    ``transfer.p2g`` -> ``transfer.grid_velocity`` -> gravity -> ``boundaries.wall_slip`` on
    six slabs -> ``transfer.g2p``), 50 substeps per ``lax.scan`` under ``jax.jit``, split over
    the host devices as in ``mpm_vs_taichi.py`` (two at 2 threads, one pinned).

Both start from the same particles (numpy ``default_rng(0)`` uniform in [0.15, 0.55]^3, the
example's box, written into the example's fields); mean and spread of the positions after
500 and 2000 substeps must agree within ``--tol``. Timing follows ``benchmarks/protocol.py``
(quiet machine, interleaved rounds, 2 threads and one thread pinned). Writes
``benchmarks/results/mpm3d_vs_taichi.json``.
"""
from __future__ import annotations

import argparse
import importlib.util
import tempfile
from pathlib import Path

import numpy as np
import protocol
from mpm_vs_taichi import (
    SCAN_LEN,
    DiffgnsJFluid,
    add_options,
    close,
    compare,
    start_taichi,
    taichi_config,
)

# the rows of the example's own table of 3D settings: n_grid -> dt
EXAMPLE_ROWS = {32: 4e-4, 64: 2e-4, 128: 8e-5}


class TaichiMPM3DExample:
    """Taichi's shipped ``examples/simulation/mpm3d.py``: its fields and ``substep`` kernel,
    unchanged except the ``ti.init`` call and the settings line (one row of its own table)."""

    def __init__(self, ti, n_grid: int, workdir: str):
        src = (Path(ti.__path__[0]) / "examples" / "simulation" / "mpm3d.py").read_text()
        head, sep, _ = src.partition("\ndef T(a):")
        line = "dim, n_grid, steps, dt = 3, 32, 25, 4e-4"
        if not sep or "ti.init(arch=ti.gpu)" not in head or line not in head:
            raise RuntimeError("Taichi's mpm3d example changed shape; cannot drive it")
        head = head.replace("ti.init(arch=ti.gpu)", "pass  # ti.init done by the benchmark")
        head = head.replace(line, f"dim, n_grid, steps, dt = 3, {n_grid}, 25, "
                            f"{EXAMPLE_ROWS[n_grid]!r}")
        path = Path(workdir) / "taichi_mpm3d_example.py"  # Taichi needs a real source file
        path.write_text(head)
        spec = importlib.util.spec_from_file_location("taichi_mpm3d_example", path)
        assert spec is not None and spec.loader is not None
        self.module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(self.module)
        self.ti = ti
        self.n_particles = int(self.module.n_particles)

    def reset(self, x0: np.ndarray):
        m = self.module
        n = len(x0)
        m.F_x.from_numpy(x0)
        m.F_v.from_numpy(np.zeros((n, 3), np.float32))
        m.F_C.from_numpy(np.zeros((n, 3, 3), np.float32))
        m.F_J.from_numpy(np.ones(n, np.float32))
        self.ti.sync()

    def run(self, n_substeps: int):
        for _ in range(n_substeps):
            self.module.substep()
        self.ti.sync()

    def positions(self) -> np.ndarray:
        return self.module.F_x.to_numpy()


def initial_positions(n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) float32 positions uniform in [0.15, 0.55]^3 (the example's ``init`` box)."""
    return np.random.default_rng(seed).uniform(0.15, 0.55, (n, 3)).astype(np.float32)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-grid", type=int, default=32, choices=sorted(EXAMPLE_ROWS),
                    help="nodes per axis: a row of the example's table (default 32)")
    add_options(ap, "mpm3d_vs_taichi.json")
    protocol.add_arguments(ap, threads="both")
    args = ap.parse_args(argv)
    run = protocol.start(args, "mpm3d_vs_taichi")
    ti = start_taichi(ap, args, run)
    import jax

    ti_config = taichi_config(ti)
    example = TaichiMPM3DExample(ti, args.n_grid, tempfile.mkdtemp(prefix="mpm3d_"))
    n = example.n_particles
    x0 = initial_positions(n)
    sims = {"taichi": example,
            "diffgns": DiffgnsJFluid(dim=3, n_grid=args.n_grid, dt=EXAMPLE_ROWS[args.n_grid],
                                     n_particles=n)}
    first, check, res, total, agree = compare(run, args, sims, sims, x0, n_particles=n)
    payload = {
        "problem": {"source": "taichi examples/simulation/mpm3d.py", "dim": 3,
                    "n_particles": n, "n_grid": args.n_grid, "dt": EXAMPLE_ROWS[args.n_grid],
                    "E": float(example.module.E), "p_vol": float(example.module.p_vol),
                    "init": f"numpy default_rng(0).uniform(0.15, 0.55, ({n}, 3)), float32",
                    "dtype": "float32"},
        "taichi_config": ti_config,
        "diffgns_config": {"jit": f"lax.scan of {SCAN_LEN} substeps", "jax": jax.__version__,
                           "kernels": "mpm_vs_taichi.DiffgnsJFluid(dim=3)",
                           "devices": len(sims["diffgns"].devices)},
    }
    close(run, args, payload, first, check, res, total, agree)


if __name__ == "__main__":
    main()
