"""OnlineLearner (saml_ros.core.online): ingest -> buffer -> primal-dual updates, telemetry, checkpoints, resume."""

from __future__ import annotations

import functools
import os
import signal
import time
from pathlib import Path

import pytest
from helpers.online import SPEC, checkpointed_learner, config, transitions, wait_until

from saml_ros.core.model.checkpoint import CheckpointStore
from saml_ros.core.online import (
    LearnerSetup,
    LoopConfig,
    ResumeError,
    TrainingProcess,
)
from saml_ros.core.runtime.child_launch import launch_child


# ------------------------------------------------------------------------------------------- training process
def _setup(run_dir: Path, **kw: object) -> LearnerSetup:
    base: dict[str, object] = {
        "system": "friction", "system_params": {}, "spec": SPEC.to_dict(), "config": config(),
        "run_dir": str(run_dir), "loop": LoopConfig(telemetry_rate=20.0, checkpoint_period=0.2), "niceness": 0,
    }
    base.update(kw)
    return LearnerSetup(**base)  # type: ignore[arg-type]


def test_training_process_trains_checkpoints_and_stops_with_a_final_checkpoint(tmp_path: Path) -> None:
    saved: list[tuple[str, int]] = []
    errors: list[str] = []
    proc = TrainingProcess(_setup(tmp_path / "run"), on_checkpoint=lambda p, v: saved.append((p, v)),
                           on_error=lambda what, text: errors.append(text))
    ready = proc.start()
    assert ready.resumed is None and ready.hidden == [4, 2] and ready.status["updates"] == 0
    assert ready.threads == 1 and ready.flush_denormal  # the defaults: one intra-op thread, subnormals flushed
    for tr in transitions(400, seed=20):
        proc.submit(tr)
    wait_until(lambda: proc.status.get("updates", 0) >= 100 and len(saved) >= 2)
    assert proc.status["buffer_size"] == 400 and proc.status["window"] == 300
    assert [v for _, v in saved] == list(range(1, len(saved) + 1))
    final = proc.stop()
    assert final is not None and final[1] >= saved[-1][1] and final[2] >= 100
    assert not errors and proc.dropped == 0
    found = CheckpointStore(tmp_path / "run").load_latest_valid()
    assert found is not None and found.version == final[1] and found.meta["updates"] == final[2]


def test_a_cancelled_start_kills_the_starting_training_process_without_waiting_for_it(tmp_path: Path) -> None:
    """A stop signal during a node's start-up: ``start(cancelled=...)`` gives up as soon as the predicate says so
    (the child is still importing torch and warming up, seconds away from ready), kills the child and writes
    nothing; without a predicate the same start runs to ready."""
    from saml_ros.core.online import StartCancelled

    t0 = time.monotonic()
    proc = TrainingProcess(_setup(tmp_path / "run"))
    launched = launch_child()
    child = launched[0]
    with pytest.raises(StartCancelled):
        proc.start(launched=launched, cancelled=lambda: time.monotonic() - t0 > 0.2)
    assert child.poll() is not None, "the starting child was not ended"
    assert proc.ready is None and time.monotonic() - t0 < 10.0
    other = TrainingProcess(_setup(tmp_path / "run2"))
    assert other.start(cancelled=lambda: False).status["updates"] == 0
    assert other.stop() is not None


def test_paused_training_process_buffers_but_neither_trains_nor_checkpoints(tmp_path: Path) -> None:
    """What a managed learner's deactivation relies on: started paused it buffers data and reports, but makes no
    update; pause() writes one checkpoint of the unsaved updates and then nothing more; resume() trains on."""
    saved: list[int] = []
    proc = TrainingProcess(_setup(tmp_path / "run", paused=True), on_checkpoint=lambda p, v: saved.append(v))
    proc.start()
    for tr in transitions(400, seed=23):
        proc.submit(tr)
    wait_until(lambda: proc.status.get("buffer_size", 0) == 400)
    time.sleep(0.5)  # 2.5 checkpoint periods
    assert proc.status["updates"] == 0 and not saved and proc.paused
    assert proc.resume()
    wait_until(lambda: proc.status.get("updates", 0) >= 50 and len(saved) >= 1)
    paused = proc.pause()
    assert paused is not None and paused[1] == saved[-1]
    updates = paused[2]
    # one checkpoint on pause, unless the last periodic one already held every update
    latest = CheckpointStore(tmp_path / "run").load_latest_valid()
    assert latest is not None and latest.version == paused[1] and latest.meta["updates"] == updates
    time.sleep(0.6)  # three checkpoint periods: no update, no checkpoint
    assert proc.status["updates"] == updates and saved[-1] == paused[1]
    assert CheckpointStore(tmp_path / "run").versions()[-1] == paused[1]
    again = proc.pause()  # pausing a paused process writes nothing
    assert again is not None and again[0] is None and again[1] == paused[1]
    assert proc.resume()
    wait_until(lambda: proc.status.get("updates", 0) > updates and saved[-1] > paused[1])
    final = proc.stop()
    assert final is not None and final[2] > updates


