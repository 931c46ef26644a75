"""The benchmarks' measuring protocol (benchmarks/protocol.py), with faked load readings:
nothing here runs a real benchmark (the timing helper is tests/test_timing.py)."""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import protocol  # noqa: E402

QUIET, LOADED = (0.4, 0.8, 1.2), (3.5, 2.0, 1.0)


def parse(*argv: str) -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    protocol.add_arguments(ap)
    return ap.parse_args(list(argv))


def start(*argv: str, load=QUIET, environ=None, **kw) -> protocol.Run:
    kw.setdefault("sleep", lambda s: None)
    return protocol.start(parse(*argv), "bench", read=lambda: load,
                          environ={} if environ is None else environ, **kw)


@pytest.fixture(autouse=True)
def no_steal(monkeypatch):
    """A virtual machine whose host takes nothing (the real one's steal varies)."""
    ticks = iter(range(0, 10**9, 1000))
    monkeypatch.setattr(protocol, "read_cpu_times", lambda: (0, next(ticks)))


# ------------------------------------------------------------------ load check
def test_loaded_machine_is_refused_with_exit_3(capsys):
    with pytest.raises(SystemExit) as e:
        start(load=LOADED)
    assert e.value.code == protocol.EXIT_LOADED == 3
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "REFUSED" in err and "3.50 > 1.00" in err


def test_threshold_is_configurable_and_inclusive():
    assert start("--max-load", "4.0", load=LOADED).valid
    assert start(load=(1.0, 1.0, 1.0)).valid  # at the threshold: quiet enough
    with pytest.raises(SystemExit):
        start(load=(1.01, 0.0, 0.0))


def test_allow_loaded_marks_run_invalid_and_labels_every_line(capsys):
    run = start("--allow-loaded", load=LOADED)
    assert not run.valid
    run.print("2.46 M particle-substeps/s\nratio 1.20")
    out = capsys.readouterr().out.splitlines()
    assert out == ["INVALID (load 3.50) 2.46 M particle-substeps/s",
                   "INVALID (load 3.50) ratio 1.20"]


def test_quiet_run_is_valid_and_unlabelled(capsys):
    run = start(load=QUIET)
    assert run.valid and run.threads == 2 and not run.pinned
    run.print("ratio 1.20")
    assert capsys.readouterr().out == "ratio 1.20\n"


def test_accuracy_only_run_is_never_refused():
    run = start(load=LOADED, timed=False)
    assert run.valid and not run.timed


def test_wait_quiet_polls_until_the_load_falls():
    readings = iter([(3.0, 0, 0), (2.0, 0, 0), (0.9, 0, 0), (5.0, 0, 0)])
    slept = []
    load = protocol.wait_for_quiet(1.0, 60.0, lambda: next(readings), slept.append, poll_s=5)
    assert load[0] == 0.9 and slept == [5, 5]


def test_wait_quiet_gives_up_after_the_timeout():
    slept = []
    load = protocol.wait_for_quiet(1.0, 12.0, lambda: LOADED, slept.append, poll_s=5)
    assert load == LOADED and sum(slept) == 15  # three polls: 0 < 5 < 10 < 12 <= 15


def test_start_waits_then_refuses_if_still_loaded():
    slept = []
    with pytest.raises(SystemExit):
        start("--wait-quiet", "10", load=LOADED, sleep=slept.append)
    assert sum(slept) >= 10


# ------------------------------------------------------------------ JSON
def test_json_records_validity_load_and_machine(tmp_path):
    run = start("--allow-loaded", load=LOADED)
    path = run.write(tmp_path / "b.json", {"ratio": 1.2})
    doc = json.loads(path.read_text())
    assert doc["valid"] is False and doc["ratio"] == 1.2 and doc["benchmark"] == "bench"
    p = doc["protocol"]
    assert p["valid"] is False and p["load_before_1_5_15"] == list(LOADED)
    assert len(p["load_after_1_5_15"]) == 3
    for key in ("date_utc", "git_commit", "command", "cpu_model", "threads", "pinned",
                "thread_mode", "xla_flags", "glibc_tunables", "OMP_NUM_THREADS", "max_load_1min"):
        assert key in p, key
    assert p["threads"] == 2 and p["date_utc"].endswith("+00:00")
    assert "python" in doc["machine"] and "cpu_count" in doc["machine"]
    assert start(load=QUIET).document({})["valid"] is True


def test_cpu_stolen_by_the_host_marks_a_quiet_run_invalid(monkeypatch, capsys):
    # start: two readings (1 s sample, no steal), then the run start and its end: 30% stolen
    readings = iter([(0, 0), (0, 100), (0, 0), (300, 1000)])
    monkeypatch.setattr(protocol, "read_cpu_times", lambda: next(readings))
    run = start(load=QUIET)
    doc = run.document({})
    assert doc["valid"] is False and doc["protocol"]["cpu_steal_during_run"] == 0.3
    assert "steal 30%" in doc["protocol"]["invalid_reason"]
    assert "INVALID bench: CPU steal 30%" in capsys.readouterr().err
    assert protocol.steal_fraction((0, 0), (50, 1000)) == 0.05  # below the 10% threshold
    assert protocol.steal_fraction(None, (1, 2)) is None


