"""The one measuring protocol of every benchmark in ``benchmarks/`` (issue 22).

A benchmark calls :func:`add_arguments` on its parser and :func:`start` first thing; every
figure it prints goes through :meth:`Run.print` and its JSON through :meth:`Run.write`::

    ap = argparse.ArgumentParser(); protocol.add_arguments(ap); args = ap.parse_args()
    run = protocol.start(args, "mpm_throughput")      # may exit 3 or re-execute pinned
    ...
    run.print(f"{rate:.2f} M particle-substeps/s")
    run.write("mpm_throughput.json", payload)

The rules:

* **Quiet machine.** The 1-minute load average is read at the start (after waiting up to
  ``--wait-quiet`` seconds for it to fall) and again when the JSON is written. A run whose
  1-minute load at start exceeds ``--max-load`` (default 1.0) is refused: one line on stderr,
  exit status 3. With ``--allow-loaded`` it goes on, its JSON says ``"valid": false`` and
  every line :meth:`Run.print` prints starts with ``INVALID (load x.xx)``.
* **Threads.** ``--threads 2`` (the default) is the machine's two cores; torch and Taichi are
  given 2 threads (:attr:`Run.threads`). ``--threads 1`` re-executes the same command under
  ``taskset -c 0`` (the lowest CPU the process may use: under ``taskset -c 1``, CPU 1) with
  XLA, OpenMP, MKL and OpenBLAS limited to one thread
  (:func:`pinned_command`, :func:`pinned_env`); the script passes :attr:`Run.threads` to
  ``torch.set_num_threads`` and ``ti.init(cpu_max_num_threads=...)``. ``--threads both``
  measures with 2 threads in this process, then runs the pinned 1-thread variant as a child
  (:meth:`Run.pinned_child`) so that the report gives both ratios.
* **Stolen CPU.** On a virtual machine the host may take CPU time from it (``steal`` in
  ``/proc/stat``), which the load average does not show: on 2026-12-03 this machine lost
  ~40% of its CPU time that way at a load of 0.2, and ran 2-2.6x slower. The steal share
  during the run is recorded; a timed run that lost more than ``MAX_STEAL`` (10%) is
  written with ``"valid": false`` and an ``invalid_reason``.
* **Record.** Every JSON holds ``valid``, the load before and after, the date (UTC), the git
  commit, the command line, the CPU model and the thread setting (``protocol`` block), next
  to the machine and software description (``machine`` block).

Timing itself (compile apart, ``block_until_ready``, medians, CPU time beside wall time,
interleaved A/B rounds) is the library's :mod:`diffgns.timing`, memory (peak RSS, XLA's
analysis, ahead-of-time compiling) :mod:`diffgns.memory`; this module adds
:func:`warm_up_jax` and :func:`fmt_rate`.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import importlib.metadata as _md
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

BENCH_DIR = Path(__file__).resolve().parent
REPO_DIR = BENCH_DIR.parent
RESULTS_DIR = BENCH_DIR / "results"

MAX_LOAD = 1.0
MAX_STEAL = 0.10  # a run whose CPU steal exceeded this share is marked (not refused)
EXIT_LOADED = 3
PIN_CPU = 0
QUIET_WAIT_BETWEEN_PHASES_S = 300.0
#: seconds the pinned child of a valid run may wait for the load at its own start
QUIET_WAIT_CHILD_S = 180.0
PINNED_ENV = "DIFFGNS_BENCH_PINNED"  # set in a process already re-executed pinned
RUN_ENV = "DIFFGNS_BENCH_RUN"  # the parent's run, for worker processes (JSON)
# one thread everywhere: XLA's CPU client, OpenMP (torch, scikit-fem), MKL, OpenBLAS
ONE_THREAD_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
ONE_THREAD_VARS = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                   "OPENBLAS_NUM_THREADS": "1"}

LoadReader = Callable[[], tuple[float, float, float]]


def read_load() -> tuple[float, float, float]:
    """The 1-, 5- and 15-minute load averages (tests replace this function)."""
    return tuple(os.getloadavg())  # type: ignore[return-value]


def read_cpu_times() -> tuple[int, int] | None:
    """(steal, total) CPU ticks since boot from ``/proc/stat`` (None off Linux)."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]
    except OSError:
        return None
    ticks = [int(f) for f in fields[:8]]  # user nice system idle iowait irq softirq steal
    return (ticks[7] if len(ticks) > 7 else 0), sum(ticks)


