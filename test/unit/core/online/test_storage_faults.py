"""Checkpoint writes that fail (ROS-free): the back-off policy, the windowed /diagnostics levels, and the online
learner and its training loop on a run directory that really stops taking writes (a path component that becomes
a file: the OS refuses every write with ENOTDIR, for root too, on any filesystem).

The learner node under a full and a read-only disk (real processes, a real tmpfs) is
``test_disk_faults.py``."""

from __future__ import annotations

import errno
import os
import threading
import time
from multiprocessing import Pipe
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from msg_schemas.telemetry import ERROR, OK, WARN
from saml_ros.core.model.checkpoint import CheckpointStore
from saml_ros.core.online import LoopConfig, OnlineConfig, OnlineLearner, run_loop
from saml_ros.core.online.messages import Checkpointed, ErrorReport, Status, Stop
from saml_ros.core.online.recent_counts import RecentCounts
from saml_ros.core.online.report import learner_diagnostics, level_counters, stopped_message
from saml_ros.core.online.storage import MAX_BACKOFF_PERIODS, WriteBackoff, WriteFailure
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import TrainConfig

SYSTEM = get_system("friction")
SPEC = ProblemSpec.for_system(SYSTEM.paper_spec(), SYSTEM)


# ------------------------------------------------------------------------------------------ back-off policy
def test_backoff_waits_one_two_four_periods_up_to_the_cap_and_resets_on_success() -> None:
    now = [100.0]
    b = WriteBackoff(clock=lambda: now[0])
    assert not b.failing and b.may_write(10.0) and b.describe(10.0) == "" and b.delay(10.0) == 0.0
    enospc = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "/run/x/.ckpt-000003.saml.ab.tmp")
    waits = []
    for _ in range(6):
        b.failed(enospc, "/run/x")
        waits.append(b.delay(10.0))
        assert not b.may_write(10.0)
        now[0] += waits[-1] - 0.01
        assert not b.may_write(10.0)  # never sooner than the back-off
        now[0] += 0.01
        assert b.may_write(10.0)
    assert waits == [10.0, 20.0, 40.0, 80.0, 80.0, 80.0] and MAX_BACKOFF_PERIODS == 8
    assert b.failures == 6 and b.errors == 6
    text = b.describe(10.0)
    assert text.startswith("No space left on device [errno 28]: /run/x/.ckpt-000003.saml.ab.tmp; 6 failed write(s)")
    assert "last good checkpoint 310 s ago" in text and "next attempt in 0.0 s" in text
    b.spent(0.25)
    b.spent(-1.0)  # a clock step back is no time spent
    assert b.values() == {"checkpoint_write_errors": 6.0, "checkpoint_write_failures": 6.0, "checkpoint_age_s": 310.0,
                          "checkpoint_write_seconds": 0.25}
    ended, outage = b.succeeded()
    assert (ended, outage) == (6, 310.0)
    assert not b.failing and b.describe(10.0) == "" and b.may_write(10.0)
    assert b.values() == {"checkpoint_write_errors": 6.0, "checkpoint_write_failures": 0.0, "checkpoint_age_s": 0.0,
                          "checkpoint_write_seconds": 0.25}
    # an error without a file name names the run directory
    f = WriteFailure.from_error(OSError(errno.EROFS, "Read-only file system"), "/run/x", 1.0)
    assert (f.reason, f.errno, f.path) == ("Read-only file system", errno.EROFS, "/run/x")
    with pytest.raises(ValueError):
        WriteBackoff(max_periods=0)


