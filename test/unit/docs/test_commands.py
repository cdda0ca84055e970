"""The commands the README and the tutorial tell a user to type are commands of this repository, with options and
parameters it accepts (checked without running them: each command-line executable's own argument parser, each
node's parameter table).

The tutorial's commands themselves run, in order, as real processes in test/e2e/your_robot/test_tutorial.py.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import re
from pathlib import Path

import pytest
from helpers import REPO
from helpers.doc_commands import shell_commands
from helpers.node_params import table_parameters

from saml_ros.executables import EXECUTABLES

#: the pages whose commands a user types first
PAGES = [REPO / "README.md", REPO / "docs" / "tutorial.md"]
#: ./dev's own commands (dev, the script): the rest go to saml_ros.executables
DEV_COMMANDS = {"demo", "test", "bench", "lint", "python"}
#: executables that are ROS nodes (parameters after --ros-args), with the system their parameters are read for
NODES = {"learner", "mpc", "friction_sim", "quadrotor_sim", "paddle_ball_sim", "lifecycle_manager"}
CASES = [(page, c.line, c.dev_argv) for page in PAGES for c in shell_commands(page) if c.dev_argv is not None]


def _parser(executable: str) -> argparse.ArgumentParser | None:
    module = importlib.import_module(EXECUTABLES[executable].split(":")[0])
    build = getattr(module, "build_parser", None)
    return build() if build is not None else None


def _ros_params(argv: list[str]) -> dict[str, str]:
    """``-p name:=value`` pairs after ``--ros-args``."""
    if "--ros-args" not in argv:
        return {}
    rest = argv[argv.index("--ros-args") + 1:]
    return dict(rest[i + 1].split(":=", 1) for i, a in enumerate(rest) if a == "-p")


@pytest.mark.parametrize(("page", "line", "argv"), CASES,
                         ids=[f"{p.name}:{n}:{' '.join(a[:2])}" for p, n, a in CASES])
def test_every_command_is_one_the_repository_accepts(page: Path, line: int, argv: list[str]) -> None:
    where = f"{page.relative_to(REPO)}:{line}: ./dev {' '.join(argv)}"
    name, args = argv[0], argv[1:]
    if name == "python":
        if args[:1] == ["-m"]:
            assert importlib.util.find_spec(args[1]) is not None, where
        elif args[:1] != ["-c"]:
            assert (REPO / args[0]).is_file(), f"{where}: no script {args[0]}"
        return
    if name in DEV_COMMANDS:
        return
    assert name in EXECUTABLES, f"{where}: no executable {name!r}"
    if name in NODES:
        params = _ros_params(args)
        system = params.get("system", "friction")
        unknown = set(params) - table_parameters(name, system)
        assert not unknown, f"{where}: {name} declares no parameter(s) {sorted(unknown)}"
        if "system_file" in params:
            assert (REPO / params["system_file"]).is_file(), where
        return
    parser = _parser(name)
    if parser is None:
        return
    with contextlib.redirect_stderr(io.StringIO()) as err:
        try:
            parser.parse_args(args)
        except SystemExit as exc:
            if exc.code == 0:  # --help
                return
            pytest.fail(f"{where}: refused ({exc.code}): {err.getvalue().strip()}")
    for value in args:  # files of the repository the command reads
        if re.match(r"(examples|config|docs)/", value):
            assert (REPO / value).exists(), f"{where}: {value} does not exist"


def test_the_reader_finds_the_commands() -> None:
    tutorial = {" ".join(argv[:1]) for _, _, argv in CASES}
    assert {"learner", "record", "train", "export", "bag_info", "mpc", "python"} <= tutorial
