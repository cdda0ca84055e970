"""Put each built-in system in one folder (issue 31 item 1): ``git mv`` of whole files, the split of modules that
hold several systems' parts, and every reference to an old place rewritten.

Run from the repository root, on a clean work tree (after :mod:`scripts.restructure_core` has run)::

    ./dev python -m scripts.restructure_systems --dry-run   # what would move, split and change
    ./dev python -m scripts.restructure_systems             # do it, then review `git diff`
    ./dev python -m scripts.restructure_systems --check     # exit 1 if anything is left to move, split or rewrite

Three tables say what happens, in this order:

1. :data:`MOVES`: old file -> new file (``git mv``); a module's references are rewritten as by
   :mod:`scripts.restructure_core` (dotted paths, ``from pkg import module``, full and short file paths), and the
   short dotted form docs use (``core.worlds.paddle_world`` -> ``systems.paddle_ball.world``).
2. :data:`SPLITS`: top-level definitions (classes, functions, constants; with the comment lines right above them)
   cut out of a module (at its path after the moves) into a new module of one system. The new module gets a
   docstring, the imports of the source that its definitions use, and an import from the source for what they use
   of the source; the source keeps only the imports still used. Every reference to a moved name elsewhere is
   rewritten (``from src import Name`` -> ``from new import Name``; dotted ``src.Name`` in text and strings).
3. :data:`NAMES`: further names that moved (rows written by hand: a package face that no longer re-exports, a
   function that went to another layer); only their references are rewritten.

Running it twice changes nothing the second time: a move whose target exists and whose source does not is done, a
split whose names are all in the target and none in the source is done. It stops with a message (exit 2) on what
it cannot do: a move whose source and target both exist, or neither; a split whose names are in neither module or
in both; a reference left after the rewrite. (A source that still uses a moved name imports it from the new module;
test_layers.py says whether that import runs against the layering.)

After merging other branches into a tree where this already ran, run it again: their new references to old
places are rewritten (their edits to a moved file arrive at its new path only if git saw the rename).
"""

from __future__ import annotations

import argparse
import ast
import functools
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from scripts.restructure_core import (
    LINE_LENGTH,
    ROOT,
    TEXT_NAMES,
    TEXT_SUFFIXES,
    _dotted_re,
    _git,
    _path_res,
    _rewrite_from_imports_py,
    _rewrite_from_imports_text,
    module_name,
)

SYS = "saml_ros/systems"
PADDLE_MPC = "saml_ros/core/mpc/paddle"

#: old file -> new file (repository-relative); no new path may be an old one
MOVES: dict[str, str] = {
    # each system's dynamics (torch f_hat and the true model) into its folder
    "saml_ros/core/systems/friction.py": f"{SYS}/friction/model.py",
    "saml_ros/core/systems/quadrotor.py": f"{SYS}/quadrotor/model.py",
    "saml_ros/core/systems/paddle_ball.py": f"{SYS}/paddle_ball/model.py",
    # the parameter checks of every system class: beside the System contract
    "saml_ros/core/systems/_checks.py": "saml_ros/core/dynamics/checks.py",
    # the paddle ball's MuJoCo world, its simulator core and its one-shot planner
    "saml_ros/core/worlds/paddle_world.py": f"{SYS}/paddle_ball/world.py",
    "saml_ros/core/worlds/paddle_sim.py": f"{SYS}/paddle_ball/sim.py",
    "saml_ros/core/worlds/assets/paddle_ball.xml": f"{SYS}/paddle_ball/assets/paddle_ball.xml",
    **{f"{PADDLE_MPC}/{m}.py": f"{SYS}/paddle_ball/mpc/{m}.py"
       for m in ("__init__", "controller", "feasible_set", "landing_error", "multistart", "problem",
                 "projected_newton")},
    # the built-in entries (split below into one entry module per system) become the package of the systems
    "saml_ros/core/systems/builtin.py": f"{SYS}/__init__.py",
    # robots described by a system file: their entries wire the generic MPC, so they sit with the systems
    "saml_ros/core/systems/system_file.py": f"{SYS}/system_file.py",
    "saml_ros/core/systems/robot_entry.py": f"{SYS}/robot_entry.py",
    # the figures of docs/systems.md draw the built-in systems
    "saml_ros/core/systems/plots.py": f"{SYS}/plots.py",
    # the tests of the systems' own parts follow them (test/unit/<part>/ mirrors saml_ros/<part>/)
    "test/unit/core/systems/test_systems.py": "test/unit/systems/test_systems.py",
    "test/unit/core/systems/test_system_file.py": "test/unit/systems/test_system_file.py",
    "test/unit/core/worlds/test_paddle_ball_world.py": "test/unit/systems/test_paddle_ball_world.py",
    "test/unit/core/mpc/test_mpc_paddle.py": "test/unit/systems/test_mpc_paddle.py",
    # modules of branches merged later (OPTIONAL: skipped where neither path exists): the quadrotor's f_hat as an
    # array-namespace form for the generic planner (the mpc-robot branch)
    "saml_ros/core/mpc/generic/quadrotor_form.py": f"{SYS}/quadrotor/generic_form.py",
}

