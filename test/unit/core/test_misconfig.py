"""Misconfigured robots: several publishers on a topic that should have one are named, and can be refused.

ROS-free: the decision (:mod:`saml_ros.core.data.publishers`). Real processes: a friction learner fed by the test's own
publishers (exact counts) and the example robot from its system file (examples/diff_drive), each time a second
node starts publishing into the namespace: the learner names both nodes on ``/diagnostics`` (WARN) and, with
``pairing.refuse_multiple_publishers``, pairs nothing from that namespace until the second node is gone. The
two-robots-one-topic closed loop (simulator, a miswired second robot, learner, MPC) is test_misconfig_loop.py.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from saml_ros.core.data.publishers import OK, WARN, PublisherGate, publisher_report, state_command_report


# ------------------------------------------------------------------------------------------ ROS-free
def test_gate_refuses_a_namespace_only_while_one_of_its_topics_has_several_publishers() -> None:
    gate = PublisherGate(["/a", "/a", "/b", "/b"], refuse=True)
    for ch in range(4):
        gate.set_count(ch, 1)
    assert all(gate.admit(ch) for ch in range(4))
    gate.set_count(0, 2)  # a second publisher on /a/state: /a's applied_cmd is refused too (nothing half-paired)
    assert [gate.admit(ch) for ch in range(4)] == [False, False, True, True]
    assert gate.blocked("/a") and not gate.blocked("/b") and gate.refused == [1, 1, 0, 0]
    gate.set_count(0, 1)
    assert all(gate.admit(ch) for ch in range(4)) and gate.refused == [1, 1, 0, 0]
    counting = PublisherGate(["/a", "/a"], refuse=False)  # the default: named, still paired
    counting.set_count(1, 3)
    assert counting.admit(0) and counting.admit(1) and counting.blocked("/a") and counting.refused == [0, 0]


def test_report_names_the_publishers_and_says_what_happens() -> None:
    channels = [("/f", "state", "/f/state"), ("/f", "applied_cmd", "/f/applied_cmd")]
    level, parts, values = publisher_report(channels, {"/f/state": ["/f/sim"], "/f/applied_cmd": ["/f/sim"]}, [1, 1])
    assert level == OK and parts == [] and values["multiple_publishers"] == ""
    assert values["/f/publisher_nodes/state"] == "/f/sim" and "/f/refused/state" not in values
    nodes = {"/f/state": ["/f/sim", "/f/robot_b"], "/f/applied_cmd": ["/f/sim"]}
    level, parts, values = publisher_report(channels, nodes, [2, 1])
    assert level == WARN and values["multiple_publishers"] == "/f/state: /f/robot_b, /f/sim"
    assert "paired as one robot's" in parts[0] and "pairing.refuse_multiple_publishers" in parts[0]
    level, parts, values = publisher_report(channels, nodes, [2, 1], refuse=True, refused=[7, 3])
    assert level == WARN and "not paired while so" in parts[0]
    assert values["/f/refused/state"] == 7 and values["/f/refused/applied_cmd"] == 3
    # matched before the graph shows the second node: still several, the count says how many
    level, parts, values = publisher_report(channels, {"/f/state": ["/f/sim"]}, [2, 1])
    assert level == WARN and values["multiple_publishers"] == "/f/state: /f/sim (2 publishers)"
    # a publisher whose node the graph has not discovered yet
    from saml_ros.core.data.publishers import UNKNOWN_NODE, node_label

    assert node_label("/_NODE_NAMESPACE_UNKNOWN_", "_NODE_NAME_UNKNOWN_") == UNKNOWN_NODE
    assert node_label("/", "sim") == "/sim" and node_label("/f", "sim") == "/f/sim"
    # the MPC: its own cmd publisher and a second controller
    level, parts, values = state_command_report([("state", "/f/state"), ("cmd", "/f/cmd")],
                                                {"/f/state": ["/f/sim"], "/f/cmd": ["/f/mpc", "/f/teleop"]})
    assert level == WARN and values["multiple_publishers"] == "/f/cmd: /f/mpc, /f/teleop"
    assert values["publisher_nodes/state"] == "/f/sim"



class _Log:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def info(self, text: str) -> None:
        self.lines.append(text)

    def warning(self, text: str) -> None:
        self.lines.append(text)


def residual_model(system_name: str, scale: float, seed: int = 0, offset: float = 0.0) -> Any:
    """A residual model with normalisation fitted on the paper's distribution, last-layer weights ~ N(0, scale)
    and last-layer biases + ``offset``: near f_hat for a tiny ``scale`` and no offset, wrong everywhere for a large
    one (in units of the residual's standard deviation)."""
    import torch

    from saml_ros.core.model.network import DynamicsModel
    from saml_ros.core.systems import get_system

    system = get_system(system_name)
    model = DynamicsModel(system, seed=seed)
    x, u, y = system.make_dataset(256, np.random.default_rng(seed))
    model.fit_normalization(x, u, y)
    with torch.no_grad():
        model.net.weights[-1].normal_(0.0, scale, generator=torch.Generator().manual_seed(seed))
        model.net.biases[-1].add_(offset)
    return model


def swap(service: Any, model: Any, version: int) -> None:
    """Hand ``model`` to the MPC service as its watcher hands over a checkpoint it loaded."""
    from saml_ros.core.model.io import LoadedModel
    from saml_ros.core.mpc.follower import ReadyModel

    loaded = LoadedModel(model, None, service.system, None, {}, {})  # type: ignore[arg-type]
    service.swap(ReadyModel(loaded, Path(f"ckpt-{version}.saml"), version, None, 0.0, "poll"))


def test_a_model_worse_than_f_hat_on_the_newest_live_transitions_is_never_flown() -> None:
    """The MPC has flown a few steps (on f_hat): a new checkpoint that predicts those transitions worse than f_hat
    is refused before its first step (the version never used); one as good as f_hat is taken."""
    from saml_ros.core.mpc.config import MPCConfig
    from saml_ros.core.mpc.service import MPCService

    sent: list[tuple[np.ndarray, int]] = []
    log = _Log()
    service = MPCService(MPCConfig.from_params({"system": "friction"}), lambda u, s: sent.append((u, s)), log)
    assert service.guarded is not None
    x, stamp = np.array([1.5, 0.0]), 10**9
    for _ in range(6):
        service.receive(x, stamp, time.perf_counter())
        x, stamp = service.system.true_step_np(x, sent[-1][0]), stamp + 100_000_000
    swap(service, residual_model("friction", 3.0, offset=30.0), 1)
    assert service.model_version == 0 and service.guarded.model is None and service.guarded.banned == {1}
    assert any("refused model version 1 (ckpt-1.saml) before flying it" in line for line in log.lines), log.lines
    assert service.guarded.counters["refused_before_flight"] == 1 and service.counters["rollbacks"] == 1
    swap(service, residual_model("friction", 1e-6), 2)
    assert service.model_version == 2 and service.guarded.tag == 2


def test_the_paddle_balls_mpc_rolls_a_model_back_on_its_post_impact_velocities() -> None:
    """guard.rollback is on by default for the one-shot paddle MPC too: its live transition is (pre-impact state,
    command, post-impact velocity). A model as good as f_hat is kept; one far off is refused before it flies once
    bounces were seen, and rolled back within min_samples bounces when none were."""
    from saml_ros.core.mpc.config import MPCConfig
    from saml_ros.core.mpc.service import MPCService
    from saml_ros.core.systems import get_entry

    config = MPCConfig.from_params({"system": "paddle_ball"})
    assert config.guard.rollback and not config.guard.needs_shooting
    sent: list[tuple[np.ndarray, int]] = []
    log = _Log()
    service = MPCService(config, lambda u, s: sent.append((u, s)), log)
    guarded = service.guarded
    assert guarded is not None and not guarded.shooting
    true_np = get_entry("paddle_ball").true_model_np
    assert true_np is not None
    truth = true_np(service.system)
    rng = np.random.default_rng(0)
    stamp = [10**9]

    def bounce() -> tuple[float, float]:
        x, _ = service.system.sample_inputs(1, rng)
        stamp[0] += 700_000_000
        service.receive(x[0], stamp[0], time.perf_counter())
        u, t = sent[-1]
        assert t == stamp[0]
        service.receive_target(truth.step1(x[0], u), stamp[0])
        return guarded.live_error_model, guarded.live_error_base

    swap(service, residual_model("paddle_ball", 1e-6, seed=1), 1)
    errors = [bounce() for _ in range(8)]
    assert guarded.tag == 1 and service.counters["rollbacks"] == 0, errors
    assert all(np.isfinite(e) for pair in errors for e in pair)
    swap(service, residual_model("paddle_ball", 3.0, seed=2), 2)  # refused: the 8 bounces flown show it is wrong
    assert guarded.tag == 1 and guarded.banned == {2} and service.counters["rollbacks"] == 1, log.lines
    assert any("refused model version 2 (ckpt-2.saml) before flying it" in line for line in log.lines)
    guarded.reset_models()  # nothing flown yet: the bad model flies until the monitor has min_samples bounces
    swap(service, residual_model("paddle_ball", 3.0, seed=3), 3)
    for _ in range(5):
        bounce()
    assert guarded.tag == 0 and guarded.banned == {3} and service.counters["rollbacks"] == 2, log.lines
    assert any("rolled back from model version 3" in line for line in log.lines)
    service.receive_target(np.zeros(3), 123)  # a target no answer was stamped with: ignored
    assert service.counters["rollbacks"] == 2


def test_the_monitor_pairs_each_state_with_the_one_answered_a_period_earlier() -> None:
    """Two friction robots on one state topic, half a period apart: the MPC answers both, and the live monitor
    scores only real transitions (each robot's state with its own previous one); pairing consecutive states, as it
    did, scored jumps between the robots and rolled a good model back."""
    from saml_ros.core.mpc.config import MPCConfig
    from saml_ros.core.mpc.service import MPCService
    from saml_ros.core.systems import get_entry

    sent: list[tuple[np.ndarray, int]] = []
    service = MPCService(MPCConfig.from_params({"system": "friction"}), lambda u, s: sent.append((u, s)), _Log())
    guarded = service.guarded
    assert guarded is not None
    guarded.set_model(residual_model("friction", 1e-6), 1)
    true_np = get_entry("friction").true_model_np
    assert true_np is not None
    truth = true_np(service.system)
    robots = {0: np.array([1.5, 0.0]), 50_000_000: np.array([-1.8, 0.0])}  # stamp offset -> state
    live_base: list[float] = []
    for k in range(20):
        for offset, x in robots.items():
            stamp = 10**9 + k * 100_000_000 + offset
            answer = service.receive(x, stamp, time.perf_counter())
            assert answer is not None
            live_base.append(answer[1]["live_error_base"])
            robots[offset] = truth.step1(x, sent[-1][0])
    # f_hat misses only the friction bumps: small one-step errors, never a 3 m jump between the robots
    assert np.isnan(live_base[:2]).all() and max(live_base[2:]) < 0.5, live_base
    assert guarded.tag == 1 and service.counters["rollbacks"] == 0
    assert len(guarded.monitor._windows) == 2  # one window per robot


def test_a_robot_on_which_f_hat_is_far_off_does_not_hide_a_model_worse_on_the_other() -> None:
    """Each stream has its own window: robot B (wired backwards) makes f_hat look terrible on its transitions, and
    mixed into one window that hid a model twice as far off as f_hat on robot A."""
    from saml_ros.core.mpc.monitor import LiveErrorMonitor

    mixed, per_robot = LiveErrorMonitor(), LiveErrorMonitor()
    said = []
    for _ in range(4):
        for stream, (e_model, e_base) in ((0, (0.1, 0.02)), (2, (1.0, 3.6))):  # A: model worse; B: f_hat worse
            mixed.add(e_model, e_base)
            said.append(per_robot.add(e_model, e_base, stream))
    assert not any(mixed.add(e, b) for e, b in ((0.1, 0.02), (1.0, 3.6)))  # one window: never
    assert said.index(True) == 4  # robot A's own window: at its third transition (min_samples)



class OneStepController:
    """A controller of the Controller protocol with no numpy model of its own (as a user's or another planner
    may be): it picks, among 41 commands, the one whose predicted next position is nearest the goal."""

    horizon = 1

    def __init__(self, system: Any) -> None:
        self.system = system
        self.model: Any = None
        self.candidates = np.linspace(system.control_low, system.control_high, 41)

    def set_model(self, model: Any) -> None:
        self.model = model

    def reset(self) -> None:
        pass

    def solve(self, x0: np.ndarray, goal: Any = None) -> Any:
        from saml_ros.core.mpc.contract import MPCResult

        xs = np.repeat(np.asarray(x0, dtype=np.float64)[None], len(self.candidates), 0)
        pred = self.system.base_step_np(xs, self.candidates) if self.model is None else \
            self.model.predict_np(xs, self.candidates)
        k = int(np.argmin(np.abs(pred[:, 0])))
        return MPCResult(self.candidates[k], self.candidates[k:k + 1], np.stack([x0, pred[k]]), float(abs(pred[k, 0])),
                         0.0, 0, True, "ok")


def test_the_roll_back_works_around_any_controller() -> None:
    """A controller without a numpy model (no ``dyn``): the monitor predicts with the model and the system's f_hat,
    and rolls a wrong model back (a robot from a system file flown by another planner is monitored the same way)."""
    from saml_ros.core.mpc.guard import GuardConfig, GuardedController
    from saml_ros.core.systems import get_system

    system = get_system("friction")
    guarded = GuardedController(OneStepController(system), OneStepController(system),  # type: ignore[arg-type]
                                GuardConfig(rollback=True))
    assert not guarded.shooting
    x, rolled = np.array([1.0, 0.0]), []
    guarded.set_model(residual_model("friction", 3.0, offset=30.0), 1)
    for _ in range(6):
        u = guarded.solve(x).u
        x_next = system.true_step_np(x, u)
        rolled.append(guarded.observe(x, u, x_next))
        x = x_next
    assert any(rolled) and guarded.tag == 0 and guarded.banned == {1}
    with pytest.raises(ValueError, match="only guard.rollback"):
        GuardedController(OneStepController(system), OneStepController(system),  # type: ignore[arg-type]
                          GuardConfig(rollback=True, infeasible=True))
