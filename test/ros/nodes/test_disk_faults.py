"""Real processes on a disk that fails under them: the learner node whose run directory fills up and turns
read-only, then recovers; the recorder whose bag's disk fills up.

Learner, what must show (issue 29): at most one log line per checkpoint period, the cause on /diagnostics
(``checkpoint_write_error``: the OS message, the path, the time since the last good write; level ERROR), training
going on at full speed, OK again once writes succeed, and ``latest`` naming a valid checkpoint the whole time.
Recorder: it stops at the first failed write (one error line, no traceback, no spinning), exits 1 saying how the
data is recovered, and ``bag_info --repair`` recovers it with a clear message.

The tests run as root, which ignores permission bits, so the failures are made with mechanisms that hold for
root: a small tmpfs mounted for the test, filled up (ENOSPC) and remounted read-only (EROFS). Where mounting is not
allowed (an unprivileged container), the run directory is made immutable (``chattr +i``: EPERM) or, failing that,
its parent directory is replaced by a file (ENOTDIR), and the recorder's file size is limited (``RLIMIT_FSIZE``:
EFBIG): one of them works everywhere, so the tests never skip.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import resource
import shutil
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from helpers import ros_helpers
from helpers.learner_node import BASE_PARAMS, Learner, RosSide, episodes

rclpy = pytest.importorskip("rclpy")

PERIOD = 0.5  # checkpoint period (s)
WINDOW = 6.0  # wall seconds per rate measurement
OUTAGE = 8.0  # wall seconds each outage lasts


# ------------------------------------------------------------------------------------------ failing disks
def _run(*cmd: str) -> subprocess.CompletedProcess[str]:
    """Run ``cmd``; a missing program is a failed run (return code 127), not an exception."""
    try:
        return subprocess.run(list(cmd), capture_output=True, text=True, timeout=30)
    except FileNotFoundError as exc:
        return subprocess.CompletedProcess(list(cmd), 127, "", str(exc))


class Tmpfs:
    """A 16 MB tmpfs mounted at ``mnt`` (root with CAP_SYS_ADMIN): filled up (ENOSPC), remounted read-only (EROFS)."""

    name = "tmpfs"

    def __init__(self, mnt: Path) -> None:
        self.mnt = mnt
        mnt.mkdir(parents=True, exist_ok=True)
        res = _run("mount", "-t", "tmpfs", "-o", "size=16m,mode=0755", "tmpfs", str(mnt))
        if res.returncode != 0:
            raise OSError(f"mount -t tmpfs failed: {res.stderr.strip()}")
        self.filler = mnt / "filler"

    def fill(self) -> int:
        """Fill the filesystem to the last page; returns the bytes written."""
        fd = os.open(self.filler, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        written = 0
        try:
            for chunk in (1 << 20, 4096):
                block = b"\0" * chunk
                while True:
                    try:
                        written += os.write(fd, block)
                    except OSError as exc:
                        if exc.errno != errno.ENOSPC:
                            raise
                        break
        finally:
            os.close(fd)
        return written

    def unfill(self) -> None:
        self.filler.unlink()

    def remount(self, mode: str) -> None:
        """``ro`` or ``rw``; retried while a file is open for writing (EBUSY)."""
        deadline = time.monotonic() + 10.0
        while True:
            res = _run("mount", "-o", f"remount,{mode}", str(self.mnt))
            if res.returncode == 0:
                return
            if time.monotonic() > deadline:
                raise OSError(f"mount -o remount,{mode} failed: {res.stderr.strip()}")
            time.sleep(0.05)

    def close(self) -> None:
        _run("umount", "-l", str(self.mnt))


class Outage:
    """One way to make the run directory refuse writes: ``start`` / ``end``, the OS message it causes, and where the
    run directory's files are meanwhile (``view``)."""

    def __init__(self, name: str, message: str, start: Any, end: Any, view: Path, away: Path | None = None) -> None:
        self.name, self.message = name, message
        self._start, self._end = start, end
        self.run_view, self.away_view = view, away or view
        self.active = False

    def start(self) -> None:
        self._start()
        self.active = True

    def end(self) -> None:
        self._end()
        self.active = False

    def view(self) -> Path:
        return self.away_view if self.active else self.run_view


