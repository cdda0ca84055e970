"""The lockstep speed limit (saml_ros/core/worlds/pacing.py)."""

from __future__ import annotations

import pytest

from saml_ros.core.worlds.pacing import Pacer

S = 10**9


def test_pacer_holds_the_limit_without_catching_up() -> None:
    p = Pacer(4.0)
    assert p.wait_s(1 * S, 100 * S) == 0.0  # the first step sets the origin
    # 0.1 s simulated at most 4x real time: due 25 ms after the origin; 5 ms have passed
    assert p.wait_s(int(1.1 * S), 100 * S + 5 * 10**6) == pytest.approx(0.020)
    # on schedule (the caller waited): the next is due 25 ms later
    assert p.wait_s(int(1.2 * S), 100 * S + 50 * 10**6 - 10**6) == pytest.approx(0.001)
    # a slow step (behind schedule): no wait, and no burst after it
    assert p.wait_s(int(1.3 * S), 101 * S) == 0.0
    assert p.wait_s(int(1.4 * S), 101 * S) == pytest.approx(0.025)
    # simulated time went back (a new run): a fresh origin
    assert p.wait_s(1 * S, 102 * S) == 0.0
    assert p.waited_s == pytest.approx(0.046)


def test_pacer_off_and_bad_limits() -> None:
    assert Pacer(0.0).wait_s(5 * S, 0) == 0.0 and Pacer(0.0).wait_s(9 * S, 1) == 0.0
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="max_speed"):
            Pacer(bad)


def test_simulator_parameter_max_speed_is_checked_with_its_name() -> None:
    """The node's parameter check refuses a negative or undefined limit, naming the parameter."""
    from sim_nodes.binding import check_params
    from sim_nodes.quadrotor_sim import BINDING

    p = {spec.name: spec.default for spec in BINDING.param_table()}
    check_params({**p, "max_speed": 5.0})
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="parameter 'max_speed' must be >= 0"):
            check_params({**p, "max_speed": bad})
