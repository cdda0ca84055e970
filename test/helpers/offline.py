"""Small offline set-ups the sweep and training-verdict tests share (in process and through the commands)."""

from __future__ import annotations

from saml_ros.offline.sweep import SweepSetup

#: the base of a small sweep
SMALL = {"samples": 1000, "epochs": 3, "seed": 0}


def sweep_setup(**kw: object) -> SweepSetup:
    """A small friction sweep (1000 samples, 3 epochs), with ``kw`` replaced."""
    base: dict[str, object] = {"system": "friction", "spec": None, "base": SMALL, "test_samples": 1000}
    base.update(kw)
    return SweepSetup(**base)  # type: ignore[arg-type]


#: a wide region (about half of the paper's sampling distribution) and a bound a 4-2 net meets in a few epochs
WIDE = {"name": "wide", "objective": {"loss": "l2", "fields": ["p", "v"]},
        "constraints": [{"name": "wide", "loss": "l2", "fields": ["p", "v"], "eps": 0.12, "mean": "conditional",
                         "region": {"norm": {"fields": ["x.p", "x.v"], "ord": "inf", "max": 1.5}}}]}
