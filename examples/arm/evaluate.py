"""Evaluate learned models of a robot on a held-out recording: one-step error inside and outside each constraint's
region, with standard errors.

    ./dev python examples/arm/evaluate.py --system-file examples/arm/system.yaml --bag runs/arm_heldout \\
        --model online=runs/arm --model offline=runs/arm_offline [--applied-effort] [--json results.json]

The held-out bag must be a flight the models never trained on (another seed, another time). Its messages are
paired with the learner's own rule (``saml_ros.bags.transitions.extract_transitions``); each model predicts every
transition's next state and its error is the spec's loss (``l2`` over the spec's fields for the example). The
base model f_hat alone is always evaluated first. Consecutive transitions at 100 Hz are strongly correlated, so
the standard error of a mean is computed from blocks of ``--block`` seconds of flight (the cluster-robust
standard error of a ratio estimator), not from the transitions as if they were independent.

By default the held-out transitions are the ones the learner's pairing rule forms from the recording. With
``--applied-effort`` (the arm) they come from the state messages alone: the arm's driver reports in
``joint_states.effort`` the torque it applied over the period that message ends, so each pair of consecutive
joint states with that torque is an exactly known transition, whatever the pairing of the command topic does;
the learner's pairing of the same recording is then checked against it (paired commands that differ from the
applied torque are mis-paired). Only transitions inside the system file's operating envelope (x, u and the next
state within their bounds) are evaluated unless ``--all-transitions``; the others are counted. User code named
in the system file (the arm's ``arm_model.py``) is imported from the system file's folder.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch


@dataclass
class Stat:
    """Mean of a per-transition loss over a set of transitions, its standard error and size."""

    mean: float
    se: float
    n: int
    blocks: int

    def __str__(self) -> str:
        if self.n == 0:
            return "-"
        return f"{self.mean:.5f} +- {self.se:.5f} (n={self.n})"


def block_stat(loss: np.ndarray, mask: np.ndarray, block_id: np.ndarray) -> Stat:
    """Mean of ``loss[mask]`` and its standard error over the blocks ``block_id`` (cluster-robust: the ratio
    estimator sum(loss) / count linearised over blocks; NaN with fewer than 2 blocks)."""
    n = int(mask.sum())
    if n == 0:
        return Stat(math.nan, math.nan, 0, 0)
    ids, inv = np.unique(block_id[mask], return_inverse=True)
    sums = np.bincount(inv, weights=loss[mask])
    counts = np.bincount(inv).astype(np.float64)
    mean = float(sums.sum() / counts.sum())
    b = len(ids)
    if b < 2:
        return Stat(mean, math.nan, n, b)
    resid = sums - mean * counts
    se = math.sqrt(b / (b - 1) * float((resid**2).sum())) / float(counts.sum())
    return Stat(mean, se, n, b)


def load_models(specs: list[str]) -> list[tuple[str, Any]]:
    """``NAME=PATH`` (a checkpoint or run directory) -> ``[(name, saml_ros.api.Model)]``."""
    from saml_ros.api import load_model

    out = []
    for text in specs:
        name, sep, path = text.partition("=")
        if not sep:
            name, path = Path(text).name, text
        out.append((name, load_model(path)))
    return out


@dataclass
class Transitions:
    """Transitions ``x (N, n_x)``, ``u (N, n_u)``, ``y (N, n_x)`` with the stamp of ``x`` (ns) and their source."""

    x: np.ndarray
    u: np.ndarray
    y: np.ndarray
    stamps: np.ndarray
    source: np.ndarray


def applied_transitions(bags: list[Path], system: Any) -> tuple[Transitions, dict[int, tuple[int, np.ndarray]]]:
    """Transitions from the state messages alone, for a robot that reports the command it applied in them: every
    two consecutive state messages ``dt`` apart (x_k, x_k+1) with ``u_k`` = the ``effort`` array of the later
    message (the torque applied over that period, in the order of the command's fields). Also returns
    ``{stamp of x_k: (bag index, u_k)}`` for checking the learner's pairing against it."""
    from saml_ros.bags.io import Bag
    from saml_ros.bags.transitions import schema_of

    codec = schema_of(system).state
    suffix = "/" + str(system.definition["state"]["topic"]).lstrip("/")
    dt_ns = round(system.dt * 1e9)
    xs, us, ys, stamps, src = [], [], [], [], []
    truth: dict[int, tuple[int, np.ndarray]] = {}
    for b, path in enumerate(bags):
        prev: tuple[int, np.ndarray] | None = None
        with Bag(path) as bag:
            for msg in bag.messages([t for t in bag.topics if t.endswith(suffix)]):
                m = bag.decode(msg)
                try:
                    x, stamp = codec.from_msg(m, msg.topic)
                except Exception:  # noqa: BLE001 - a malformed message ends the chain, like a lost one
                    prev = None
                    continue
                effort = np.asarray(m.effort, dtype=np.float64)
                if prev is not None and abs(stamp - prev[0] - dt_ns) <= 1000 and effort.shape == (system.control.size,):
                    xs.append(prev[1])
                    us.append(effort)
                    ys.append(x)
                    stamps.append(prev[0])
                    src.append(b)
                    truth[prev[0]] = (b, effort)
                prev = (stamp, x)
    n_x, n_u = system.state.size, system.control.size
    out = Transitions(np.array(xs).reshape(-1, n_x), np.array(us).reshape(-1, n_u), np.array(ys).reshape(-1, n_x),
                      np.array(stamps, dtype=np.int64), np.array(src, dtype=np.int64))
    return out, truth


def pairing_check(data: Any, truth: dict[int, tuple[int, np.ndarray]], tol: float = 1e-6) -> dict[str, int]:
    """The learner's paired commands against the applied ones: checked / mis-paired / without a reading."""
    checked = mispaired = unchecked = 0
    for stamp, src, u in zip(data.stamps, data.source, data.u):
        applied = truth.get(int(stamp))
        if applied is None or applied[0] != int(src):
            unchecked += 1
            continue
        checked += 1
        mispaired += int(np.max(np.abs(applied[1] - u)) > tol)
    return {"checked": checked, "mispaired": mispaired, "unchecked": unchecked}


def evaluate(system_file: Path, bags: list[Path], models: list[str], block: float = 1.0,
             applied_effort: bool = False, within_bounds: bool = True) -> dict[str, Any]:
    """Everything the script prints, as a dict (see the module docstring)."""
    sys.path.insert(0, str(system_file.resolve().parent))  # the system file's own code (its base model)
    from saml_ros.bags.transitions import extract_transitions
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.user_code import load_system_file

    system = load_system_file(system_file)
    paired = extract_transitions(bags, system)  # the learner's own pairing rule
    result: dict[str, Any] = {"system": system.name, "bags": [str(b) for b in bags], "block_s": block,
                              "counts": paired.counts, "constraints": {},
                              "transitions_from": "applied effort" if applied_effort else "the learner's pairing"}
    data: Any = paired
    if applied_effort:
        data, truth = applied_transitions(bags, system)
        result["pairing_check"] = pairing_check(paired, truth)
    if within_bounds:  # the file's operating envelope: x, u and the next state inside their bounds
        lo_x, hi_x, lo_u, hi_u = system.state_low, system.state_high, system.control_low, system.control_high
        keep = np.all((data.x >= lo_x) & (data.x <= hi_x) & (data.y >= lo_x) & (data.y <= hi_x), axis=1) & \
            np.all((data.u >= lo_u - 1e-9) & (data.u <= hi_u + 1e-9), axis=1)
        result["outside_bounds"] = int((~keep).sum())
        data = Transitions(data.x[keep], data.u[keep], data.y[keep], data.stamps[keep], data.source[keep])
    result["transitions"] = len(data.x)
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    x, u, y = (torch.as_tensor(a, dtype=torch.float64) for a in (data.x, data.u, data.y))
    block_id = data.source * 1_000_000 + (data.stamps - int(data.stamps.min())) // round(block * 1e9)
    with torch.no_grad():
        preds: list[tuple[str, np.ndarray]] = [("f_hat", system.base_model(x, u).double().numpy())]
    for name, model in load_models(models):
        if tuple(model.state_fields) != tuple(system.state.names) or \
                tuple(model.control_fields) != tuple(system.control.names):
            raise SystemExit(f"evaluate: model {name!r} ({model.path}) has fields {model.state_fields} / "
                             f"{model.control_fields}, the system file {system.state.names} / {system.control.names}")
        preds.append((name, model.predict(data.x, data.u)))
    result["models"] = [n for n, _ in preds]
    for term, mask_t in zip(spec.constraints, spec.masks(x, u, y)[1:]):
        mask = np.ones(len(data.x), bool) if mask_t is None else mask_t.numpy().astype(bool)
        rows = {}
        for name, pred in preds:
            loss = term.per_sample(torch.as_tensor(pred), y).numpy()
            rows[name] = {"in": asdict(block_stat(loss, mask, block_id)),
                          "out": asdict(block_stat(loss, ~mask, block_id)),
                          "all": asdict(block_stat(loss, np.ones_like(mask), block_id))}
        result["constraints"][term.name] = {"eps": term.eps, "loss": term.loss, "rows": rows}
    return result


def format_table(result: dict[str, Any]) -> str:
    """The result as markdown tables, one per constraint."""
    lines = [f"{result['system']}: {result['transitions']} held-out transitions from {', '.join(result['bags'])} "
             f"(from {result['transitions_from']}; standard errors over {result['block_s']:g} s blocks)"]
    if "outside_bounds" in result:
        lines.append(f"{result['outside_bounds']} transitions outside the system file's bounds not evaluated")
    c = result["counts"]
    keys = ("intervals", "paired", "gap", "no_cmd", "stale_cmd", "ambiguous_cmd", "mixed_cmd", "late")
    lines.append("the learner's pairing of this recording: " + ", ".join(f"{k} {c.get(k, 0)}" for k in keys))
    if "pairing_check" in result:
        a = result["pairing_check"]
        lines.append(f"its paired commands against the applied effort: {a['checked']} checked, {a['mispaired']} "
                     f"mis-paired, {a['unchecked']} without an effort reading")
    for cname, cons in result["constraints"].items():
        lines += ["", f"| model (one-step {cons['loss']} error) | inside '{cname}' (eps {cons['eps']:g}) | outside |",
                  "|---|---|---|"]
        for name, row in cons["rows"].items():
            lines.append(f"| {name} | {Stat(**row['in'])} | {Stat(**row['out'])} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--system-file", required=True, type=Path)
    ap.add_argument("--bag", required=True, nargs="+", type=Path, help="held-out recording(s)")
    ap.add_argument("--model", action="append", default=[], metavar="NAME=PATH",
                    help="a checkpoint or run directory to evaluate (repeatable); f_hat is always evaluated")
    ap.add_argument("--block", type=float, default=1.0, help="seconds of flight per block of the standard errors")
    ap.add_argument("--applied-effort", action="store_true",
                    help="held-out transitions from consecutive state messages and the effort the robot reports having "
                         "applied (and the learner's pairing checked against it)")
    ap.add_argument("--all-transitions", action="store_true",
                    help="also evaluate transitions outside the system file's bounds (by default only those with "
                         "x, u and the next state inside the operating envelope are)")
    ap.add_argument("--json", type=Path, help="also write the results to this file")
    args = ap.parse_args(argv)
    if not args.block > 0:
        ap.error("--block must be > 0")
    result = evaluate(args.system_file, args.bag, args.model, args.block, args.applied_effort,
                      not args.all_transitions)
    print(format_table(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
