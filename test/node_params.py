"""The parameters a saml_ros node declares, listed from the running node (``rcl_interfaces/srv/ListParameters``).

:func:`declared_parameters` starts each requested node as a real process (private ROS domain, all at once) and
asks it, as ``ros2 param list`` does, so the answer is what the node really declares, including the ones rclpy
adds (``use_sim_time``, ``start_type_description_service``). Once the node parameters live in ROS-free config
dataclasses, this can read those instead; the callers only need ``{(executable, system): names}``.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterable
from pathlib import Path

from ros_helpers import TestNode, ros_domain, wait_for

#: node name of each executable (the simulators are ``<system>_sim``)
NODE_NAME = {"learner": "learner", "mpc": "mpc", "record": "record"}


def node_name(executable: str) -> str:
    return NODE_NAME.get(executable, executable)


def _launch_args(executable: str, system: str, scratch: Path) -> tuple[list[str], list[str]]:
    """``(arguments before --ros-args, ROS arguments)`` that start ``executable`` for ``system``, idle."""
    if executable == "record":
        return ["--system", system, "-o", str(scratch / f"bag-{system}")], []
    ros = ["-p", f"system:={system}"] if executable in ("learner", "mpc") else []
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
                wait_for(lambda p=proc, srv=service: not p.alive() or any(  # type: ignore[misc]
                    n == srv for n, _ in probe.node.get_service_names_and_types()), timeout=timeout, what=service)
                assert proc.alive(), f"{exe} for {system} exited:\n{proc.output()}"
                response = probe.call(ListParameters, service, ListParameters.Request(), timeout=timeout)
                out[(exe, system)] = set(response.result.names)
        finally:
            probe.close()
    return out
