"""bringup's configuration (ROS-free): the defaults of a system, a YAML file, ``--set`` overrides, and the ROS
parameter file of each node.

A configuration is a mapping with ``system``, ``sim_time`` (s of simulated time, 0 = until stopped), optionally
``record`` (a bag directory), and the node sections ``sim``, ``learner``, ``mpc`` of ROS parameters. A system's
defaults are its registry entry's ``bringup``; ``config/bringup_quadrotor.yaml`` holds the quadrotor's.

A robot described by a system file (:func:`robot_config`) has no simulator: its configuration holds
``system_file`` and ``robot`` (the commands that start the robot's own processes, e.g. its simulator); the learner
and the MPC take the file (``system_file``), never ``system``.

The optional section ``learner_ua`` starts a second learner on the same stream that trains the Uniformly Accurate
baseline (the ``learner`` parameters, then these, with ``uniform: true``): node ``learner_ua``, topics
``learner_ua/model_error`` and ``learner_ua/checkpoint``, checkpoints in ``<run dir>/checkpoints_ua``. The MPC
follows only the first (Sufficiently Accurate) learner.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from saml_ros.core.systems import get_entry

#: the node sections of a configuration (``learner_ua`` optional)
NODE_SECTIONS = ("sim", "learner", "mpc", "learner_ua")
#: the run directory's checkpoint folders of the learner and of the optional UA learner
CHECKPOINTS, CHECKPOINTS_UA = "checkpoints", "checkpoints_ua"
#: the system a configuration without one runs
DEFAULT_SYSTEM = "quadrotor"


def default_config(system: str) -> dict[str, Any]:
    """A deep copy of ``system``'s default bringup configuration (its registry entry's ``bringup``)."""
    return copy.deepcopy(dict(get_entry(system).bringup))


def robot_config(system_file: str | Path, robot: Sequence[str] = ()) -> dict[str, Any]:
    """The configuration of a robot described by a system file: its ``name`` as ``system``, the learner and the MPC
    on the file (the MPC's rate and horizon are the file's ``mpc:`` section's), ``robot``: commands starting the
    robot's own processes (each run in the robot's namespace). Loads and registers the file (``SystemFileError``)."""
    from saml_ros.user_code import load_system_file

    path = str(Path(system_file).resolve())
    system = load_system_file(path)
    return {"system": system.name, "system_file": path, "robot": list(robot), "sim_time": 0.0,
            "sim": {"mode": "realtime"}, "learner": {}, "mpc": {}}


def merge_config(base: dict[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` updated by ``override`` (node sections are merged key by key); unknown keys are refused."""
    out = copy.deepcopy(base)
    for key, value in override.items():
        if key in NODE_SECTIONS:
            if not isinstance(value, Mapping):
                raise ValueError(f"config section {key!r} must be a mapping of parameters, got {value!r}")
            out.setdefault(key, {}).update(copy.deepcopy(dict(value)))
        elif key in ("system", "sim_time", "record", "system_file", "robot"):
            out[key] = value
        else:
            raise ValueError(f"unknown config key {key!r}; valid: system, sim_time, record, system_file, robot, "
                             f"{', '.join(NODE_SECTIONS)}")
    return out


def load_config(path: Path | None, system: str | None) -> dict[str, Any]:
    """The defaults of the system (from ``--system`` or the file's ``system``), updated by the YAML file."""
    override: dict[str, Any] = {}
    if path is not None:
        data = yaml.safe_load(Path(path).read_text())
        if not isinstance(data, dict):
            raise ValueError(f"{path}: a bringup config must be a YAML mapping")
        override = data
    name = system or override.get("system") or DEFAULT_SYSTEM
    if system and override.get("system") not in (None, system):
        raise ValueError(f"--system {system} contradicts the config's system {override['system']!r}")
    return merge_config(default_config(name), {k: v for k, v in override.items() if k != "system"})


def apply_sets(config: dict[str, Any], sets: Sequence[str]) -> dict[str, Any]:
    """Apply ``--set section.param=value`` overrides (``value`` parsed as YAML); ``sim_time=60`` also works."""
    out = copy.deepcopy(config)
    for item in sets:
        key, sep, raw = item.partition("=")
        if not sep:
            raise ValueError(f"--set wants section.param=value, got {item!r}")
        value = yaml.safe_load(raw)
        section, _, param = key.partition(".")
        if section in NODE_SECTIONS and param:
            out.setdefault(section, {})[param] = value
        elif key in ("sim_time", "record"):
            out[key] = value
        else:
            raise ValueError(f"--set {item!r}: the key must be sim_time or one of {NODE_SECTIONS} followed by .param")
    return out


def ros_params_file(params: Mapping[str, Any]) -> str:
    """A ROS 2 parameter file (YAML) applying ``params`` to every node of the process (``/**``)."""
    clean = {k: (list(v) if isinstance(v, tuple) else v) for k, v in params.items()}
    return yaml.safe_dump({"/**": {"ros__parameters": clean}}, sort_keys=True)


def node_params(config: Mapping[str, Any], run_dir: Path) -> dict[str, dict[str, Any]]:
    """The ROS parameters of each node section, with the ones bringup owns (system, run_dir, use_sim_time and
    ``autostart: false``: bringup drives the learner's and the MPC's lifecycle transitions itself)."""
    system = config["system"]
    lockstep = config["sim"].get("mode", "lockstep") == "lockstep"
    sim = dict(config["sim"])
    # a robot's nodes take its system file (never system and system_file together)
    who = {"system_file": config["system_file"]} if config.get("system_file") else {"system": system}
    learner = {**who, "run_dir": str(run_dir / CHECKPOINTS), **config["learner"], "autostart": False}
    mpc = {**who, "run_dir": str(run_dir / CHECKPOINTS), **config["mpc"], "autostart": False}
    out = {"sim": sim, "learner": learner, "mpc": mpc}
    if config.get("learner_ua") is not None:
        out["learner_ua"] = {**learner, "run_dir": str(run_dir / CHECKPOINTS_UA), **config["learner_ua"],
                             "uniform": True}
    if lockstep:
        for name in ("learner", "mpc", "learner_ua"):
            if name in out:
                out[name].setdefault("use_sim_time", True)
    return out