# ------------------------------------------------------------------------------------------ windowed levels
def test_recent_counts_are_the_increase_over_the_window_and_survive_a_counter_reset() -> None:
    now = [0.0]
    rc = RecentCounts(10.0, clock=lambda: now[0])
    assert rc.update({"a": 3}) == {"a": 3.0}  # counted before the first report: recent
    now[0] = 5.0
    assert rc.update({"a": 3}) == {"a": 3.0}
    now[0] = 10.0
    assert rc.update({"a": 3}) == {"a": 0.0}  # the 3 are older than the window now
    now[0] = 11.0
    assert rc.update({"a": 5}) == {"a": 2.0}
    now[0] = 12.0
    assert rc.update({"a": 1}) == {"a": 3.0}  # restarted from 0 and counted 1: +1, never negative
    now[0] = 30.0
    assert rc.update({"a": 1, "b": 2}) == {"a": 0.0, "b": 2.0}
    with pytest.raises(ValueError):
        RecentCounts(0.0)


def _diag(status: dict[str, float], totals: dict[str, int] | None = None, process: dict[str, int] | None = None,
          recent: dict[str, float] | None = None, notes: dict[str, str] | None = None) -> tuple[int, str, dict[str, Any]]:
    base = {"buffer_size": 500.0, "updates": 2000.0, "model_version": 4.0}
    return learner_diagnostics(totals or {"paired": 500}, {**base, **status}, process or {}, {}, [], [],
                               recent=recent, notes=notes)


def test_levels_come_from_recent_windows_and_counters_stay_counters() -> None:
    # the old behaviour without a window: anything ever counted keeps the level up
    process = {"train_errors": 3, "dropped": 0}
    level, _, values = _diag({}, {"paired": 500, "nan": 2}, process)
    assert level == ERROR and values["train_errors"] == 3 and values["rejected/nan"] == 2
    # with a window in which nothing grew: OK, and the counters are still reported as they are
    quiet = dict.fromkeys(level_counters({"nan": 2}, {}, process), 0.0)
    level, _, values = _diag({}, {"paired": 500, "nan": 2}, process, recent=quiet)
    assert level == OK and values["train_errors"] == 3 and values["rejected/nan"] == 2
    assert _diag({}, recent={**quiet, "rejected": 1.0})[0] == WARN
    assert _diag({}, recent={**quiet, "dropped": 1.0})[0] == ERROR
    # a failing checkpoint write is ERROR now, named with its cause; back to OK after a good write
    text = "No space left on device [errno 28]: /r/.ckpt-000005.saml.x.tmp; 2 failed write(s) in a row, ..."
    level, message, values = _diag({"checkpoint_write_failures": 2.0, "checkpoint_write_errors": 2.0,
                                    "checkpoint_age_s": 31.25, "unsaved_updates": 900.0}, recent=quiet,
                                   notes={"checkpoint_write_error": text})
    assert level == ERROR and message.startswith("checkpoint writes failing: No space left on device")
    assert values["checkpoint_write_error"] == text and values["checkpoint_write_failures"] == 2
    assert values["checkpoint_age_s"] == 31.2 and values["unsaved_updates"] == 900
    level, message, values = _diag({"checkpoint_write_failures": 0.0, "checkpoint_write_errors": 2.0}, recent=quiet,
                                   notes={"checkpoint_write_error": ""})
    assert level == OK and "failing" not in message and values["checkpoint_write_errors"] == 2


def test_a_final_checkpoint_that_cannot_be_written_is_an_error_saying_what_is_not_saved() -> None:
    error, text = stopped_message((None, 4, 5000), 5000, 800, 200, "shutdown", unsaved=1200)
    assert error and "could not be written" in text and "1200 updates are not saved" in text and "version 4" in text
    error, text = stopped_message((None, 4, 5000), 5000, 800, 200, "shutdown", unsaved=0)
    assert not error and "version 4 is current" in text


# ------------------------------------------------------------------------------------------ a real failing run_dir
class Unwritable:
    """``base / "a" / "run"`` as the run directory; :meth:`start` turns ``base / "a"`` into a file (the directory
    moves to ``base / "away"``), so every write into the run directory fails with ENOTDIR; :meth:`end` undoes it."""

    def __init__(self, base: Path) -> None:
        self.base = base
        self.run_dir = base / "a" / "run"
        self.run_dir.mkdir(parents=True)
        self.broken = False

    def start(self) -> None:
        os.rename(self.base / "a", self.base / "away")
        (self.base / "a").write_text("a file where the run directory's parent was\n")
        self.broken = True

    def end(self) -> None:
        (self.base / "a").unlink()
        os.rename(self.base / "away", self.base / "a")
        self.broken = False

    def view(self) -> Path:
        """Where the run directory's files are now."""
        return self.base / "away" / "run" if self.broken else self.run_dir