#: rows of :data:`MOVES` for files that exist only once another branch is merged
OPTIONAL = {"saml_ros/core/mpc/generic/quadrotor_form.py"}


@dataclass(frozen=True)
class Split:
    """Top-level ``names`` of module file ``source`` (its path after :data:`MOVES`) into the new file ``target``."""

    source: str
    target: str
    names: tuple[str, ...]
    doc: str


SPLITS: tuple[Split, ...] = (
    # the numpy twins of each system's base and true model (the MPC's exact-Jacobian f_hat)
    Split("saml_ros/core/mpc/dynamics_np.py", f"{SYS}/friction/dynamics_np.py", ("FrictionBaseNP", "FrictionTrueNP"),
          "The friction system's numpy twins: f_hat and the true model on float64 arrays with exact Jacobians (the "
          "MPC's prediction model, :class:`saml_ros.core.mpc.dynamics_np.NumpyDynamics`)."),
    Split("saml_ros/core/mpc/dynamics_np.py", f"{SYS}/quadrotor/dynamics_np.py",
          ("QuadrotorBaseNP", "QuadrotorTrueNP", "_cross"),
          "The quadrotor's numpy twins: f_hat (vectorised and scalar, with exact Jacobians; the C kernel of the "
          "shooting SQP rounds as the scalar one) and the true model (the MPC's oracle)."),
    Split("saml_ros/core/mpc/dynamics_np.py", f"{SYS}/paddle_ball/dynamics_np.py", ("PaddleBaseNP", "PaddleTrueNP"),
          "The paddle ball's numpy twins: the impact map of f_hat and of the true model with exact Jacobians."),
    # the shooting MPC's problem of each time-stepped system
    Split("saml_ros/core/mpc/shooting/tasks.py", f"{SYS}/friction/task.py", ("friction_task",),
          "The friction system's MPC problem (paper eq. double_integrator_mpc) as a shooting task."),
    Split("saml_ros/core/mpc/shooting/tasks.py", f"{SYS}/quadrotor/task.py", ("quadrotor_task",),
          "The quadrotor's MPC problem (paper eq. quad3d_mpc: landing at a target) as a shooting task."),
    # each time-stepped system's simulator world: start states, safe command, ground contact
    Split("saml_ros/core/worlds/sim_core.py", f"{SYS}/friction/world.py", ("friction_start", "friction_model"),
          "The friction system's simulator world: episode starts and the safe command of a stepped simulator."),
    Split("saml_ros/core/worlds/sim_core.py", f"{SYS}/quadrotor/world.py",
          ("quadrotor_start", "ground_contact", "_normalize_quaternion", "quadrotor_model"),
          "The quadrotor's simulator world: episode starts, the ground (landing height), the safe command."),
    # the paddle world's bounce sequences and data collection, apart from the world itself
    Split(f"{SYS}/paddle_ball/world.py", f"{SYS}/paddle_ball/bounces.py",
          ("Controller", "BounceChooser", "REHIT", "OFF_PLAN", "NOT_UP", "LANDS_OUT", "BounceRecord",
           "bounce_sequence", "SLOW_BALL_SPEED", "random_commands", "CollectStats", "collect_impacts",
           "impacts_to_arrays"),
          "Sequences of impacts in the paddle-ball world (:mod:`.world`): a high-level controller keeping the ball "
          "bouncing (:func:`bounce_sequence`) and the collection of impact transitions with random commands."),
    # one registry entry per system, in its folder; what the entries share
    Split(f"{SYS}/__init__.py", f"{SYS}/common.py", ("T", "_as", "_shooting_controllers"),
          "What the built-in systems' entries share: a system checked against its class, the shooting MPC's "
          "controllers."),
    Split(f"{SYS}/__init__.py", f"{SYS}/friction/entry.py",
          ("_friction_class", "_friction_schema", "_friction_task", "_friction_base_np", "_friction_true_np",
           "_friction_model", "_friction_simulator", "FRICTION"),
          "The friction system's registry entry: where each of its parts lives (imported when asked for)."),
    Split(f"{SYS}/__init__.py", f"{SYS}/quadrotor/entry.py",
          ("_quadrotor_class", "_quadrotor_schema", "_quadrotor_task", "_quadrotor_base_np", "_quadrotor_true_np",
           "_quadrotor_model", "_quadrotor_simulator", "QUADROTOR"),
          "The quadrotor's registry entry: where each of its parts lives (imported when asked for)."),
    Split(f"{SYS}/__init__.py", f"{SYS}/paddle_ball/entry.py",
          ("_paddle_class", "_paddle_schema", "_paddle_controllers", "_paddle_base_np", "_paddle_true_np",
           "_paddle_simulator", "_paddle_goal", "PADDLE_BALL"),
          "The paddle ball's registry entry: where each of its parts lives (imported when asked for)."),
)

