"""Move modules of ``saml_ros/core`` (issue 31) with ``git mv`` and rewrite every reference to them.

Run from the repository root, on a clean work tree::

    ./dev python -m scripts.restructure_core --dry-run   # what would move and which files would change
    ./dev python -m scripts.restructure_core             # do it (git mv + rewrites), then review `git diff`
    ./dev python -m scripts.restructure_core --check     # exit 1 if anything is left to move or rewrite

The table :data:`MOVES` maps an old file to its new file. For a module of a package (``saml_ros``, ``sim_nodes``,
``msg_schemas``) every reference in the repository's tracked text files is rewritten:

* dotted paths wherever they stand (``import``, ``from ... import``, strings such as ``"pkg.mod:func"``,
  ``:mod:`` roles, ``mock.patch`` targets): ``saml_ros.core.model_io`` -> ``saml_ros.core.model.io``;
* imports of the module as a name of its package, ``from saml_ros.core import model_io, spec``: the moved names
  are imported from their new package under the name they had (``from saml_ros.core.model import io as
  model_io``), so the code using them is unchanged;
* file paths (``saml_ros/core/model_io.py`` and the short ``core/model_io.py``).

A test file's move rewrites its path only. Running the script twice changes nothing the second time (a move whose
target exists and whose source does not is done; a reference to an old path no longer exists). It stops with a
message (exit 2) on what it cannot do: a move whose source and target both exist, or neither; a reference that is
left after the rewrite (for instance an import split over lines in a non-Python file). New packages get an
``__init__.py`` with a docstring and ``__all__`` (their modules) unless they have one.

After merging other branches into a tree where this already ran, run it again: their new references to old paths
are rewritten, and :func:`loose_core_modules` names the modules at the top of ``saml_ros/core`` that the table does
not place (add a row for each).
"""

from __future__ import annotations

import argparse
import ast
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("saml_ros", "sim_nodes", "msg_schemas")

#: old file -> new file (repository-relative). Order does not matter; no new path may be an old one.
MOVES: dict[str, str] = {
    # data in: buffer, pairing (exact stamps and resampled), plausibility, several publishers
    "saml_ros/core/buffer.py": "saml_ros/core/data/buffer.py",
    "saml_ros/core/pairing.py": "saml_ros/core/data/pairing.py",
    "saml_ros/core/resampling.py": "saml_ros/core/data/resampling.py",
    "saml_ros/core/plausibility.py": "saml_ros/core/data/plausibility.py",
    "saml_ros/core/publishers.py": "saml_ros/core/data/publishers.py",
    # the model: network, I/O, evidence, checkpoints, export
    "saml_ros/core/models.py": "saml_ros/core/model/network.py",
    "saml_ros/core/model_io.py": "saml_ros/core/model/io.py",
    "saml_ros/core/model_evidence.py": "saml_ros/core/model/evidence.py",
    "saml_ros/core/checkpoint.py": "saml_ros/core/model/checkpoint.py",
    # export reads checkpoints for other controllers; its CasADi format builds on the MPC's symbolic model, so it
    # sits above the core, beside api.py (load_model), the other face for users' own code
    "saml_ros/core/export.py": "saml_ros/export.py",
    # what only the MPC uses: the checkpoint follower, acceptance, the live monitor
    "saml_ros/core/model_watch.py": "saml_ros/core/mpc/follower.py",
    "saml_ros/core/model_acceptance.py": "saml_ros/core/mpc/acceptance.py",
    "saml_ros/core/model_monitor.py": "saml_ros/core/mpc/monitor.py",
    # the learner's configuration and report, and its recent-window counters
    "saml_ros/core/learner_config.py": "saml_ros/core/online/config.py",
    "saml_ros/core/learner_report.py": "saml_ros/core/online/report.py",
    "saml_ros/core/recent_counts.py": "saml_ros/core/online/recent_counts.py",
    # runtime helpers (used by nodes and the online learner's processes)
    "saml_ros/core/lifecycle.py": "saml_ros/core/runtime/lifecycle.py",
    "saml_ros/core/device.py": "saml_ros/core/runtime/device.py",
    "saml_ros/core/native_build.py": "saml_ros/core/runtime/native_build.py",
    "saml_ros/core/child_launch.py": "saml_ros/core/runtime/child_launch.py",
    # the dynamics every layer builds on: the System contract, quaternions, f_hat building blocks
    "saml_ros/core/systems/base.py": "saml_ros/core/dynamics/system.py",
    "saml_ros/core/systems/quaternion.py": "saml_ros/core/dynamics/quaternion.py",
    "saml_ros/core/systems/base_models.py": "saml_ros/core/dynamics/base_models.py",
    # modules of branches merged later (OPTIONAL: skipped where neither path exists)
    "saml_ros/core/systems/base_forms.py": "saml_ros/core/dynamics/base_forms.py",
    "saml_ros/core/systems/mpc_section.py": "saml_ros/core/mpc/generic/section.py",
    # the tests follow the package (test/unit/<part>/ mirrors saml_ros/<part>/)
    "test/unit/core/test_buffer.py": "test/unit/core/data/test_buffer.py",
    "test/unit/core/test_pairing.py": "test/unit/core/data/test_pairing.py",
    "test/unit/core/test_state_rate_pairing.py": "test/unit/core/data/test_state_rate_pairing.py",
    "test/unit/core/test_resampling.py": "test/unit/core/data/test_resampling.py",
    "test/unit/core/test_plausibility.py": "test/unit/core/data/test_plausibility.py",
    "test/unit/core/test_checkpoint.py": "test/unit/core/model/test_checkpoint.py",
    "test/unit/core/test_model_io.py": "test/unit/core/model/test_model_io.py",
    "test/unit/core/test_model_acceptance.py": "test/unit/core/mpc/test_model_acceptance.py",
    "test/unit/core/test_device.py": "test/unit/core/runtime/test_device.py",
    "test/unit/core/test_storage_faults.py": "test/unit/core/online/test_storage_faults.py",
}