def steal_fraction(before: tuple[int, int] | None, after: tuple[int, int] | None
                   ) -> float | None:
    """Share of CPU time the hypervisor took from this virtual machine between two
    :func:`read_cpu_times` readings (None when unknown). The load average does not see it:
    a virtual machine whose host is busy runs slower at load 0."""
    if before is None or after is None or after[1] <= before[1]:
        return None
    return (after[0] - before[0]) / (after[1] - before[1])


def sample_steal(seconds: float = 2.0, sleep: Callable[[float], None] = time.sleep
                 ) -> float | None:
    """The steal fraction over the next ``seconds``."""
    before = read_cpu_times()
    sleep(seconds)
    return steal_fraction(before, read_cpu_times())


# ------------------------------------------------------------------ command line
def add_arguments(parser: argparse.ArgumentParser, threads: str = "2") -> None:
    """Add the protocol's options to a benchmark's parser (``threads``: the default mode)."""
    g = parser.add_argument_group("measuring protocol (benchmarks/protocol.py)")
    g.add_argument("--max-load", type=float, default=MAX_LOAD,
                   help="refuse to run when the 1-minute load at start exceeds this")
    g.add_argument("--allow-loaded", action="store_true",
                   help="run anyway above --max-load; the JSON says valid: false and every "
                        "printed figure is labelled INVALID")
    g.add_argument("--wait-quiet", type=float, default=0.0, metavar="SECONDS",
                   help="wait up to this long for the load to fall below --max-load")
    g.add_argument("--threads", choices=("2", "1", "both"), default=threads,
                   help="2: both cores; 1: re-run pinned to one core (taskset) with one "
                        "thread; both: 2 threads here, then the pinned 1-thread run")
    g.add_argument("--result-to", default=None, help=argparse.SUPPRESS)


# ------------------------------------------------------------------ thread modes
def pinned_command(argv: Sequence[str], executable: str = sys.executable,
                   affinity: Sequence[int] | None = None) -> list[str]:
    """The command that re-runs ``argv`` (script + arguments) pinned to one CPU with one
    thread: ``taskset -c <cpu> python script ... --threads 1``. The CPU is the lowest of
    ``affinity`` (default: this process's), so a run started on all cores is pinned to
    ``PIN_CPU`` (0) and one started under ``taskset -c 1`` stays on CPU 1 (an
    accuracy-only sweep beside another job on CPU 0)."""
    if affinity is None:
        affinity = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    cpu = min(affinity) if affinity else PIN_CPU
    return ["taskset", "-c", str(cpu), executable, *argv, "--threads", "1"]


def pinned_env(environ: Mapping[str, str]) -> dict[str, str]:
    """``environ`` with XLA, OpenMP, MKL and OpenBLAS limited to one thread (XLA flags
    already set are kept) and the marker that stops a second re-execution."""
    env = dict(environ)
    flags = env.get("XLA_FLAGS", "").strip()
    env["XLA_FLAGS"] = f"{flags} {ONE_THREAD_XLA_FLAGS}".strip()
    env.update(ONE_THREAD_VARS)
    env[PINNED_ENV] = "1"
    return env


