"""The test tree's layout rules and shared fixtures.

Where a test goes (``docs/testing.md``):

* ``test/unit/<part>/``: in-process tests of one part of the package (``<part>`` mirrors the package: ``core/``,
  ``core/training/``, ``core/mpc/``, ``msg_schemas/``, ``bags/``, ...). No child process, no ROS graph: a test here
  that starts a process or initialises rclpy fails, naming the folder it belongs in (compilers building the native
  kernels are allowed).
* ``test/ros/<part>/``: tests that start processes (nodes, executables, a fresh interpreter, colcon) or join a ROS
  graph (rclpy in the test process).
* ``test/e2e/``: whole workflows: record -> replay -> train, robots defined outside the package.
* ``test/helpers/``: code the tests share (never a test; no test imports another test file).

Every test under ``ros/`` and ``e2e/`` gets the ``ros`` marker here (``e2e/`` also ``e2e``), by folder, so a new file
cannot forget it: ``./dev test -m "not ros"`` runs the unit tests alone (and then does not even import the others).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
from helpers.bag_test_helpers import bad_bags, friction_bag  # noqa: F401  (fixtures for every test, by name)
from helpers.ros_helpers import ros_env, ros_node  # noqa: F401

from saml_ros.core.dynamics.system import System
from saml_ros.core.layout import make_layout

if TYPE_CHECKING:
    import torch


# No test renders MuJoCo: without an OpenGL backend, importing mujoco does not load glfw, whose import starts a
# version-probe process (which the unit tests' no-process rule below refuses) and costs 0.2 s in every process.
os.environ.setdefault("MUJOCO_GL", "disable")

TEST_DIR = Path(__file__).resolve().parent
#: top-level folder -> markers every test in it gets
FOLDER_MARKERS = {"unit": (), "ros": ("ros",), "e2e": ("ros", "e2e")}
#: processes a unit test may start: the compilers and build tools that build the native kernels on first use
BUILD_TOOLS = re.compile(r"^(c\+\+|g\+\+|gcc|cc|clang\+\+|clang|ninja|ld|ldconfig)(-[0-9.]+)?$")


def pytest_configure(config: pytest.Config) -> None:
    """One intra-op torch thread in every process that runs tests, as the nodes and scripts use: on this shared
    2-core machine torch's default of one thread per core made a small network's training step 25x slower under
    load (150 ms instead of 6 ms, measured). The xdist controller runs no test and does not import torch (2 s of
    CPU before the workers start)."""
    if getattr(config.option, "numprocesses", None) and not hasattr(config, "workerinput"):
        return
    import torch

    torch.set_num_threads(1)


def _folder(path: Path) -> str | None:
    """The top-level folder of ``test/`` that holds ``path`` (``None`` outside test/ or directly in it)."""
    try:
        parts = path.resolve().relative_to(TEST_DIR).parts
    except ValueError:
        return None
    return parts[0] if len(parts) > 1 else None


def pytest_sessionstart(session: pytest.Session) -> None:
    """Before any test (in the controller, not in each xdist worker): remove the Fast DDS shared-memory files no
    live process uses, left by processes killed earlier (benchmarks cut short, crashes; 1,174 of them here once).
    Two suite runs made beside such leftovers (3 December) had 2 failures each, processes that heard nothing from
    another for 60-90 s; the next run after removing them passed 930 of 930 (one run: a correlation, not a proof).
    Each test also removes what its own processes leave (ros_helpers.clean_shm)."""
    if hasattr(session.config, "workerinput"):
        return
    from helpers.ros_helpers import clean_shm

    removed = clean_shm(set(), min_age=5.0)
    if removed:
        print(f"\nremoved {len(removed)} unused Fast DDS shared-memory files from /dev/shm", flush=True)


def _deselected_by_markexpr(config: pytest.Config, markers: tuple[str, ...]) -> bool:
    """True when ``-m`` deselects every test carrying ``markers``, whatever other markers it has."""
    expr = config.getoption("markexpr", "")
    if not expr or not markers:
        return False
    from _pytest.mark.expression import Expression

    compiled = Expression.compile(expr)
    others = sorted(set(re.findall(r"[A-Za-z_][A-Za-z0-9_]*", expr)) - {"and", "or", "not", *markers})
    for bits in range(2 ** len(others)):  # every assignment of the other names in the expression
        on = {name for i, name in enumerate(others) if bits >> i & 1} | set(markers)
        if compiled.evaluate(lambda name, *_, on=on, **__: name in on):  # type: ignore[arg-type]
            return False
    return True


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    """``-m "not ros"`` does not import the process tests at all (their modules import rclpy and friends); the
    helpers package is never collected."""
    if collection_path == TEST_DIR / "helpers":
        return True
    folder = _folder(collection_path / "x") if collection_path.is_dir() else _folder(collection_path)
    if folder in FOLDER_MARKERS and _deselected_by_markexpr(config, FOLDER_MARKERS[folder]):
        return True
    return None


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The markers by folder (a test file directly in test/ or in an unknown folder is an error); the files in
    the order they run best in on several workers (:func:`longest_files_first`)."""
    misplaced = set()
    for item in items:
        folder = _folder(item.path)
        if folder not in FOLDER_MARKERS:
            misplaced.add(str(item.path))
            continue
        for name in FOLDER_MARKERS[folder]:
            item.add_marker(name)
    if misplaced:
        raise pytest.UsageError(f"test files outside test/unit, test/ros and test/e2e (see test/conftest.py): "
                                f"{sorted(misplaced)}")
    items[:] = longest_files_first(items, read_durations())


