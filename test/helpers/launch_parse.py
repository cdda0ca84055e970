"""Read saml_ros's ROS 2 launch files (XML) without the ``launch`` package: which nodes they start, with what.

``launch`` is not on PyPI, so the tests evaluate the files here: arguments (``<arg>``, with command-line
overrides), ``<let>``, ``<include>`` (with ``<arg>`` children), ``<node>`` with ``if`` / ``unless``, ``<param from>``
(ROS parameter files, the sections that match the node) and ``<param name value>``. The substitutions the files
use are evaluated as launch does: ``$(var NAME)``, ``$(find-pkg-share saml_ros)`` (the source tree, whose
``config/`` and ``launch/`` are installed side by side under ``share/saml_ros``) and ``$(eval 'EXPR')`` (Python,
with ``math``). Anything else raises :class:`LaunchParseError`, so a file using a construct this reader does not
know fails its test instead of passing unchecked.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[2]
PACKAGE = "saml_ros"
#: the elements and attributes this reader evaluates (anything else in a launch file is an error)
NODE_ATTRS = {"pkg", "exec", "name", "namespace", "output", "args", "if", "unless", "on_exit"}
ARG_ATTRS = {"name", "default", "description"}
#: where :func:`evaluate` keeps the ``share`` directory among the launch configurations (not a valid arg name)
SHARE_KEY = "$share"


class LaunchParseError(Exception):
    """The launch file uses something this reader does not evaluate, or is malformed."""


@dataclass
class ParamSource:
    """One ``<param>`` of a node: a parameter file (``path``) or one ``name`` = ``value``."""

    path: Path | None = None
    name: str | None = None
    value: Any = None


@dataclass
class LaunchedNode:
    """A ``<node>`` the launch file starts (its condition held), with everything substituted."""

    pkg: str
    executable: str
    name: str
    namespace: str
    args: list[str]
    params: list[ParamSource]
    on_exit: str | None
    source: Path

    @property
    def fqn(self) -> str:
        return f"{self.namespace.rstrip('/')}/{self.name}"

    def parameters(self) -> dict[str, Any]:
        """The node's parameters as ROS applies them: files and values in order, later ones win."""
        out: dict[str, Any] = {}
        for src in self.params:
            if src.path is not None:
                out.update(file_parameters(src.path, self.namespace, self.name))
            else:
                assert src.name is not None
                out[src.name] = src.value
        return out


@dataclass
class LaunchResult:
    """What evaluating one launch file gave: its nodes, the arguments it declared (with defaults) and the files
    it read."""

    nodes: list[LaunchedNode] = field(default_factory=list)
    arguments: dict[str, str | None] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)


def package_share() -> Path:
    """What ``$(find-pkg-share saml_ros)`` stands for here: the source tree (same layout as the install)."""
    return REPO


def _find_close(text: str, start: int) -> int:
    """Index of the ``)`` closing the substitution whose body starts at ``start`` (parentheses balanced, as in
    nested substitutions and Python expressions; ``\\)`` is a literal)."""
    depth, i = 1, start
    while i < len(text):
        c = text[i]
        if c == "\\":
            i += 2
            continue
        if c == "(":
            depth += 1
        elif c == ")":
            depth -= 1
            if depth == 0:
                return i
        i += 1
    raise LaunchParseError(f"unclosed substitution in {text!r}")


def substitute(text: str, config: dict[str, str]) -> str:
    """``text`` with every ``$(...)`` evaluated against the launch configurations ``config``."""
    out: list[str] = []
    i = 0
    while i < len(text):
        if text.startswith("$(", i):
            end = _find_close(text, i + 2)
            out.append(_evaluate(text[i + 2:end], config))
            i = end + 1
        else:
            out.append(text[i])
            i += 1
    return "".join(out)


def _evaluate(body: str, config: dict[str, str]) -> str:
    kind, _, arg = body.partition(" ")
    if kind == "var":
        name = arg.strip()
        if name not in config:
            raise LaunchParseError(f"$(var {name}): no such launch argument")
        return config[name]
    if kind == "find-pkg-share":
        if arg.strip() != PACKAGE:
            raise LaunchParseError(f"$(find-pkg-share {arg}): only {PACKAGE} is known here")
        return config.get(SHARE_KEY, str(package_share()))
    if kind == "eval":
        arg = arg.strip()
        if len(arg) < 2 or arg[0] not in "'\"" or arg[-1] != arg[0]:
            raise LaunchParseError(f"$(eval ...) wants one quoted expression, got {arg!r}")
        expr = substitute(arg[1:-1].replace("\\" + arg[0], arg[0]), config)
        scope: dict[str, Any] = dict(vars(math))
        scope["math"] = math
        return str(eval(expr, {}, scope))  # noqa: S307 - the project's own launch files, as launch does
    raise LaunchParseError(f"substitution $({kind} ...) is not evaluated by this reader")


def _truth(value: str, where: str) -> bool:
    low = value.strip().lower()
    if low in ("true", "1"):
        return True
    if low in ("false", "0"):
        return False
    raise LaunchParseError(f"{where}: condition {value!r} is neither true nor false")


def _param_value(text: str) -> Any:
    """A ``<param value>`` as launch_ros types it: YAML, an empty string stays a string."""
    value = yaml.safe_load(text if text else "''")
    if isinstance(value, list):
        return list(value)
    return value


def _flatten(prefix: str, data: Any, out: dict[str, Any]) -> None:
    if isinstance(data, dict):
        for key, value in data.items():
            _flatten(f"{prefix}.{key}" if prefix else str(key), value, out)
    else:
        out[prefix] = data


