"""Import structure, read from the source (the AST of every module, every import statement wherever it stands:
module level, inside functions, under ``if TYPE_CHECKING``):

* no import cycle between the package's modules (saml_ros, sim_nodes, msg_schemas);
* the ROS-free core (``saml_ros.core``) imports neither rclpy nor a node module (``saml_ros.nodes``, ``sim_nodes``),
  and loads no module by a name in a string (``importlib.import_module``, ``__import__``).

A package's ``__init__`` importing its own submodules (its face) is what packages do; importing ``a.b.c`` is
counted as an edge to ``a.b.c`` only, not to the packages ``a`` and ``a.b`` Python initialises on the way.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest
from helpers import REPO as ROOT

PACKAGES = ("saml_ros", "sim_nodes", "msg_schemas")
CORE = "saml_ros.core"
FORBIDDEN_IN_CORE = ("rclpy", "saml_ros.nodes", "sim_nodes")


def _module_files() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


MODULES = _module_files()


def _imports(name: str, source: str | None = None) -> list[tuple[str, int]]:
    """``(imported module, line)`` for every import in module ``name`` (``from X import Y``: ``X.Y`` when that is
    a module, else ``X``); relative imports resolved. ``source``: the module's text (default: its file)."""
    path = MODULES[name]
    tree = _tree(name) if source is None else ast.parse(source, filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                full = f"{base}.{alias.name}"
                out.append((full if full in MODULES else base, node.lineno))
    return out


@functools.cache
def _tree(name: str) -> ast.Module:
    """The AST of module ``name``'s file, parsed once per test run (the checks below read every module, several
    times: parsing is their cost)."""
    return ast.parse(MODULES[name].read_text(), filename=str(MODULES[name]))


def _by_name_loads(name: str) -> list[tuple[str, int]]:
    """Calls that import a module named by a value: ``importlib.import_module(...)``, ``__import__(...)``."""
    tree = _tree(name)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            called = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
            if called in ("import_module", "__import__"):
                out.append((ast.unparse(node), node.lineno))
    return out


def _graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports (a copy of the graph built once per test run)."""
    return {m: set(targets) for m, targets in _module_graph().items()}


@functools.cache
def _module_graph() -> dict[str, frozenset[str]]:
    return {m: frozenset(t for t, _ in _imports(m) if t in MODULES and t != m) for m in MODULES}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_checker_sees_cycles_and_resolves_relative_imports() -> None:
    """The checker itself: a planted cycle is found, an acyclic chain is not, relative imports resolve."""
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []
    planted = "from . import trainer\nfrom ..spec import ProblemSpec\ndef f():\n    import rclpy.node\n"
    assert _imports("saml_ros.core.training", planted) == [
        ("saml_ros.core.training.trainer", 1), ("saml_ros.core.spec", 2), ("rclpy.node", 4)]
    planted = "from .engines import fast\nfrom .config import TrainConfig\n"
    assert _imports("saml_ros.core.training.trainer", planted) == [
        ("saml_ros.core.training.engines.fast", 1), ("saml_ros.core.training.config", 2)]


def test_no_import_cycles() -> None:
    cycles = _cycles(_graph())
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


@pytest.mark.parametrize("name", sorted(m for m in MODULES if m == CORE or m.startswith(CORE + ".")))
def test_core_imports_neither_rclpy_nor_a_node_module(name: str) -> None:
    bad = [f"line {ln}: {t}" for t, ln in _imports(name)
           if any(t == f or t.startswith(f + ".") for f in FORBIDDEN_IN_CORE)]
    assert not bad, f"{name} imports " + ", ".join(bad)
    loads = _by_name_loads(name)
    assert not loads, f"{name} loads modules by name: " + ", ".join(f"line {ln}: {c}" for c, ln in loads)

def _closure(start: str, graph: dict[str, set[str]]) -> set[str]:
    seen, todo = {start}, [start]
    while todo:
        for w in graph[todo.pop()]:
            if w not in seen:
                seen.add(w)
                todo.append(w)
    return seen


def test_core_reaches_no_node_module_through_other_modules() -> None:
    """Transitively too (rclpy is only checked directly above: msg_schemas imports it lazily where it builds
    rclpy QoS profiles and messages, which the core never calls)."""
    graph = _graph()
    core = [m for m in MODULES if m == CORE or m.startswith(CORE + ".")]
    bad = {m: sorted(t for t in _closure(m, graph) if t.startswith(("saml_ros.nodes", "sim_nodes"))) for m in core}
    assert not {m: b for m, b in bad.items() if b}


def _defines(name: str, cls: str) -> bool:
    tree = _tree(name)
    return any(isinstance(n, ast.ClassDef) and n.name == cls for n in tree.body)


def test_loading_a_model_does_not_import_the_trainer() -> None:
    """model_io / model_watch (what the MPC node loads models with) reach no module of the training package and
    none that defines the trainer."""
    graph = _graph()
    assert any(_defines(m, "PrimalDualTrainer") for m in MODULES)
    for m in ("saml_ros.core.model.io", "saml_ros.core.mpc.follower"):
        reached = sorted(t for t in _closure(m, graph)
                         if t.startswith("saml_ros.core.training") or _defines(t, "PrimalDualTrainer"))
        assert not reached, f"{m} reaches {reached}"


# ------------------------------------------------------------------------------------------- packages
def _package(name: str) -> str:
    """The package a module counts in for the package graph: a subpackage of ``saml_ros.core`` (with its own
    subpackages, e.g. ``saml_ros.core.mpc.shooting`` counts as ``saml_ros.core.mpc``), ``saml_ros.core`` for the
    core's loose modules, a subpackage of ``saml_ros`` (``saml_ros.nodes``) or one of its top modules
    (``saml_ros.api``: the faces for users' code each count alone), and ``msg_schemas`` / ``sim_nodes`` whole."""
    parts = name.split(".")
    if parts[:2] == ["saml_ros", "core"]:
        deep = len(parts) >= 3 and (ROOT / "saml_ros" / "core" / parts[2]).is_dir()
        return ".".join(parts[:3]) if deep else CORE
    if parts[0] == "saml_ros":  # a subpackage, or one of the faces at the top (api, export, user_code, ...) alone
        return ".".join(parts[:2])
    return parts[0]


def _package_graph() -> dict[str, set[str]]:
    """Package -> the packages its modules import (every import counts: inside functions, under TYPE_CHECKING)."""
    graph: dict[str, set[str]] = {}
    for m, targets in _graph().items():
        graph.setdefault(_package(m), set())
        graph[_package(m)] |= {_package(t) for t in targets if _package(t) != _package(m)}
    return graph


def test_the_package_checker_sees_cycles() -> None:
    """A planted lazy import from the registry's table up into the MPC closes a package cycle (so the check below
    can fail); a system's folder counts as the systems' package."""
    graph = _package_graph()
    assert "saml_ros.core.systems" in graph["saml_ros.core.mpc"]  # the MPC looks entries up in the table
    planted = {k: set(v) for k, v in graph.items()}
    planted["saml_ros.core.systems"].add("saml_ros.core.mpc")
    assert any({"saml_ros.core.systems", "saml_ros.core.mpc"} <= set(c) for c in _cycles(planted))
    assert _package("saml_ros.core.mpc.shooting.sqp") == "saml_ros.core.mpc"
    assert _package("saml_ros.systems.quadrotor.task") == "saml_ros.systems"
    assert _package("saml_ros.core.spec") == CORE and _package("saml_ros.nodes.mpc") == "saml_ros.nodes"


def test_no_import_cycles_between_packages() -> None:
    """No cycle between packages, imports inside functions and under TYPE_CHECKING included, and no exception:
    the systems' registry table (``saml_ros.core.systems``) sits below the layers its entries wire, the systems
    (``saml_ros.systems``) above them (issue 31 item 1)."""
    cycles = _cycles(_package_graph())
    assert not cycles, "package cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_the_core_imports_no_system() -> None:
    """Nothing in ``saml_ros.core`` imports a system's folder (``saml_ros.systems``): the core reaches a system only
    through its registry entry, which the systems fill in from above."""
    bad = sorted(f"{m} -> {t}" for m, targets in _graph().items() if m == CORE or m.startswith(CORE + ".")
                 for t in targets if t == "saml_ros.systems" or t.startswith("saml_ros.systems."))
    assert not bad, bad


MAX_LOOSE_CORE_MODULES = 8
MAX_MODULE_LINES = 700


def test_core_has_few_loose_modules() -> None:
    loose = sorted(p.name for p in (ROOT / "saml_ros" / "core").glob("*.py") if p.name != "__init__.py")
    assert len(loose) <= MAX_LOOSE_CORE_MODULES, f"{len(loose)} loose modules in saml_ros/core: {loose}"


def test_no_module_is_too_long() -> None:
    lengths = {m: len(p.read_text().splitlines()) for m, p in MODULES.items()}
    long = {m: n for m, n in lengths.items() if n > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines (split them): {long}"