def thread_setting(threads: int, pinned: bool) -> dict[str, Any]:
    """What the JSON records of the thread mode."""
    affinity = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None
    return {"threads": threads, "pinned": pinned, "cpu_affinity": affinity,
            "xla_flags": os.environ.get("XLA_FLAGS"),
            # glibc's malloc tunables (huge pages: diffgns.hugepages) change allocation costs
            "glibc_tunables": os.environ.get("GLIBC_TUNABLES"),
            **{k: os.environ.get(k) for k in ONE_THREAD_VARS}}


def _reexec_pinned() -> None:  # pragma: no cover - replaces the process
    cmd = pinned_command(sys.argv)
    print(f"re-running pinned, one thread: {shlex.join(cmd)}", file=sys.stderr, flush=True)
    try:
        os.execvpe(cmd[0], cmd, pinned_env(os.environ))
    except OSError as e:
        sys.exit(f"cannot pin to one core ({e}); install util-linux's taskset")


# ------------------------------------------------------------------ the run
@dataclass
class Run:
    """One benchmark run under the protocol (made by :func:`start`).

    Attributes:
        name: benchmark name (the script's stem).
        valid: False when the 1-minute load at start exceeded ``max_load``.
        load_before: (1, 5, 15)-minute load averages at the start.
        threads: 2 or 1 (pass to torch / Taichi).
        pinned: True in the ``taskset``-pinned 1-thread process.
        mode: the ``--threads`` choice ("2", "1" or "both").
    """

    name: str
    valid: bool
    load_before: tuple[float, float, float]
    max_load: float = MAX_LOAD
    threads: int = 2
    pinned: bool = False
    mode: str = "2"
    allow_loaded: bool = False
    timed: bool = True
    result_to: str | None = None
    cpu_at_start: tuple[int, int] | None = field(default_factory=lambda: read_cpu_times())
    steal_at_start: float | None = None
    started_utc: str = field(default_factory=lambda: _now())
    argv: list[str] = field(default_factory=lambda: list(sys.argv))

    @property
    def tag(self) -> str:
        """``[2 threads] `` / ``[1 thread, pinned] `` in a two-mode report, else empty."""
        if self.pinned:
            return "[1 thread, pinned] "
        return f"[{self.threads} threads] " if self.mode == "both" else ""

    @property
    def prefix(self) -> str:
        """``INVALID (load x.xx) `` for a loaded run, else empty."""
        return "" if self.valid else f"INVALID (load {self.load_before[0]:.2f}) "

    def label(self, text: str, tag: bool = True) -> str:
        """``text`` with every line prefixed by :attr:`prefix` (and :attr:`tag`)."""
        pre = self.prefix + (self.tag if tag else "")
        if not pre:
            return text
        return "\n".join(pre + line for line in str(text).split("\n"))

    def print(self, *parts: Any, file=None, tag: bool = True) -> None:
        """``print`` through :meth:`label` (flushes)."""
        print(self.label(" ".join(str(p) for p in parts), tag), file=file or sys.stdout,
              flush=True)

    def metadata(self, read: LoadReader | None = None) -> dict[str, Any]:
        """The ``protocol`` block of the JSON (reads the load after the run now)."""
        return {
            "valid": self.valid,
            "measures_time": self.timed,
            "max_load_1min": self.max_load,
            "allow_loaded": self.allow_loaded,
            "load_before_1_5_15": list(self.load_before),
            "load_after_1_5_15": list((read or read_load)()),
            "cpu_steal_at_start": self.steal_at_start,
            "cpu_steal_during_run": steal_fraction(self.cpu_at_start, read_cpu_times()),
            "max_steal": MAX_STEAL,
            "date_utc": self.started_utc,
            "finished_utc": _now(),
            "git_commit": git_commit(),
            "command": shlex.join([sys.executable, *self.argv]),
            "cpu_model": cpu_model(),
            "thread_mode": self.mode,
            **thread_setting(self.threads, self.pinned),
        }

    def document(self, payload: Mapping[str, Any], read: LoadReader | None = None
                 ) -> dict[str, Any]:
        """The JSON document: ``valid``, ``protocol``, ``machine``, then ``payload``."""
        meta = self.metadata(read)
        valid = meta["valid"]
        steal = meta["cpu_steal_during_run"]
        if self.timed and steal is not None and steal > MAX_STEAL:
            valid = meta["valid"] = False  # the host took the CPU: as good as a loaded run
            meta["invalid_reason"] = (f"CPU steal {steal:.0%} of the run's CPU time > "
                                      f"{MAX_STEAL:.0%} (the virtual machine's host was busy)")
            print(f"INVALID {self.name}: {meta['invalid_reason']}", file=sys.stderr,
                  flush=True)
        child = payload.get("one_thread_pinned")
        if isinstance(child, Mapping) and child.get("valid") is False:
            valid = False  # a combined report is as valid as its weakest part
        return {"benchmark": self.name, "valid": valid, "protocol": meta,
                "machine": machine_info(), **payload}

    def write(self, name: str | os.PathLike, payload: Mapping[str, Any]) -> Path:
        """Write :meth:`document` to ``benchmarks/results/<name>``, or to ``name`` when it
        has a folder, or to the parent's ``--result-to`` in a pinned child run; ``.json`` is
        appended to a name without it (``--out front`` writes ``front.json``)."""
        if not str(name).endswith(".json"):
            name = f"{name}.json"
        path = Path(self.result_to) if self.result_to else results_path(name)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.document(payload), indent=2, default=_json_default)
                        + "\n")
        return path

    def finish(self, name: str | os.PathLike, payload: Mapping[str, Any],
               figures: Callable[[Path], Any] | None = None) -> Path:
        """Close the run: for ``--threads both`` run the pinned 1-thread variant first (unless
        ``payload`` already holds it, as ``one_thread_pinned``), write the JSON, and, in the
        run the user started (not a pinned child), ``figures(json_path)``."""
        payload = dict(payload)
        if self.mode == "both" and not self.pinned and "one_thread_pinned" not in payload:
            payload["one_thread_pinned"] = self.pinned_child()
        path = self.write(name, payload)
        if figures is not None and not self.result_to:
            figures(path)
        return path

    # -- subprocesses
    def worker_env(self, environ: Mapping[str, str] | None = None) -> dict[str, str]:
        """Environment for a worker process of this run (see :func:`worker_run`)."""
        env = dict(os.environ if environ is None else environ)
        env[RUN_ENV] = json.dumps({"name": self.name, "valid": self.valid,
                                   "load_before": list(self.load_before),
                                   "threads": self.threads, "pinned": self.pinned,
                                   "mode": self.mode})
        return env

    def pinned_child(self, extra_args: Sequence[str] = (), wait_s: float | None = None,
                     runner: Callable[..., subprocess.CompletedProcess] = subprocess.run,
                     ) -> dict[str, Any]:
        """Run this script's pinned 1-thread variant (``--threads both``) and return its JSON
        document (or ``{"valid": False, "refused": True, ...}`` if it was refused).

        A valid run first waits (up to ``wait_s``, default
        :data:`QUIET_WAIT_BETWEEN_PHASES_S`) for the load that its own 2-thread phase left
        behind to fall below ``max_load``; an invalid (``--allow-loaded``) run does not wait.
        """
        if self.valid:
            wait_for_quiet(self.max_load,
                           QUIET_WAIT_BETWEEN_PHASES_S if wait_s is None else wait_s)
        fd, tmp = tempfile.mkstemp(prefix=f"{self.name}_1thread_", suffix=".json")
        os.close(fd)
        # the child waits too: its own start-up (imports) can lift a load that has only just
        # fallen to the threshold back above it (seen: refused at 1.04 right after the wait)
        child_wait = 0 if not self.valid else QUIET_WAIT_CHILD_S
        cmd = pinned_command([*self.argv, *extra_args, "--result-to", tmp, "--wait-quiet",
                              f"{child_wait:g}"])
        proc = runner(cmd, env=pinned_env(os.environ))
        try:
            if proc.returncode == EXIT_LOADED:
                return {"valid": False, "refused": True,
                        "reason": "1-minute load above --max-load at the start of the "
                                  "pinned 1-thread run", "command": shlex.join(cmd)}
            if proc.returncode:
                raise RuntimeError(f"pinned 1-thread run failed ({proc.returncode}): "
                                   f"{shlex.join(cmd)}")
            return json.loads(Path(tmp).read_text())
        finally:
            Path(tmp).unlink(missing_ok=True)