def _trained_learner(run_dir: Path, clock: Any = time.monotonic) -> OnlineLearner:
    cfg = OnlineConfig(min_transitions=200, train=TrainConfig(batch_size=64, primal_lr=3e-3, dual_lr=1e-2),
                       buffer_capacity=2000, telemetry_window=200)
    learner = OnlineLearner(SYSTEM, SPEC, cfg, store=CheckpointStore(run_dir, keep=3), clock=clock)
    x, u = SYSTEM.sample_inputs(400, np.random.default_rng(0))
    learner.add_batch(x, u, SYSTEM.true_step_np(x, u))
    return learner


def test_learner_backs_off_a_failing_run_dir_keeps_latest_and_recovers(tmp_path: Path,
                                                                        caplog: pytest.LogCaptureFixture) -> None:
    now = [0.0]
    disk = Unwritable(tmp_path)
    learner = _trained_learner(disk.run_dir, clock=lambda: now[0])
    learner.update(20)
    assert learner.save_checkpoint() == (disk.run_dir / "ckpt-000001.saml", 1)
    disk.start()
    learner.update(20)
    now[0] = 1.0
    assert learner.checkpoint_due(1.0)
    with pytest.raises(NotADirectoryError):
        learner.save_checkpoint()
    status = learner.status()
    assert status["checkpoint_write_failures"] == 1 and status["unsaved_updates"] == 20
    assert "Not a directory [errno 20]" in learner.writes.describe(1.0)
    assert not learner.checkpoint_due(1.0)  # backed off: not at once ...
    now[0] = 1.99
    assert not learner.checkpoint_due(1.0)
    now[0] = 2.0
    assert learner.checkpoint_due(1.0)  # ... one period later
    with pytest.raises(NotADirectoryError):
        learner.save_checkpoint()
    now[0] = 3.5
    assert not learner.checkpoint_due(1.0)  # then two periods
    store = CheckpointStore(disk.view())
    assert store.latest() == (disk.view() / "ckpt-000001.saml", 1) and store.load_latest() is not None
    disk.end()
    now[0] = 4.0
    assert learner.checkpoint_due(1.0)
    with caplog.at_level("WARNING", logger="saml_ros"):
        assert learner.save_checkpoint() == (disk.run_dir / "ckpt-000002.saml", 2)
    assert "writing works again after 2 failed write(s), 4.0 s without a good checkpoint" in caplog.text
    status = learner.status()
    assert status["checkpoint_write_failures"] == 0 and status["checkpoint_write_errors"] == 2
    assert status["unsaved_updates"] == 0 and learner.writes.describe(1.0) == ""
    loaded = CheckpointStore(disk.run_dir).load_latest()
    assert loaded is not None and loaded[1]["updates"] == 40


