"""docs/architecture.md's "Layout" lists the core and the systems as they are: every entry under ``saml_ros/core/``
and ``saml_ros/systems/`` exists, and every folder whose contents it lists (``saml_ros/core/`` itself, ``mpc/``,
``mpc/shooting/``, ``saml_ros/systems/paddle_ball/mpc/`` ...) lists all of its modules and subpackages (issue 31:
one line per folder, true to the tree)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from helpers import REPO

DOC = REPO / "docs" / "architecture.md"
TOPS = ("saml_ros/core/", "saml_ros/systems/")


def _layout_tree(text: str, top: str = TOPS[0]) -> dict[str, list[str]]:
    """``folder -> [listed names]`` for the ``top`` part of the Layout block (names by indentation: two spaces per
    level; a line whose name column is blank continues the one above)."""
    block = text.split("## Layout", 1)[1].split("```", 2)[1]
    tree: dict[str, list[str]] = {}
    stack: list[str] = []
    inside = False
    for line in block.splitlines():
        if line.startswith(top):
            inside, stack = True, [top.rstrip("/")]
            tree[stack[0]] = []
            continue
        if not inside:
            continue
        m = re.match(r"^( +)(\S+)", line)
        if not line.strip() or not line.startswith(" "):
            if line.strip():
                break  # the next top-level entry
            continue
        assert m is not None
        depth = len(m.group(1)) // 2
        if len(m.group(1)) >= 20:  # a continuation line in the description column
            continue
        name = m.group(2)
        stack = stack[:depth]
        parent = "/".join(stack)
        tree.setdefault(parent, []).append(name)
        if name.endswith("/"):
            stack.append(name.rstrip("/"))
            tree.setdefault("/".join(stack), [])
    return tree


def _children(folder: Path) -> set[str]:
    mods = {p.name for p in folder.glob("*.py") if p.name != "__init__.py"}
    pkgs = {p.name + "/" for p in folder.iterdir() if (p / "__init__.py").is_file()}
    return mods | pkgs


def test_the_reader_sees_the_layout() -> None:
    tree = _layout_tree(DOC.read_text())
    assert "mpc/" in tree["saml_ros/core"] and "contract.py" in tree["saml_ros/core/mpc"]
    assert "sqp.py" in tree["saml_ros/core/mpc/shooting"]
    systems = _layout_tree(DOC.read_text(), "saml_ros/systems/")
    assert "quadrotor/" in systems["saml_ros/systems"] and "problem.py" in systems["saml_ros/systems/paddle_ball/mpc"]


@pytest.mark.parametrize("top", TOPS)
def test_the_layout_lines_match_the_tree(top: str) -> None:
    tree = _layout_tree(DOC.read_text(), top)
    problems = []
    for folder, listed in tree.items():
        path = REPO / folder
        for name in listed:
            if not (path / name.rstrip("/")).exists():
                problems.append(f"{folder}/{name} is listed but does not exist")
        if listed:
            missing = sorted(_children(path) - set(listed))
            problems += [f"{folder}/{name} exists but is not listed" for name in missing]
    assert not problems, "docs/architecture.md, Layout: " + "; ".join(problems)