#: rows of :data:`MOVES` for files that exist only once another branch is merged
OPTIONAL = {"saml_ros/core/systems/base_forms.py", "saml_ros/core/systems/mpc_section.py"}

#: docstrings of the packages the table creates (their ``__all__`` lists their modules)
NEW_PACKAGES: dict[str, str] = {
    "saml_ros/core/data": "Data in, ROS-free: the replay buffer, pairing of messages into transitions (exact stamps "
                          "and resampled), plausibility bounds, the several-publishers decision.",
    "saml_ros/core/model": "The learned model: the network, its checkpoint I/O without the trainer, the data "
                           "evidence stored with it, versioned checkpoints.",
    "saml_ros/core/dynamics": "The dynamics every layer builds on (no registry, no MPC, no simulator): the System "
                              "contract, quaternion helpers, the f_hat building blocks of system files.",
    "saml_ros/core/runtime": "Runtime helpers of the nodes and the learner's processes: lifecycle, the training "
                             "device, where native code is built, starting the training interpreter.",
}

#: ``file:Class`` (new paths) of the errors re-based on :class:`saml_ros.core.errors.SamlError` (issue 31 item 3): the
#: class keeps its built-in base (``class SpecError(SamlError, ValueError)``; ``Exception`` is replaced)
SAML_ERRORS: tuple[str, ...] = (
    "saml_ros/core/spec.py:SpecError",
    "saml_ros/core/params.py:ParamErrors",
    "saml_ros/core/model/checkpoint.py:CheckpointError",
    "saml_ros/core/model/io.py:UnhealthyModel",
    "saml_ros/export.py:ExportError",
    "saml_ros/core/runtime/lifecycle.py:TransitionRefused",
    "saml_ros/core/runtime/device.py:DeviceError",
    "saml_ros/core/dynamics/base_models.py:BaseModelError",
    "saml_ros/systems/system_file.py:SystemFileError",
    "saml_ros/core/worlds/sim_core.py:CommandRejected",
    "saml_ros/core/online/resume.py:ResumeError",
    "saml_ros/bags/io.py:BagError",
    "saml_ros/offline/sweep.py:SweepError",
    "saml_ros/offline/parallel.py:RayUnavailable",
    "saml_ros/nodes/learner.py:ConfigError",
    "msg_schemas/base.py:SchemaError",
    "msg_schemas/field_path.py:FieldPathError",
    # generic-mpc's (skipped where the file does not exist yet)
    "saml_ros/core/mpc/generic/section.py:MPCSectionError",
    "saml_ros/core/mpc/generic/goals.py:GoalRefused",
)
OPTIONAL_ERRORS = {"saml_ros/core/mpc/generic/section.py", "saml_ros/core/mpc/generic/goals.py"}
ERRORS_MODULE = "saml_ros/core/errors.py"

