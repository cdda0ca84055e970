"""The README, docs/*.md and the examples' READMEs describe the repository as it is, for a reader who has only
the repository.

* no path of a development machine (``/tmp/...``, ``/work/...``, ``/home/...``, ``../shared``): a reader cannot
  open it, and a number that rests on it cannot be checked;
* no time of day anywhere and no date in a heading (the history of how a number moved is CHANGELOG.md's; the
  result files under docs/results/, written by commands, carry their own dates and are not checked here);
* every repository file or folder, test file and test function named exists (``test/unit/...``, ``saml_ros/...``,
  ``test_x.py``, ``test_y``), and every relative link points at a file of the repository;
* every figure linked from the README or docs/ is one a command of the repository writes: its file name is one
  the code writes (a string literal, an f-string's ``{...}`` matching anything), or the figure's own path is the
  output argument of a ``./dev`` / ``ros2`` command written in the docs.
"""

from __future__ import annotations

import ast
import re
from functools import cache
from pathlib import Path

import pytest
from helpers import REPO

#: the pages checked: what a user reads (CHANGELOG.md and the generated files under docs/results/ are history)
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md")), *sorted((REPO / "examples").glob("*/README.md"))]
#: top-level folders of the repository whose files the docs name
REPO_DIRS = ("test", "saml_ros", "bench", "config", "examples", "launch", "layouts", "scripts", "sim_nodes",
             "msg_schemas", "docs")
#: where the code that writes figures lives
CODE_DIRS = ("saml_ros", "bench", "scripts", "examples", "sim_nodes")

MACHINE_PATH_RE = re.compile(r"(?<![\w./:~-])(/tmp/|/work/|/home/|/Users/|/root/|/mnt/|\.\./shared\b)")
TIME_OF_DAY_RE = re.compile(r"(?<![\w:.\[-])(?:[01]?\d|2[0-3]):[0-5]\d(?::[0-5]\d)?(?![\w:\]])")
MONTHS = "January|February|March|April|May|June|July|August|September|October|November|December"
DATE_RE = re.compile(rf"\b\d{{1,2}} (?:{MONTHS})\b|\b(?:{MONTHS}) \d{{1,2}}\b|\b(?:{MONTHS}) 20\d\d\b"
                     r"|\b20\d\d-[01]\d-[0-3]\d\b")
#: a path into the repository; one followed by a placeholder (``config/loop_<system>.yaml``, ``assets/*.xml``) is
#: a pattern, not a file, and is not matched
REPO_PATH_RE = re.compile(rf"(?<![\w./~$-])((?:{'|'.join(REPO_DIRS)})/[\w.\-/]*[\w/])(?![\w./<*{{-])")
TEST_FILE_RE = re.compile(r"(?<![\w/.-])(test_\w+\.py)\b")
TEST_NAME_RE = re.compile(r"`(test_\w+)(?:\[[^\]`]*\])?`")
LINK_RE = re.compile(r"(!?)\[[^\]]*\]\(([^)\s]+)\)")
CODE_SPAN_RE = re.compile(r"`[^`\n]+`")
FENCE_RE = re.compile(r"^```.*?^```", re.S | re.M)


def _rel(path: Path) -> str:
    return str(path.relative_to(REPO))


def _lines(page: Path) -> list[tuple[int, str]]:
    return list(enumerate(page.read_text(encoding="utf-8").splitlines(), start=1))


def _prose(text: str) -> str:
    """``text`` without fenced code blocks and inline code (kept as blanks so that line numbers stay)."""
    text = FENCE_RE.sub(lambda m: "\n" * m.group(0).count("\n"), text)
    return CODE_SPAN_RE.sub(" ", text)


def _find(pattern: re.Pattern[str], text: str) -> list[tuple[int, str]]:
    """(line number, the match's first group or the whole match) for every match of ``pattern`` in ``text``."""
    return [(text.count("\n", 0, m.start()) + 1, m.group(1) if pattern.groups else m.group(0))
            for m in pattern.finditer(text)]


@pytest.mark.parametrize("page", PAGES, ids=_rel)
def test_no_path_of_a_development_machine(page: Path) -> None:
    bad = [f"{_rel(page)}:{n}: {m}" for n, line in _lines(page) for m in MACHINE_PATH_RE.findall(line)]
    assert not bad, "paths outside the repository (a reader cannot open them):\n" + "\n".join(bad)


