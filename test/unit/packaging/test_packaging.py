"""The ament_python packaging: package.xml, setup.cfg, the executables table, and a real colcon build."""

from __future__ import annotations

import configparser
import re
import sys
import xml.etree.ElementTree as ET

import pytest
from helpers import REPO

import saml_ros
from saml_ros import executables
from saml_ros.executables import EXECUTABLES

REQUIRED_EXEC_DEPENDS = {
    "rclpy", "std_msgs", "sensor_msgs", "nav_msgs", "geometry_msgs", "diagnostic_msgs", "rosgraph_msgs",
    "std_srvs", "builtin_interfaces", "python3-numpy", "python3-scipy", "python3-yaml",
    "python3-matplotlib", "python3-tqdm",
}  # fmt: skip
TARGET_RE = re.compile(r"^(saml_ros|sim_nodes)(\.[a-z_][a-z0-9_]*)+:[a-z_][a-z0-9_]*$")


def _package_xml() -> ET.Element:
    return ET.parse(REPO / "package.xml").getroot()


def test_package_xml_is_format_3_ament_python() -> None:
    root = _package_xml()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == "saml_ros"
    assert root.findtext("version") == saml_ros.__version__
    assert root.findtext("license") == "Apache-2.0"
    maintainer = root.find("maintainer")
    assert maintainer is not None and maintainer.get("email", "").endswith("@example.org")
    assert root.findtext("export/build_type") == "ament_python"
    exec_depends = {e.text for e in root.findall("exec_depend")}
    assert REQUIRED_EXEC_DEPENDS <= exec_depends, REQUIRED_EXEC_DEPENDS - exec_depends
    assert {e.text for e in root.findall("test_depend")} == {"python3-pytest"}


def test_setup_cfg_installs_scripts_where_ros2_run_looks() -> None:
    cfg = configparser.ConfigParser(interpolation=None)
    cfg.read(REPO / "setup.cfg")
    assert cfg["develop"]["script_dir"] == "$base/lib/saml_ros"
    assert cfg["install"]["install_scripts"] == "$base/lib/saml_ros"


def test_pyproject_holds_tool_config_only() -> None:
    # A [build-system] or [project] table would change how setuptools/pip build the package.
    import tomllib

    tables = set(tomllib.loads((REPO / "pyproject.toml").read_text()))
    assert tables == {"tool"}


def test_every_executable_target_is_well_formed() -> None:
    assert len(EXECUTABLES) >= 12
    for name, target in EXECUTABLES.items():
        assert re.fullmatch(r"[a-z][a-z0-9_]*", name), name
        assert TARGET_RE.fullmatch(target), f"{name}: {target!r}"
        assert target.endswith(":main"), f"{name}: {target!r}"


def test_packaging_doc_lists_every_executable() -> None:
    text = (REPO / "docs" / "packaging.md").read_text()
    for name, target in EXECUTABLES.items():
        assert f"| `{name}` | `{target}` |" in text, name


def test_entry_rejects_unknown_names_with_the_list(capsys: pytest.CaptureFixture[str]) -> None:
    assert executables.main(["no_such_exe"]) == 2
    err = capsys.readouterr().err
    assert "no_such_exe" in err and all(name in err for name in EXECUTABLES)
    assert executables.main([]) == 2
    capsys.readouterr()
    assert executables.main(["--help"]) == 0
    out = capsys.readouterr().out
    assert all(name in out for name in EXECUTABLES)


_seen_argv: list[list[str]] = []


def _probe() -> int:
    _seen_argv.append(list(sys.argv))
    return 7


def test_entry_dispatches_lazily_with_argv(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(executables.EXECUTABLES, "probe", f"{__name__}:_probe")
    monkeypatch.setitem(executables.EXECUTABLES, "ghost", "saml_ros.no_such_module:main")
    monkeypatch.setattr(sys, "argv", ["entry"])
    assert executables.main(["probe", "--flag", "x"]) == 7
    assert _seen_argv[-1] == ["probe", "--flag", "x"]
    assert executables.main(["ghost"]) == 2
    assert "not available" in capsys.readouterr().err