#: never rewritten: history (the changelog), this table and its test (planted old paths), and requirements.txt
#: (``./dev`` reinstalls the shared virtual environment when its hash changes; its comments may keep an old path)
KEEP = {"CHANGELOG.md", "scripts/restructure_core.py", "test/unit/scripts/test_restructure_core.py",
        "requirements.txt"}
TEXT_SUFFIXES = {".py", ".md", ".yaml", ".yml", ".xml", ".cfg", ".toml", ".txt", ".rst", ".ini", ".json", ".sh",
                 ".launch", ".c", ".cpp", ".h"}
TEXT_NAMES = {"dev", "setup.py", "Makefile"}
LINE_LENGTH = 120  # ruff's (pyproject.toml)


def module_name(path: str) -> str | None:
    """``saml_ros/core/model_io.py`` -> ``saml_ros.core.model_io``; ``None`` outside the packages."""
    parts = Path(path).with_suffix("").parts
    if parts[0] not in PACKAGES or not path.endswith(".py"):
        return None
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@dataclass
class Plan:
    moves: list[tuple[str, str]] = field(default_factory=list)
    new_inits: list[str] = field(default_factory=list)
    edits: dict[str, str] = field(default_factory=dict)  # path -> new text
    problems: list[str] = field(default_factory=list)


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, check=True, capture_output=True, text=True).stdout


def tracked_text_files() -> list[str]:
    out = []
    for rel in _git("ls-files", "-z").split("\0"):
        p = Path(rel)
        if not rel or rel in KEEP or not (ROOT / rel).is_file():
            continue
        if p.suffix in TEXT_SUFFIXES or p.name in TEXT_NAMES:
            out.append(rel)
    return out


def _module_pairs() -> list[tuple[str, str]]:
    pairs = []
    for old, new in MOVES.items():
        a, b = module_name(old), module_name(new)
        if (a is None) != (b is None):
            raise SystemExit(f"restructure: {old} -> {new} moves a file into or out of the packages")
        if a and b:
            pairs.append((a, b))
    return pairs


def _check_table() -> None:
    olds = set(MOVES)
    for new in MOVES.values():
        if new in olds:
            raise SystemExit(f"restructure: {new} is both a target and a source in MOVES")
    mods = _module_pairs()
    old_mods = {a for a, _ in mods}
    for _, b in mods:
        if any(b == a or b.startswith(a + ".") for a in old_mods):
            raise SystemExit(f"restructure: new module {b} starts with an old module path (not idempotent)")


# ------------------------------------------------------------------------------------------- rewriting text
def _dotted_re(old: str) -> re.Pattern[str]:
    return re.compile(r"(?<![\w.])" + re.escape(old) + r"(?![\w])")


def _path_res(old: str) -> list[tuple[re.Pattern[str], str]]:
    """Patterns of a file path: the full one and, below saml_ros/, the short ``core/...`` form docs use."""
    out = [(re.compile(r"(?<![\w/.])" + re.escape(old) + r"(?![\w])"), "")]
    if old.startswith("saml_ros/"):
        short = old[len("saml_ros/"):]
        out.append((re.compile(r"(?<![\w/.])" + re.escape(short) + r"(?![\w])"), "short"))
    return out


