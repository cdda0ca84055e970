"""The launch files (launch/*.launch.xml), checked by evaluating them (``launch`` is not on PyPI; launch_parse.py).

* every node they start is a saml_ros executable, every parameter file exists, every ``$(var)`` is declared;
* every parameter they set, in a file or inline, is one the node declares (from the tables the nodes declare
  from, test/node_params.py; one test asks real nodes that the tables are what they declare);
* the managed nodes (learner, MPC) start with ``autostart: false`` and a ``lifecycle_manager`` activates exactly
  them, as bringup does;
* the closed loops give each node exactly bringup's parameters for the system (the registry entry's
  ``bringup`` defaults through bringup.default_config and bringup.node_params),
  so ``ros2 launch saml_ros <system>.launch.xml`` and ``bringup --system <system>`` cannot drift apart.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from helpers.launch_parse import REPO, VAR_RE, LaunchParseError, LaunchResult, evaluate, file_sections, substitute
from helpers.node_params import table_parameters

from saml_ros import bringup
from saml_ros.core.systems.registry import SYSTEM_NAMES
from saml_ros.executables import EXECUTABLES

LAUNCH = REPO / "launch"
SYSTEMS = SYSTEM_NAMES


STANDALONE = [LAUNCH / "learner.launch.xml", LAUNCH / "mpc.launch.xml"]
#: the managed (lifecycle) nodes
MANAGED = ("learner", "mpc")


def _cases() -> list[tuple[Path, dict[str, str]]]:
    """Every launch file with the argument sets it is checked with (defaults, each system, recording)."""
    cases: list[tuple[Path, dict[str, str]]] = []
    for path in sorted(LAUNCH.glob("*.launch.xml")):
        if path.name == "loop.launch.xml" or path in STANDALONE:
            cases += [(path, {"system": s}) for s in SYSTEMS]
            cases += [(path, {"system": s, "record": "bags/x", "spec": "config/specs/friction.yaml"})
                      for s in SYSTEMS if path.name == "loop.launch.xml"]
            cases.append((path, {"system": "friction", "autostart": "false"}))
        else:
            cases += [(path, {}), (path, {"record": "bags/x"})]
    return cases


CASES = _cases()


def _system_of(result: LaunchResult) -> str:
    for node in result.nodes:
        params = node.parameters()
        if "system" in params:
            return str(params["system"])
        if node.executable.endswith("_sim"):
            return node.executable[: -len("_sim")]
    raise AssertionError("no node names its system")


@pytest.fixture(scope="module")
def declared() -> dict[tuple[str, str], set[str]]:
    """Parameter names declared by every (executable, system) the launch files start (from the nodes' tables)."""
    targets = {(n.executable, _system_of(r)) for path, args in CASES for r in [evaluate(path, args)] for n in r.nodes}
    targets |= {(f"{s}_sim", s) for s in SYSTEMS} | {("learner", s) for s in SYSTEMS} | {("mpc", s) for s in SYSTEMS}
    return {t: table_parameters(*t) for t in targets}


def test_every_launch_file_is_checked() -> None:
    names = {p.name for p in LAUNCH.glob("*.launch.xml")}
    assert {f"{s}.launch.xml" for s in SYSTEMS} | {"loop.launch.xml", "learner.launch.xml", "mpc.launch.xml"} <= names
    assert {p.name for p, _ in CASES} == names
    assert not [p for p in LAUNCH.iterdir() if not p.name.endswith(".launch.xml")]


@pytest.mark.parametrize(("path", "args"), CASES, ids=[f"{p.name}-{'-'.join(a.values()) or 'defaults'}" for p, a in CASES])
def test_launch_file_names_existing_executables_files_and_arguments(path: Path, args: dict[str, str]) -> None:
    result = evaluate(path, args)
    assert result.nodes, path
    for node in result.nodes:
        assert node.pkg == "saml_ros", node
        assert node.executable in EXECUTABLES, f"{path.name}: no executable {node.executable!r}"
        for src in node.params:
            if src.path is not None:
                assert src.path.is_file(), f"{path.name}: parameter file {src.path} does not exist"
                assert src.path.is_relative_to(REPO / "config"), src.path  # installed to share/saml_ros/config
    for file in result.files:
        used = set(VAR_RE.findall(file.read_text()))
        assert used <= set(result.arguments) | {"recording"}, f"{file.name}: undeclared {used - set(result.arguments)}"
    # the namespace, run directory, spec and use_sim_time are launch arguments of every file with a learner
    if any(n.executable == "learner" for n in result.nodes):
        assert {"namespace", "run_dir", "spec", "use_sim_time"} <= set(result.arguments), path.name
    # launch drives the managed nodes: they start unconfigured and lifecycle_manager (unless autostart:=false)
    # configures and activates exactly them
    managed = [n for n in result.nodes if n.executable in MANAGED]
    managers = [n for n in result.nodes if n.executable == "lifecycle_manager"]
    assert managed and all(n.parameters()["autostart"] is False for n in managed), path.name
    if args.get("autostart") == "false":
        assert not managers, path.name
    else:
        (manager,) = managers
        assert manager.namespace == managed[0].namespace and manager.on_exit is None
        assert manager.parameters() == {"node_names": [n.name for n in managed]}, path.name


@pytest.mark.parametrize(("path", "args"), CASES, ids=[f"{p.name}-{'-'.join(a.values()) or 'defaults'}" for p, a in CASES])
def test_every_parameter_a_launch_file_sets_is_declared_by_its_node(
        path: Path, args: dict[str, str], declared: dict[tuple[str, str], set[str]]) -> None:
    result = evaluate(path, args)
    system = _system_of(result)
    for node in result.nodes:
        names = declared[(node.executable, system)]
        unknown = set(node.parameters()) - names
        assert not unknown, f"{path.name} {args}: {node.fqn} declares no parameter(s) {sorted(unknown)}"


#: config/*.yaml in the ROS parameter-file format (bringup_*.yaml are bringup configurations: test_bringup.py)
PARAM_FILES = sorted(p for p in (REPO / "config").glob("*.yaml") if not p.name.startswith("bringup_"))


@pytest.mark.parametrize("path", PARAM_FILES, ids=lambda p: p.name)
def test_every_parameter_file_names_declared_parameters(path: Path, declared: dict[tuple[str, str], set[str]]) -> None:
    """Every section's names are declared by the node it targets."""
    for key, params in file_sections(path).items():
        name = key.rsplit("/", 1)[-1]
        if name == "**":  # config/learner.yaml and config/mpc.yaml: one node, named after the file
            name = path.stem
        system = str(params.get("system", name[: -len("_sim")] if name.endswith("_sim") else ""))
        names = declared[(name, system)]
        assert set(params) <= names, f"{path.name} [{key}]: undeclared {sorted(set(params) - names)}"


def _expected_loop(system: str, run_dir: Path, recording: bool) -> dict[str, dict[str, Any]]:
    """What bringup gives each node of the loop, plus what only the launch file sets (it has no monitor node)."""
    config = bringup.default_config(system)
    expected = bringup.node_params(config, run_dir)
    expected["sim"].update(max_sim_time=float(config["sim_time"]), min_state_subscribers=2 + int(recording),
                           min_applied_cmd_subscribers=1 + int(recording))
    expected["learner"]["spec_file"] = ""
    expected["lifecycle_manager"] = {"node_names": ["learner", "mpc"]}  # bringup's monitor does this itself
    if recording:
        expected["record"] = {"use_sim_time": True}
    return expected


@pytest.mark.parametrize("system", SYSTEMS)
@pytest.mark.parametrize("recording", [False, True])
def test_closed_loop_launch_gives_bringups_parameters(system: str, recording: bool, tmp_path: Path) -> None:
    args = {"run_dir": str(tmp_path)} | ({"record": str(tmp_path / "bag")} if recording else {})
    result = evaluate(LAUNCH / f"{system}.launch.xml", args)
    by_role = {("sim" if n.executable.endswith("_sim") else n.executable): n for n in result.nodes}
    expected = _expected_loop(system, tmp_path, recording)
    assert set(by_role) == set(expected)
    for role, node in by_role.items():
        assert node.namespace == f"/{system}", node
        assert node.parameters() == expected[role], f"{system} {role}: launch vs bringup"
    assert by_role["sim"].executable == f"{system}_sim" and by_role["sim"].on_exit == "shutdown"
    assert result.arguments["sim_time"] == str(bringup.default_config(system)["sim_time"])
    if recording:
        assert by_role["record"].args == ["--system", system, "-o", str(tmp_path / "bag")]


@pytest.mark.parametrize("system", SYSTEMS)
def test_standalone_learner_and_mpc_launch_files(system: str) -> None:
    args = {"system": system, "namespace": "/robot1", "run_dir": "runs/robot1", "spec": "my_spec.yaml"}
    (learner, _) = evaluate(LAUNCH / "learner.launch.xml", args).nodes
    (mpc, _) = evaluate(LAUNCH / "mpc.launch.xml", {k: v for k, v in args.items() if k != "spec"}).nodes
    expected = bringup.node_params(bringup.default_config(system), Path("runs/robot1"))
    lp, mp = learner.parameters(), mpc.parameters()
    assert learner.fqn == "/robot1/learner" and mpc.fqn == "/robot1/mpc"
    assert lp == {**expected["learner"], "spec_file": "my_spec.yaml", "use_sim_time": False}
    assert mp == {**expected["mpc"], "mode": "realtime", "rate_hz": 10.0, "use_sim_time": False}
    assert lp["run_dir"] == mp["run_dir"] == "runs/robot1/checkpoints"  # the MPC reads what the learner writes


def test_loop_parameter_files_hold_bringups_defaults() -> None:
    assert {p.name for p in (REPO / "config").glob("loop_*.yaml")} == {f"loop_{s}.yaml" for s in SYSTEMS}
    for system in SYSTEMS:
        sections = file_sections(REPO / "config" / f"loop_{system}.yaml")
        config = bringup.default_config(system)
        assert sections == {f"/**/{system}_sim": config["sim"],
                            "/**/learner": {"system": system, **config["learner"]},
                            "/**/mpc": {"system": system, **config["mpc"]}}


def test_reader_refuses_what_it_does_not_evaluate(tmp_path: Path) -> None:
    with pytest.raises(LaunchParseError, match="env"):
        substitute("$(env HOME)", {})
    with pytest.raises(LaunchParseError, match="no such launch argument"):
        substitute("$(var nope)", {})
    assert substitute("$(eval '3 if $(var r) else 2')", {"r": "True"}) == "3"
    assert substitute("$(eval '\\'$(var x)\\' != \\'\\'')", {"x": ""}) == "False"
    bad = tmp_path / "bad.launch.xml"
    bad.write_text('<launch><group><node pkg="saml_ros" exec="mpc"/></group></launch>')
    with pytest.raises(LaunchParseError, match="group"):
        evaluate(bad)
    bad.write_text('<launch><node pkg="saml_ros" exec="mpc" respawn="true"/></launch>')
    with pytest.raises(LaunchParseError, match="respawn"):
        evaluate(bad)