@contextlib.contextmanager
def failing_disks(base: Path) -> Iterator[tuple[Path, list[Outage], str]]:
    """``(run_dir, outages, how)``: the run directory and the outages this machine allows, best first."""
    try:
        fs = Tmpfs(base / "mnt")
    except OSError as why:
        no_mount = str(why)
    else:
        run_dir = fs.mnt / "run"
        run_dir.mkdir()
        try:
            yield run_dir, [
                Outage("disk full", "No space left on device", fs.fill, fs.unfill, run_dir),
                Outage("read-only", "Read-only file system", lambda: fs.remount("ro"), lambda: fs.remount("rw"),
                       run_dir),
            ], "a 16 MB tmpfs, filled up, then remounted read-only"
        finally:
            fs.close()
        return
    run_dir = base / "a" / "run"
    run_dir.mkdir(parents=True)
    if shutil.which("chattr") and _run("chattr", "+i", str(run_dir)).returncode == 0:
        _run("chattr", "-i", str(run_dir))
        try:
            yield run_dir, [Outage("immutable", "Operation not permitted", lambda: _run("chattr", "+i", str(run_dir)),
                                   lambda: _run("chattr", "-i", str(run_dir)), run_dir)], \
                f"chattr +i on the run directory ({no_mount})"
        finally:
            _run("chattr", "-i", str(run_dir))
        return

    def break_parent() -> None:
        os.rename(base / "a", base / "away")
        (base / "a").write_text("a file where the run directory's parent was\n")

    def mend_parent() -> None:
        (base / "a").unlink()
        os.rename(base / "away", base / "a")

    yield run_dir, [Outage("not a directory", "Not a directory", break_parent, mend_parent, run_dir,
                           base / "away" / "run")], f"the run directory's parent replaced by a file ({no_mount}; " \
                                                    "chattr +i not available)"