def test_steal_is_read_from_proc_stat(monkeypatch):
    monkeypatch.undo()  # the real /proc/stat, not the autouse fake
    if not Path("/proc/stat").exists():
        pytest.skip("no /proc/stat")
    before = protocol.read_cpu_times()
    sum(i * i for i in range(2_000_000))  # some CPU time passes
    after = protocol.read_cpu_times()
    assert 0 <= before[0] <= after[0] <= after[1] and after[1] > before[1]
    assert 0.0 <= protocol.steal_fraction(before, after) <= 1.0


def test_both_ratios_line_names_refused_and_invalid_pinned_runs():
    assert protocol.both_ratios(0.8312, 1.009, {"valid": True}) == (
        "2 threads 0.831; 1 thread pinned 1.009")
    assert protocol.both_ratios(0.7, None, {}, digits=2) == (
        "2 threads 0.70; 1 thread pinned refused (load) INVALID (pinned run loaded)")


def test_combined_report_is_invalid_if_its_pinned_part_is():
    run = start(load=QUIET)
    assert run.document({"one_thread_pinned": {"valid": True}})["valid"] is True
    assert run.document({"one_thread_pinned": {"valid": False}})["valid"] is False


def test_a_record_name_without_json_gets_the_suffix(tmp_path):
    run = start(load=QUIET)
    assert run.write(tmp_path / "front", {}) == tmp_path / "front.json"
    assert run.write(tmp_path / "a.b", {}) == tmp_path / "a.b.json"
    assert run.write(tmp_path / "c.json", {}) == tmp_path / "c.json"
    assert json.loads((tmp_path / "front.json").read_text())["benchmark"] == "bench"


def test_results_path_names_a_file_in_results_or_a_given_path(tmp_path):
    assert protocol.results_path("x.json") == protocol.RESULTS_DIR / "x.json"
    assert protocol.results_path(tmp_path / "x.json") == tmp_path / "x.json"


# ------------------------------------------------------------------ threads
def test_pinned_command_and_env():
    cmd = protocol.pinned_command(["bench.py", "--repeats", "3"], executable="/py")
    assert cmd == ["taskset", "-c", "0", "/py", "bench.py", "--repeats", "3", "--threads", "1"]
    # a run started under `taskset -c 1` stays on CPU 1; on all cores it takes CPU 0
    assert protocol.pinned_command(["b.py"], "/py", affinity=[1])[:3] == ["taskset", "-c", "1"]
    assert protocol.pinned_command(["b.py"], "/py", affinity=[1, 0])[2] == "0"
    env = protocol.pinned_env({"XLA_FLAGS": "--xla_foo=1", "HOME": "/h"})
    assert env["XLA_FLAGS"] == ("--xla_foo=1 --xla_cpu_multi_thread_eigen=false "
                                "intra_op_parallelism_threads=1")
    assert env["OMP_NUM_THREADS"] == env["MKL_NUM_THREADS"] == "1"
    assert env["OPENBLAS_NUM_THREADS"] == "1" and env[protocol.PINNED_ENV] == "1"
    assert env["HOME"] == "/h"
    assert protocol.pinned_env({})["XLA_FLAGS"] == protocol.ONE_THREAD_XLA_FLAGS


def test_later_thread_option_wins_so_appending_is_enough():
    args = parse("--threads", "both", "--result-to", "a.json", "--wait-quiet", "0",
                 "--threads", "1")
    assert args.threads == "1" and args.result_to == "a.json"


def test_one_thread_mode_re_executes_itself_pinned(monkeypatch):
    calls = []

    def fake_exec(file, cmd, env):
        calls.append((file, cmd, env))
        raise SystemExit(0)

    monkeypatch.setattr(protocol.os, "execvpe", fake_exec)
    monkeypatch.setattr(protocol.sys, "argv", ["bench.py", "--threads", "1"])
    with pytest.raises(SystemExit):
        start("--threads", "1")
    (file, cmd, env), = calls
    assert file == "taskset" and cmd[:3] == ["taskset", "-c", "0"]
    assert cmd[-2:] == ["--threads", "1"] and cmd[4] == "bench.py"
    assert env[protocol.PINNED_ENV] == "1" and "intra_op_parallelism_threads=1" in env[
        "XLA_FLAGS"]


def test_pinned_process_does_not_re_execute(monkeypatch):
    monkeypatch.setattr(protocol.os, "execvpe", lambda *a: pytest.fail("re-executed"))
    run = start("--threads", "1", environ={protocol.PINNED_ENV: "1"})
    assert run.threads == 1 and run.pinned and run.tag == "[1 thread, pinned] "


