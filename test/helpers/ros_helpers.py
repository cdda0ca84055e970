"""Helpers for tests that run real ROS 2 processes (simulators, learner, MPC, recorder, ...).

Usage in a test module under ``test/ros/`` or ``test/e2e/`` (the fixtures ``ros_env`` and ``ros_node`` are
registered in ``test/conftest.py``)::

    from helpers.ros_helpers import RosDomain, TestNode, wait_for

    def test_something(ros_env: RosDomain, ros_node: TestNode) -> None:
        sim = ros_env.launch("quadrotor_sim", "-p", "mode:=lockstep")    # stopped at teardown
        states = ros_node.subscribe(Odometry, "/quadrotor/state")
        wait_for(lambda: len(states) >= 3, timeout=30, what="3 states")

* :func:`ros_domain` (fixture :func:`ros_env`): claims a private ``ROS_DOMAIN_ID`` in 1..100 (a lock file per
  id, so concurrent pytest runs on this machine never share one), sets it and
  ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` in ``os.environ`` for the test process and its children, stops
  every process launched through it (SIGINT, then SIGKILL) and removes the Fast DDS shared-memory segments
  that appeared during the test and that no live process maps or holds open (:func:`clean_shm`; segments
  of other users' running participants are therefore never touched).
* :func:`launch`: a saml_ros executable in its own process group, started with this venv's Python
  (``python -m saml_ros.executables NAME --ros-args ...``), output in a log file (:meth:`Process.output`).
* :class:`TestNode` (fixture :func:`ros_node`): a stock rclpy node spun in a background thread, with helpers to
  collect messages, publish and call services.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[2]
#: where domain-id claims live (one lock file per id, shared by every pytest run on the machine)
CLAIM_DIR = Path(tempfile.gettempdir()) / "saml_ros_ros_domains"
SHM = Path("/dev/shm")
DOMAIN_IDS = range(1, 101)
#: generous default timeout (s) for start-up and discovery on the shared, slow test machine
STARTUP_TIMEOUT = 45.0
#: util-linux's setpriv: runs a command with a parent-death signal (``None`` where it is missing)
SETPRIV = shutil.which("setpriv")
_SHM_PATTERN = re.compile(r"^(?:sem\.)?(?:fastrtps|fastdds)_(?P<id>port(?P<port>\d+)|[0-9a-f]+)(?:_el|_sl|_mutex)?$")


def wait_for(predicate: Callable[[], Any], timeout: float = STARTUP_TIMEOUT, period: float = 0.02,
             what: str = "condition") -> Any:
    """Poll ``predicate`` until it returns something truthy (returned); ``TimeoutError`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() >= deadline:
            raise TimeoutError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(period)


# ------------------------------------------------------------------------------------------ processes
class Process:
    """A launched node process; :meth:`stop` sends SIGINT, then SIGKILL to its process group."""

    def __init__(self, name: str, popen: subprocess.Popen[bytes], log_path: Path) -> None:
        self.name = name
        self.popen = popen
        self.log_path = log_path

    @property
    def pid(self) -> int:
        return self.popen.pid

    def alive(self) -> bool:
        return self.popen.poll() is None

    def signal(self, sig: int) -> None:
        """Send ``sig`` to the process (not its group)."""
        if self.alive():
            self.popen.send_signal(sig)

    def wait(self, timeout: float) -> int | None:
        """Exit code, or ``None`` if still running after ``timeout`` s."""
        try:
            return self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            return None

    def stop(self, timeout: float = 10.0) -> int:
        """SIGINT and wait up to ``timeout`` s, then SIGKILL the process group; returns the exit code."""
        if self.alive():
            with contextlib.suppress(ProcessLookupError):
                self.popen.send_signal(signal.SIGINT)
            if self.wait(timeout) is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.popen.pid, signal.SIGKILL)
                self.popen.wait(10.0)
        return int(self.popen.returncode)

    def output(self) -> str:
        """Everything the process wrote to stdout and stderr so far."""
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def __repr__(self) -> str:
        return f"Process({self.name!r}, pid={self.pid}, alive={self.alive()})"


def launch(executable: str, *ros_args: str, env: dict[str, str] | None = None, namespace: str | None = None,
           params_file: str | Path | None = None, log_dir: Path | None = None, args: Sequence[str] = (),
           cwd: Path | None = None) -> Process:
    """Start saml_ros executable ``executable`` (see ``saml_ros/executables.py``) in a new process group.

    ``ros_args`` go after ``--ros-args`` (e.g. ``"-p", "mode:=lockstep"``); ``namespace`` adds
    ``-r __ns:=<namespace>`` and ``params_file`` ``--params-file``. ``args`` come before ``--ros-args``.
    The environment is ``os.environ`` (so the test's ROS domain) updated with ``env``; the working directory is
    the repository unless ``cwd`` is given.
    """
    cmd = [sys.executable, "-m", "saml_ros.executables", executable, *args]
    ros = list(ros_args)
    if namespace is not None:
        ros += ["-r", f"__ns:={namespace}"]
    if params_file is not None:
        ros += ["--params-file", str(params_file)]
    if ros:
        cmd += ["--ros-args", *ros]
    full_env = dict(os.environ)
    full_env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), full_env.get("PYTHONPATH", "")) if p)
    full_env["PYTHONUNBUFFERED"] = "1"
    full_env.update(env or {})
    log_dir = log_dir if log_dir is not None else Path(tempfile.mkdtemp(prefix="saml_ros_logs_"))
    log_path = log_dir / f"{executable}-{time.monotonic_ns()}.log"
    with open(log_path, "wb") as log:
        popen = subprocess.Popen(dying_with_test(cmd), stdout=log, stderr=subprocess.STDOUT, env=full_env,
                                 cwd=cwd or REPO,
                                 start_new_session=True)
    return Process(executable, popen, log_path)


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, exited but not yet reaped by its parent, counts as gone)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def dying_with_test(argv: Sequence[str]) -> list[str]:
    """``argv`` run so that the process gets SIGTERM when the test process that starts it dies.

    The tests start their nodes in their own sessions (so a signal to the test's group does not reach them); a
    pytest worker that is SIGKILLed (a run cut short) used to leave them running with PPID 1 for hours, costing
    CPU and sharing ROS domains with later runs. ``setpriv --pdeathsig TERM`` sets the parent-death signal and
    then execs ``argv`` (the process keeps its pid); it is kept across exec. Where setpriv is missing the command
    runs as given.
    """
    return [SETPRIV, "--pdeathsig", "TERM", "--", *argv] if SETPRIV else list(argv)


# ---------------------------------------------------------------------------------------- ROS domains
def _claim(domain: int) -> int | None:
    """Exclusive claim on ``domain`` (an open, flocked fd) or ``None`` if another run holds it."""
    CLAIM_DIR.mkdir(parents=True, exist_ok=True)
    fd = os.open(CLAIM_DIR / f"{domain}.lock", os.O_CREAT | os.O_RDWR, 0o666)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return None
    return fd


def claim_domain(name: str = "") -> tuple[int, int]:
    """``(domain id, claim fd)``: a free id in 1..100, starting from a hash of ``name`` and the pid."""
    start = int(hashlib.sha256(f"{name}:{os.getpid()}".encode()).hexdigest(), 16) % len(DOMAIN_IDS)
    for i in range(len(DOMAIN_IDS)):
        domain = DOMAIN_IDS[(start + i) % len(DOMAIN_IDS)]
        fd = _claim(domain)
        if fd is not None:
            return domain, fd
    raise RuntimeError("all ROS domain ids 1..100 are claimed by other test runs")


def shm_entries() -> set[str]:
    """Fast DDS entries in /dev/shm."""
    try:
        return {p.name for p in SHM.iterdir() if _SHM_PATTERN.match(p.name)}
    except OSError:
        return set()


def _shm_in_use() -> set[str] | None:
    """Names of /dev/shm files some live process (that we may inspect) maps or holds open; ``None`` if /proc
    cannot be listed."""
    used: set[str] = set()
    prefix = f"{SHM}/"
    try:
        pids = [p for p in os.listdir("/proc") if p.isdigit()]
    except OSError:
        return None
    for pid in pids:
        try:
            with open(f"/proc/{pid}/maps", errors="replace") as maps:
                for line in maps:
                    at = line.find(prefix)
                    if at >= 0:
                        used.add(line[at + len(prefix):].split()[0])
            for fd in os.listdir(f"/proc/{pid}/fd"):
                with contextlib.suppress(OSError):
                    target = os.readlink(f"/proc/{pid}/fd/{fd}")
                    if target.startswith(prefix):
                        used.add(target[len(prefix):])
        except (FileNotFoundError, ProcessLookupError):
            continue  # the process ended meanwhile
        except PermissionError:
            # another user's process: its segments belong to that user, and /dev/shm's sticky bit keeps us
            # from deleting them anyway
            continue
    return used


def clean_shm(before: set[str], min_age: float = 0.5) -> list[str]:
    """Remove the Fast DDS segments that appeared since ``before`` and that no live process uses.

    A segment (with its ``_el`` lock file and ``sem.*_mutex``) goes only if no process maps it or holds any
    of its files open (checked in /proc) and its files are older than ``min_age`` s (so a segment being
    created right now is never touched). Participants of other users are alive, so they are never removed.
    Call it after this process's own participants are destroyed. Returns the removed names.
    """
    groups: dict[str, list[str]] = {}
    for name in shm_entries() - before:
        m = _SHM_PATTERN.match(name)
        if m is not None:
            groups.setdefault(m.group("id"), []).append(name)
    if not groups:
        return []
    used = _shm_in_use()
    if used is None:
        return []
    now = time.time()
    removed: list[str] = []
    for names in groups.values():
        try:
            young = any(now - (SHM / n).stat().st_mtime < min_age for n in names)
        except OSError:
            continue
        if young or any(n in used for n in names):
            continue
        for n in names:
            with contextlib.suppress(OSError):
                (SHM / n).unlink()
                removed.append(n)
    return removed


class RosDomain:
    """A claimed ROS domain; :meth:`launch` starts processes that are stopped when the domain closes."""

    def __init__(self, domain_id: int, log_dir: Path) -> None:
        self.domain_id = domain_id
        self.log_dir = log_dir
        self.processes: list[Process] = []

    def launch(self, executable: str, *ros_args: str, **kwargs: Any) -> Process:
        """:func:`launch` in this domain; the process is stopped at teardown."""
        kwargs.setdefault("log_dir", self.log_dir)
        proc = launch(executable, *ros_args, **kwargs)
        self.processes.append(proc)
        return proc

    def start(self, name: str, argv: Sequence[str], cwd: Path, env: dict[str, str] | None = None) -> Process:
        """Any command ``argv`` (a user's script, a command of the docs) in this domain, in a new process group,
        output logged under ``name``; stopped at teardown like :meth:`launch`'s."""
        log = self.log_dir / f"{name}-{time.monotonic_ns()}.log"
        with open(log, "wb") as out:
            popen = subprocess.Popen(dying_with_test(argv), stdout=out, stderr=subprocess.STDOUT, cwd=cwd,
                                     env=dict(os.environ, PYTHONUNBUFFERED="1") if env is None else env,
                                     start_new_session=True)
        proc = Process(name, popen, log)
        self.processes.append(proc)
        return proc

    def stop_all(self) -> None:
        for proc in self.processes:
            with contextlib.suppress(Exception):
                proc.stop()


@contextlib.contextmanager
def ros_domain(name: str = "") -> Iterator[RosDomain]:
    """Claim a private ROS domain for the block (see the module docstring)."""
    domain, fd = claim_domain(name)
    saved = {k: os.environ.get(k) for k in ("ROS_DOMAIN_ID", "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_LOCALHOST_ONLY")}
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ.pop("ROS_LOCALHOST_ONLY", None)
    before = shm_entries()
    log_dir = Path(tempfile.mkdtemp(prefix=f"saml_ros_d{domain}_"))
    dom = RosDomain(domain, log_dir)
    try:
        yield dom
    finally:
        dom.stop_all()
        clean_shm(before)
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
        shutil.rmtree(log_dir, ignore_errors=True)
        os.close(fd)


# --------------------------------------------------------------------------------------- in-test node
class TestNode:
    """A stock rclpy node in its own context, spun by a background thread (see :func:`test_node`)."""

    __test__ = False  # not a pytest class

    def __init__(self, name: str = "test_probe") -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(f"{name}_{os.getpid()}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="test-node-spin", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - shutting down
                if self._stop.is_set() or not self.context.ok():
                    return
                raise

    def subscribe(self, msg_type: Any, topic: str, qos: Any = None,
                  callback: Callable[[Any], None] | None = None) -> list[Any]:
        """Collect every message of ``topic`` into the returned list (``qos``: an rclpy profile, default
        reliable, keep last 1000)."""
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        received: list[Any] = []

        def on_msg(msg: Any) -> None:
            received.append(msg)
            if callback is not None:
                callback(msg)

        profile = qos if qos is not None else QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.node.create_subscription(msg_type, topic, on_msg, profile)
        return received

    def publisher(self, msg_type: Any, topic: str, qos: Any = None) -> Any:
        """An rclpy publisher (``qos`` default reliable, keep last 100)."""
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        profile = qos if qos is not None else QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        return self.node.create_publisher(msg_type, topic, profile)

    def call(self, srv_type: Any, name: str, request: Any = None, timeout: float = STARTUP_TIMEOUT,
             resend_after: float | None = None) -> Any:
        """Call service ``name`` once it is available; returns the response (``TimeoutError`` otherwise).

        ``resend_after``: for a service that changes nothing when asked twice (a state or parameter query, setting
        a parameter to one value), the same request is sent again every ``resend_after`` s until one is answered:
        DDS can drop a request or its response sent while one side of the service's discovery lags the other,
        and nothing sends it again."""
        client = self.node.create_client(srv_type, name)
        try:
            wait_for(lambda: client.service_is_ready(), timeout, what=f"service {name}")
            req = request if request is not None else srv_type.Request()
            futures = [client.call_async(req)]
            sent = time.monotonic()
            deadline = sent + timeout
            while not any(f.done() for f in futures):
                now = time.monotonic()
                if now > deadline:
                    raise TimeoutError(f"no response of {name} within {timeout:g} s ({len(futures)} request(s))")
                if resend_after is not None and now - sent >= resend_after:
                    futures.append(client.call_async(req))
                    sent = now
                time.sleep(0.01)
            return next(f for f in futures if f.done()).result()
        finally:
            self.node.destroy_client(client)

    def close(self) -> None:
        import rclpy

        self._stop.set()
        self._thread.join(timeout=5.0)
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        # Destroying the context destroys the DDS participant, which unmaps the shared-memory segments of the
        # processes it talked to, so clean_shm can remove those of dead nodes.
        self.context.destroy()


@pytest.fixture
def ros_env(request: pytest.FixtureRequest) -> Iterator[RosDomain]:
    """A private ROS domain for one test; processes started with ``ros_env.launch`` are stopped after it."""
    with ros_domain(request.node.name) as dom:
        yield dom


@pytest.fixture
def ros_node(ros_env: RosDomain) -> Iterator[TestNode]:
    """A :class:`TestNode` in the test's ROS domain (closed before the domain)."""
    node = TestNode()
    try:
        yield node
    finally:
        node.close()
