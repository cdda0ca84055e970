"""A demo run's paired evaluation re-flown with other live-monitor margins on the same checkpoints (docs/mpc.md,
"The margin scales with the robot"):

    ./dev python scripts/demo_margins.py runs/<demo run> 0.02 0.05 0.08 abs:0.01

Each argument after the run directory is a ``guard.margin_relative`` (or ``abs:X``: ``guard.margin`` X with no
relative part); the rest of the MPC's configuration is the run's ``bringup.yaml``. Prints the demo's evaluation and
checks for each.
"""

from __future__ import annotations

import sys
from pathlib import Path

import yaml


def main(argv: list[str]) -> int:
    from saml_ros.demo.cli import checks, format_evaluation, run_evaluation

    if len(argv) < 2:
        print(__doc__)
        return 2
    run = Path(argv[0])
    for setting in argv[1:]:
        config = yaml.safe_load((run / "bringup.yaml").read_text())
        absolute = setting.startswith("abs:")
        value = float(setting[4:] if absolute else setting)
        config["mpc"]["guard.margin"] = value if absolute else 0.0
        config["mpc"]["guard.margin_relative"] = 0.0 if absolute else value
        ev = run_evaluation(run, config, 30, 10, 0)
        if ev is None:
            print(f"{run}: no SA checkpoint")
            return 1
        print(f"== {'guard.margin' if absolute else 'guard.margin_relative'} {value:g}")
        print(format_evaluation(ev))
        print("\n".join(checks(ev)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
