"""Problem spec: validation messages, regions, losses and estimators."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
import torch
from helpers import REPO

from saml_ros.core.layout import make_layout
from saml_ros.core.spec import ProblemSpec, SpecError

STATE = make_layout("state", [("p", "m"), ("v", "m/s")])
CONTROL = make_layout("control", [("u", "m/s^2")])
TARGET = STATE


def compile_(d: Any) -> Any:
    return ProblemSpec.from_dict(d, STATE, CONTROL, TARGET)


SELECTIVE = {
    "name": "selective",
    "objective": {"loss": "l2"},
    "constraints": [{"name": "near_origin", "loss": "l2", "eps": 0.035,
                     "region": {"norm": {"fields": ["x.p", "x.v"], "ord": "inf", "max": 0.5}}}],
}
NORMALIZED = {
    "name": "normalized",
    "objective": {"loss": "normalized", "region": {"norm": {"fields": ["next.p", "next.v"], "min": 0.1}}},
    "constraints": [{"name": "slow", "loss": "l2", "eps": 0.1,
                     "region": {"not": {"norm": {"fields": ["next.p", "next.v"], "min": 0.1}}}}],
}


@pytest.mark.parametrize(
    "bad, needle",
    [
        ({"objective": {"loss": "l2"}, "constraints": [{"eps": 0.1, "region": {"box": {"x.q": [0, 1]}}}]},
         "'x.q'"),
        ({"objective": {"loss": "l2", "fields": ["w"]}}, "'w'"),
        ({"objective": {"loss": "l2"}, "constraints": [{"eps": 0.0}]}, "eps"),
        ({"objective": {"loss": "l2"}, "constraints": [{"eps": -1}]}, "eps"),
        ({"objective": {"loss": "l2"}, "constraints": [{"loss": "l2"}]}, "eps: missing"),
        ({"objective": {"loss": "l3"}}, "unknown loss 'l3'"),
        ({"objective": {"loss": "l2", "mean": "sometimes"}}, "mean"),
        ({"objective": {"loss": "l2", "regoin": None}}, "unknown key(s) ['regoin']"),
        ({"objective": {"loss": "l2", "region": {"box": {"p": [0, 1]}}}}, "SOURCE.NAME"),
        ({"objective": {"loss": "l2", "region": {"box": {"y.p": [0, 1]}}}}, "unknown field source 'y'"),
        ({"objective": {"loss": "l2", "region": {"box": {"x.p": [1, 0]}}}}, "empty interval"),
        ({"objective": {"loss": "l2", "region": {"circle": {}}}}, "unknown region kind 'circle'"),
        ({"objective": {"loss": "l2", "region": {"norm": {"fields": ["x.p"], "ord": 3, "max": 1}}}}, "ord"),
        ({"objective": {"loss": "l2", "region": {"norm": {"fields": ["x.p"]}}}}, "min and/or max"),
        ({"objective": {"loss": "l2", "region": {"box": {"x.p": "__import__('os')"}}}}, "[lo, hi]"),
        ({"objective": {"loss": "l2", "region": {"box": {"x.p": [0, "1"]}}}}, "expected a number"),
        ({"constraints": []}, "missing 'objective'"),
        ({"objective": {"loss": "l2"}, "constraints": [{"name": "a", "eps": 1}, {"name": "a", "eps": 1}]},
         "duplicate"),
        ({"objective": {"loss": "l2"}, "constraints": [{"name": "a b", "eps": 1}]}, "name"),
        ("objective: l2", "expected a mapping"),
    ],
)
def test_validation_names_the_problem(bad: Any, needle: Any) -> None:
    with pytest.raises(SpecError) as e:
        compile_(bad)
    assert needle in str(e.value)


def test_paper_examples_compile_and_round_trip() -> None:
    for d in (SELECTIVE, NORMALIZED):
        s = compile_(d)
        again = compile_(s.to_dict())
        assert again.to_dict() == s.to_dict()
    s = compile_(SELECTIVE)
    assert s.constraint_names == ["near_origin"] and s.constraints[0].mean == "conditional"
    assert s.uniform().n_constraints == 0


def test_regions() -> None:
    s = compile_(SELECTIVE)
    x = torch.tensor([[0.1, 0.4], [0.6, 0.0], [-0.5, -0.5], [0.0, 0.51]])
    u = torch.zeros(4, 1)
    m = s.constraints[0].region.mask(x, u, x)
    assert m.tolist() == [True, False, True, False]
    comp = compile_({"objective": {"loss": "l2", "region": {"any_of": [
        {"box": {"x.p": [None, -0.2]}},
        {"all_of": [{"box": {"u.u": [0, None]}}, {"not": {"box": {"next.v": [0, 1]}}}]},
    ]}}})
    x = torch.tensor([[-0.3, 0.0], [0.0, 2.0], [0.0, 0.5], [0.0, 2.0]])
    u = torch.tensor([[0.0], [1.0], [1.0], [-1.0]])
    assert comp.objective.region.mask(x, u, x).tolist() == [True, True, False, False]


def test_losses_and_estimators() -> None:
    s = compile_({
        "objective": {"loss": "l1"},
        "constraints": [
            {"name": "c", "loss": "l2", "eps": 0.5, "mean": "conditional", "region": {"box": {"x.p": [0, None]}}},
            {"name": "u", "loss": "l2", "eps": 0.5, "mean": "unconditional", "region": {"box": {"x.p": [0, None]}}},
            {"name": "h", "loss": "huber", "huber_delta": 1.0, "eps": 1.0},
            {"name": "q", "loss": "squared_l2", "eps": 1.0},
            {"name": "n", "loss": "normalized", "eps": 1.0},
        ],
    })
    x = torch.tensor([[1.0, 0.0], [-1.0, 0.0]])
    u = torch.zeros(2, 1)
    y = torch.tensor([[3.0, 4.0], [0.0, 1.0]])
    pred = torch.tensor([[[0.0, 0.0], [0.0, 3.0]]])  # errors (3, 4) and (0, 2)
    v = s.evaluate(x, u, y, pred)
    assert v.objective.item() == pytest.approx((7 + 2) / 2)
    g = v.constraints[0].tolist()
    assert g[0] == pytest.approx(5.0 - 0.5)           # conditional: only sample 0 is in the region
    assert g[1] == pytest.approx(5.0 / 2 - 0.5)       # unconditional: E[l * I]
    assert g[2] == pytest.approx(((2.5 + 3.5) + 1.5) / 2 - 1.0)  # huber per field, summed
    assert g[3] == pytest.approx((25 + 4) / 2 - 1.0)
    assert g[4] == pytest.approx((5 / 5 + 2 / 1) / 2 - 1.0)
    assert v.region_fraction[0, 0].item() == pytest.approx(0.5)
    lam = torch.tensor([[1.0, 0, 0, 0, 0]])
    assert v.lagrangian(lam).item() == pytest.approx(4.5 + 4.5)


def test_conditional_constraint_with_empty_region_contributes_nothing() -> None:
    s = compile_(SELECTIVE)
    x = torch.full((3, 2), 2.0)
    pred = torch.zeros(1, 3, 2, requires_grad=True)
    v = s.evaluate(x, torch.zeros(3, 1), x, pred)
    assert v.constraints.item() == 0.0
    v.constraints.sum().backward()
    assert pred.grad is not None and torch.count_nonzero(pred.grad) == 0
    assert math.isfinite(v.objective.item())


def test_yaml_file_errors_name_the_file(tmp_path: Path) -> None:
    f = tmp_path / "spec.yaml"
    f.write_text("objective: {loss: l2}\nconstraints:\n  - {eps: 0.1, region: {box: {x.vx: [0, 1]}}}\n")

    class Sys:
        state, control, target = STATE, CONTROL, TARGET

    with pytest.raises(SpecError) as e:
        ProblemSpec.from_yaml(f, Sys())
    assert str(f) in str(e.value) and "'x.vx'" in str(e.value)
    f.write_text("objective: [unclosed\n")
    with pytest.raises(SpecError, match="not valid YAML"):
        ProblemSpec.from_yaml(f, Sys())


def test_shipped_spec_files_are_the_papers() -> None:

    from saml_ros.core.systems import SYSTEM_NAMES, get_system

    root = REPO / "config" / "specs"
    for name in SYSTEM_NAMES:
        system = get_system(name)
        spec = ProblemSpec.from_yaml(root / f"{name}.yaml", system)
        assert spec.to_dict() == ProblemSpec.for_system(system.paper_spec(), system).to_dict()