def _section_matches(key: str, namespace: str, name: str) -> bool:
    fqn = f"{namespace.rstrip('/')}/{name}"
    if key in ("/**", "**"):
        return True
    if key.startswith("/**/"):
        return key[4:] == name
    if key.startswith("/"):
        return key == fqn
    if "/" in key or "*" in key:
        raise LaunchParseError(f"parameter file section {key!r} uses a pattern this reader does not evaluate")
    return namespace in ("", "/") and key == name


def file_parameters(path: Path, namespace: str, name: str) -> dict[str, Any]:
    """The parameters ROS parameter file ``path`` gives node ``namespace/name`` (dotted names)."""
    data = yaml.safe_load(path.read_text())
    if not isinstance(data, dict):
        raise LaunchParseError(f"{path}: not a ROS parameter file")
    out: dict[str, Any] = {}
    for key, section in data.items():
        if not isinstance(section, dict) or set(section) != {"ros__parameters"}:
            raise LaunchParseError(f"{path}: section {key!r} must hold exactly ros__parameters")
        if _section_matches(str(key), namespace, name):
            _flatten("", section["ros__parameters"], out)
    return out


def file_sections(path: Path) -> dict[str, dict[str, Any]]:
    """Every section of ROS parameter file ``path``: ``{key: {dotted name: value}}``."""
    data = yaml.safe_load(path.read_text())
    out: dict[str, dict[str, Any]] = {}
    for key, section in data.items():
        flat: dict[str, Any] = {}
        _flatten("", section["ros__parameters"], flat)
        out[str(key)] = flat
    return out


def _attrs(el: ET.Element, allowed: set[str], where: str) -> None:
    unknown = set(el.attrib) - allowed
    if unknown:
        raise LaunchParseError(f"{where}: <{el.tag}> attribute(s) {sorted(unknown)} are not evaluated by this reader")


def _condition(el: ET.Element, config: dict[str, str], where: str) -> bool:
    if "if" in el.attrib and not _truth(substitute(el.attrib["if"], config), where):
        return False
    return not ("unless" in el.attrib and _truth(substitute(el.attrib["unless"], config), where))


def evaluate(path: Path, arguments: dict[str, str] | None = None, share: Path | None = None) -> LaunchResult:
    """Evaluate launch file ``path`` as ``ros2 launch path name:=value ...`` with ``arguments``; ``share`` is what
    ``$(find-pkg-share saml_ros)`` stands for (default: the source tree, :func:`package_share`)."""
    result = LaunchResult()
    config = dict(arguments or {})
    if share is not None:
        config[SHARE_KEY] = str(share)
    _evaluate_file(Path(path), config, result)
    result.arguments.pop(SHARE_KEY, None)
    return result


def _evaluate_file(path: Path, config: dict[str, str], result: LaunchResult) -> None:
    result.files.append(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise LaunchParseError(f"{path}: {exc}") from None
    if root.tag != "launch":
        raise LaunchParseError(f"{path}: the root element must be <launch>, not <{root.tag}>")
    for el in root:
        where = f"{path.name}: <{el.tag} {' '.join(f'{k}={v!r}' for k, v in el.attrib.items())}>"
        if el.tag == "arg":
            _attrs(el, ARG_ATTRS, where)
            name = el.attrib["name"]
            default = el.attrib.get("default")
            result.arguments.setdefault(name, default)
            if name not in config:
                if default is None:
                    raise LaunchParseError(f"{where}: argument {name!r} has no default and was not given")
                config[name] = substitute(default, config)
        elif el.tag == "let":
            _attrs(el, {"name", "value"}, where)
            config[el.attrib["name"]] = substitute(el.attrib["value"], config)
        elif el.tag == "include":
            _attrs(el, {"file", "if", "unless"}, where)
            if not _condition(el, config, where):
                continue
            inner = dict(config)
            for child in el:
                if child.tag != "arg":
                    raise LaunchParseError(f"{where}: <include> may only hold <arg>, not <{child.tag}>")
                inner[child.attrib["name"]] = substitute(child.attrib["value"], config)
            _evaluate_file(Path(substitute(el.attrib["file"], config)), inner, result)
        elif el.tag == "node":
            _attrs(el, NODE_ATTRS, where)
            if not _condition(el, config, where):
                continue
            params: list[ParamSource] = []
            for child in el:
                if child.tag != "param":
                    raise LaunchParseError(f"{where}: <node> may only hold <param>, not <{child.tag}>")
                if "from" in child.attrib:
                    params.append(ParamSource(path=Path(substitute(child.attrib["from"], config))))
                else:
                    params.append(ParamSource(name=substitute(child.attrib["name"], config),
                                              value=_param_value(substitute(child.attrib["value"], config))))
            sub = {k: substitute(v, config) for k, v in el.attrib.items() if k not in ("if", "unless")}
            result.nodes.append(LaunchedNode(
                pkg=sub["pkg"], executable=sub["exec"], name=sub.get("name", sub["exec"]),
                namespace=sub.get("namespace", "/"), args=sub.get("args", "").split(), params=params,
                on_exit=sub.get("on_exit"), source=path,
            ))
        else:
            raise LaunchParseError(f"{where}: element <{el.tag}> is not evaluated by this reader")


#: ``$(var NAME)`` references (for checks that every argument used is declared)
VAR_RE = re.compile(r"\$\(var ([A-Za-z_][A-Za-z0-9_-]*)\)")
