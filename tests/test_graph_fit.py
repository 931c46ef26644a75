"""The one training loop (diffgns.graph.fit): exact resume, logs, schedule, validation,
SIGTERM and Ctrl-C checkpoints, on a least-squares problem small enough to run in seconds."""
import csv
import json
import os
import signal

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from diffgns.graph.fit import (
    CHECKPOINT,
    TrainConfig,
    TrainingInterrupted,
    fit,
    learning_rate,
    load_checkpoint,
    make_optimizer,
    step_rng,
)

W_TRUE = np.array([1.5, -2.0, 0.5])


def _problem(tcfg: TrainConfig, hook=None):
    """(update, params0, opt_state0): linear least squares on batches drawn from the step."""
    opt = make_optimizer(tcfg)

    @jax.jit
    def step_fn(p, s, x, y):
        loss, g = jax.value_and_grad(lambda p: jnp.mean((x @ p["w"] - y) ** 2))(p)
        u, s = opt.update(g, s, p)
        return optax.apply_updates(p, u), s, loss

    def update(p, s, step):
        rng, _ = step_rng(tcfg.seed, step)
        x = rng.normal(size=(tcfg.batch_size, 3)).astype(np.float32)
        if hook:
            hook(step)
        p, s, loss = step_fn(p, s, x, x @ W_TRUE.astype(np.float32))
        return p, s, (loss, 2 * loss)

    p0 = {"w": jnp.zeros(3)}
    return update, p0, opt.init(p0)


def _cfg(steps, **kw):
    return TrainConfig(steps=steps, batch_size=8, lr=0.5, lr_final=0.05, lr_decay_steps=30,
                       log_every=5, checkpoint_every=10, validate_every=10, **kw)


def _fit(out, steps, hook=None, **kw):
    update, p0, s0 = _problem(_cfg(steps), hook)
    return fit(update, p0, s0, _cfg(steps), out, {"run": "toy"}, ["loss", "twice"],
               progress=False, **kw)


def test_fit_learns_logs_the_schedule_and_resumes_exactly(tmp_path):
    p, _, step = _fit(tmp_path / "a", 40)
    assert step == 40
    np.testing.assert_allclose(np.asarray(p["w"]), W_TRUE, atol=0.15)
    rows = list(csv.DictReader((tmp_path / "a" / "train_log.csv").open()))
    assert list(rows[0]) == ["step", "loss", "twice", "lr", "seconds"]
    assert [int(r["step"]) for r in rows] == list(range(5, 45, 5))
    for r in rows:  # the logged rate is the schedule's at that step, floored at lr_final
        assert float(r["lr"]) == pytest.approx(max(0.5 * 0.1 ** (int(r["step"]) / 30), 0.05),
                                               rel=5e-3)
        assert float(r["twice"]) == pytest.approx(2 * float(r["loss"]), rel=1e-4)
    assert float(rows[-1]["loss"]) < 0.05 * float(rows[0]["loss"])
    # stopped at 20 (a checkpoint), then resumed to 40: the same parameters, bit for bit
    _fit(tmp_path / "b", 20)
    p2, _, _ = _fit(tmp_path / "b", 40)
    np.testing.assert_array_equal(np.asarray(p2["w"]), np.asarray(p["w"]))
    assert json.loads((tmp_path / "b" / "checkpoint.json").read_text()) == {"run": "toy",
                                                                           "step": 40}
    rows_b = list(csv.DictReader((tmp_path / "b" / "train_log.csv").open()))
    assert [int(r["step"]) for r in rows_b] == list(range(5, 45, 5))  # one header only


def test_learning_rate_schedule_decays_to_the_floor():
    lr = learning_rate(_cfg(1))
    assert float(lr(0)) == pytest.approx(0.5)
    assert float(lr(15)) == pytest.approx(0.5 * 0.1**0.5, rel=1e-5)
    assert float(lr(30)) == pytest.approx(0.05, rel=1e-5)
    assert float(lr(1000)) == pytest.approx(0.05, rel=1e-6)


def test_validation_runs_on_its_period_and_at_the_end(tmp_path):
    seen = []

    def validate(p):
        seen.append(np.asarray(p["w"]).copy())
        return {"error": float(np.abs(np.asarray(p["w"]) - W_TRUE).max())}

    _fit(tmp_path, 25, validate=validate, show=("error",))
    lines = [json.loads(s) for s in (tmp_path / "valid_log.jsonl").read_text().splitlines()]
    assert [d["step"] for d in lines] == [10, 20, 25]
    assert lines[-1]["error"] < lines[0]["error"]


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_checkpoints_the_step_in_flight_and_the_run_resumes(tmp_path, signum, capsys):
    straight, _, _ = _fit(tmp_path / "straight", 30)
    before = [signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)]
    kill = lambda step: step == 12 and os.kill(os.getpid(), signum)
    with pytest.raises(TrainingInterrupted) as e:
        _fit(tmp_path / "run", 30, hook=kill)
    assert e.value.code == 128 + signum and e.value.step == 13  # the step in flight completed
    assert [signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)] == before  # restored
    err = capsys.readouterr().err
    name = signal.Signals(signum).name
    assert f"training interrupted by {name}; checkpoint of step 13 written to" in err
    from diffgns.cli.checks import report_interrupt

    assert report_interrupt(e.value) == 128 + signum  # the command line adds no second line
    assert capsys.readouterr().err == ""
    update, p0, s0 = _problem(_cfg(30))
    _, _, step = load_checkpoint(tmp_path / "run" / CHECKPOINT, p0, s0)
    assert step == 13
    rows = list(csv.DictReader((tmp_path / "run" / "train_log.csv").open()))
    assert int(rows[-1]["step"]) == 13
    resumed, _, _ = _fit(tmp_path / "run", 30)
    np.testing.assert_array_equal(np.asarray(resumed["w"]), np.asarray(straight["w"]))