@pytest.mark.parametrize("page", PAGES, ids=_rel)
def test_no_time_of_day_and_no_date_in_a_heading(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    bad = [f"{_rel(page)}:{n}: time of day {m!r}" for n, m in _find(TIME_OF_DAY_RE, _prose(text))]
    bad += [f"{_rel(page)}:{n}: date in a heading: {line}" for n, line in _lines(page)
            if line.startswith("#") and (DATE_RE.search(line) or TIME_OF_DAY_RE.search(line))]
    assert not bad, "history belongs in CHANGELOG.md, not in a reference page:\n" + "\n".join(bad)


@pytest.mark.parametrize("page", PAGES, ids=_rel)
def test_no_date_in_prose(page: Path) -> None:
    """A reference page describes the present: no date in its text, also where a line break splits one."""
    prose = _prose(page.read_text(encoding="utf-8"))
    joined = re.sub(r"\s+", " ", prose)
    bad = [m.group(0) for m in DATE_RE.finditer(joined)]
    assert not bad, f"{_rel(page)}: dates {bad}: history belongs in CHANGELOG.md and the result files"


@cache
def _test_files() -> dict[str, list[Path]]:
    files: dict[str, list[Path]] = {}
    for path in (REPO / "test").rglob("test_*.py"):
        files.setdefault(path.name, []).append(path)
    return files


@cache
def _test_functions() -> frozenset[str]:
    names = set()
    for paths in _test_files().values():
        for path in paths:
            names |= set(re.findall(r"^\s*(?:async )?def (test_\w+)", path.read_text(encoding="utf-8"), re.M))
    return frozenset(names)


def _exists(token: str) -> bool:
    token = token.split("::")[0].split("#")[0].rstrip(".")
    return bool(token) and (REPO / token).exists()


@pytest.mark.parametrize("page", PAGES, ids=_rel)
def test_every_repository_file_and_test_named_exists(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    bad = [f"{_rel(page)}:{n}: {m} does not exist" for n, m in _find(REPO_PATH_RE, text) if not _exists(m)]
    bad += [f"{_rel(page)}:{n}: no test file {m} under test/" for n, m in _find(TEST_FILE_RE, text)
            if m not in _test_files()]
    bad += [f"{_rel(page)}:{n}: no test function {m}" for n, m in _find(TEST_NAME_RE, text)
            if m not in _test_functions() and f"{m}.py" not in _test_files()]  # a test or a test module
    for n, (_, target) in _find_links(text):
        if target.startswith(("http://", "https://", "mailto:")):
            continue
        path, _, anchor = target.partition("#")
        linked = (page.parent / path).resolve() if path else page
        if not linked.exists():
            bad.append(f"{_rel(page)}:{n}: link to {target}, no such file")
        elif anchor and linked.suffix == ".md" and anchor not in _anchors(linked):
            bad.append(f"{_rel(page)}:{n}: link to {target}, no such heading in {_rel(linked)}")
    assert not bad, "\n".join(bad)


def _anchors(page: Path) -> set[str]:
    """The anchors GitHub gives the headings of ``page`` (lower case, punctuation dropped, spaces to ``-``,
    ``-1``, ``-2``, ... for repeated headings)."""
    seen: dict[str, int] = {}
    anchors = set()
    for line in FENCE_RE.sub("", page.read_text(encoding="utf-8")).splitlines():
        if not re.match(r"#{1,6} ", line):
            continue
        slug = re.sub(r"[^\w\- ]", "", line.lstrip("#").strip().lower()).replace(" ", "-")
        anchors.add(slug if slug not in seen else f"{slug}-{seen[slug]}")
        seen[slug] = seen.get(slug, 0) + 1
    return anchors


def _find_links(text: str) -> list[tuple[int, tuple[str, str]]]:
    """(line, (``!`` for an image else ``""``, target)) for every markdown link outside code."""
    prose = _prose(text)
    return [(prose.count("\n", 0, m.start()) + 1, (m.group(1), m.group(2))) for m in LINK_RE.finditer(prose)]


def _literal_pattern(node: ast.AST) -> str | None:
    """A regex for the strings a string literal or an f-string can be (``{...}`` parts match anything)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return re.escape(node.value)
    if isinstance(node, ast.JoinedStr):
        return "".join(re.escape(v.value) if isinstance(v, ast.Constant) and isinstance(v.value, str) else ".+"
                       for v in node.values)
    return None


@cache
def _written_figure_patterns() -> tuple[re.Pattern[str], ...]:
    """The image file names the code can write: every literal naming a .png / .svg / .gif / .jpg file."""
    patterns = set()
    for folder in CODE_DIRS:
        for path in (REPO / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                pattern = _literal_pattern(node)
                if pattern and re.search(r"\\?\.(png|svg|gif|jpg)$", pattern):
                    patterns.add(pattern.rsplit("/", 1)[-1])
    return tuple(re.compile(p) for p in sorted(patterns))


@cache
def _command_lines() -> tuple[str, ...]:
    """Every line of the README and docs/ that runs a command of the repository."""
    lines = []
    for page in PAGES:  # a command continued over several lines (``\`` at the end) is one line here
        lines += page.read_text(encoding="utf-8").replace("\\\n", " ").splitlines()
    return tuple(line for line in lines if re.search(r"(\./dev |ros2 (run|launch) )", line))


def _written_by_a_command(figure: Path) -> bool:
    if any(p.fullmatch(figure.name) for p in _written_figure_patterns()):
        return True
    rel = _rel(figure)
    return any(rel in line for line in _command_lines())


@pytest.mark.parametrize("page", PAGES, ids=_rel)
def test_every_figure_is_written_by_a_command(page: Path) -> None:
    bad = []
    for n, (image, target) in _find_links(page.read_text(encoding="utf-8")):
        if not image or target.startswith(("http://", "https://")):
            continue
        figure = (page.parent / target).resolve()
        if not figure.is_file():
            bad.append(f"{_rel(page)}:{n}: figure {target} does not exist")
        elif not _written_by_a_command(figure):
            bad.append(f"{_rel(page)}:{n}: no command of the repository writes {target} (name it in the code, or "
                       f"write the command that makes {_rel(figure)} beside it)")
    assert not bad, "\n".join(bad)


def test_the_checks_catch_what_they_look_for() -> None:
    """The patterns find a machine path, a time of day, a dated heading, a missing file and an unwritten figure."""
    assert MACHINE_PATH_RE.search("see /work/scratch/x.log") and MACHINE_PATH_RE.search("`../shared/design.md`")
    assert not MACHINE_PATH_RE.search("share/saml_ros/config and https://example.org/home/x")
    assert TIME_OF_DAY_RE.search("measured 23:31-23:35 UTC") and TIME_OF_DAY_RE.search("(at 9:05)")
    assert not TIME_OF_DAY_RE.search("a ratio of 1.5:1 or 10:1, test.py:123, [1:30]")
    assert DATE_RE.search("## Issue 15 (3 December 2026)") and DATE_RE.search("## 2026-12-03")
    assert not _exists("test/test_nothing_here.py") and _exists("test/unit/docs/test_docs.py::test_x")
    assert "test_docs.py" in _test_files() and "test_the_checks_catch_what_they_look_for" in _test_functions()
    assert _anchors(REPO / "docs" / "testing.md") == {"testing"}
    assert not _written_by_a_command(REPO / "docs" / "figures" / "nobody_writes_this.png")
    assert _written_by_a_command(REPO / "x" / "convergence_boxplot.png")  # convergence.py writes it
    assert _written_by_a_command(REPO / "x" / "friction_periodic_error_map_u1.png")  # an f-string in friction.py


@pytest.mark.parametrize("page", ["README.md", "docs/experiments.md", "docs/demo.md"])
def test_the_capacity_table_is_the_one_the_sweep_wrote(page: str) -> None:
    """The capacity sweep's table (size, SA and UA headroom captured, solve time, verdict) is the one of
    docs/results/experiments/capacity/results.md, row for row (`./dev experiment capacity --out
    docs/results/experiments/capacity` writes it)."""
    written = (REPO / "docs" / "results" / "experiments" / "capacity" / "results.md").read_text(encoding="utf-8")
    lines = written.splitlines()
    first = next((i for i, line in enumerate(lines) if line.startswith("|")), len(lines))
    end = next((i for i in range(first, len(lines)) if not lines[i].startswith("|")), len(lines))
    rows = lines[first:end]
    text = (REPO / page).read_text(encoding="utf-8").splitlines()
    assert len(rows) > 2, "the sweep's results.md holds no table"
    start = text.index(rows[0]) if rows[0] in text else -1
    assert start >= 0 and text[start:start + len(rows)] == rows, (
        f"{page}'s capacity table differs from docs/results/experiments/capacity/results.md")


@pytest.mark.parametrize("page", ["README.md", "docs/experiments.md"])
def test_the_claims_tables_are_the_one_the_experiments_wrote(page: str) -> None:
    """The README's and docs/experiments.md's claims tables are `./dev experiment all`'s claims.md, row for row, so
    they cannot drift from the run they cite (rerun the command, then copy its table into them)."""
    written = (REPO / "docs" / "results" / "experiments" / "claims.md").read_text(encoding="utf-8")
    rows = [line for line in written.splitlines() if line.startswith("|")]
    text = (REPO / page).read_text(encoding="utf-8").splitlines()
    assert len(rows) > 2, "claims.md holds no table"
    start = text.index(rows[0]) if rows[0] in text else -1
    assert start >= 0 and text[start:start + len(rows)] == rows, (
        f"{page}'s claims table differs from docs/results/experiments/claims.md")


def test_the_colcon_recipe_is_the_same_in_the_readme_and_packaging_md() -> None:
    """One recipe for Ubuntu 24.04 with Jazzy from apt: the README's and docs/packaging.md's code blocks agree."""
    def recipe(page: Path) -> str:
        text = page.read_text(encoding="utf-8")
        match = re.search(r"```bash\n(.*?)```", text[text.index("## Building with colcon"):], re.S)
        assert match is not None, f"{page}: no code block under '## Building with colcon'"
        return match.group(1)

    readme = recipe(REPO / "README.md")
    assert readme == recipe(REPO / "docs" / "packaging.md")
    assert "daqp" in readme and "whl/cpu" in readme and "rosdep install" in readme