def test_pinned_child_runs_this_script_pinned_and_returns_its_json(monkeypatch):
    monkeypatch.setattr(protocol.sys, "argv", ["bench.py", "--threads", "both"])
    run = start("--threads", "both")
    seen = {}

    def runner(cmd, env):
        seen.update(cmd=cmd, env=env)
        out = cmd[cmd.index("--result-to") + 1]
        Path(out).write_text(json.dumps({"valid": True, "ratio": 0.7}))
        return subprocess.CompletedProcess(cmd, 0)

    doc = run.pinned_child(wait_s=0, runner=runner)
    assert doc == {"valid": True, "ratio": 0.7}
    cmd = seen["cmd"]
    assert cmd[:3] == ["taskset", "-c", "0"] and cmd[-2:] == ["--threads", "1"]
    assert "bench.py" in cmd and seen["env"][protocol.PINNED_ENV] == "1"
    assert not Path(cmd[cmd.index("--result-to") + 1]).exists()  # temp file removed
    assert parse(*cmd[5:]).threads == "1"
    # the child of a valid run may itself wait for the load its start-up can cause
    assert parse(*cmd[5:]).wait_quiet == protocol.QUIET_WAIT_CHILD_S > 0


def test_refused_pinned_child_is_reported_not_raised():
    run = start()
    doc = run.pinned_child(wait_s=0, runner=lambda cmd, env: subprocess.CompletedProcess(
        cmd, protocol.EXIT_LOADED))
    assert doc["refused"] and doc["valid"] is False
    with pytest.raises(RuntimeError):
        run.pinned_child(wait_s=0, runner=lambda cmd, env: subprocess.CompletedProcess(cmd, 1))


def test_worker_inherits_the_parents_label():
    run = start("--allow-loaded", "--threads", "both", load=LOADED)
    env = run.worker_env({})
    w = protocol.worker_run("x", env)
    assert not w.valid and w.label("t") == "INVALID (load 3.50) [2 threads] t"


def test_finish_adds_the_pinned_run_once_and_draws_figures_only_in_the_users_run(
        tmp_path, monkeypatch):
    run = start("--threads", "both")
    calls, drawn = [], []
    monkeypatch.setattr(run, "pinned_child", lambda: calls.append(1) or {"valid": True})
    path = run.finish(tmp_path / "a.json", {"x": 1}, drawn.append)
    doc = json.loads(path.read_text())
    assert calls == [1] and doc["one_thread_pinned"] == {"valid": True} and drawn == [path]
    run.finish(tmp_path / "b.json", {"one_thread_pinned": {"valid": True}})
    assert calls == [1]  # already measured by the script itself
    child = start("--threads", "1", "--result-to", str(tmp_path / "c.json"),
                  environ={protocol.PINNED_ENV: "1"})
    assert child.finish("ignored.json", {}, drawn.append) == tmp_path / "c.json"
    assert drawn == [path]  # a pinned child writes its JSON for the parent, no figures


def test_every_benchmark_script_runs_under_the_protocol():
    """Issue 22: one protocol for every speed figure. A script in benchmarks/ that prints
    timings must take the protocol's options and start a protocol run."""
    bench = Path(protocol.__file__).parent
    scripts = [p for p in bench.glob("*.py")
               if p.name not in ("protocol.py", "conftest.py") and not p.name.startswith("test_")]
    assert len(scripts) >= 15
    missing = [p.name for p in scripts
               if "protocol.add_arguments(" not in p.read_text()
               or "protocol.start(" not in p.read_text()]
    assert missing == [], f"benchmarks outside the protocol: {missing}"


def test_worker_xla_flags_come_before_the_pinned_runs_bare_token(monkeypatch):
    """XLA stops parsing XLA_FLAGS at the bare ``intra_op_parallelism_threads=1`` of a pinned
    run: a worker's own flags (e.g. two host devices) must come before it, or they are
    silently ignored."""
    seen = {}

    def fake_run(cmd, stdout, text, env):
        seen["flags"] = env["XLA_FLAGS"]
        return subprocess.CompletedProcess(cmd, 0, stdout='TAG{"ok": 1}\n')

    monkeypatch.setattr(protocol.subprocess, "run", fake_run)
    monkeypatch.setenv("XLA_FLAGS", protocol.ONE_THREAD_XLA_FLAGS)
    run = protocol.Run(name="x", valid=True, load_before=(0.0, 0.0, 0.0), threads=1,
                       pinned=True, mode="1")
    out, rc = protocol.run_worker(run, ["-c", "pass"], "TAG",
                                  xla_flags="--xla_force_host_platform_device_count=2")
    assert out == {"ok": 1} and rc == 0
    tokens = seen["flags"].split()
    assert tokens[0] == "--xla_force_host_platform_device_count=2"
    assert tokens[-1] == "intra_op_parallelism_threads=1"