def start(args: argparse.Namespace, name: str, timed: bool = True,
          read: LoadReader | None = None, sleep: Callable[[float], None] = time.sleep,
          environ: Mapping[str, str] | None = None) -> Run:
    """Begin a run: re-execute pinned for ``--threads 1``, wait for and check the load.

    ``timed=False`` is for scripts that print no speed figure (accuracy only): the load is
    recorded but never refuses them. Exits with status 3 (one line on stderr) when the
    1-minute load exceeds ``--max-load`` and ``--allow-loaded`` is not given.
    """
    env = os.environ if environ is None else environ
    pinned = env.get(PINNED_ENV) == "1"
    if args.threads == "1" and not pinned:
        _reexec_pinned()
    read = read or read_load
    load = wait_for_quiet(args.max_load, args.wait_quiet if timed else 0.0, read, sleep)
    quiet = load[0] <= args.max_load
    if timed and not quiet and not args.allow_loaded:
        print(f"REFUSED {name}: 1-minute load {load[0]:.2f} > {args.max_load:.2f} at start; "
              "run on a quiet machine (--allow-loaded records an INVALID run)",
              file=sys.stderr, flush=True)
        sys.exit(EXIT_LOADED)
    threads = 1 if pinned or args.threads == "1" else 2
    steal = sample_steal(1.0, sleep) if timed else None
    if steal is not None and steal > MAX_STEAL:
        print(f"warning: {name}: the host took {steal:.0%} of this machine's CPU in the last "
              "second (steal); the run will be marked invalid if that goes on",
              file=sys.stderr, flush=True)
    return Run(name=name, valid=quiet or not timed, load_before=load, max_load=args.max_load,
               threads=threads, pinned=pinned, mode=args.threads,
               allow_loaded=args.allow_loaded, timed=timed, result_to=args.result_to,
               steal_at_start=steal)


