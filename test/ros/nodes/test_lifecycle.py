"""The learner and the MPC as managed nodes, driven through their lifecycle_msgs services (real processes).

One friction loop for the whole module (a realtime simulator, a learner and an MPC started with
``autostart: false``), walked through the lifecycle in order by the tests below: refused and failed
transitions, configure and activate, the learner's deactivation (one checkpoint, then no training and no
checkpoint until it is activated again), the MPC's deactivation (no command at all; the simulator falls back to
its safe command after its command timeout), cleanup, ``lifecycle_manager`` bringing both up again, and a
``shutdown`` transition ending the process. ``autostart: true`` (the default) is what every other node test
runs, bringup and the launch files drive the transitions themselves (test_bringup.py, test_launch.py).
"""

from __future__ import annotations

import os
import re
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from helpers.ros_helpers import Process, RosDomain, TestNode, ros_domain, wait_for

rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from lifecycle_msgs.msg import Transition  # noqa: E402
from lifecycle_msgs.srv import ChangeState, GetState  # noqa: E402
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue  # noqa: E402
from rcl_interfaces.srv import SetParameters  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from msg_schemas import DATA_QOS, TELEMETRY_QOS  # noqa: E402
from msg_schemas.telemetry import diagnostics_from_msg  # noqa: E402
from saml_ros.core.model.checkpoint import CheckpointStore  # noqa: E402
from saml_ros.nodes.lifecycle_client import GOAL  # noqa: E402

NS = "/friction"
LEARNER, MPC = f"{NS}/learner", f"{NS}/mpc"
TIMEOUT = 60.0
CHECKPOINT_PERIOD = 1.0


@dataclass
class Loop:
    dom: RosDomain
    probe: TestNode
    sim: Process
    learner: Process
    mpc: Process
    run_dir: Path
    cmds: list[float]  # arrival times (monotonic s) of the MPC's commands
    diags: list[Any]

    def change(self, fqn: str, label: str = "", transition_id: int = 0) -> bool:
        """Whether ``fqn`` made the transition. DDS can drop a request or its answer while one side of the
        service's discovery lags the other: with no answer in 5 s the node's state says which (changed: the
        answer was lost, the transition's goal state tells its outcome; unchanged: the request is sent again)."""
        request = ChangeState.Request(transition=Transition(id=transition_id, label=label))
        before = self.state(fqn)
        deadline = time.monotonic() + TIMEOUT
        while True:
            try:
                return bool(self.probe.call(ChangeState, f"{fqn}/change_state", request, timeout=5.0).success)
            except TimeoutError:
                state = self.state(fqn)
                while state.endswith("ing") and time.monotonic() < deadline:  # configuring, activating, ...
                    time.sleep(0.2)
                    state = self.state(fqn)
                if state != before:
                    return state == GOAL.get(label)
                if time.monotonic() > deadline:
                    raise

    def state(self, fqn: str) -> str:
        return str(self.probe.call(GetState, f"{fqn}/get_state", timeout=TIMEOUT, resend_after=5.0)
                   .current_state.label)

    def diagnostics(self, fqn: str) -> dict[str, str]:
        """The newest /diagnostics values of node ``fqn`` ({} before its first report)."""
        for msg in reversed(list(self.diags)):
            for entry in diagnostics_from_msg(msg)[0]:
                if entry.name == fqn:
                    return dict(entry.values)
        return {}

    def next_diagnostics(self, fqn: str) -> dict[str, str]:
        """The first /diagnostics report of ``fqn`` that arrives from now on."""
        n = len(self.diags)
        wait_for(lambda: any(e.name == fqn for m in list(self.diags)[n:] for e in diagnostics_from_msg(m)[0]),
                 TIMEOUT, what=f"diagnostics of {fqn}")
        return self.diagnostics(fqn)

    def latest_version(self) -> int:
        latest = CheckpointStore(self.run_dir).latest()
        return 0 if latest is None else latest[1]


