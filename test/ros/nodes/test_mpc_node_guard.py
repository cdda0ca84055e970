"""The guarded MPC (core.mpc.guard) and the live model monitor (core.model_monitor), ROS-free.

The closed-loop tests fly the quadrotor on the simulator's dynamics (true step + ground contact): a checkpoint the
real online learner wrote after seeing only hover data is valid but wrong far from it; unguarded its landings end
far worse than f_hat's, guarded the loop keeps landing as well as f_hat.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

import numpy as np
from helpers.models import QUAD, TASK, hover_only_checkpoint
from helpers.ros_helpers import RosDomain

from saml_ros.demo.landing import aggressive_starts, plant


# ------------------------------------------------------------------------------------------ closed loop over ROS
def test_mpc_node_guards_a_hover_only_checkpoint_rolls_back_on_status_and_keeps_landing(
    tmp_path: Path, ros_env: RosDomain
) -> None:
    """The MPC node in its own process (guard on as in the demo) and the test stepping the simulator's dynamics in
    lockstep: a hover-only 5-member checkpoint is caught (ensemble fallbacks or a roll back) on far, fast starts and
    every landing ends near the pad; a hover-only single model (no ensemble to disagree) is rolled back by the live
    monitor once its live error exceeds f_hat's, visibly on ``mpc/status`` and ``/diagnostics``, and the loop keeps
    landing."""
    from test_mpc_node import DT_NS, T0_NS, MPCProcess, Probe

    f = plant(QUAD, TASK.landing_height)
    hover_only_checkpoint(tmp_path)  # version 1 in tmp_path / "hover", loaded before the first solve
    params = {"system": "quadrotor", "run_dir": str(tmp_path / "hover"), "poll_period": 0.1,
              "goal.position": "[0.0, 0.0, 0.2]", "task.tilt_max": 0.2, "guard.max_disagreement": 0.1,
              "guard.bound_residual": True, "guard.rollback": True}
    proc = MPCProcess(tmp_path, ros_env.domain_id, params)
    probe = Probe(ros_env.domain_id)
    k = [0]

    def land(x0: np.ndarray) -> float:
        """One 5 s landing episode from ``x0`` (stamps jump between episodes: a new warm start); its final error."""
        k[0] += 10
        x = x0
        for _ in range(TASK.steps):
            x = f(x, probe.step(x, T0_NS + k[0] * DT_NS, proc))
            k[0] += 1
        return float(np.linalg.norm(x[:3] - TASK.reachable))

    def status_since(n: int) -> list[dict[str, float]]:
        probe.executor.spin_once(timeout_sec=0.0)
        return probe.status[n:]

    try:
        probe.wait_connected(proc)
        starts = aggressive_starts(QUAD, 5, 999)
        errors = [land(x0) for x0 in starts[:3]]
        probe.spin_until(lambda: len(probe.status) >= 3 * TASK.steps, 10, "the status of every step", proc)
        s = probe.status[-1]
        assert probe.status[0]["model_version"] == 1.0, probe.status[0]
        assert s["guard_fallbacks"] + s["guard_rollbacks"] >= 1, s  # caught
        assert max(errors) < 0.5, errors  # and the loop kept landing

        n = len(probe.status)
        hover_only_checkpoint(tmp_path, n_models=1)  # version 2: one model, nothing to disagree
        deadline = time.monotonic() + 30
        while not status_since(n) or probe.status[-1]["model_version"] != 2.0:
            x = QUAD.hover_state((0.0, 0.0, 0.5))
            probe.step(x, T0_NS + k[0] * DT_NS, proc)
            k[0] += 20  # hovering with a new warm start each time: nothing for the monitor yet
            assert time.monotonic() < deadline, proc.log()
        n_swap = len(probe.status) - 1
        errors += [land(x0) for x0 in starts[3:]]
        probe.spin_until(lambda: len(probe.status) >= n_swap + 2 * TASK.steps, 10, "the status of every step", proc)
        flown = probe.status[n_swap:]
        back = [i for i, st in enumerate(flown) if st["model_version"] != 2.0]
        assert back, "the single hover-only model was never rolled back"
        i = back[0]
        assert flown[i]["guard_rollbacks"] == s["guard_rollbacks"] + 1 and flown[i]["model_version"] < 2.0, flown[i]
        # the monitor's reason: on the transitions flown with version 2 its live error exceeded f_hat's
        model_err = [st["live_error_model"] for st in flown[1:i + 1]]
        base_err = [st["live_error_base"] for st in flown[1:i + 1]]
        assert np.nanmean(model_err) > np.nanmean(base_err), (model_err, base_err)
        assert all(st["model_version"] != 2.0 for st in flown[i:])  # never used again
        probe.spin_until(lambda: probe.diag.get("guard_rolled_back_versions", "").split(",").count("2") == 1, 10,
                         "the roll back on /diagnostics", proc)
        assert max(errors) < 0.5, errors  # every landing, before and after the roll back
    finally:
        probe.close()
        rc = proc.stop(signal.SIGTERM)
    assert rc == 0, proc.log()
    assert "rolled back from model version 2" in proc.log()