def test_training_process_reports_resume_errors_and_survives_being_killed(tmp_path: Path) -> None:
    run = tmp_path / "run"
    checkpointed_learner(tmp_path, seed=21, updates=30)  # a real checkpoint of a (4, 2) friction model in run
    with pytest.raises(ResumeError, match="hidden"):
        TrainingProcess(_setup(run, config=config(hidden=(8,)))).start()
    errors: list[str] = []
    proc = TrainingProcess(_setup(run), on_error=lambda what, text: errors.append(text))
    ready = proc.start()
    assert ready.resumed is not None and ready.resumed["version"] == 1 and ready.resumed["updates"] == 30
    pid = proc.pid
    assert pid is not None
    os.kill(pid, signal.SIGKILL)
    wait_until(lambda: proc.restarts == 1 and proc.pid != pid)
    assert "exited unexpectedly" in errors[0]
    for tr in transitions(300, seed=22):
        proc.submit(tr)
    wait_until(lambda: proc.status.get("updates", 0) > 30)  # resumed from version 1, then trained on
    final = proc.stop()
    assert final is not None and final[2] > 30


def test_training_process_applies_its_thread_and_subnormal_settings(tmp_path: Path) -> None:
    """What the child reports is what torch says inside it after applying the setup's settings."""
    messages: list[str] = []
    proc = TrainingProcess(_setup(tmp_path / "run", threads=3, flush_denormal=False),
                           on_log=lambda level, text: messages.append(text))
    ready = proc.start()
    try:
        assert ready.threads == 3 and not ready.flush_denormal and proc.ready == ready
        assert any("3 torch intra-op thread(s), subnormal floats not flushed" in m for m in messages)
    finally:
        proc.stop()
    with pytest.raises(ValueError, match="threads"):
        _setup(tmp_path / "run", threads=-1)


def _collect(into: list[str], level: int, text: str) -> None:
    into.append(text)


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is Linux's")
def test_training_process_runs_at_the_lower_priority_it_was_given(tmp_path: Path) -> None:
    """idle: the training process (and the threads it starts) run under SCHED_IDLE; niceness: its nice value is
    ours plus the increment; neither lowers this process. Read from the OS, not from the child's report."""
    for kw, policy, nice in (({"idle": True}, os.SCHED_IDLE, None), ({"niceness": 7}, os.SCHED_OTHER, 7)):
        messages: list[str] = []
        proc = TrainingProcess(_setup(tmp_path / f"run{policy}", **kw), on_log=functools.partial(_collect, messages))
        proc.start()
        try:
            pid = proc.pid
            assert pid is not None
            # every thread of the child (its loop's threads once it has set itself up; in a full suite run it may
            # still be one), read from the OS
            deadline = time.monotonic() + 5.0
            while len(tids := [int(t) for t in os.listdir(f"/proc/{pid}/task")]) < 2 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert tids, pid
            assert {os.sched_getscheduler(t) for t in tids} == {policy}, kw
            if nice is not None:
                assert {os.getpriority(os.PRIO_PROCESS, t) for t in tids} == {os.getpriority(os.PRIO_PROCESS, 0) + nice}
            assert any(("SCHED_IDLE" if policy == os.SCHED_IDLE else f"nice {os.nice(0) + 7}") in m
                       for m in messages), messages
            if policy == os.SCHED_IDLE and os.geteuid() == 0:
                # stop() first returns a starved idle child to the normal policy (where allowed, as root here)
                proc._lift_idle_policy()
                assert {os.sched_getscheduler(t) for t in tids} == {os.SCHED_OTHER}
        finally:
            proc.stop()
    assert os.sched_getscheduler(0) == os.SCHED_OTHER


def test_the_node_prelaunches_the_training_interpreter_without_importing_torch() -> None:
    """The node starts the training interpreter first thing, so that it imports torch in parallel: the launcher
    must not import torch itself."""
    import subprocess
    import sys

    code = ("import sys; from saml_ros.nodes.learner import prelaunch_trainer; proc, conn = prelaunch_trainer(); "
            "print('torch' in sys.modules); conn.close(); proc.wait(30)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == "False", out.stderr


def test_the_training_process_pays_its_one_time_costs_before_it_is_ready(tmp_path: Path) -> None:
    """The first torch optimizer imports torch._dynamo (2-3 s): warm_up does it before "ready", so the first
    update (while a robot is already streaming) does not; the log says what became of the fused kernel."""
    import subprocess
    import sys

    code = ("import sys; from saml_ros.core.online.child import warm_up; before = 'torch._dynamo' in sys.modules; "
            "w = warm_up(); print(before, 'torch._dynamo' in sys.modules, w['kernel'])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    before, after, *kernel = out.stdout.split()
    assert (before, after) == ("False", "True"), out.stderr
    assert " ".join(kernel).startswith(("loaded", "not used: ", "not built yet"))
    messages: list[str] = []
    proc = TrainingProcess(_setup(tmp_path / "run"), on_log=lambda level, text: messages.append(text))
    proc.start()
    try:
        assert any(m.startswith("training process warmed up in") for m in messages), messages
    finally:
        proc.stop()
