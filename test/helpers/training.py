"""Small training problems on the friction system and the comparison of two training runs, shared by the tests
of the fast engine (test_fast_train.py) and of the fused kernel (test_fused_kernel.py)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from saml_ros.core.systems import get_system
from saml_ros.core.training import PrimalDualTrainer

FRICTION = get_system("friction")
NEAR = {"norm": {"fields": ["x.p", "x.v"], "ord": "inf", "max": 0.5}}
FAST_V = {"box": {"x.v": [1.0, None]}}


def spec_dict(objective: dict[str, Any], *constraints: dict[str, Any]) -> dict[str, Any]:
    return {"name": "t", "objective": objective, "constraints": list(constraints)}


SPECS = {
    "paper": FRICTION.paper_spec(),
    "uniform": spec_dict({"loss": "l2"}),
    "unconditional": spec_dict({"loss": "l2"}, {"name": "c", "loss": "l2", "eps": 0.002, "region": NEAR,
                                             "mean": "unconditional"}),
    "squared_l2": spec_dict({"loss": "squared_l2"}, {"name": "c", "loss": "squared_l2", "eps": 1e-3, "region": NEAR}),
    "huber_l1_fields": spec_dict({"loss": "huber", "huber_delta": 0.05, "fields": ["v"]},
                             {"name": "c", "loss": "l1", "eps": 0.02, "region": NEAR, "fields": ["v"]}),
    # objective region + normalized loss, like the paddle ball's spec
    "normalized": spec_dict({"loss": "normalized", "region": {"not": NEAR}},
                        {"name": "c", "loss": "l2", "eps": 0.05, "region": NEAR}),
    # three groups, the l2 group's terms are not contiguous (columns 0 and 2); one region is often empty
    "mixed": spec_dict({"loss": "l2"}, {"name": "a", "loss": "l1", "eps": 0.05, "region": NEAR},
                   {"name": "b", "loss": "l2", "eps": 0.03, "region": FAST_V, "mean": "unconditional"},
                   {"name": "c", "loss": "squared_l2", "eps": 1e-3,
                    "region": {"box": {"x.p": [1.9, None], "x.v": [2.4, None]}}}),
}


def friction_data(n: int, seeds: list[int] | None, noise: float = 0.0) -> tuple[np.ndarray, ...]:
    noise_d = {"v": noise} if noise else None
    if seeds is None:
        return FRICTION.make_dataset(n, np.random.default_rng(0), noise_d)
    parts = [FRICTION.make_dataset(n, np.random.default_rng(s), noise_d) for s in seeds]
    return tuple(np.stack([p[i] for p in parts]) for i in range(3))


def assert_same_run(plain: PrimalDualTrainer, fast: PrimalDualTrainer, rtol: float, atol: float) -> None:
    assert plain.engine_used == "plain" and fast.engine_used == "fast"
    assert plain.steps == fast.steps and plain.epochs_done == fast.epochs_done
    torch.testing.assert_close(plain.rng.get_state(), fast.rng.get_state(), rtol=0, atol=0)
    for (name, a), b in zip(plain.model.named_parameters(), fast.model.parameters()):
        torch.testing.assert_close(b, a, rtol=rtol, atol=atol, msg=lambda m, n=name: f"{n}: {m}")  # type: ignore[misc]
    torch.testing.assert_close(fast.lam, plain.lam, rtol=rtol, atol=atol)
    for opt_p, opt_f in ((plain.primal_opt, fast.primal_opt), (plain.dual.optimizer, fast.dual.optimizer)):
        sp, sf = opt_p.state_dict()["state"], opt_f.state_dict()["state"]
        assert sp.keys() == sf.keys()
        for k in sp:
            for key in sp[k]:
                torch.testing.assert_close(sf[k][key], sp[k][key], rtol=rtol, atol=atol * 1e-2)
    hp, hf = plain.history.as_arrays(), fast.history.as_arrays()
    assert plain.history.step == fast.history.step and plain.history.epoch == fast.history.epoch
    for key in ("objective", "constraints", "lambdas", "lagrangian"):
        np.testing.assert_allclose(hf[key], hp[key], rtol=rtol, atol=atol, err_msg=key)


#: every dual method with parameters that make its arithmetic matter within a short run
METHODS: dict[str, dict[str, Any]] = {
    "lagrangian": {"dual_method": "lagrangian"},
    "nupi": {"dual_method": "nupi", "dual_lr": 0.05, "nupi_kp": 5.0, "nupi_ema": 0.3},
    "augmented": {"dual_method": "augmented", "penalty": 0.5},
    "augmented_adam_named": {"dual_method": "augmented", "penalty": 0.05, "dual_optimizer": "adam", "dual_lr": 0.05},
    "resilient": {"dual_method": "resilient", "relax_cost": 2.0},
    "resilient_sgd": {"dual_method": "resilient", "relax_cost": 2.0, "dual_optimizer": "sgd", "dual_lr": 1.0},
}