#: further moved names, ``old.module.Name`` -> ``new.module.Name`` (references rewritten only)
NAMES: dict[str, str] = {
    # the MPC's face no longer re-exports the paddle ball's planner
    **{f"saml_ros.core.mpc.{n}": f"saml_ros.systems.paddle_ball.mpc.{n}"
       for n in ("GaussNewtonPaddle", "PaddleGoal", "SLSQPPaddle", "paddle_goal")},
    # a stepped simulator from the registry: the worlds' layer looks the entry up
    "saml_ros.core.systems.registry.build_stepped_sim": "saml_ros.core.worlds.sim_core.build_stepped_sim",
}

#: new packages (a folder under a package without ``__init__.py``) and their docstrings
NEW_PACKAGES: dict[str, str] = {
    f"{SYS}/friction": "The double integrator with friction: its dynamics (:mod:`.model`), numpy twins "
                       "(:mod:`.dynamics_np`), MPC task (:mod:`.task`), simulator world (:mod:`.world`) and registry "
                       "entry (:mod:`.entry`).",
    f"{SYS}/quadrotor": "The quadrotor with ground effect: its dynamics (:mod:`.model`), numpy twins "
                        "(:mod:`.dynamics_np`), MPC task (:mod:`.task`), simulator world (:mod:`.world`) and "
                        "registry entry (:mod:`.entry`).",
    f"{SYS}/paddle_ball": "The paddle ball: its dynamics (:mod:`.model`), numpy twins (:mod:`.dynamics_np`), one-shot "
                          "planner (:mod:`.mpc`), MuJoCo world (:mod:`.world`, :mod:`.bounces`), simulator core "
                          "(:mod:`.sim`) and registry entry (:mod:`.entry`).",
}

#: never rewritten: history (the changelog), this table and its test, requirements.txt (see restructure_core)
KEEP = {"CHANGELOG.md", "scripts/restructure_systems.py", "test/unit/scripts/test_restructure_systems.py",
        "requirements.txt"}


# ------------------------------------------------------------------------------------------- the tables
def _mod(path: str) -> str:
    name = module_name(path)
    if name is None:
        raise SystemExit(f"restructure_systems: {path} is not a module of the packages")
    return name


@functools.cache
def moved_names() -> dict[str, str]:
    """Every moved dotted path: modules of :data:`MOVES`, names of :data:`SPLITS` and :data:`NAMES`."""
    out: dict[str, str] = {}
    for old, new in MOVES.items():
        a, b = module_name(old), module_name(new)
        if (a is None) != (b is None):
            raise SystemExit(f"restructure_systems: {old} -> {new} moves a file into or out of the packages")
        if a and b:
            out[a] = b
    for s in SPLITS:
        src, dst = _mod(s.source), _mod(s.target)
        old_src = next((module_name(o) for o, n in MOVES.items() if n == s.source), None)
        for n in s.names:
            out[f"{src}.{n}"] = f"{dst}.{n}"
            if old_src:  # the name at the source's old place too
                out[f"{old_src}.{n}"] = f"{dst}.{n}"
    out.update(NAMES)
    return out


