"""The MPC's model in use (ROS-free, the MPC node's logic in :class:`~saml_ros.core.mpc.service.MPCService`): a
checkpoint holding it again is a no-op, it is re-checked on the states it flies as a new checkpoint is, and a roll
back says why in numbers."""

from __future__ import annotations

import math
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.models import QUAD, quad_evidence, quad_model, save_quad_checkpoint

from saml_ros.core.model.checkpoint import CheckpointStore
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc import follower
from saml_ros.core.mpc.config import MPCConfig
from saml_ros.core.mpc.monitor import LiveErrorMonitor, MonitorConfig
from saml_ros.core.mpc.service import MPCService


class Log:
    """What the service logs (info and warning lines)."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str]] = []

    def info(self, msg: str) -> None:
        self.lines.append(("info", msg))

    def warning(self, msg: str) -> None:
        self.lines.append(("warning", msg))

    def having(self, text: str) -> list[str]:
        return [m for _, m in self.lines if text in m]


def _wait(pred: object, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():  # type: ignore[operator]
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


#: the re-check period and the watcher's poll period in these tests (the product's: 1 s and 0.5 s): the background
#: thread's re-checks come as they do in a node, ten times as often, so the tests wait for them, not for seconds
RECHECK_PERIOD_S = 0.1
POLL_PERIOD_S = 0.02


@pytest.fixture(autouse=True)
def _fast_rechecks(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(follower, "RECHECK_PERIOD_S", RECHECK_PERIOD_S)


def _count_vets(service: MPCService) -> list[int]:
    """From now on, every acceptance check the watcher runs (a new checkpoint's or a re-check of the model in use)
    adds one to the returned counter (``[n]``), then runs as before."""
    calls = [0]
    vet = service.watcher._vet
    assert vet is not None

    def counted(loaded: object) -> object:
        calls[0] += 1
        return vet(loaded)  # type: ignore[arg-type]

    service.watcher._vet = counted  # type: ignore[assignment]
    return calls


def _broken_far_out(push: float = 3.0) -> DynamicsModel:
    """A quadrotor model right where it was trained (|px| <= 2 m) and wrong from px = 3 m on (vz pushed by ``push``
    m/s per metre; ``helpers.models.quad_model`` with a push its plans survive: they stay plausible, so the MPC
    flies them)."""
    model = quad_model(hidden=(4,))
    with torch.no_grad():
        h = model.net.weights[0]
        i = QUAD.state.index("px")
        std, mean = float(model.in_std[0, 0, i]), float(model.in_mean[0, 0, i])
        h[0, :, 0] = 0.0
        h[0, i, 0] = std
        model.net.biases[0][0, 0, 0] = mean - 3.0
        model.net.slopes[0].fill_(0.0)
        model.net.weights[1][0, 0, :] = 0.0
        model.net.weights[1][0, 0, QUAD.target.index("vz")] = push / float(model.out_std[0, 0, QUAD.target.index("vz")])
    return model


def test_a_reannounced_model_in_use_is_a_no_op_and_the_model_in_use_is_rechecked_on_the_states_flown(
        tmp_path: Path) -> None:
    store = CheckpointStore(tmp_path / "run")
    path, version = save_quad_checkpoint(store, _broken_far_out(), quad_evidence(px=2.0))
    log = Log()
    # the live monitor off (it is on by default and would roll the model back first): the re-check alone
    service = MPCService(MPCConfig.from_params({"system": "quadrotor", "run_dir": str(store.run_dir),
                                                "guard.rollback": False, "poll_period": POLL_PERIOD_S}),
                         lambda u, s: None, log)
    service.start()  # no state flown yet: the checkpoint passes on its own probe set and is used
    try:
        assert service.model_version == version == 1
        far = QUAD.hover_state((5.0, 0.0, 2.0))
        for k in range(3):  # the vehicle flies where the model is broken
            service.control_step(far, 10**9 + k * 10**8, time.perf_counter())
        # the same model announced again from another directory (a copy): nothing to do, never refused
        copy = tmp_path / "copy" / path.name
        copy.parent.mkdir()
        shutil.copy(path, copy)
        service.notify(str(copy), version, QUAD.schema_hash())
        _wait(lambda: service.watcher.stats()["reannounced"] == 1)
        stats = service.watcher.stats()
        assert stats["loaded"] == 1 and stats["refused/residual"] in (0, 1)  # 1 only from the re-check below
        assert log.having("holds the model in use (version 1): nothing to do")
        # the model in use is re-checked on the states it flies (at most RECHECK_PERIOD_S later): refused, retired
        _wait(lambda: service.watcher.stats()["in_use_refused"] == 1, timeout=10 * RECHECK_PERIOD_S + 10)
        assert service.model_version == 1  # until the next control step takes it out
        service.control_step(far, 10**9 + 3 * 10**8, time.perf_counter())
        assert service.model_version == 0 and service.model_path == ""
        diag = service.diagnostic_values()
        assert diag["models_retired"] == 1 and diag["checkpoints_refused/residual"] == 1
        assert diag["checkpoints_reannounced"] == 1 and "the model in use" in diag["last_refusal"]
        assert log.having("no longer passes the acceptance check on the states it flies (residual)")
        assert log.having("model version 1 retired (residual on the states flown); planning with the base model")
        assert not [m for m in log.having("refused checkpoint")], log.lines  # the copy was never refused
        # the retired model is not taken up again, nor re-checked: f_hat stays until a newer checkpoint
        vets = _count_vets(service)
        time.sleep(3 * RECHECK_PERIOD_S)
        service.control_step(far, 10**9 + 4 * 10**8, time.perf_counter())
        assert service.model_version == 0 and service.watcher.stats()["in_use_refused"] == 1
        assert vets == [0]
    finally:
        service.stop()


def test_a_good_model_in_use_passes_its_rechecks(tmp_path: Path) -> None:
    store = CheckpointStore(tmp_path / "run")
    save_quad_checkpoint(store, quad_model(), quad_evidence())
    log = Log()
    # the live monitor off (it is on by default and would roll the model back first): the re-check alone
    service = MPCService(MPCConfig.from_params({"system": "quadrotor", "run_dir": str(store.run_dir),
                                                "guard.rollback": False, "poll_period": POLL_PERIOD_S}),
                         lambda u, s: None, log)
    service.start()
    try:
        vets = _count_vets(service)
        x = QUAD.hover_state((1.0, -1.0, 2.0))
        for k in range(3):
            service.control_step(x, 10**9 + k * 10**8, time.perf_counter())
        _wait(lambda: vets[0] >= 3)  # three re-checks of the model in use on the states flown, all passed
        service.control_step(x, 10**9 + 3 * 10**8, time.perf_counter())
        assert service.model_version == 1 and service.watcher.stats()["in_use_refused"] == 0
    finally:
        service.stop()


# ------------------------------------------------------------------------------------------ the roll-back line
def test_the_monitors_verdict_survives_the_reset_that_follows_a_roll_back() -> None:
    m = LiveErrorMonitor(MonitorConfig(window=3, min_samples=2, ratio=1.0, margin=0.01))
    assert m.describe_verdict() == ""
    assert not m.add(0.5, 0.001)
    assert m.add(0.7, 0.003)
    m.reset()  # what the roll back does before the line is logged
    assert math.isnan(m.mean_base)  # what the line printed before ("f_hat's nan")
    text = m.describe_verdict()
    assert text == ("its live one-step squared error, mean 0.6 over the last 2 steps it planned, exceeded f_hat's "
                    "0.002 on the same steps (x 1 + margin 0.01)")


def test_the_mpc_logs_a_roll_back_with_the_numbers_that_caused_it(tmp_path: Path) -> None:
    """A guarded MPC (roll back on) flies a model far off (an output bias of 2 m/s on vz): it is rolled back to
    f_hat and the log line holds the window's means, not NaN."""
    from saml_ros.demo.landing import plant

    store = CheckpointStore(tmp_path / "run")
    save_quad_checkpoint(store, quad_model(bias={"vz": 2.0}), None)
    log = Log()
    sent: list[np.ndarray] = []
    cfg = MPCConfig.from_params({"system": "quadrotor", "run_dir": str(store.run_dir), "guard.rollback": True})
    service = MPCService(cfg, lambda u, s: sent.append(np.asarray(u)), log)
    service.start()
    try:
        assert service.model_version == 1
        f = plant(QUAD, 0.0)
        x = QUAD.hover_state((0.5, 0.5, 1.5))
        for k in range(10):
            service.control_step(x, 10**9 + k * 10**8, time.perf_counter())
            x = f(x, sent[-1])
            if service.model_version == 0:
                break
    finally:
        service.stop()
    lines = log.having("rolled back from model version 1 to the base model f_hat")
    assert len(lines) == 1, log.lines
    assert "nan" not in lines[0] and "exceeded f_hat's" in lines[0], lines[0]
    assert service.diagnostic_values()["rollbacks"] == 1