def _rewrite_from_imports_py(text: str, moved: dict[str, str], rel: str, problems: list[str]) -> str:
    """``from P import a, b as c`` where ``P.a`` is a moved module: split into the unmoved rest and one
    ``from NEWPKG import NEWNAME as a`` per moved module. Uses the AST (multi-line, parenthesised forms)."""
    if not any(o.rsplit(".", 1)[1] in text for o in moved):
        return text
    try:
        tree = ast.parse(text)
    except SyntaxError as e:
        problems.append(f"{rel}: cannot parse ({e}); its 'from ... import module' forms are not rewritten")
        return text
    lines = text.splitlines(keepends=True)
    edits: list[tuple[int, int, str]] = []  # (first line index, last line index, replacement)
    for node in ast.walk(tree):
        if not (isinstance(node, ast.ImportFrom) and node.module and node.level == 0):
            continue
        hits = [a for a in node.names if f"{node.module}.{a.name}" in moved]
        if not hits:
            continue
        first, last = node.lineno - 1, (node.end_lineno or node.lineno) - 1
        indent = lines[first][: len(lines[first]) - len(lines[first].lstrip())]
        stmt_lines = lines[first: last + 1]
        if not stmt_lines[0].lstrip().startswith("from ") or ";" in "".join(stmt_lines):
            problems.append(f"{rel}:{node.lineno}: an import form this script does not rewrite")
            continue
        trailing = ""
        tail = stmt_lines[-1].rstrip("\n")
        m = re.search(r"\s+#.*$", tail)
        if m and len(stmt_lines) == 1:
            trailing = m.group(0)
        new = []
        rest = [a for a in node.names if a not in hits]
        if rest:
            names = ", ".join(a.name + (f" as {a.asname}" if a.asname else "") for a in rest)
            new.append(f"{indent}from {node.module} import {names}{trailing}\n")
        for a in hits:
            pkg, name = moved[f"{node.module}.{a.name}"].rsplit(".", 1)
            bind = a.asname or a.name
            new.append(f"{indent}from {pkg} import {name}" + (f" as {bind}" if bind != name else "")
                       + (trailing if not rest else "") + "\n")
        edits.append((first, last, "".join(new)))
    for first, last, rep in sorted(edits, reverse=True):
        lines[first: last + 1] = [rep]
    return "".join(lines)


_FROM_LINE = re.compile(r"^(?P<indent>[ \t>]*)from (?P<pkg>[\w.]+) import (?P<names>[^\n(]+)$", re.M)


def _rewrite_from_imports_text(text: str, moved: dict[str, str]) -> str:
    """The one-line ``from P import a, b`` forms in non-Python files (code blocks of docs)."""
    def one(m: re.Match[str]) -> str:
        pkg, names = m.group("pkg"), [n.strip() for n in m.group("names").split(",")]
        hits: list[str] = []
        rest: list[str] = []
        for n in names:
            base = n.split(" as ")[0].strip()
            (hits if f"{pkg}.{base}" in moved else rest).append(n)
        if not hits:
            return m.group(0)
        out = [f"{m.group('indent')}from {pkg} import {', '.join(rest)}"] if rest else []
        for n in hits:
            base, _, asname = (p.strip() for p in n.partition(" as "))
            newpkg, newname = moved[f"{pkg}.{base}"].rsplit(".", 1)
            bind = asname or base
            out.append(f"{m.group('indent')}from {newpkg} import {newname}" + (f" as {bind}" if bind != newname else ""))
        return "\n".join(out)

    return _FROM_LINE.sub(one, text)


def rewrite(text: str, rel: str, problems: list[str]) -> str:
    moved = dict(_module_pairs())
    if rel.endswith(".py"):
        text = _rewrite_from_imports_py(text, moved, rel, problems)
    else:
        text = _rewrite_from_imports_text(text, moved)
    # longest first, so that no shorter old path rewrites a part of a longer one
    for old, new in sorted(moved.items(), key=lambda kv: -len(kv[0])):
        text = _dotted_re(old).sub(new, text)
    for old, new in sorted(MOVES.items(), key=lambda kv: -len(kv[0])):
        for pattern, kind in _path_res(old):
            text = pattern.sub(new[len("saml_ros/"):] if kind == "short" else new, text)
    return text


def leftovers(text: str, rel: str) -> list[str]:
    """References to old paths that are still in ``text`` (after :func:`rewrite` there must be none)."""
    out = []
    moved = dict(_module_pairs())
    # each pattern holds its old path as a literal: a text without that substring cannot match (a substring test
    # is ~100x cheaper than the look-behind search, which the tree-wide check runs on every file)
    for old in moved:
        if old in text and _dotted_re(old).search(text):
            out.append(f"{rel}: dotted path {old}")
        pkg, name = old.rsplit(".", 1)
        if f"from {pkg} import " not in text:
            continue
        for m in re.finditer(r"from " + re.escape(pkg) + r" import (\([^)]*\)|[^\n]*)", text):
            if re.search(r"(?<![\w.])" + re.escape(name) + r"(?![\w])", m.group(1)):
                out.append(f"{rel}: 'from {pkg} import {name}'")
    for old in MOVES:
        for pattern, kind in _path_res(old):
            if (old[len("saml_ros/"):] if kind == "short" else old) in text and pattern.search(text):
                out.append(f"{rel}: file path {old}")
    return out