def _check_tables() -> None:
    olds = set(MOVES)
    for new in MOVES.values():
        if new in olds:
            raise SystemExit(f"restructure_systems: {new} is both a target and a source in MOVES")
    moved = moved_names()
    for old, new in moved.items():
        if new == old or new.startswith(old + "."):
            raise SystemExit(f"restructure_systems: {new} starts with the old path {old} (not idempotent)")


# ------------------------------------------------------------------------------------------ rewriting text
def rewrite(text: str, rel: str, problems: list[str]) -> str:
    """``text`` with every reference to a moved module, name or file rewritten."""
    moved = moved_names()
    if rel.endswith(".py"):
        text = _rewrite_from_imports_py(text, moved, rel, problems)
    else:
        text = _rewrite_from_imports_text(text, moved)
    for old, new in sorted(moved.items(), key=lambda kv: -len(kv[0])):  # longest first
        text = _dotted_re(old).sub(new, text)
    for old, new in sorted(moved.items(), key=lambda kv: -len(kv[0])):  # the short ``core.x.y`` form of docs
        if old.startswith("saml_ros.core."):
            text = _dotted_re(old[len("saml_ros."):]).sub(new[len("saml_ros."):], text)
    for old, new in sorted(MOVES.items(), key=lambda kv: -len(kv[0])):
        for pattern, kind in _path_res(old):
            text = pattern.sub(new[len("saml_ros/"):] if kind == "short" else new, text)
    return text


@functools.cache
def _leftover_patterns() -> tuple[re.Pattern[str], re.Pattern[str], dict[str, set[str]], re.Pattern[str]]:
    """One pattern each (compiled once): dotted old paths (full and short), ``from <old package> import ...``
    statements (with the moved names per package), old file paths (full and short)."""
    moved = moved_names()
    dotted = set(moved) | {o[len("saml_ros."):] for o in moved if o.startswith("saml_ros.core.")}
    alt = "|".join(re.escape(d) for d in sorted(dotted, key=len, reverse=True))
    names: dict[str, set[str]] = {}
    for old in moved:
        pkg, name = old.rsplit(".", 1)
        names.setdefault(pkg, set()).add(name)
    pkgs = "|".join(re.escape(p) for p in sorted(names, key=len, reverse=True))
    files = {old for old in MOVES} | {old[len("saml_ros/"):] for old in MOVES if old.startswith("saml_ros/")}
    falt = "|".join(re.escape(f) for f in sorted(files, key=len, reverse=True))
    return (re.compile(r"(?<![\w.])(" + alt + r")(?![\w])"),
            re.compile(r"from (" + pkgs + r") import (\([^)]*\)|[^\n]*)"), names,
            re.compile(r"(?<![\w/.])(" + falt + r")(?![\w])"))


def leftovers(text: str, rel: str) -> list[str]:
    """References to old places still in ``text`` (after :func:`rewrite` there must be none)."""
    dotted, from_re, names, files = _leftover_patterns()
    out = [f"{rel}: dotted path {m.group(1)}" for m in dotted.finditer(text)]
    for m in from_re.finditer(text):
        for name in sorted(names[m.group(1)]):
            if re.search(r"(?<![\w.])" + re.escape(name) + r"(?![\w])", m.group(2)):
                out.append(f"{rel}: 'from {m.group(1)} import {name}'")
    out += [f"{rel}: file path {m.group(1)}" for m in files.finditer(text)]
    return out


def tracked_text_files() -> list[str]:
    out = []
    for rel in _git("ls-files", "-z").split("\0"):
        p = Path(rel)
        if rel and rel not in KEEP and (ROOT / rel).is_file() and (p.suffix in TEXT_SUFFIXES or p.name in TEXT_NAMES):
            out.append(rel)
    return out


