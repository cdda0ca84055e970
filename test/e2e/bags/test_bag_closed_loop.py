"""Offline pairing equals online pairing: the transitions ``bag_data`` extracts from a recording equal the
number the learner node paired in the same run (its ``paired`` counter, recorded from /diagnostics).

* with the stock publisher process (bag_publisher.py) in place of the simulator (learner + recorder);
* with the real closed loop: ``friction_sim`` (lockstep) + ``mpc`` + ``learner`` + ``record``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from helpers.bag_publisher import rollout
from helpers.bag_test_helpers import publish, start_recorder, unique_ns
from helpers.learner_node import RosSide
from helpers.ros_helpers import RosDomain, wait_for

from msg_schemas.telemetry import diagnostics_from_msg
from saml_ros.bags.io import Bag
from saml_ros.bags.transitions import extract_transitions

#: learner parameters for these runs: pairing only (training would only compete for the 2 CPU cores)
LEARNER = ("-p", "system:=friction", "-p", "min_transitions:=100000", "-p", "buffer.capacity:=100000",
           "-p", "diagnostics_rate:=4.0")


def start_learner(ros_env: RosDomain, ns: str, run: Path) -> Any:
    """The learner node in ``ns``, once it is up (a ros_helpers.Process)."""
    learner = ros_env.launch("learner", *LEARNER, "-p", f"run_dir:={run}", namespace=ns)
    wait_for(lambda: "training starts after" in learner.output() or not learner.alive(), what="the learner")
    assert learner.alive(), learner.output()
    return learner


def learner_paired(bag: Path, ns: str) -> int:
    """The learner's last ``paired`` counter in the bag's /diagnostics (-1 if it never reported)."""
    paired = -1
    with Bag(bag) as b:
        for m in b.messages(["/diagnostics"]):
            entries, _ = diagnostics_from_msg(b.decode(m))
            for e in entries:
                if e.name == f"{ns}/learner" and "paired" in e.values:
                    paired = int(e.values["paired"])
    return paired


def learner_matched(side: RosSide, ns: str) -> Callable[[], bool]:
    """Whether the learner in ``ns`` reports (on /diagnostics) a publisher on its state and command topics."""
    return lambda: side.counter(f"{ns}/publishers/state") > 0 and side.counter(f"{ns}/publishers/applied_cmd") > 0


def settle_paired(side: RosSide, pred: Callable[[int], bool], what: str) -> None:
    """Wait until the learner's ``paired`` counter, as the test reads /diagnostics, satisfies ``pred``, then 1 s
    more (four more reports at 4 Hz) so the recorder, another reader of /diagnostics, has it too."""
    side.wait(lambda: pred(side.counter("paired")), 60.0, what)
    time.sleep(1.0)


def test_bag_transitions_equal_what_the_learner_paired_from_a_publisher(ros_env: RosDomain, tmp_path: Path) -> None:
    bag, ns = tmp_path / "bag", unique_ns()
    learner = start_learner(ros_env, ns, tmp_path / "run")
    rec = start_recorder(ros_env, bag, "--system", "friction", "--namespace", ns)
    side = RosSide(ros_env.domain_id, ns)
    try:
        events = rollout("friction", 300, 60, 4, 10**9)
        report = publish(events, tmp_path, "--system", "friction", "--namespace", ns, "--rate", "150", "--clock",
                         "--cmd", "--wait-subscribers", "2", "--wait-timeout", "60", recorder=rec,
                         ready=learner_matched(side, ns))
        # the learner's final counters reach the bag through /diagnostics (4 Hz)
        settle_paired(side, lambda n: n == report["transitions"], f"the learner to pair {report['transitions']}")
    finally:
        side.close()
    assert rec.stop() == 0, rec.output()
    assert learner.stop() == 0, learner.output()
    out = extract_transitions([bag], "friction")
    assert len(out) == report["transitions"] == learner_paired(bag, ns), learner.output()


def test_bag_transitions_equal_what_the_learner_paired_in_the_closed_loop(ros_env: RosDomain,
                                                                          tmp_path: Path) -> None:
    bag, ns, run = tmp_path / "bag", unique_ns(), tmp_path / "run"
    learner = start_learner(ros_env, ns, run)
    rec = start_recorder(ros_env, bag, "--system", "friction", "--namespace", ns)
    # The simulator (lockstep) sends its first state once a controller publishes and the learner, the MPC and the
    # recorder subscribe. A reader drops what a writer sends before the reader has matched it (the writer may
    # see the reader first), so the MPC starts only once the recorder has matched the simulator's publishers.
    sim = ros_env.launch("friction_sim", "-p", "mode:=lockstep", "-p", "max_sim_time:=15.0",
                         "-p", "episode_steps:=40", "-p", "seed:=3", "-p", "min_state_subscribers:=3",
                         "-p", "min_applied_cmd_subscribers:=2", namespace=ns)
    wait_for(lambda: all(f"record: matched {ns}/{t} " in rec.output() for t in ("state", "applied_cmd"))
             or not rec.alive() or not sim.alive(), what="the recorder to match the simulator's publishers")
    assert rec.alive() and sim.alive(), rec.output() + sim.output()
    side = RosSide(ros_env.domain_id, ns)
    try:
        # the learner's own side of the match, from its /diagnostics
        side.wait(learner_matched(side, ns), 60.0, "the learner to match the simulator's publishers")
        mpc = ros_env.launch("mpc", "-p", "system:=friction", "-p", f"run_dir:={run}", namespace=ns)
        deadline = time.monotonic() + 150
        while sim.alive() and time.monotonic() < deadline:
            for proc in (learner, mpc, rec):
                assert proc.alive(), f"{proc.name} died:\n{proc.output()}"
            time.sleep(0.2)
        assert sim.wait(1) == 0, sim.output()
        # the simulator is done: the count stops moving once the learner has paired what it received
        seen: list[int] = []

        def still(n: int) -> bool:
            seen.append(n)
            return n > 0 and len(seen) > 50 and seen[-50] == n  # unchanged for 1 s (50 reads 20 ms apart)

        settle_paired(side, still, "the learner's paired count to settle")
    finally:
        side.close()
    assert rec.stop() == 0, rec.output()
    assert learner.stop() == 0, learner.output()
    assert mpc.stop() == 0, mpc.output()
    out = extract_transitions([bag], "friction")
    assert len(out) > 100
    assert len(out) == learner_paired(bag, ns), learner.output()