def both_ratios(r2: float, r1: float | None, pinned: Mapping[str, Any], digits: int = 3
                ) -> str:
    """The one line of a two-mode report: ``2 threads <r2>; 1 thread pinned <r1>`` with
    ``refused (load)`` when the pinned child measured nothing and ``INVALID (pinned run
    loaded)`` when its JSON (``pinned``) is not valid."""
    one = "refused (load)" if r1 is None else f"{r1:.{digits}f}"
    bad = "" if pinned.get("valid", False) else " INVALID (pinned run loaded)"
    return f"2 threads {r2:.{digits}f}; 1 thread pinned {one}{bad}"


def wait_for_quiet(max_load: float, timeout_s: float, read: LoadReader | None = None,
                   sleep: Callable[[float], None] = time.sleep, poll_s: float = 5.0
                   ) -> tuple[float, float, float]:
    """Poll the load until its 1-minute average is at most ``max_load`` or ``timeout_s``
    has passed; returns the last reading."""
    read = read or read_load
    load = read()
    waited = 0.0
    while load[0] > max_load and waited < timeout_s:
        sleep(poll_s)
        waited += poll_s
        load = read()
    return load


def worker_run(name: str, environ: Mapping[str, str] | None = None) -> Run:
    """The parent's :class:`Run` in a worker process (no load check, no JSON of its own):
    its lines are labelled like the parent's."""
    env = os.environ if environ is None else environ
    d = json.loads(env[RUN_ENV]) if RUN_ENV in env else {}
    return Run(name=d.get("name", name), valid=d.get("valid", True),
               load_before=tuple(d.get("load_before", read_load())),  # type: ignore[arg-type]
               threads=d.get("threads", 2), pinned=d.get("pinned", False),
               mode=d.get("mode", "2"))


