"""The parameters a saml_ros node declares: from its ROS-free table, and from the running node.

:func:`table_parameters` reads the tables the nodes declare from (``learner_params``, ``MPCConfig.params``, the
simulator bindings, the lifecycle and lifecycle_manager tables) plus what rclpy adds to every node
(``use_sim_time``, ``start_type_description_service``): fast, no process. :func:`declared_parameters` starts
each requested node as a real process (private ROS domain, all at once) and asks it, as ``ros2 param list``
does (``rcl_interfaces/srv/ListParameters``); test_launch.py checks once that both agree, which is what makes
the tables a proof of the declared set.
"""

from __future__ import annotations

import importlib
import tempfile
from collections.abc import Iterable
from pathlib import Path

from helpers.ros_helpers import TestNode, ros_domain, wait_for

#: node name of each executable (the simulators are ``<system>_sim``)
NODE_NAME = {"learner": "learner", "mpc": "mpc", "record": "record", "lifecycle_manager": "lifecycle_manager"}
#: parameters rclpy declares on every node
RCLPY_PARAMS = {"use_sim_time", "start_type_description_service"}


def table_parameters(executable: str, system: str) -> set[str]:
    """The parameter names ``executable`` declares for ``system``, from the tables it declares them from."""
    from saml_ros.core.mpc.config import MPCConfig
    from saml_ros.core.online.config import learner_params
    from saml_ros.core.runtime.lifecycle import LIFECYCLE_PARAMS, MANAGER_PARAMS

    managed = {p.name for p in LIFECYCLE_PARAMS}
    if executable == "learner":
        return {p.name for p in learner_params()} | managed | RCLPY_PARAMS
    if executable == "mpc":
        return {p.name for p in MPCConfig.params(system)} | managed | RCLPY_PARAMS
    if executable == "lifecycle_manager":
        return {p.name for p in MANAGER_PARAMS} | RCLPY_PARAMS
    if executable == "record":
        return set(RCLPY_PARAMS)
    if executable.endswith("_sim"):
        binding = importlib.import_module(f"sim_nodes.{executable}").BINDING
        return {p.name for p in binding.all_params()} | {f"system.{n}" for n, _ in binding.system_params} | RCLPY_PARAMS
    raise KeyError(f"no parameter table for executable {executable!r}")


def node_name(executable: str) -> str:
    return NODE_NAME.get(executable, executable)


def _launch_args(executable: str, system: str, scratch: Path) -> tuple[list[str], list[str]]:
    """``(arguments before --ros-args, ROS arguments)`` that start ``executable`` for ``system``, idle."""
    if executable == "record":
        return ["--system", system, "-o", str(scratch / f"bag-{system}")], []
    ros = ["-p", f"system:={system}", "-p", "autostart:=false"] if executable in ("learner", "mpc") else []
    if executable == "lifecycle_manager":  # waits for a node that never comes
        ros += ["-p", "node_names:=[/nowhere/node]", "-p", "timeout:=1000.0"]
    if executable.endswith("_sim"):
        ros += ["-p", "mode:=realtime", "-p", "start_delay:=1000.0"]  # declared, never stepping
    if executable == "learner":
        ros += ["-p", f"run_dir:={scratch / f'learner-{system}'}"]
    return [], ros


def declared_parameters(targets: Iterable[tuple[str, str]], timeout: float = 120.0) -> dict[tuple[str, str], set[str]]:
    """``{(executable, system): names of the parameters that node declares}`` for every node of ``targets``
    (each started in its system's namespace, ``/<system>``)."""
    from rcl_interfaces.srv import ListParameters

    wanted = sorted(set(targets))
    out: dict[tuple[str, str], set[str]] = {}
    with ros_domain("declared_parameters") as dom, tempfile.TemporaryDirectory(prefix="saml_params_") as tmp:
        probe = TestNode("param_probe")
        try:
            procs = {}
            for exe, system in wanted:
                args, ros = _launch_args(exe, system, Path(tmp))
                procs[(exe, system)] = dom.launch(exe, *ros, namespace=f"/{system}", args=args)
            for (exe, system), proc in procs.items():
                service = f"/{system}/{node_name(exe)}/list_parameters"
                wait_for(
                    lambda p=proc, srv=service: (
                        not p.alive()
                        or any(  # type: ignore[misc]
                            n == srv for n, _ in probe.node.get_service_names_and_types()
                        )
                    ),
                    timeout=timeout,
                    what=service,
                )
                assert proc.alive(), f"{exe} for {system} exited:\n{proc.output()}"
                # read-only: asked again every 15 s (a request sent just after discovery can be lost)
                response = probe.call(ListParameters, service, timeout=timeout, resend_after=15.0)
                out[(exe, system)] = set(response.result.names)
        finally:
            probe.close()
    return out