#: where a node refuses a lifecycle transition on a bad value (``except ValueError`` then ``raise
#: TransitionRefused``), it refuses on any :class:`SamlError` too (issue 31 item 3: the nodes catch and report it)
NODE_FILES = ("saml_ros/nodes/learner.py", "saml_ros/nodes/mpc.py")
_REFUSE = re.compile(r"^(?P<i>[ ]*)except (?P<what>ValueError|\((?!SamlError)[^)]*\bValueError\b[^)]*\)) as exc:"
                     r"(?P<rest>[^\n]*\n[ ]*raise TransitionRefused\()", re.M)


def catch_saml_errors(text: str) -> str:
    """``text`` with every ``except ValueError`` (or a tuple holding it) that raises ``TransitionRefused`` also
    catching ``SamlError`` (and importing it); unchanged where it already does."""
    def one(m: re.Match[str]) -> str:
        what = m.group("what").strip("()")
        return f"{m.group('i')}except (SamlError, {what}) as exc:{m.group('rest')}"

    new = _REFUSE.sub(one, text)
    if new != text and not re.search(r"^from saml_ros\.core\.errors import SamlError$", new, re.M):
        future = re.search(r"^from __future__ import [^\n]*\n", new, re.M)
        at = future.end() if future else 0
        new = new[:at] + "\nfrom saml_ros.core.errors import SamlError\n" + new[at:]
    return new


def rebase_error(text: str, cls: str) -> str | None:
    """``text`` with ``class cls(...)`` deriving from ``SamlError`` (and importing it); the same text if it already
    does; ``None`` if the class is not defined at the top level of ``text``."""
    m = re.search(r"^class " + re.escape(cls) + r"\((?P<bases>[^)]*)\):", text, re.M)
    if m is None:
        return None
    bases = [b.strip() for b in m.group("bases").split(",") if b.strip()]
    if "SamlError" in bases:
        return text
    bases = ["SamlError", *(b for b in bases if b != "Exception")]
    text = text[: m.start()] + f"class {cls}({', '.join(bases)}):" + text[m.end():]
    if not re.search(r"^from saml_ros\.core\.errors import SamlError$", text, re.M):
        future = re.search(r"^from __future__ import [^\n]*\n", text, re.M)
        at = future.end() if future else 0
        text = text[:at] + "\nfrom saml_ros.core.errors import SamlError\n" + text[at:]
    return text


# ------------------------------------------------------------------------------------------------ planning
def plan() -> Plan:
    _check_table()
    p = Plan()
    for old, new in MOVES.items():
        a, b = (ROOT / old).exists(), (ROOT / new).exists()
        if a and b:
            p.problems.append(f"both {old} and {new} exist: merge them by hand, then run again")
        elif a:
            p.moves.append((old, new))
        elif not b and old not in OPTIONAL:
            p.problems.append(f"neither {old} nor {new} exists")
    present = [new for old, new in MOVES.items() if (ROOT / old).exists() or (ROOT / new).exists()]
    for d in sorted({str(Path(new).parent) for new in present}):
        if module_name(d + "/__init__.py") and not (ROOT / d / "__init__.py").exists():
            p.new_inits.append(d + "/__init__.py")
    for rel in tracked_text_files():
        try:
            text = (ROOT / rel).read_text()
        except UnicodeDecodeError:
            continue
        new = rewrite(text, rel, p.problems)
        if new != text:
            p.edits[rel] = new
    if not (ROOT / ERRORS_MODULE).exists():
        p.problems.append(f"{ERRORS_MODULE} (SamlError) is missing: check it out from the restructure branch")
    new_of = {new: old for old, new in MOVES.items()}
    for item in SAML_ERRORS:
        rel, cls = item.split(":")
        src = new_of.get(rel, rel) if not (ROOT / rel).exists() else rel  # planned before the moves
        if not (ROOT / src).exists():
            if rel not in OPTIONAL_ERRORS:
                p.problems.append(f"{item}: no such file")
            continue
        text = p.edits.get(src, (ROOT / src).read_text())
        rebased = rebase_error(text, cls)
        if rebased is None:
            p.problems.append(f"{item}: no top-level class {cls} (moved? update SAML_ERRORS)")
        elif rebased != text:
            p.edits[src] = rebased
    for rel in NODE_FILES:
        if (ROOT / rel).exists():
            text = p.edits.get(rel, (ROOT / rel).read_text())
            caught = catch_saml_errors(text)
            if caught != text:
                p.edits[rel] = caught
    return p