# ------------------------------------------------------------------------------------ the order files run in
#: each test file's recorded duration (s: its tests' set-up, call and tear-down summed), written by
#: ``./dev test --record-durations``
DURATIONS_FILE = TEST_DIR / "durations.json"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--record-durations", action="store_true",
                     help=f"write each test file's duration in this run into {DURATIONS_FILE.name} (files not run keep "
                          "theirs): the order the next runs start files in")


def read_durations(path: Path = DURATIONS_FILE) -> dict[str, float]:
    """``{file relative to the repository: seconds}`` (empty when the file is missing or unreadable)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return {str(k): float(v) for k, v in data.items() if isinstance(v, int | float)} if isinstance(data, dict) else {}


def longest_files_first(items: list[pytest.Item], durations: dict[str, float]) -> list[pytest.Item]:
    """``items`` grouped by file, the files in decreasing recorded duration (the tests of a file in their own
    order); a file without a record counts as the median file.

    ``./dev test`` hands out whole files (``--dist loadfile``) in this order (``--no-loadscope-reorder``; xdist's
    own order, most tests first, started the long one-test process files last, so one worker could run the last
    of them while the other had nothing left): longest first, each to the first free worker, leaves only short
    files for the end."""
    order: dict[str, int] = {}
    files: list[str] = []
    for item in items:
        f = item.nodeid.split("::", 1)[0]
        if f not in order:
            order[f] = len(files)
            files.append(f)
    known = sorted(durations[f] for f in files if f in durations)
    default = known[len(known) // 2] if known else 0.0
    rank = {f: (-durations.get(f, default), order[f]) for f in files}
    return sorted(items, key=lambda item: rank[item.nodeid.split("::", 1)[0]])


_RECORDED: dict[str, float] = {}


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """With ``--record-durations``: each file's set-up, call and tear-down times summed (in the controller, from
    every worker's reports)."""
    f = report.nodeid.split("::", 1)[0]
    _RECORDED[f] = _RECORDED.get(f, 0.0) + report.duration


def pytest_sessionfinish(session: pytest.Session) -> None:
    if not session.config.getoption("record_durations") or hasattr(session.config, "workerinput") or not _RECORDED:
        return
    merged = read_durations() | {f: round(s, 1) for f, s in _RECORDED.items()}
    DURATIONS_FILE.write_text(json.dumps(dict(sorted(merged.items())), indent=1) + "\n")


# ------------------------------------------------------------------------------------- unit tests stay in-process
def _refuse(what: str) -> None:
    raise AssertionError(f"a unit test {what}: move it to test/ros/ (tests that start processes or join a ROS graph; "
                         f"see test/conftest.py)")


@pytest.fixture(autouse=True)
def _unit_tests_start_no_process(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """Under test/unit/: starting a process (other than a compiler building a native kernel) or initialising rclpy
    fails the test."""
    if _folder(request.node.path) != "unit":
        return
    popen_init = subprocess.Popen.__init__

    def checked_popen(self: subprocess.Popen[Any], args: Any, *a: Any, **k: Any) -> None:
        first = args if isinstance(args, str | bytes | Path) else next(iter(args), "")
        name = Path(str(first).split()[0] if isinstance(first, str) else str(first)).name
        if not BUILD_TOOLS.match(name):
            _refuse(f"started the process {args!r}")
        popen_init(self, args, *a, **k)

    monkeypatch.setattr(subprocess.Popen, "__init__", checked_popen)
    import multiprocessing.process

    monkeypatch.setattr(multiprocessing.process.BaseProcess, "start", lambda self: _refuse("started a process"))
    try:
        import rclpy.context
    except ImportError:
        return
    monkeypatch.setattr(rclpy.context.Context, "init", lambda self, *a, **k: _refuse("initialised rclpy"))


# ---------------------------------------------------------------------------------------------------- fixtures
@pytest.fixture
def restore_registry() -> Iterator[None]:
    """The system registry (global and mutable: robots loaded from system files, systems a test registers) as it
    was before the test: entries and loaders added during the test are removed, replaced ones put back."""
    from saml_ros.core.systems import registry

    entries, loaders = dict(registry._ENTRIES), list(registry._LOADERS)
    try:
        yield
    finally:
        registry._ENTRIES.clear()
        registry._ENTRIES.update(entries)
        registry._LOADERS[:] = loaders


@pytest.fixture(autouse=True)
def _registry_left_as_found(request: pytest.FixtureRequest) -> Iterator[None]:
    """A test that leaves a system registered fails, naming it: the registry is global, and a robot a test loaded
    (a system file registers its robot by name) changed what later tests of the same worker saw (test_registry's
    list of names failed once the file order changed). Use the ``restore_registry`` fixture."""
    from saml_ros.core.systems import registry

    before = set(registry._ENTRIES)
    yield
    added = sorted(set(registry._ENTRIES) - before)
    if added and "restore_registry" not in request.fixturenames:
        for name in added:
            registry._ENTRIES.pop(name, None)
        pytest.fail(f"the test left system(s) {added} registered: use the restore_registry fixture", pytrace=False)


class ToySystem(System):
    """A 1-d toy system used by trainer tests: a full model sees a constant input, so it can only
    predict one constant c for every sample — the learning problem is convex in c."""

    name = "toy"
    state = make_layout("state", [("s", "1")])
    control = make_layout("control", [("a", "1")])
    target = make_layout("target", [("y", "1")])
    dt = 0.1
    paper_hidden = ()

    @property
    def control_low(self) -> np.ndarray:
        return np.array([-1.0])

    @property
    def control_high(self) -> np.ndarray:
        return np.array([1.0])

    def true_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        return x

    def base_step(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        import torch

        return torch.zeros_like(x)

    def sample_inputs(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        return np.ones((n, 1)), np.zeros((n, 1))

    def paper_spec(self) -> dict:
        return {"objective": {"loss": "squared_l2"}}


@pytest.fixture
def toy_system() -> ToySystem:
    return ToySystem()
