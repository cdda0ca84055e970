"""The commands the README and the tutorial tell a user to type are commands of this repository, with options and
parameters it accepts (checked without running them: each command-line executable's own argument parser, each
node's parameter table).

The tutorial's workflow itself (the example robot driven, recorded and learned by real processes, trained from the
bag, exported, controlled by the MPC) runs end to end in test/e2e/your_robot/.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import re
import shlex
from pathlib import Path

import pytest
from helpers import REPO
from helpers.node_params import table_parameters

from saml_ros.executables import EXECUTABLES

#: the pages whose commands a user types first
PAGES = [REPO / "README.md", REPO / "docs" / "tutorial.md"]
#: ./dev's own commands (dev, the script): the rest go to saml_ros.executables
DEV_COMMANDS = {"demo", "test", "bench", "lint", "python"}
#: executables that are ROS nodes (parameters after --ros-args), with the system their parameters are read for
NODES = {"learner", "mpc", "friction_sim", "quadrotor_sim", "paddle_ball_sim", "lifecycle_manager"}
FENCE_RE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)


def _commands(page: Path) -> list[tuple[int, list[str]]]:
    """(line, argv after ``./dev``) for every ``./dev`` command in the page's shell code blocks (continued lines
    joined, comments dropped, ``$s`` of a loop as ``0``, several commands of one line split at ``;``)."""
    text = page.read_text(encoding="utf-8")
    found = []
    for block in FENCE_RE.finditer(text):
        if block.group(1) not in ("", "bash", "sh"):
            continue
        first_line = text.count("\n", 0, block.start()) + 2
        for offset, line in enumerate(block.group(2).replace("\\\n", " ").splitlines()):
            line = re.sub(r"(^|\s)#.*", "", line).replace("$s", "0")
            lexer = shlex.shlex(line, posix=True, punctuation_chars=";&|")
            lexer.whitespace_split = True
            words: list[str] = []
            for token in [*lexer, ";"]:
                if token and set(token) <= set(";&|"):  # the end of one command
                    if "./dev" in words:
                        found.append((first_line + offset, words[words.index("./dev") + 1:]))
                    words = []
                else:
                    words.append(token)
    return found


CASES = [(page, n, argv) for page in PAGES for n, argv in _commands(page)]


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