# ------------------------------------------------------------------------------------------ splitting
def _defined(node: ast.stmt) -> list[str]:
    """Names a top-level statement defines (class, function, assignment targets)."""
    if isinstance(node, ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
        return [node.name]
    if isinstance(node, ast.Assign):
        return [t.id for t in node.targets if isinstance(t, ast.Name)]
    if isinstance(node, ast.AnnAssign | ast.AugAssign) and isinstance(node.target, ast.Name):
        return [node.target.id]
    return []


def _used(nodes: list[ast.stmt]) -> set[str]:
    """Identifiers the statements read (names and the roots of attribute chains)."""
    out: set[str] = set()
    for node in nodes:
        for n in ast.walk(node):
            if isinstance(n, ast.Name):
                out.add(n.id)
    return out


def _span(lines: list[str], node: ast.stmt) -> tuple[int, int]:
    """0-based ``[first, end)`` lines of a statement with its decorators and the comment lines right above it."""
    first = min([node.lineno, *(d.lineno for d in getattr(node, "decorator_list", []))]) - 1
    while first > 0 and lines[first - 1].lstrip().startswith("#"):
        first -= 1
    return first, node.end_lineno or node.lineno


@dataclass
class _Import:
    """One imported name: ``stmt`` regenerates it alone; ``typing_only`` under ``if TYPE_CHECKING``."""

    bound: str
    stmt: str
    typing_only: bool


def _imports(tree: ast.Module) -> list[_Import]:
    out = []

    def add(node: ast.stmt, typing_only: bool) -> None:
        if isinstance(node, ast.Import):
            for a in node.names:
                out.append(_Import(a.asname or a.name.split(".")[0],
                                   f"import {a.name}" + (f" as {a.asname}" if a.asname else ""), typing_only))
        elif isinstance(node, ast.ImportFrom) and node.module != "__future__":
            for a in node.names:
                out.append(_Import(a.asname or a.name, f"from {'.' * node.level}{node.module or ''} import {a.name}"
                                   + (f" as {a.asname}" if a.asname else ""), typing_only))

    for node in tree.body:
        if isinstance(node, ast.If) and ast.unparse(node.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING"):
            for inner in node.body:
                add(inner, True)
        else:
            add(node, False)
    return out


def _import_lines(tree: ast.Module, lines: list[str]) -> set[int]:
    """0-based lines of the module's top-level imports (and ``if TYPE_CHECKING`` blocks)."""
    out: set[int] = set()
    for node in tree.body:
        is_tc = isinstance(node, ast.If) and ast.unparse(node.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING")
        if isinstance(node, ast.Import | ast.ImportFrom) or is_tc:
            if isinstance(node, ast.ImportFrom) and node.module == "__future__":
                continue
            out.update(range(node.lineno - 1, node.end_lineno or node.lineno))
    return out


def _import_block(imports: list[_Import]) -> str:
    typing = [i.stmt for i in imports if i.typing_only]
    plain = [i.stmt for i in imports if not i.typing_only and i.stmt != "from typing import TYPE_CHECKING"]
    if typing:
        plain.append("from typing import TYPE_CHECKING")
    text = "\n".join(dict.fromkeys(plain)) + "\n"
    if typing:
        text += "\nif TYPE_CHECKING:\n" + "".join(f"    {s}\n" for s in dict.fromkeys(typing))
    return text


def _docstring(doc: str) -> str:
    if len(doc) < 110:
        return f'"""{doc}"""\n'
    words, out, line = doc.split(), [], ""
    for word in words:
        if len(line) + len(word) + 1 > 116:
            out.append(line)
            line = word
        else:
            line = f"{line} {word}" if line else word
    return '"""' + "\n".join([*out, line]) + '\n"""\n'


def split_texts(source_text: str, split: Split, problems: list[str]) -> tuple[str, str] | None:
    """``(new source text, target text)`` of ``split`` applied to ``source_text``; ``None`` with a problem."""
    tree = ast.parse(source_text)
    lines = source_text.splitlines(keepends=True)
    found: dict[str, ast.stmt] = {}
    for node in tree.body:
        for n in _defined(node):
            if n in split.names:
                found[n] = node
    missing = [n for n in split.names if n not in found]
    if missing:
        problems.append(f"split {split.source} -> {split.target}: {missing} not defined at the top of the source")
        return None
    nodes = sorted({id(n): n for n in found.values()}.values(), key=lambda n: n.lineno)
    cut: list[tuple[int, int]] = [_span(lines, n) for n in nodes]
    body = []
    for first, end in cut:
        block = "".join(lines[first:end]).rstrip("\n")
        body.append(block)
    removed = {i for first, end in cut for i in range(first, end)}
    rest_lines = [ln for i, ln in enumerate(lines) if i not in removed]
    rest_text = re.sub(r"\n{4,}", "\n\n\n", "".join(rest_lines))
    rest_tree = ast.parse(rest_text)
    # the source must not use what moved (the new module would import the source and the source the new module)
    rest_defs = {d for node in rest_tree.body for d in _defined(node)}
    still = sorted((_used(rest_tree.body) & set(split.names)) - rest_defs)
    # the moved code: what it needs of the source's imports and of the source's own definitions
    moved_nodes = list(nodes)
    used = _used(moved_nodes)
    imports = [i for i in _imports(tree) if i.bound in used]
    src_mod = _mod(split.source)
    own = sorted((used & rest_defs) - {i.bound for i in imports})
    own_imports = [_Import(n, f"from {src_mod} import {n}", False) for n in own]
    target = (_docstring(split.doc) + "\nfrom __future__ import annotations\n\n" + _import_block(imports + own_imports)
              + "\n\n" + "\n\n\n".join(body) + "\n")
    target = re.sub(r"\n{4,}", "\n\n\n", target)
    # the source keeps only the imports it still uses; it imports back what it still uses of the moved names
    rest_used = _used([n for n in rest_tree.body if not isinstance(n, ast.Import | ast.ImportFrom | ast.If)]
                      + [n for n in rest_tree.body if isinstance(n, ast.If)
                         and ast.unparse(n.test) not in ("TYPE_CHECKING", "typing.TYPE_CHECKING")])
    all_imports = _imports(rest_tree)
    keep = [i for i in all_imports if i.bound in rest_used or i.bound not in used]
    keep += [_Import(n, f"from {_mod(split.target)} import {n}", False) for n in still]
    imp_lines = _import_lines(rest_tree, rest_text.splitlines(keepends=True))
    rest_split = rest_text.splitlines(keepends=True)
    if imp_lines and keep != all_imports:  # regenerated only where an import goes or comes
        first = min(imp_lines)
        new_lines = [ln for i, ln in enumerate(rest_split) if i not in imp_lines]
        rest_text = "".join(new_lines[:first]) + _import_block(keep) + "".join(new_lines[first:])
    rest_text = re.sub(r"\n{4,}", "\n\n\n", rest_text)
    return rest_text, target


# ------------------------------------------------------------------------------------------------ planning
@dataclass
class Plan:
    moves: list[tuple[str, str]] = field(default_factory=list)
    splits: list[Split] = field(default_factory=list)
    edits: list[str] = field(default_factory=list)  # files whose references change (on the current tree)
    problems: list[str] = field(default_factory=list)


def _after_moves(path: str) -> Path:
    """Where ``path`` (a path after the moves) is now: its old place while the move is still to do."""
    old = next((o for o, n in MOVES.items() if n == path), None)
    return ROOT / (old if old and (ROOT / old).exists() else path)


def _split_state(split: Split) -> str:
    """``"done"``, ``"todo"`` or a problem."""
    src = _after_moves(split.source)
    tgt = ROOT / split.target
    in_src = set()
    if src.exists():
        in_src = {d for node in ast.parse(src.read_text()).body for d in _defined(node)} & set(split.names)
    in_tgt = set()
    if tgt.exists():
        in_tgt = {d for node in ast.parse(tgt.read_text()).body for d in _defined(node)} & set(split.names)
    if not in_src and in_tgt == set(split.names):
        return "done"
    if in_src == set(split.names) and not in_tgt:
        return "todo"
    return (f"split {split.source} -> {split.target}: names in the source {sorted(in_src)}, in the target "
            f"{sorted(in_tgt)}; merge them by hand, then run again")


def plan() -> Plan:
    _check_tables()
    p = Plan()
    for old, new in MOVES.items():
        a, b = (ROOT / old).exists(), (ROOT / new).exists()
        if a and b:
            p.problems.append(f"both {old} and {new} exist: merge them by hand, then run again")
        elif a:
            p.moves.append((old, new))
        elif not b and old not in OPTIONAL:
            p.problems.append(f"neither {old} nor {new} exists")
    for s in SPLITS:
        state = _split_state(s)
        if state == "todo":
            p.splits.append(s)
        elif state != "done":
            p.problems.append(state)
    for rel in tracked_text_files():
        try:
            text = (ROOT / rel).read_text()
        except UnicodeDecodeError:
            continue
        if rewrite(text, rel, p.problems) != text:
            p.edits.append(rel)
    return p


def _new_inits() -> list[str]:
    out = []
    for path in [*(n for o, n in MOVES.items() if (ROOT / n).exists() or o not in OPTIONAL),
                 *(s.target for s in SPLITS)]:
        if not path.endswith(".py"):
            continue
        d = Path(path).parent
        while str(d) != "." and module_name(str(d / "__init__.py")):
            if not (ROOT / d / "__init__.py").exists() and str(d) not in out:
                out.append(str(d))
            d = d.parent
    return sorted(out)


def apply(p: Plan) -> list[str]:
    """Do the plan; return the Python files written (for isort and the line-length check)."""
    written: set[str] = set()
    for old, new in p.moves:
        (ROOT / new).parent.mkdir(parents=True, exist_ok=True)
        _git("mv", old, new)
    for d in _new_inits():
        doc = NEW_PACKAGES.get(d)
        if doc is None:
            raise SystemExit(f"restructure_systems: no docstring for the new package {d} in NEW_PACKAGES")
        (ROOT / d / "__init__.py").write_text(_docstring(doc))
        _git("add", f"{d}/__init__.py")
        written.add(f"{d}/__init__.py")
    problems: list[str] = []
    for s in p.splits:
        texts = split_texts((ROOT / s.source).read_text(), s, problems)
        if texts is None:
            raise SystemExit("restructure_systems: " + "; ".join(problems))
        (ROOT / s.source).write_text(texts[0])
        (ROOT / s.target).parent.mkdir(parents=True, exist_ok=True)
        (ROOT / s.target).write_text(texts[1])
        _git("add", s.target)
        written |= {s.source, s.target}
    for rel in tracked_text_files():
        try:
            text = (ROOT / rel).read_text()
        except UnicodeDecodeError:
            continue
        new = rewrite(text, rel, problems)
        if new != text:
            (ROOT / rel).write_text(new)
            if rel.endswith(".py"):
                written.add(rel)
    if problems:
        raise SystemExit("restructure_systems: " + "; ".join(problems))
    return sorted(written)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dry-run", action="store_true", help="print what would move, split and change; touch nothing")
    ap.add_argument("--check", action="store_true", help="exit 1 if anything is left to move, split or rewrite")
    args = ap.parse_args(argv)

    p = plan()
    if p.problems:
        print("restructure_systems: cannot go on:\n  " + "\n  ".join(p.problems), file=sys.stderr)
        return 2
    for old, new in p.moves:
        print(f"move   {old} -> {new}")
    for s in p.splits:
        print(f"split  {s.source} -> {s.target}: {', '.join(s.names)}")
    for rel in p.edits:
        print(f"edit   {rel}")
    if args.check:
        return 1 if (p.moves or p.splits or p.edits) else 0
    if args.dry_run:
        print(f"(dry run: {len(p.moves)} moves, {len(p.splits)} splits, {len(p.edits)} files with references to "
              f"rewrite now; the splits' files are rewritten after them)")
        return 0
    written = apply(p)
    left = []
    for rel in tracked_text_files():
        try:
            left += leftovers((ROOT / rel).read_text(), rel)
        except UnicodeDecodeError:
            continue
    if left:
        print("restructure_systems: references left that this script did not rewrite (fix by hand):\n  "
              + "\n  ".join(left), file=sys.stderr)
        return 2
    py = [r for r in written if (ROOT / r).exists()]
    if py:  # the rewritten and generated imports sort differently: let ruff's isort order them (nothing else)
        subprocess.run([sys.executable, "-m", "ruff", "check", "--quiet", "--fix", "--select", "I001", *py],
                       cwd=ROOT, check=False)
    long_lines = [f"{r}:{i}" for r in py for i, line in enumerate((ROOT / r).read_text().splitlines(), 1)
                  if len(line) > LINE_LENGTH]
    if long_lines:
        print(f"restructure_systems: lines over {LINE_LENGTH} characters (ruff does not enforce it; wrap where it "
              f"reads better):\n  "
              + "\n  ".join(long_lines), file=sys.stderr)
    print(f"done: {len(p.moves)} moves, {len(p.splits)} splits, {len(p.edits)}+ files rewritten")
    return 0


if __name__ == "__main__":
    sys.exit(main())
