"""The MPC node and its model watcher.

ROS-free part: :class:`~saml_ros.core.mpc.follower.ModelWatcher` (loading, refusing, handing over).
Node part (real processes, private ROS_DOMAIN_ID): the node answers states with the right stamps and bounds,
starts on the base model, switches to checkpoints that appear while it runs, refuses corrupt and foreign
checkpoints and keeps running.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from helpers.checkpoints import save_model, write_corrupt
from helpers.models import quad_evidence, quad_model, save_quad_checkpoint, trap_model
from helpers.mpc_node import DT_NS, T0_NS, MPCProcess, Probe
from helpers.ros_helpers import RosDomain

from saml_ros.core.model.checkpoint import CheckpointStore
from saml_ros.core.systems import get_system


def _hover(pos: tuple[float, float, float]) -> np.ndarray:
    return get_system("quadrotor").hover_state(pos)  # type: ignore[attr-defined]


@pytest.fixture


def domain(ros_env: RosDomain) -> int:
    """A private ROS domain (claimed by ros_helpers; Fast DDS leftovers are cleaned after the test)."""
    return ros_env.domain_id


def test_node_answers_every_state_with_its_stamp_within_bounds(tmp_path: Path, domain: int) -> None:
    system = get_system("quadrotor")
    proc = MPCProcess(tmp_path, domain, {"system": "quadrotor", "run_dir": str(tmp_path / "run")})
    probe = Probe(domain)
    try:
        probe.wait_connected(proc)
        rng = np.random.default_rng(0)
        stamps = []
        for k in range(15):
            x = _hover((rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(0.5, 3)))
            x[3:6] = rng.uniform(-1, 1, 3)
            stamp = T0_NS + k * DT_NS
            u = probe.step(x, stamp, proc)
            stamps.append(stamp)
            assert np.all(u >= system.control_low) and np.all(u <= system.control_high), u
        # a state far above the target: the MPC must not command more than f_max nor less than 0
        u = probe.step(_hover((0.0, 0.0, 30.0)), T0_NS + 20 * DT_NS, proc)
        assert np.all((u >= 0) & (u <= 10.0))
        bad = _hover((0.0, 0.0, 1.0))
        bad[0] = np.nan
        probe.state_pub.publish(probe.schema.state_to_msg(bad, T0_NS + 21 * DT_NS))
        probe.step(_hover((0.0, 0.0, 1.0)), T0_NS + 22 * DT_NS, proc)
        probe.spin_until(lambda: int(probe.diag.get("rejected/nan", "0")) >= 1, 10, "rejected/nan in /diagnostics",
                         proc)
        assert T0_NS + 21 * DT_NS not in probe.cmds  # never answered
        assert set(stamps) <= set(probe.cmds)
        probe.spin_until(lambda: len(probe.status) >= 17, 5, "mpc/status", proc)
        assert all(s["model_version"] == 0 for s in probe.status)  # no checkpoint: the base model
        assert all(s["solve_time_ms"] > 0 and s["iterations"] >= 1 for s in probe.status)
    finally:
        probe.close()
        rc = proc.stop(signal.SIGINT)
    assert rc == 0, proc.log()
    assert "no checkpoint yet: running on the base model" in proc.log()


def test_node_hot_swaps_checkpoints_and_refuses_bad_ones(tmp_path: Path, domain: int) -> None:
    store = CheckpointStore(tmp_path / "run")
    proc = MPCProcess(tmp_path, domain, {"system": "quadrotor", "run_dir": str(store.run_dir),
                                         "poll_period": 0.2, "deadline_ms": 100.0})
    probe = Probe(domain)
    k = [0]

    def fly_until(pred: Any, what: str, timeout: float = 60.0) -> None:
        """Keep the loop running (one state per answer) until ``pred()``."""
        deadline = time.monotonic() + timeout
        while not pred():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for {what}\n{proc.log()}")
            x = _hover((1.0, -1.0, 2.0 - 0.01 * (k[0] % 100)))
            probe.step(x, T0_NS + k[0] * DT_NS, proc)
            k[0] += 1

    def last(name: str) -> float:
        probe.executor.spin_once(timeout_sec=0.0)
        return probe.status[-1][name] if probe.status else -1.0

    try:
        probe.wait_connected(proc)
        fly_until(lambda: len(probe.status) >= 5, "the first solves")
        assert last("model_version") == 0
        good, _ = save_model(store, "quadrotor", seed=1)  # appears while the loop runs
        fly_until(lambda: last("model_version") == 1, "the switch to version 1")
        write_corrupt(store, good)  # version 2: truncated
        fly_until(lambda: last("checkpoints_refused") >= 1, "the corrupt checkpoint to be refused")
        save_model(store, "friction")  # version 3: another system
        fly_until(lambda: last("checkpoints_refused") >= 2, "the foreign checkpoint to be refused")
        fly_until(lambda: len(probe.status) >= k[0] - 1 and k[0] > 40, "more solves")
        assert last("model_version") == 1  # kept its model
        # a checkpoint announced on learner/checkpoint, in a directory the node does not poll
        from msg_schemas.telemetry import CheckpointInfo, checkpoint_to_msg

        other = CheckpointStore(tmp_path / "elsewhere")
        save_model(other, "quadrotor", seed=5)
        path, version = save_model(other, "quadrotor", seed=6)
        probe.ckpt_pub.publish(checkpoint_to_msg(CheckpointInfo(str(path), version, get_system("quadrotor")
                                                                .schema_hash(), 0.0)))
        fly_until(lambda: last("model_version") == version, "the announced checkpoint")
        probe.spin_until(lambda: int(probe.diag.get("checkpoints_refused", "0")) >= 2, 10, "diagnostics", proc)
        assert int(probe.diag["checkpoints_refused/corrupt"]) == 1
        assert int(probe.diag["checkpoints_refused/incompatible"]) == 1
        assert "expected 'quadrotor'" in probe.diag["last_refusal"]
        swaps = [s for s in probe.status if s["swap_ms"] > 0]
        assert len(swaps) == 2
        # the swap happens between two solves and costs next to nothing (loading is off the control thread; the
        # bound is loose: a loaded machine preempts any step)
        assert all(s["swap_ms"] < 250.0 for s in swaps), swaps
        assert sorted(probe.cmds) == [T0_NS + i * DT_NS for i in range(k[0])]  # every state answered, in order
    finally:
        probe.close()
        rc = proc.stop(signal.SIGTERM)
    assert rc == 0, proc.log()
    log = proc.log()
    assert "refused checkpoint (corrupt)" in log and "refused checkpoint (incompatible)" in log


def test_node_realtime_mode_answers_the_newest_state(tmp_path: Path, domain: int) -> None:
    proc = MPCProcess(tmp_path, domain, {"system": "quadrotor", "mode": "realtime", "rate_hz": 5.0})
    probe = Probe(domain)
    try:
        probe.wait_connected(proc)
        probe.step(_hover((0.5, 0.5, 1.0)), T0_NS, proc)  # warm up: first solve
        burst = [T0_NS + k * DT_NS for k in range(1, 6)]
        for stamp in burst:  # five states within one control period: only the newest is answered
            probe.state_pub.publish(probe.schema.state_to_msg(_hover((0.5, 0.5, 1.0)), stamp))
        probe.spin_until(lambda: burst[-1] in probe.cmds, 10, "the answer to the newest state", proc)
        probe.spin_until(lambda: int(probe.diag.get("skipped_states", "0")) >= 1, 10, "skipped_states", proc)
        t_end = time.monotonic() + 1.0
        while time.monotonic() < t_end:
            probe.executor.spin_once(timeout_sec=0.05)
        answered = [s for s in burst if s in probe.cmds]
        assert answered[-1] == burst[-1] and len(answered) < len(burst), answered
    finally:
        probe.close()
        rc = proc.stop(signal.SIGINT)
    assert rc == 0, proc.log()


def test_node_refuses_poisoned_checkpoints_keeps_its_model_keeps_landing_and_answers_failures_safely(
    tmp_path: Path, domain: int
) -> None:
    """One MPC process: it starts on a good checkpoint, refuses a non-finite, an implausible (a residual of 1e6 m)
    and an out-of-evidence checkpoint that appear while the test lands the quadrotor with it (the test process
    steps the true dynamics, like a lockstep simulator), keeps its model and lands; then an implausible state and a
    model that is broken away from its training data (accepted: nothing in its data or the recent states shows
    it) are answered with hover thrust."""
    quad = get_system("quadrotor")
    store = CheckpointStore(tmp_path / "run")
    ev = quad_evidence()
    save_quad_checkpoint(store, quad_model(), ev)  # version 1, loaded before the first solve
    proc = MPCProcess(tmp_path, domain, {"system": "quadrotor", "run_dir": str(store.run_dir), "poll_period": 0.1})
    probe = Probe(domain)
    k = [0]

    def step(x: np.ndarray) -> np.ndarray:
        u = probe.step(x, T0_NS + k[0] * DT_NS, proc)
        k[0] += 1
        return u

    def diag(key: str) -> int:
        probe.executor.spin_once(timeout_sec=0.0)
        return int(probe.diag.get(key, "0"))

    try:
        probe.wait_connected(proc)
        x = _hover((1.0, -1.0, 2.0))
        poison = {5: ("non_finite", quad_model(1), "weights"), 12: ("implausible", quad_model(2, {"pz": 1e6}), None),
                  19: ("residual", quad_model(3, {"vz": 30.0}), None)}
        for i in range(45):
            if i in poison:
                save_quad_checkpoint(store, poison[i][1], ev, poison[i][2])
            x = quad.true_step_np(x, step(x))
            if x[2] < 0.1:  # the simulator's ground contact
                x[2], x[5], x[10:13] = 0.1, max(x[5], 0.0), 0.0
        probe.spin_until(lambda: diag("checkpoints_refused") >= 3, 10, "the three refusals", proc)
        for reason in ("non_finite", "implausible", "residual"):
            assert diag(f"checkpoints_refused/{reason}") == 1, probe.diag
        assert {s["model_version"] for s in probe.status} == {1.0}  # kept its model throughout
        assert np.linalg.norm(x[:2]) < 0.3 and x[2] < 0.4, x[:6]  # and landed on it
        assert diag("safe_commands") == 0 and all(s["safe"] == 0.0 for s in probe.status)

        n_status = len(probe.status)
        np.testing.assert_array_equal(step(_hover((0.0, 0.0, 2e4))), quad.safe_control())  # 20 km up
        probe.spin_until(lambda: len(probe.status) > n_status and diag("safe_commands/bounds") == 1, 10,
                         "the safe command for an implausible state", proc)
        assert probe.status[-1]["safe"] == 1.0 and diag("rejected/bounds") == 1

        # broken beyond px = 3 m, where neither its training data (|px| <= 2 m) nor the recent states reach
        save_quad_checkpoint(store, trap_model("quadrotor", "px", 3.0, 3e38, torch.float32), quad_evidence(1, px=2.0))
        deadline = time.monotonic() + 20
        while probe.status[-1]["model_version"] != 5.0:
            assert time.monotonic() < deadline, proc.log()
            step(_hover((0.5, 0.0, 1.5)))
        np.testing.assert_array_equal(step(_hover((5.0, 0.0, 1.5))), quad.safe_control())
        assert np.all(np.isfinite(step(_hover((0.5, 0.0, 1.5)))))  # and plans again where the model is sane
        probe.spin_until(lambda: diag("safe_commands/non_finite") + diag("safe_commands/implausible") == 1, 10,
                         "the safe command for a failed solve", proc)
        assert diag("safe_commands") == 2 and probe.diag.get("checkpoints_refused") == "3"
        assert sorted(probe.cmds) == [T0_NS + i * DT_NS for i in range(k[0])]  # every state answered
    finally:
        probe.close()
        rc = proc.stop(signal.SIGTERM)
    assert rc == 0, proc.log()
    log = proc.log()
    for reason in ("non_finite", "implausible", "residual"):
        assert f"refused checkpoint ({reason})" in log
    assert "sent the safe command" in log
