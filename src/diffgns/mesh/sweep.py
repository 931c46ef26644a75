"""Reynolds-number sweeps on ONE cylinder geometry and ONE mesh: the learnable MeshGraphNet task.

Issue 23: the earlier datasets drew geometry, Reynolds number and inflow per flow on ~2,100-node
meshes and the network never learnt to shed. A sweep fixes what the network need not learn:

* the Schäfer-Turek channel (2.2 x 0.41 m, cylinder D = 0.1 m at (0.2, 0.2) m) and one coarse
  mesh (~1,300 vertices, :data:`COARSE_MESH`; checked against the 2,121-vertex dataset mesh and
  Schäfer-Turek 2D-2 in ``docs/guides/meshnet.md``);
* the peak inflow speed ``Um`` (1.5 m/s by default, ``Ubar = 1`` m/s); only the viscosity
  changes, ``nu = Ubar D / Re``, so the network's ln(nu) input is ln(Re) up to a constant;
* a frame interval of 0.02 s: ~14-17 frames per shedding period for Re 100-250 (St 0.30-0.36
  at ``Ubar / D = 10`` Hz).

One long trajectory per Reynolds number, stored after a spin-up (a short spin pulse of the
cylinder, ``kick``, breaks the symmetry so shedding starts within a few periods); training
cuts it into windows (one-step samples or K-frame unrolls). Trajectory ``i`` is the CFD run
of ``reynolds[i]``, independent of the others, so runs go to ``workers`` processes (one core
each) and an interrupted sweep resumes by skipping stored keys
(:class:`~diffgns.mesh.dataset.CylinderDatasetWriter`). The CFD is deterministic, so a
trajectory already stored in another sweep file of the same recipe (``reuse``, matched by
Re) is copied from it instead of run again: one wide sweep can feed the narrower training
files of earlier stages in seconds.

Command line (``make meshnet-data`` runs the training and held-out sweeps)::

    python -m diffgns.mesh.sweep --out data/sweep_train.h5 --re 100 125 150 175 200 225 250
"""
from __future__ import annotations

import argparse
import json
import math
import os
import signal
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from diffgns.errors import InputError, Interrupted, run_module
from diffgns.io.dataset import read_metadata
from diffgns.mesh.datagen import CylinderRun, simulate_case
from diffgns.mesh.dataset import CylinderDatasetWriter, iter_cylinder_dataset

#: mesh settings of the sweep (vertex count and the check against the finer meshes in the
#: guide): edge 0.01 m at the cylinder, 0.02 m along 1 m of wake, at most 0.045 m elsewhere.
COARSE_MESH = dict(size_cylinder=0.01, size_far=0.045, grading=0.3, size_wake=0.02)

#: convective CFL of the sweep's time step. At 0.15 (the CylinderRun default) the runs at
#: Re 200, 225 and 250 blew up during the spin pulse (t = 0.22-0.28 s, |u| > 10 Um; measured
#: 2026-12-03), Re 250 also with half the pulse; at 0.075 all three pass it.
SWEEP_CFL = 0.075

#: Reynolds numbers of ``make meshnet-data``: training (7, evenly spaced over 100-250) and
#: held-out (3 between training values, 2 outside the range).
TRAIN_RE = (100.0, 125.0, 150.0, 175.0, 200.0, 225.0, 250.0)
HELDOUT_RE = (110.0, 165.0, 220.0, 85.0, 275.0)


def sweep_run(n_frames: int = 201, frame_dt: float = 0.02, spinup: float = 20.0
              ) -> CylinderRun:
    """The CFD run of every sweep trajectory: ``n_frames`` frames ``frame_dt`` s apart after
    ``spinup`` D / Ubar, the coarse mesh, a spin pulse of peak surface speed Ubar over 0.3 s,
    and the sweep's time step (:data:`SWEEP_CFL`). ValueError on invalid values."""
    return CylinderRun(n_frames=n_frames, frame_dt=frame_dt, spinup=spinup, kick=1.0,
                       kick_time=0.3, cfl=SWEEP_CFL, **COARSE_MESH)