def run_worker(run: Run, args: Sequence[str], tag: str, xla_flags: str = ""
               ) -> tuple[dict[str, Any] | None, int]:
    """Run ``python <args>`` as a worker of ``run`` and return (the JSON it printed after
    ``tag`` on a line of its stdout or None, its exit code). The worker inherits the thread
    setting (and pinning) of this process; ``xla_flags`` are added to its ``XLA_FLAGS``."""
    env = run.worker_env()
    if xla_flags:  # before the inherited flags: XLA stops parsing XLA_FLAGS at the bare
        # `intra_op_parallelism_threads=1` of a pinned run, so a flag after it is ignored
        env["XLA_FLAGS"] = f"{xla_flags} {env.get('XLA_FLAGS', '')}".strip()
    p = subprocess.run([sys.executable, *args], stdout=subprocess.PIPE, text=True, env=env)
    for line in p.stdout.splitlines():
        if line.startswith(tag):
            return json.loads(line[len(tag):]), p.returncode
    return None, p.returncode


# ------------------------------------------------------------------ record
def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _json_default(x: Any) -> Any:
    try:
        return float(x)
    except (TypeError, ValueError):
        return str(x)


def results_path(name: str | os.PathLike) -> Path:
    """``benchmarks/results/<name>`` for a bare file name, else ``name`` itself."""
    p = Path(name)
    return p if p.parent != Path(".") else RESULTS_DIR / p


def git_commit() -> dict[str, Any]:
    """HEAD of the repository and whether tracked files differ from it."""
    def git(*a: str) -> str | None:
        try:
            return subprocess.run(["git", "-C", str(REPO_DIR), *a], capture_output=True,
                                  text=True, timeout=20, check=True).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return None

    status = git("status", "--porcelain", "--untracked-files=no")
    return {"commit": git("rev-parse", "HEAD"), "dirty": None if status is None else bool(status)}


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def warm_up_jax() -> None:
    """Initialise the JAX backend (client, thread pools) so that the first measured
    compile does not also pay for it."""
    import jax
    import jax.numpy as jnp

    jax.block_until_ready(jnp.arange(8.0).sum() + 1.0)


def fmt_rate(x: float) -> str:
    """Human-readable rate (e.g. particle-substeps/s): ``"1.234 M"`` or ``"56.7 k"``."""
    return f"{x / 1e6:.3f} M" if x >= 1e5 else f"{x / 1e3:.1f} k"


def use_agg():
    """Select matplotlib's non-interactive Agg backend and return ``matplotlib.pyplot``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _version(dist: str) -> str | None:
    try:
        return _md.version(dist)
    except _md.PackageNotFoundError:
        return None


def machine_info() -> dict[str, Any]:
    """Machine and software description stored with every result."""
    info: dict[str, Any] = {
        "cwd": os.getcwd(), "pythonpath": os.environ.get("PYTHONPATH"),
        "platform": platform.platform(), "machine": platform.machine(),
        "cpu_model": cpu_model(), "cpu_count": os.cpu_count(),
        "python": sys.version.split()[0],
        **{d: _version(d) for d in ("jax", "jaxlib", "numpy", "taichi", "torch",
                                    "torch_geometric")},
    }
    jax = sys.modules.get("jax")
    if jax is not None:  # only if the benchmark uses it: importing JAX here costs seconds
        try:
            info["jax_backend"] = jax.default_backend()
            info["jax_devices"] = [str(d) for d in jax.devices()]
            info["jax_enable_x64"] = bool(jax.config.jax_enable_x64)
        except Exception as e:  # pragma: no cover - informational only
            info["jax_error"] = repr(e)
    return info