def test_training_loop_keeps_training_with_bounded_errors_while_writes_fail(tmp_path: Path) -> None:
    """The training loop on a run directory that stops taking writes for 1.25 s, with a checkpoint period of 0.125 s:
    at most one error report per period (the back-off makes it fewer), every status names the cause, training goes
    on, and the first write after the recovery succeeds."""
    disk = Unwritable(tmp_path)
    learner = _trained_learner(disk.run_dir)
    parent, child = Pipe()
    got: list[tuple[float, Any]] = []
    lock = threading.Lock()

    def send(msg: Any) -> None:
        with lock:
            got.append((time.monotonic(), msg))

    loop = LoopConfig(telemetry_rate=20.0, checkpoint_period=0.125)
    thread = threading.Thread(target=run_loop, args=(learner, loop, child, send), daemon=True)
    thread.start()

    def of(kind: type[Any], what: str | None = None, since: float = 0.0) -> list[tuple[float, Any]]:
        with lock:
            return [(t, m) for t, m in got if isinstance(m, kind) and t >= since and (what is None or m.what == what)]

    def wait(pred: Any, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while not pred():
            assert time.monotonic() < deadline, "timed out"
            time.sleep(0.02)

    try:
        wait(lambda: len(of(Checkpointed)) >= 2)
        disk.start()
        t0 = time.monotonic()
        updates0 = learner.updates


        def after_first_error() -> list[Any]:
            """The statuses sent after the first error report (under load the first attempt can come late)."""
            with lock:
                seq = list(got)
            first = next((i for i, (t, m) in enumerate(seq) if t >= t0 and isinstance(m, ErrorReport)
                          and m.what == "checkpoint"), None)
            return [] if first is None else [m for _, m in seq[first + 1:] if isinstance(m, Status)]

        wait(lambda: time.monotonic() - t0 >= 1.25 and len(after_first_error()) >= 3)
        errors = of(ErrorReport, "checkpoint", t0)
        statuses = after_first_error()
        updates1 = learner.updates
        window = time.monotonic() - t0
        disk.end()
        t1 = time.monotonic()
        wait(lambda: len(of(Checkpointed, since=t1)) >= 1, timeout=30.0)
    finally:
        parent.send(Stop())
        thread.join(30)
    assert 1 <= len(errors) <= window / 0.125 + 1, [m for _, m in errors]
    assert all("Not a directory" in m.message and "stays the latest" in m.message for _, m in errors)
    assert statuses and all(m.status["checkpoint_write_failures"] >= 1 for m in statuses)
    assert all("Not a directory [errno 20]" in m.notes["checkpoint_write_error"] for m in statuses)
    assert updates1 > updates0  # training went on
    last = of(Status)[-1][1]
    assert last.status["checkpoint_write_failures"] == 0 and last.notes["checkpoint_write_error"] == ""


# ------------------------------------------------------------------------------------------ a bag cut off
def test_repair_says_in_words_where_a_cut_off_bag_stopped(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A bag file cut at every 997th byte (a killed recorder, a full disk): every repair that recovers something says
    where and why reading stopped, never the MCAP reader's internal text ("unpack requires a buffer of 8 bytes",
    a bare "EndOfFile")."""
    from helpers.bag_publisher import rollout

    from msg_schemas import DATA_QOS, TypestoreFactory, get_schema
    from saml_ros.bags import info as bag_info
    from saml_ros.bags.io import BagError, BagWriter, jazzy_typestore, repair_bag

    factory = TypestoreFactory(jazzy_typestore())
    schema = get_schema("friction")
    w = BagWriter(tmp_path / "live", flush_period=0.0)  # a chunk per message: cuts land in and between chunks
    w.add_topic("/friction/state", "sensor_msgs/msg/JointState", DATA_QOS)
    for ev in rollout("friction", 60, 0, seed=1, t0_ns=10**9):
        w.write_msg("/friction/state", schema.state_to_msg(ev["x"], ev["stamp"], factory=factory), ev["stamp"])
    w.flush()
    data = (tmp_path / "live" / "live.mcap").read_bytes()
    w.close()
    problems = []
    for i, cut in enumerate(range(997, len(data), 997)):
        src = tmp_path / f"cut{i}"
        src.mkdir()
        (src / "x.mcap").write_bytes(data[:cut])
        try:
            res = repair_bag(src)
        except BagError:
            continue  # nothing complete before the cut
        problems.append(res.problem)
    assert len(problems) >= 5
    for p in problems:
        assert p.startswith("x.mcap: the file ends inside a record after byte ") and "was cut off" in p, p
        assert "unpack" not in p and "EndOfFile" not in p
    # and as bag_info --repair prints it
    assert bag_info.main([str(tmp_path / "cut3"), "--repair", "--out", str(tmp_path / "out3")]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("bag_info: recovered ") and "source stopped early: x.mcap: the file ends inside a record" \
        in first, first