def _init_text(pkg_dir: str) -> str:
    mods = sorted(Path(n).stem for o, n in MOVES.items() if str(Path(n).parent) == pkg_dir
                  and ((ROOT / o).exists() or (ROOT / n).exists()))
    doc = NEW_PACKAGES.get(pkg_dir)
    if doc is None:
        raise SystemExit(f"restructure: no docstring for the new package {pkg_dir} in NEW_PACKAGES")
    body = "\n".join(f"    \"{m}\"," for m in mods)
    lines = [f'"""{doc}"""' if len(doc) < 110 else '"""' + _wrap(doc) + '\n"""', "", f"__all__ = [\n{body}\n]", ""]
    return "\n".join(lines)


def _wrap(text: str, width: int = 116) -> str:
    out, line = [], ""
    for word in text.split():
        if len(line) + len(word) + 1 > width:
            out.append(line)
            line = word
        else:
            line = f"{line} {word}" if line else word
    return "\n".join([*out, line])


def loose_core_modules() -> list[str]:
    """Modules at the top of saml_ros/core (beside its subpackages) after the moves."""
    return sorted(p.name for p in (ROOT / "saml_ros" / "core").glob("*.py") if p.name != "__init__.py")


def apply(p: Plan) -> None:
    for old, new in p.moves:
        (ROOT / new).parent.mkdir(parents=True, exist_ok=True)
        _git("mv", old, new)
    for init in p.new_inits:
        (ROOT / init).write_text(_init_text(str(Path(init).parent)))
        _git("add", init)
    for rel, text in p.edits.items():  # planned on the old paths
        (ROOT / MOVES.get(rel, rel)).write_text(text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dry-run", action="store_true", help="print what would move and change; touch nothing")
    ap.add_argument("--check", action="store_true", help="exit 1 if anything is left to move or rewrite")
    ap.add_argument("--diff", action="store_true", help="with --dry-run: print the changed lines of every file")
    args = ap.parse_args(argv)

    p = plan()
    if p.problems:
        print("restructure: cannot go on:\n  " + "\n  ".join(p.problems), file=sys.stderr)
        return 2
    for old, new in p.moves:
        print(f"move  {old} -> {new}")
    for init in p.new_inits:
        print(f"new   {init}")
    for rel, text in sorted(p.edits.items()):
        before = (ROOT / rel).read_text().splitlines()
        after = text.splitlines()
        print(f"edit  {rel}" + (f"  ({sum(1 for a, b in zip(before, after) if a != b)} lines)"
                                if len(before) == len(after) else ""))
        if args.diff:
            import difflib
            sys.stdout.writelines(difflib.unified_diff([x + "\n" for x in before], [x + "\n" for x in after],
                                                       rel, rel, n=0))
    if args.check:
        return 1 if (p.moves or p.edits or p.new_inits) else 0
    if args.dry_run:
        print(f"(dry run: {len(p.moves)} moves, {len(p.new_inits)} new packages, {len(p.edits)} files to edit)")
        return 0
    apply(p)
    left = []
    for rel in tracked_text_files():
        try:
            left += leftovers((ROOT / rel).read_text(), rel)
        except UnicodeDecodeError:
            continue
    if left:
        print("restructure: references left that this script did not rewrite (fix by hand):\n  "
              + "\n  ".join(left), file=sys.stderr)
        return 2
    edited = sorted({MOVES.get(r, r) for r in p.edits if r.endswith(".py")} | set(p.new_inits))
    if edited:  # the rewritten imports sort differently: let ruff's isort order them (nothing else)
        subprocess.run([sys.executable, "-m", "ruff", "check", "--quiet", "--fix", "--select", "I001",
                        *edited], cwd=ROOT, check=False)
    long_lines = [f"{r}:{i}" for r in edited for i, line in enumerate((ROOT / r).read_text().splitlines(), 1)
                  if len(line) > LINE_LENGTH]
    if long_lines:
        print(f"restructure: lines over {LINE_LENGTH} characters after the rewrite (wrap them by hand):\n  "
              + "\n  ".join(long_lines), file=sys.stderr)
    loose = loose_core_modules()
    print(f"done: {len(p.moves)} moves, {len(p.new_inits)} new packages, {len(p.edits)} files edited; "
          f"{len(loose)} loose modules in saml_ros/core: {', '.join(loose)}")
    if len(loose) > 8:
        print("restructure: more than 8 loose modules in saml_ros/core: add rows to MOVES", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