def test_ctrl_c_keeps_the_last_completed_step(tmp_path):
    def interrupt(step):
        if step == 7:
            raise KeyboardInterrupt

    with pytest.raises(TrainingInterrupted) as e:  # no traceback: exit status 130
        _fit(tmp_path, 30, hook=interrupt)
    assert e.value.code == 130 and e.value.step == 7
    update, p0, s0 = _problem(_cfg(30))
    p, _, step = load_checkpoint(tmp_path / CHECKPOINT, p0, s0)
    assert step == 7
    ref, _, _ = _fit(tmp_path / "ref", 7)
    np.testing.assert_array_equal(np.asarray(p["w"]), np.asarray(ref["w"]))


def test_resume_after_a_hard_kill_drops_later_log_rows_and_keeps_counting_seconds(tmp_path):
    """Killed (SIGKILL) after logging steps the checkpoint does not hold: the resumed run
    drops those rows and logs them again; ``seconds`` continues from the checkpoint."""
    _fit(tmp_path, 20, validate=lambda p: {"e": 0.0})
    log, valid = tmp_path / "train_log.csv", tmp_path / "valid_log.jsonl"
    with log.open("a") as f:  # written after the checkpoint at 20, then killed
        f.write("25,1,2,0.1,999.0\n26,1")
    with valid.open("a") as f:
        f.write(json.dumps({"step": 25, "e": 1.0}) + "\n")
    before = float(list(csv.DictReader(log.open()))[3]["seconds"])
    _fit(tmp_path, 30, validate=lambda p: {"e": 0.0})
    rows = list(csv.DictReader(log.open()))
    assert [int(r["step"]) for r in rows] == [5, 10, 15, 20, 25, 30]
    assert float(rows[4]["seconds"]) >= before and float(rows[4]["seconds"]) != 999.0
    assert [json.loads(s)["step"] for s in valid.read_text().splitlines()] == [10, 20, 30]


def test_checkpoints_are_orbax_and_a_killed_save_keeps_the_previous_one(tmp_path):
    """The run folder holds one orbax step folder (the newest) and the sidecar; an
    unfinished orbax save (a temporary folder left by a hard kill) is ignored on resume."""
    _fit(tmp_path, 20)
    ck = tmp_path / CHECKPOINT
    assert sorted(p.name for p in ck.iterdir()) == ["20"]
    assert (ck / "20" / "state").is_dir() and (ck / "20" / "host").is_dir()
    (ck / "30.orbax-checkpoint-tmp-123").mkdir()  # a save killed before its rename
    update, p0, s0 = _problem(_cfg(30))
    _, _, step = load_checkpoint(tmp_path, p0, s0)
    assert step == 20
    p, _, _ = _fit(tmp_path, 30)
    ref, _, _ = _fit(tmp_path / "ref", 30)
    np.testing.assert_array_equal(np.asarray(p["w"]), np.asarray(ref["w"]))


def test_a_run_with_a_legacy_msgpack_checkpoint_resumes_exactly(tmp_path):
    """Runs written before orbax left ``checkpoint.msgpack`` (flax msgpack of params,
    optimiser state, step and host): fit resumes from it, bit-identical, and saves in orbax."""
    from flax import serialization

    from diffgns.graph.fit import LEGACY_CHECKPOINT, checkpoint_host_state

    p20, s20, _ = _fit(tmp_path / "a", 20)
    state = serialization.to_state_dict(dict(params=p20, opt_state=s20, step=np.asarray(20)))
    state["host"] = dict(seconds=1.5)
    old = tmp_path / "old"
    old.mkdir()
    (old / LEGACY_CHECKPOINT).write_bytes(serialization.msgpack_serialize(state))
    assert checkpoint_host_state(old / LEGACY_CHECKPOINT) == {"seconds": 1.5}
    update, p0, s0 = _problem(_cfg(30))
    assert load_checkpoint(old / LEGACY_CHECKPOINT, p0, s0)[2] == 20
    p, _, step = _fit(old, 30)
    ref, _, _ = _fit(tmp_path / "ref", 30)
    assert step == 30
    np.testing.assert_array_equal(np.asarray(p["w"]), np.asarray(ref["w"]))
    assert load_checkpoint(old, p0, s0)[2] == 30  # now from orbax
    assert checkpoint_host_state(old)["seconds"] >= 1.5