@dataclass(frozen=True)
class Sweep:
    """A Reynolds-number sweep (SI units).

    Attributes:
        reynolds: ``Re = Ubar D / nu`` of each trajectory, in order (> 0).
        u_max: peak inflow speed ``Um``, m/s (``Ubar = 2 Um / 3``).
        radius, center, length, height: the cylinder and the channel, m.
        run: frames, frame interval, spin-up (in ``D / Ubar``), mesh sizes, CFL and kick
            (:class:`~diffgns.mesh.datagen.CylinderRun`).
    """

    reynolds: tuple[float, ...]
    u_max: float = 1.5
    radius: float = 0.05
    center: tuple[float, float] = (0.2, 0.2)
    length: float = 2.2
    height: float = 0.41
    run: CylinderRun = field(default_factory=lambda: sweep_run())

    def __post_init__(self):
        re = tuple(float(r) for r in self.reynolds)
        if not re or not all(math.isfinite(r) and r > 0 for r in re):
            raise InputError("--re", f"Reynolds numbers must be positive numbers, got "
                             f"{self.reynolds}", "give at least one Re > 0")
        object.__setattr__(self, "reynolds", re)
        for name in ("u_max", "radius", "length", "height"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InputError(f"--{name.replace('_', '-')}", f"must be > 0, got {v}")

    def case(self, i: int) -> dict:
        """Case dict of trajectory ``i`` (the keys :func:`simulate_case` reads)."""
        u_bar = 2.0 * self.u_max / 3.0
        re = self.reynolds[i]
        return dict(reynolds=re, u_max=self.u_max, nu=u_bar * 2.0 * self.radius / re,
                    radius=self.radius, center=list(self.center), length=self.length,
                    height=self.height)


def _simulate(job: tuple[int, dict, CylinderRun]) -> tuple[int, dict, dict, float]:
    """One CFD run in a worker process: (index, arrays, attrs, wall seconds)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops the pool
    i, case, run = job
    t0 = time.perf_counter()
    arrays, attrs = simulate_case(case, run)
    return i, arrays, attrs, time.perf_counter() - t0


def reusable(source: str | Path, sweep: Sweep) -> dict[float, str]:
    """``{Re: key}`` of the trajectories stored in the finished sweep file ``source`` whose
    recipe equals ``sweep``'s in everything but the Reynolds numbers (InputError otherwise:
    another mesh, frame interval, spin-up, channel or inflow would be different data)."""
    try:
        theirs = dict(read_metadata(source).get("sweep") or {})
    except (OSError, ValueError) as e:
        raise InputError("--reuse", f"{source}: not a finished sweep file ({e})") from None
    if not theirs:
        raise InputError("--reuse", f"{source}: not a sweep file (no 'sweep' recipe)")
    ours = asdict(sweep)
    res = [float(r) for r in theirs.pop("reynolds")]
    ours.pop("reynolds")
    theirs = json.loads(json.dumps(theirs))  # tuples as lists, as stored
    if theirs != json.loads(json.dumps(ours)):
        diff = sorted(k for k in ours if json.loads(json.dumps(ours[k])) != theirs.get(k))
        raise InputError("--reuse", f"{source}: another sweep recipe (differs in {diff})",
                         "reuse only a sweep with the same mesh, frames and channel")
    return {r: f"{i:05d}" for i, r in enumerate(res)}


def generate_sweep(path: str | Path, sweep: Sweep, workers: int = 2,
                   progress: bool = True, reuse: str | Path | None = None) -> dict:
    """Write the trajectories of ``sweep`` to ``path`` (HDF5 + metadata; staged as
    ``<path>.partial`` until complete; resumes). ``reuse``: a finished sweep file of the
    same recipe whose trajectories at the same Re are copied instead of computed
    (:func:`reusable`). Returns ``{"wall_s": total wall seconds, "cases": [(key, Re, CFD
    seconds, Strouhal, lift drift), ...]}`` for the runs made now, and ``"reused"``: the
    number of trajectories copied."""
    if not (isinstance(workers, int) and workers >= 1):
        raise InputError("--workers", f"must be a count >= 1, got {workers}")
    recipe = dict(kind="cylinder-sweep", **asdict(sweep))
    source = {} if reuse is None else reusable(reuse, sweep)
    t0, done, copied = time.perf_counter(), [], 0
    with CylinderDatasetWriter(path, metadata_extra=dict(sweep=asdict(sweep)), recipe=recipe,
                               staged=True) as w:
        todo = [i for i in range(len(sweep.reynolds)) if not w.has(f"{i:05d}")]
        wanted = {source[sweep.reynolds[i]]: i for i in todo if sweep.reynolds[i] in source}
        if wanted and reuse is not None:
            for key, arrays, attrs in iter_cylinder_dataset(reuse):
                if key in wanted:
                    i = wanted[key]
                    w.write(f"{i:05d}", arrays, dict(attrs, index=i))
                    copied += 1
            todo = [i for i in todo if i not in wanted.values()]
        if todo:
            pool = get_context("spawn").Pool(min(workers, len(todo)))
            try:
                jobs = [(i, sweep.case(i), sweep.run) for i in todo]
                for i, arrays, attrs, secs in pool.imap_unordered(_simulate, jobs):
                    w.write(f"{i:05d}", arrays, dict(attrs, index=i))
                    done.append((f"{i:05d}", sweep.reynolds[i], round(secs, 1),
                                 attrs["strouhal"], attrs["cl_amplitude_drift"]))
                    if progress:
                        print(f"  Re {sweep.reynolds[i]:g}: {secs:.0f} s, St "
                              f"{attrs['strouhal']:.4f}, lift drift "
                              f"{attrs['cl_amplitude_drift']:.3f}", flush=True)
            finally:  # normal end, an error or SIGTERM/SIGINT: no CFD process outlives us
                pool.terminate()
                pool.join()
        w.finalize()
    return dict(wall_s=time.perf_counter() - t0, cases=sorted(done), reused=copied)


def draw_reynolds(lo: float, hi: float, n: float, seed: int) -> tuple[float, ...]:
    """``n`` Reynolds numbers uniform in ``[lo, hi]`` from ``seed``, rounded to 0.1.

    The draw depends on the seed alone, so a held-out set is named by its command; it is
    meant to be drawn after the model it tests is frozen.
    """
    if not (0 < lo < hi) or n < 1 or n != int(n):
        raise ValueError(f"need 0 < LO < HI and a whole N >= 1, got LO={lo}, HI={hi}, N={n}")
    draws = np.random.default_rng(seed).uniform(lo, hi, int(n))
    out = tuple(float(r) for r in np.round(draws, 1))
    if len(set(out)) != len(out):
        raise ValueError(f"the draw repeats a Reynolds number: {out}; use another seed")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m diffgns.mesh.sweep", description=__doc__
                                .split("\n\n")[0])
    p.add_argument("--out", required=True, help="output .h5 file (resumed if it exists)")
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--re", type=float, nargs="+",
                       help="Reynolds numbers Ubar D / nu, one trajectory each")
    which.add_argument("--draw", type=float, nargs=3, metavar=("LO", "HI", "N"),
                       help="N Reynolds numbers drawn uniformly in [LO, HI] from --seed "
                            "(held-out sets drawn after a model is frozen)")
    p.add_argument("--seed", type=int, default=0, help="seed of --draw")
    p.add_argument("--frames", type=int, default=201, help="stored frames per trajectory")
    p.add_argument("--frame-dt", type=float, default=0.02, help="time between frames, s")
    p.add_argument("--spinup", type=float, default=20.0,
                   help="simulated time before the first stored frame, units of D / Ubar")
    p.add_argument("--workers", type=int, default=2, help="CFD processes (one core each)")
    p.add_argument("--reuse", default=None,
                   help="finished sweep file of the same recipe: its trajectories at the "
                        "same Re are copied, not recomputed (the CFD is deterministic)")
    a = p.parse_args(argv)
    try:
        run = sweep_run(a.frames, a.frame_dt, a.spinup)
    except ValueError as e:
        raise InputError("--frames/--frame-dt/--spinup", str(e)) from None
    if a.draw is not None:
        lo, hi, n = a.draw
        try:
            reynolds = draw_reynolds(lo, hi, n, a.seed)
        except ValueError as e:
            raise InputError("--draw", str(e)) from None
        print(f"drawn Re (seed {a.seed}): {' '.join(f'{r:g}' for r in reynolds)}")
    else:
        reynolds = tuple(a.re)

    def stop(signum, frame):
        raise Interrupted(signum)

    signal.signal(signal.SIGTERM, stop)  # SIGINT raises KeyboardInterrupt already
    os.environ.setdefault("OMP_NUM_THREADS", "1")  # inherited by the CFD processes
    res = generate_sweep(a.out, Sweep(reynolds, run=run), workers=a.workers,
                         reuse=a.reuse)
    print(f"{a.out}: {len(res['cases'])} new trajectories in {res['wall_s']:.0f} s wall "
          f"({a.workers} workers), {res['reused']} copied from {a.reuse}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    run_module(main, "; stored trajectories kept, run the same command to resume")