@pytest.fixture(scope="module")
def loop(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Loop]:
    run_dir = tmp_path_factory.mktemp("lifecycle") / "checkpoints"
    with ros_domain("lifecycle") as dom:
        probe = TestNode("lifecycle_probe")
        cmds: list[float] = []
        probe.subscribe(JointState, f"{NS}/cmd", DATA_QOS.to_rclpy(), callback=lambda m: cmds.append(time.monotonic()))
        diags = probe.subscribe(DiagnosticArray, "/diagnostics", TELEMETRY_QOS.to_rclpy())
        managed = ["-p", "system:=friction", "-p", "autostart:=false", "-p", f"run_dir:={run_dir}",
                   "-p", "diagnostics_rate:=4.0"]
        learner = dom.launch("learner", *managed, "-p", "min_transitions:=20", "-p", "spec_file:=/no/such/spec.yaml",
                             "-p", f"checkpoint_period:={CHECKPOINT_PERIOD}", "-p", "telemetry_rate:=4.0", namespace=NS)
        mpc = dom.launch("mpc", *managed, namespace=NS)
        sim = dom.launch("friction_sim", "-p", "mode:=realtime", "-p", "rate_hz:=20.0", "-p", "cmd_timeout:=0.3",
                         "-p", "start_delay:=0.5", "-p", "diagnostics_period:=0.25", "-p", "publish_clock:=false",
                         namespace=NS)
        try:
            yield Loop(dom, probe, sim, learner, mpc, run_dir, cmds, diags)
        finally:
            probe.close()


def test_refused_and_failed_transitions_leave_the_nodes_waiting(loop: Loop) -> None:
    assert loop.state(LEARNER) == "unconfigured" and loop.state(MPC) == "unconfigured"
    # no such transition from unconfigured: refused with success false (rclpy alone would raise in its executor)
    assert not loop.change(MPC, transition_id=Transition.TRANSITION_ACTIVATE)
    assert not loop.change(LEARNER, transition_id=99)
    assert not loop.change(LEARNER, label="jump")
    wait_for(lambda: "refused transition 99" in loop.learner.output(), 10.0, what="the refusal in the log")
    assert loop.learner.alive() and loop.mpc.alive()
    assert loop.state(LEARNER) == "unconfigured" and loop.state(MPC) == "unconfigured"
    # configure reads the parameters as they are then: a bad spec fails, the corrected one succeeds
    assert not loop.change(LEARNER, "configure")
    assert "configure failed: parameter 'spec_file': no such file" in loop.learner.output()
    assert loop.state(LEARNER) == "unconfigured"
    value = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value="")
    result = loop.probe.call(SetParameters, f"{LEARNER}/set_parameters",
                             SetParameters.Request(parameters=[Parameter(name="spec_file", value=value)]))
    assert result.results[0].successful
    assert loop.change(LEARNER, "configure") and loop.change(MPC, "configure")
    assert loop.state(LEARNER) == "inactive" and loop.state(MPC) == "inactive"
    assert not loop.change(MPC, "deactivate")  # not active
    # configured but inactive: no subscription, no command, no training
    time.sleep(1.0)
    assert not loop.cmds and loop.latest_version() == 0
    assert loop.probe.node.count_subscribers(f"{NS}/state") == 0
    values = loop.next_diagnostics(LEARNER)
    assert values["lifecycle"] == "inactive" and int(values["updates"]) == 0 and int(values["invalid_transitions"]) == 1


def test_deactivated_learner_writes_one_checkpoint_then_neither_trains_nor_writes(loop: Loop) -> None:
    assert loop.change(MPC, "activate") and loop.change(LEARNER, "activate")
    wait_for(lambda: loop.latest_version() >= 2, TIMEOUT, what=f"two checkpoints:\n{loop.learner.output()}")
    assert loop.change(LEARNER, "deactivate")
    # every update is in a checkpoint after a deactivation: one written now, or (when a periodic checkpoint was
    # written between the last update and the pause: seen under load) the current one already holds them all
    match = re.findall(r"training paused after (\d+) updates \(checkpoint version (\d+) (written|is current)\)",
                       loop.learner.output())
    assert len(match) == 1, loop.learner.output()
    updates, version = int(match[0][0]), int(match[0][1])
    assert loop.latest_version() == version and version >= (3 if match[0][2] == "written" else 2)
    found = CheckpointStore(loop.run_dir).load_latest_valid()
    assert found is not None and found.meta["updates"] == updates
    time.sleep(3 * CHECKPOINT_PERIOD)
    values = loop.next_diagnostics(LEARNER)  # the training process still reports its counters while paused
    assert values["lifecycle"] == "inactive" and int(values["updates"]) == updates
    assert loop.latest_version() == version
    assert loop.change(LEARNER, "activate")
    wait_for(lambda: loop.latest_version() > version, TIMEOUT, what="a checkpoint after activation")
    wait_for(lambda: int(loop.diagnostics(LEARNER)["updates"]) > updates, TIMEOUT, what="updates after activation")