# ------------------------------------------------------------------------------------------ observation
class LatestWatch:
    """Reads ``latest`` and the checkpoint it names every 0.1 s in a thread (as any reader would: the MPC, a user's
    script): every read must succeed and the version must never go down. ``lock`` is held while reading, so an
    outage that moves the run directory starts and ends between two reads."""

    def __init__(self, outages: list[Outage]) -> None:
        self.outages = outages
        self.lock = threading.Lock()
        self.versions: list[int] = []
        self.problems: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _read(self, view: Path) -> int:
        from saml_ros.core.model.checkpoint import read_checkpoint

        for _ in range(5):  # the named file may be pruned between reading the pointer and opening it: read again
            name, version = (view / "latest").read_text().split()
            path = view / name
            if path.exists():
                _, meta = read_checkpoint(path)  # verifies the checksums: a partial file raises
                assert int(meta["version"]) == int(version), (meta["version"], version)
                return int(version)
        raise AssertionError(f"{view}: latest names a file that keeps vanishing")

    def _run(self) -> None:
        while not self._stop.is_set():
            with self.lock:
                view = next((o.view() for o in self.outages if o.active), self.outages[0].run_view)
                try:
                    v = self._read(view)
                    if self.versions and v < self.versions[-1]:
                        self.problems.append(f"latest went back from {self.versions[-1]} to {v}")
                    self.versions.append(v)
                except Exception as exc:  # noqa: BLE001 - every failure to read latest is a finding
                    self.problems.append(f"{type(exc).__name__}: {exc}")
            self._stop.wait(0.1)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` (s)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _lines(log: str, text: str) -> int:
    return sum(1 for line in log.splitlines() if text in line)


class Side(RosSide):
    """:class:`RosSide` for the learner in ``ns`` only (two learners publish on /diagnostics here)."""

    def __init__(self, domain: int, ns: str) -> None:
        self.full_name = f"{ns}/learner"
        super().__init__(domain, ns)

    def _on_diag(self, msg: Any) -> None:
        entries, _ = self.tele.diagnostics_from_msg(msg)
        for e in entries:
            if e.name == self.full_name:
                with self.lock:
                    self.diag, self.diag_level, self.diag_message = dict(e.values), e.level, e.message


class Run:
    """One learner process and the test's side of it."""

    def __init__(self, dom: ros_helpers.RosDomain, params: dict[str, Any], ns: str) -> None:
        self.ns = ns
        self.learner = Learner(dom, params, ns=ns)
        self.side = Side(dom.domain_id, ns)
        self.pid = 0

    def start(self, seed: int) -> None:
        self.learner.wait_log("training starts after", timeout=90.0)
        self.pid = int(re.search(r"training process pid (\d+)", self.learner.log()).group(1))  # type: ignore[union-attr]
        self.side.connect(self.ns)
        self.side.send(self.ns, episodes(400, np.random.default_rng(seed), t0=10**9, ep_len=8))

    def sample(self) -> tuple[float, float, float, float]:
        """``(wall time, updates, CPU seconds of the training process, seconds it spent writing checkpoints)``."""
        with self.side.lock:
            written = float(self.side.diag.get("checkpoint_write_seconds", "nan"))
        return time.monotonic(), self.side.last()["updates"], _cpu_seconds(self.pid), written


@dataclass
class Window:
    """One measurement window of the learner."""

    wall: float  # s
    updates: float
    cpu: float  # s of the training process
    writing: float  # s the training process spent writing checkpoints (good or failed attempts)

    @classmethod
    def measure(cls, run: Run, seconds: float) -> Window:
        t0, u0, c0, w0 = run.sample()
        time.sleep(seconds)
        t1, u1, c1, w1 = run.sample()
        return cls(t1 - t0, u1 - u0, c1 - c0, w1 - w0)

    @property
    def training_share(self) -> float:
        """The share of the window the training loop did not spend writing checkpoints."""
        return 1.0 - self.writing / self.wall

    def __str__(self) -> str:
        return (f"{self.updates / self.wall:.0f} updates/s ({self.updates / max(self.cpu, 1e-3):.0f} per CPU s), "
                f"{100 * self.writing / self.wall:.1f} % of the time writing")


# ------------------------------------------------------------------------------------------ the test
def test_full_and_read_only_run_dir_under_a_running_learner(tmp_path: Path, ros_env: ros_helpers.RosDomain) -> None:
    """The learner's run directory fills up, then turns read-only, 8 s each, under a learner training at full speed.

    Training rate: at full speed the rate is the update speed times the share of time the training loop does not
    spend writing checkpoints (it does nothing else at this pace: ingest is idle, metrics are a few ms per report).
    The test asserts that share during each outage at least 0.6 x the share right before and after it, and at most
    one failed attempt per checkpoint period (the back-off; each attempt logs a line). Idle, the outages' share was
    above the normal windows' (0.994 against 0.97: fewer writes); at load ~6 (three test workers and more beside
    them on the 2 cores) one outage window measured 0.73 x: the share is wall time, and a preempted write's wall time
    grows with the load. The rate itself is printed, not asserted: on this shared 2-core machine (load 8-12) the rate
    of a learner whose disk is fine moved by 0.9-1.8x between 6 s windows of one run (measured against a second,
    untouched learner beside it). Before the back-off a failed write was retried at once, 16-25 times a second, and
    the attempts took half the training loop's time with a 6000-transition buffer (``./dev bench storage`` run on
    the code before it; issue 29 measured training 4x slower): both checks fail that.
    """
    spec = tmp_path / "loose.yaml"  # a bound every model meets: the feasibility verdict leaves the level at OK
    from saml_ros.core.systems import get_system

    raw = get_system("friction").paper_spec()
    raw["constraints"][0]["eps"] = 5.0
    spec.write_text(yaml.safe_dump(raw))
    with failing_disks(tmp_path) as (run_dir, outages, how):
        print(f"failing writes with {how}")
        params = dict(BASE_PARAMS, min_transitions=200, checkpoint_period=PERIOD, diagnostics_rate=4.0,
                      spec_file=str(spec), training_niceness=0, run_dir=str(run_dir))
        run = Run(ros_env, params, "/friction")
        tester, learner = run.side, run.learner
        watch: LatestWatch | None = None
        windows: dict[str, Window] = {}
        try:
            run.start(3)
            # the level before any outage: OK, or WARN while the held-out stretches hold too few in-region
            # transitions for a verdict (the first seconds of a stream); never ERROR
            tester.wait(lambda: tester.counter("model_version") >= 3 and 0 <= tester.diag_level <= 1, 60.0,
                        "training, checkpoints and level OK or WARN")
            base_level = tester.diag_level
            watch = LatestWatch(outages)
            windows["normal 0"] = Window.measure(run, WINDOW)
            for i, outage in enumerate(outages):
                version = tester.counter("model_version")
                lines0 = _lines(learner.log(), "cannot write a checkpoint")
                with watch.lock:
                    outage.start()
                t0 = time.monotonic()
                try:
                    windows[outage.name] = Window.measure(run, WINDOW)
                    tester.wait(lambda: tester.diag_level == 2 and tester.counter("checkpoint_write_failures") >= 1,
                                max(0.0, OUTAGE - (time.monotonic() - t0)) + 5.0, f"ERROR on /diagnostics ({outage.name})")
                    with tester.lock:
                        diag, message = dict(tester.diag), tester.diag_message
                    time.sleep(max(0.0, OUTAGE - (time.monotonic() - t0)))
                    lines = _lines(learner.log(), "cannot write a checkpoint") - lines0
                    duration = time.monotonic() - t0
                finally:
                    with watch.lock:
                        outage.end()
                print(f"{outage.name}: {lines} error lines in {duration:.1f} s; /diagnostics: {message!r}")
                # the cause, named: the OS message, the path, the time since the last good write
                assert outage.message in diag["checkpoint_write_error"], diag
                assert str(run_dir) in diag["checkpoint_write_error"] and "last good checkpoint" in \
                    diag["checkpoint_write_error"], diag
                assert message.startswith("checkpoint writes failing: " + outage.message), message
                assert float(diag["checkpoint_age_s"]) > 0 and int(diag["checkpoint_write_errors"]) >= 1
                # bounded log lines: at most one per checkpoint period
                assert 1 <= lines <= duration / PERIOD + 1, (lines, duration)
                # OK again once writes succeed: a new checkpoint, the cause gone, training errors not counted
                tester.wait(lambda v=version: tester.diag_level <= base_level  # type: ignore[misc]
                            and tester.counter("model_version") > v
                            and tester.diag.get("checkpoint_write_error") == "", 30.0,
                            f"the level before the outage again after the {outage.name}")
                assert tester.counter("checkpoint_write_failures") == 0 and tester.counter("train_errors") == 0
                assert "writing works again after" in learner.log()
                windows[f"normal {i + 1}"] = Window.measure(run, WINDOW)
            assert learner.proc.alive()
            assert learner.stop() == 0
        finally:
            if watch is not None:
                watch.stop()
            tester.close()
            print(f"--- learner log (tail) ---\n{learner.log()[-3000:]}")
        print("; ".join(f"{k}: {w}" for k, w in windows.items()) + f"; load {os.getloadavg()}")
        assert watch is not None and not watch.problems, watch.problems[:5]
        assert len(watch.versions) > 50 and watch.versions[-1] > watch.versions[0]
        for i, outage in enumerate(outages):
            normal = (windows[f"normal {i}"].training_share + windows[f"normal {i + 1}"].training_share) / 2
            assert windows[outage.name].training_share >= 0.6 * normal, windows
            assert windows[outage.name].updates > 0
        assert "final checkpoint version" in learner.log()


# ------------------------------------------------------------------------------------------ the recorder
def test_recorder_on_a_full_disk_stops_cleanly_and_its_bag_is_recovered(tmp_path: Path, ros_env: ros_helpers.RosDomain,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    from saml_ros.bags import info as bag_info

    mnt = tmp_path / "small"
    mnt.mkdir()
    mounted = _run("mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mnt)).returncode == 0
    try:
        bag = mnt / "bag"
        sim = ros_env.launch("friction_sim", "-p", "mode:=realtime", "-p", "rate_hz:=200.0", namespace="/friction")
        rec = ros_env.launch("record", args=["--system", "friction", "-o", str(bag), "--flush-period", "0.1"])
        ros_helpers.wait_for(lambda: "record: matched /friction/state" in rec.output() or not rec.alive(),
                             what="the recorder to record")
        if not mounted:  # no tmpfs here: the recorder's files may not grow past 256 KB (EFBIG; Python ignores SIGXFSZ)
            resource.prlimit(rec.pid, resource.RLIMIT_FSIZE, (256 * 1024, 256 * 1024))
        rc = rec.wait(90.0)
        out = rec.output()
        sim.stop()
        print(out[-2000:])
        assert rc == 1, out
        assert "Traceback" not in out
        assert _lines(out, "[ERROR]") == 1, out  # one line, then it stops: no retry, no spinning
        assert ("No space left on device" if mounted else "File too large") in out
        assert f"the messages flushed before the error are recovered with `bag_info --repair {bag}`" in out
        capsys.readouterr()
        assert bag_info.main([str(bag), "--repair", "--out", str(tmp_path / "repaired")]) == 0
        printed = capsys.readouterr().out
    finally:
        if mounted:
            _run("umount", "-l", str(mnt))
    first = printed.splitlines()[0]
    assert first.startswith("bag_info: recovered ") and "the recording was cut off" in first, printed
    assert "unpack requires" not in printed and "EndOfFile" not in printed
    assert int(re.search(r"recovered (\d+) messages", first).group(1)) > 100  # type: ignore[union-attr]
    assert "/friction/state" in printed
