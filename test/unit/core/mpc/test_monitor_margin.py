"""The live monitor's default margin scales with the robot (core/mpc/monitor.py): relative to f_hat's mean squared
one-step error over the model's data (its checkpoint evidence), else over the live transitions seen so far.

The absolute 0.01 it had was sized for the quadrotor; on the example diff-drive base (squared one-step errors about
1e-5) it never rolled back: the tutorial's MPC flew a model whose error on the steps it planned was 3.8e-5 against
f_hat's 3.1e-8 and stopped 0.17 m from the goal."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from saml_ros.core.model.evidence import DataEvidence
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc.guard import GuardConfig, make_guarded_controller
from saml_ros.core.mpc.monitor import LiveErrorMonitor, MonitorConfig, data_scale
from saml_ros.user_code import load_system_file

REPO = Path(__file__).resolve().parents[4]
EXAMPLE = REPO / "examples" / "diff_drive"
#: the threshold the monitor had before: absolute, sized for the quadrotor
OLD_DEFAULT = MonitorConfig(margin=0.01, margin_relative=0.0)


#: robots these tests load from system files are forgotten after each test (test/conftest.py)
pytestmark = pytest.mark.usefixtures("restore_registry")


def feed(m: LiveErrorMonitor, err_model: float, err_base: float, n: int = 5) -> bool:
    return any([m.add(err_model, err_base) for _ in range(n)])


def test_the_default_margin_rolls_back_on_a_diff_drive_and_keeps_a_good_quadrotor_model() -> None:
    # diff-drive sized: f_hat's mean squared error over the example's wander data is about 6.3e-4; the tutorial's
    # model erred 3.8e-5 per planned step where f_hat erred 3.1e-8
    dd = {"evidence": {"residual_rms": np.sqrt([4.0e-6, 2.8e-6, 5.1e-5, 1.1e-4, 4.7e-4]).tolist()}}
    assert data_scale(dd) == pytest.approx(6.378e-4)
    m = LiveErrorMonitor()
    m.data_scale = data_scale(dd)
    assert feed(m, 3.8e-5, 3.1e-8)
    assert "margin 1.28e-05" in m.describe_verdict()
    old = LiveErrorMonitor(OLD_DEFAULT)
    old.data_scale = data_scale(dd)
    assert not feed(old, 3.8e-5, 3.1e-8)  # what the absolute default did: the model flew on
    # a model as good as f_hat's error there within a fraction of the data's scale is kept
    m.reset()
    assert not feed(m, 1e-5, 3.1e-8)
    # quadrotor sized (f_hat's mean squared error over the demo learner's data about 0.13): where f_hat is exact
    # (above the ground effect) a good model's small error is kept, a model far off is rolled back
    q = LiveErrorMonitor()
    q.data_scale = 0.13
    assert not feed(q, 1e-3, 0.0)
    assert feed(q, 0.05, 0.0)


def test_without_evidence_the_live_f_hat_errors_set_the_scale_and_an_absolute_margin_still_applies() -> None:
    m = LiveErrorMonitor()
    assert m.scale == 0.0 and m.margin == 0.0
    for _ in range(10):
        m.note_base(6e-4)
    m.note_base(math.nan)  # skipped
    assert m.live_base_mean == pytest.approx(6e-4) and m.margin == pytest.approx(0.02 * 6e-4)
    m.data_scale = 1e-2  # the checkpoint's evidence wins
    assert m.margin == pytest.approx(2e-4)
    m.reset()  # a new model: the live errors noted stay
    assert m.live_base_mean == pytest.approx(6e-4)
    fixed = LiveErrorMonitor(MonitorConfig(margin=0.003, margin_relative=0.0))
    fixed.data_scale = 1e-2
    assert fixed.margin == 0.003
    assert data_scale({}) != data_scale({})  # NaN: no evidence
    assert math.isnan(data_scale({"evidence": {"residual_rms": ["a"]}}))
    with pytest.raises(ValueError):
        MonitorConfig(margin_relative=-0.1)


def test_the_guard_scales_its_monitor_by_the_checkpoint_evidence_and_rolls_back_a_biased_diff_drive_model() -> None:
    """The example diff-drive base at rest on dry floor (f_hat nearly exact there): a model biased by 6 mm per step
    in x (squared error 3.6e-5, what the tutorial's model did at its goal) is refused before flight and rolled back
    by the default guard with its checkpoint's evidence; the old absolute margin let it fly."""
    sys.path.insert(0, str(EXAMPLE))
    try:
        import dynamics as dd  # type: ignore[import-not-found]
        import evaluate as dd_eval  # type: ignore[import-not-found]
    finally:
        sys.path.remove(str(EXAMPLE))
    s = load_system_file(EXAMPLE / "system.yaml")
    x, u, y = dd_eval.transitions(3000, 7, 0.0)
    ev = DataEvidence.from_data(s, x, u, y)
    assert ev is not None
    _, meta_ev = ev.to_payload(tuple(s.target.names))
    meta = {"evidence": meta_ev}
    scale = data_scale(meta)
    assert 1e-4 < scale < 3e-3  # f_hat's squared one-step error over wandering: slip on the dry floor and the patch
    model = DynamicsModel(s, (8,), "residual", seed=0).double()
    model.fit_normalization(x, u, y)
    rest_x, rest_u = np.array([[-1.0, 0.5, 0.3, 0.0, 0.0]]), np.zeros((1, 2))
    with torch.no_grad():
        model.net.weights[-1].zero_()
        phi0 = model.predict_np(rest_x, rest_u)[0] - s.base_step_np(rest_x, rest_u)[0]
        model.net.biases[-1].fill_(1.0)
        phi1 = model.predict_np(rest_x, rest_u)[0] - s.base_step_np(rest_x, rest_u)[0]
        want = np.array([0.006, 0.0, 0.0, 0.0, 0.0])
        model.net.biases[-1].copy_(torch.as_tensor((want - phi0) / (phi1 - phi0)))
    robot = dd.make_robot(rest_x[0])
    transitions = []
    for _ in range(6):  # at rest: the robot does not move, f_hat says so
        xs = robot.state()
        robot.step(np.zeros(2), s.dt)
        transitions.append((xs, np.zeros(2), robot.state()))

    def fly(config: MonitorConfig) -> tuple[bool, int]:
        g = make_guarded_controller(s, "fast", GuardConfig(rollback=True, monitor=config), horizon=5)
        took = g.offer_model(model, 1, meta)
        for xs, us, ys in transitions:
            g.solve(xs)  # planned with the model (the monitor scores only such steps); the robot held at rest
            g.observe(xs, us, ys)
        return took, g.counters["rollbacks"]

    g = make_guarded_controller(s, "fast", GuardConfig(rollback=True), horizon=5)
    assert g.offer_model(model, 1, meta) and g.monitor.data_scale == pytest.approx(scale)
    xs, us, ys = transitions[0]
    g.solve(xs)
    g.observe(xs, us, ys)
    assert 3e-5 < g.live_error_model < 4.5e-5 and g.live_error_base < 1e-9
    assert g.values()["monitor_margin"] == pytest.approx(0.02 * scale)
    took, rollbacks = fly(MonitorConfig())
    assert took and rollbacks == 1  # flown, then rolled back after min_samples steps
    old_took, old_rollbacks = fly(OLD_DEFAULT)
    assert old_took and old_rollbacks == 0
    # a second model offered after those steps is scored before it flies (the newest live transitions)
    g = make_guarded_controller(s, "fast", GuardConfig(rollback=True), horizon=5)
    for xs, us, ys in transitions:
        g.observe(xs, us, ys)
    assert not g.offer_model(model, 2, meta) and g.counters["refused_before_flight"] == 1