def test_deactivated_mpc_commands_nothing_and_the_simulator_falls_back(loop: Loop) -> None:
    sim = f"{NS}/friction_sim"
    wait_for(lambda: loop.cmds and time.monotonic() - loop.cmds[-1] < 0.5, TIMEOUT, what="commands")
    before = int(loop.next_diagnostics(sim).get("cmd_timeouts", 0))
    assert loop.change(MPC, "deactivate")
    assert loop.state(MPC) == "inactive"
    time.sleep(0.3)  # commands already on the wire
    n = len(loop.cmds)
    time.sleep(2.0)
    assert len(loop.cmds) == n  # not one command in 2 s (40 states)
    after = int(loop.next_diagnostics(sim)["cmd_timeouts"])
    assert after - before >= 20, (before, after)  # the simulator applied its safe command
    assert loop.next_diagnostics(MPC)["lifecycle"] == "inactive"
    assert loop.change(MPC, "activate")
    wait_for(lambda: len(loop.cmds) > n, TIMEOUT, what="commands after activation")


def test_cleanup_releases_everything_and_lifecycle_manager_brings_the_nodes_up(loop: Loop) -> None:
    pid = int(re.findall(r"training process pid (\d+)", loop.learner.output())[-1])
    assert loop.change(LEARNER, "deactivate") and loop.change(MPC, "deactivate")
    assert loop.change(LEARNER, "cleanup") and loop.change(MPC, "cleanup")
    assert loop.state(LEARNER) == "unconfigured" and loop.state(MPC) == "unconfigured"
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)  # the training process ended
    wait_for(lambda: loop.probe.node.count_publishers(f"{NS}/cmd") == 0, 10.0, what="no cmd publisher")
    # the learner's subscriptions are gone (their removal comes from another process than the MPC's)
    wait_for(lambda: loop.probe.node.count_subscribers(f"{NS}/applied_cmd") == 0, 30.0,
             what="no applied_cmd subscriber")
    version = loop.latest_version()
    manager = loop.dom.launch("lifecycle_manager", "-p", "node_names:=[learner, mpc]", namespace=NS)
    assert manager.wait(TIMEOUT) == 0, manager.output()
    assert loop.state(LEARNER) == "active" and loop.state(MPC) == "active"
    assert f"resumed from version {version}" in loop.learner.output()
    n = len(loop.cmds)
    wait_for(lambda: len(loop.cmds) > n, TIMEOUT, what="commands after the lifecycle manager")


def test_shutdown_transition_ends_the_process(loop: Loop) -> None:
    version = loop.latest_version()
    wait_for(lambda: loop.latest_version() > version, TIMEOUT, what="training after the restart")
    assert loop.change(LEARNER, "shutdown") and loop.change(MPC, "shutdown")
    assert loop.learner.wait(15.0) == 0 and loop.mpc.wait(15.0) == 0
    assert "cleanup: checkpoint version" in loop.learner.output()  # the deactivation had saved everything
    # the final state is on disk: written now, or by a periodic checkpoint that happened to be the last update
    tail = loop.learner.output().rsplit("resumed from", 1)[-1]
    assert re.search(r"shutdown: (final checkpoint version \d+|checkpoint version \d+ is current)", tail), tail
    assert "Traceback" not in loop.learner.output() + loop.mpc.output()
