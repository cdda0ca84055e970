"""``ros2 run saml_ros train`` / ``./dev train``: train a Sufficiently (or Uniformly) Accurate model offline.

Data comes from the system's paper sampling distribution (default) or from recorded bags (``--bag``).
Writes into ``--out``: ``ckpt-000001.saml`` + ``latest`` (usable by the MPC node), ``history.json``,
``training_curves.png`` and ``metrics.json`` (held-out evaluation per constraint region).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from saml_ros.core.checkpoint import CheckpointStore
from saml_ros.core.device import DeviceError, resolve_device
from saml_ros.core.model_evidence import DataEvidence
from saml_ros.core.spec import ProblemSpec, SpecError
from saml_ros.core.systems import get_entry, get_system, system_names
from saml_ros.core.training import TrainConfig, save_checkpoint
from saml_ros.core.training.config import DUAL_METHODS
from saml_ros.offline.pipelines import evaluate_models, generate_datasets, mean_std, train_models
from saml_ros.offline.plots import plot_training_curves


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="train",
        description="Train a residual (or full) dynamics model with the primal-dual method (Algorithm 1).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--system", choices=system_names())
    which.add_argument("--system-file", type=Path, help="a robot described by a system file (docs/your_robot.md); "
                       "its data comes from --bag")
    p.add_argument("--spec", type=Path, help="problem spec YAML (default: the paper's spec for the system)")
    p.add_argument("--uniform", action="store_true", help="drop the constraints: the Uniformly Accurate baseline")
    p.add_argument("--kind", choices=("residual", "full"), default="residual")
    p.add_argument("--hidden", type=int, nargs="+", help="hidden layer sizes (default: the paper's for the system)")
    p.add_argument("--samples", type=int, help="training transitions to generate (default: the paper's)")
    p.add_argument("--test-samples", type=int, default=10000, help="held-out transitions for metrics.json")
    p.add_argument("--noise", action="append", default=[], metavar="FIELD=SIGMA",
                   help="Gaussian noise on a target field of the training data, e.g. v=0.2 (repeatable)")
    p.add_argument("--bag", type=Path, nargs="+", help="train from recorded bags instead of generated data")
    p.add_argument("--epochs", type=int, help="epochs (default: the paper's for the system)")
    p.add_argument("--dual-method", choices=DUAL_METHODS, default=TrainConfig.dual_method,
                   help="how the multipliers move (docs/training.md); 'paper' is Algorithm 1 with the paper's "
                        "learning rates and constant schedules unless given here")
    p.add_argument("--batch-size", type=int, help=f"default {TrainConfig.batch_size}")
    p.add_argument("--primal-lr", type=float, help="default: the method's (TrainConfig / TrainConfig.paper())")
    p.add_argument("--dual-lr", type=float, help="default: the method's (TrainConfig / TrainConfig.paper())")
    p.add_argument("--primal-optimizer", choices=("adam", "sgd"))
    p.add_argument("--dual-optimizer", choices=("adam", "sgd"))
    p.add_argument("--train", action="append", default=[], metavar="FIELD=VALUE",
                   help="any other TrainConfig field, e.g. primal_schedule=cosine or nupi_kp=5 (repeatable)")
    p.add_argument("--restarts", type=int, default=1,
                   help="train this many initialisations per seed and keep the best feasible one on a held-out "
                        "split (docs/training.md)")
    p.add_argument("--holdout", type=float, default=0.2, help="fraction of each seed's data held out for --restarts")
    p.add_argument("--prelu-init", type=float, default=0.25,
                   help="initial PReLU slope of the first hidden layer (0.25: PyTorch's; -1: |h|, for sign-symmetric "
                        "residuals such as Coulomb friction; docs/training.md)")
    p.add_argument("--seed", type=int, default=0, help="first seed")
    p.add_argument("--seeds", type=int, default=1, help="train this many seeds at once (one ensemble)")
    p.add_argument("--out", type=Path, help="output run directory (default: runs/train-<system>-<time>)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--device", default="cpu", help="training device: cpu (default) | cuda | cuda:N; checked before "
                                                   "anything runs")
    return p


def _parse_noise(items: list[str]) -> dict[str, float]:
    out = {}
    for it in items:
        name, _, val = it.partition("=")
        try:
            out[name.strip()] = float(val)
        except ValueError:
            raise SystemExit(f"train: --noise expects FIELD=SIGMA, got {it!r}") from None
    return out


def train_config(args: argparse.Namespace, epochs: int) -> TrainConfig:
    """The training config of the command line: the method's defaults (:meth:`TrainConfig.paper` for ``paper``,
    else :class:`TrainConfig`'s), then the options given.

    Raises:
        ValueError: a bad ``--train FIELD=VALUE`` or value.
    """
    base = TrainConfig.paper() if args.dual_method == "paper" else TrainConfig()
    d: dict[str, Any] = {**base.__dict__, "epochs": epochs, "seed": args.seed, "dual_method": args.dual_method,
                         "device": args.device}
    for name in ("batch_size", "primal_lr", "dual_lr", "primal_optimizer", "dual_optimizer"):
        if getattr(args, name) is not None:
            d[name] = getattr(args, name)
    fields = TrainConfig.__dataclass_fields__
    for item in args.train:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or name not in fields:
            raise ValueError(f"--train expects FIELD=VALUE with FIELD one of {sorted(fields)}, got {item!r}")
        kind = type(getattr(base, name))
        d[name] = text.strip() if kind is str else kind(float(text)) if kind is int else kind(text)
    return TrainConfig.from_dict(d)


def load_spec(system: Any, path: Path | None, uniform: bool) -> ProblemSpec:
    spec = ProblemSpec.from_yaml(path, system) if path else ProblemSpec.for_system(system.paper_spec(), system)
    return spec.uniform() if uniform else spec


class _Refused(Exception):
    """A bad command line or input: printed as ``train: <message>``, exit status 2."""


def _load_system(args: argparse.Namespace) -> Any:
    """The system of ``--system`` or ``--system-file`` (a robot: registered, and it needs ``--bag``)."""
    if args.system_file is None:
        return get_system(args.system)
    from saml_ros.core.systems.system_file import SystemFileError
    from saml_ros.user_code import load_system_file

    try:
        system = load_system_file(args.system_file)  # registers the robot
    except SystemFileError as exc:
        raise _Refused(str(exc)) from None
    if not args.bag:
        raise _Refused(f"{system.name} comes from a system file and has no simulator in saml_ros: give its "
                       "recordings with --bag")
    if args.hidden is None:
        args.hidden = list(system.paper_hidden)
    return system


Arrays = tuple[np.ndarray, np.ndarray, np.ndarray]


def _training_data(args: argparse.Namespace, system: Any, seeds: list[int], n_train: int,
                   noise: dict[str, float]) -> tuple[Arrays, Arrays, str]:
    """``(train (x, u, y), held-out (x, u, y), description)``: from ``--bag`` (a fifth held out, shuffled with
    the seed) or generated from the paper's sampling distribution per seed."""
    if not args.bag:
        x, u, y = generate_datasets(system, n_train, seeds, noise)
        test = system.make_dataset(args.test_samples, np.random.default_rng(10_000 + args.seed), noise)
        return (x, u, y), test, f"{n_train} generated transitions per seed (paper sampling distribution)"
    from saml_ros.bags.transitions import transitions_from_bags

    try:
        x, u, y = transitions_from_bags(args.bag, system)
    except Exception as exc:  # bag errors carry a message naming the bag and the problem
        raise _Refused(str(exc)) from None
    source = f"{len(x)} transitions from {len(args.bag)} bag(s)"
    perm = np.random.default_rng(10_000 + args.seed).permutation(len(x))
    n_test = max(1, len(x) // 5) if len(x) >= 10 else 0
    test_idx, train_idx = perm[:n_test], perm[n_test:]
    if len(train_idx) < 2:
        raise _Refused(f"only {len(train_idx)} training transitions in the bag(s); need at least 2")
    return ((x[train_idx], u[train_idx], y[train_idx]), (x[test_idx], u[test_idx], y[test_idx]), source)


def _test_metrics(result: Any, spec: ProblemSpec, test: Arrays) -> tuple[dict[str, Any], Any]:
    """The held-out metrics of ``metrics.json`` and the evaluation they come from."""
    xt, ut, yt = test
    ev = evaluate_models(result.model, spec, xt, ut, yt)
    return {
        "n": int(len(xt)),
        "objective": ev.objective.tolist(),
        "constraints": dict(zip(spec.constraint_names, ev.constraints.T.tolist())),
        "regions": {r.name: {"inside": r.inside.tolist(), "outside": r.outside.tolist(),
                             "overall": r.overall.tolist(), "frac_inside": r.frac_inside}
                    for r in ev.regions},
    }, ev


def _print_summary(result: Any, metrics: dict[str, Any], ev: Any) -> None:
    """The run's closing lines: time, held-out errors per region, lambda, selection, feasibility verdicts."""
    print(f"train: done in {result.train_seconds:.1f} s ({result.trainer.steps} updates)")
    if ev is not None:
        print(f"train: held-out objective {mean_std(np.asarray(metrics['test']['objective']))}")
        for r in ev.regions:
            print(f"train: constraint '{r.name}': error inside {mean_std(r.inside)}, "
                  f"outside {mean_std(r.outside)} ({100 * r.frac_inside:.1f}% of test data inside)")
    print(f"train: lambda = {np.round(result.trainer.lam.double().numpy() + 0.0, 4).tolist()}")  # + 0.0: no "-0.0"
    if result.selection is not None:
        for line in result.selection.describe():
            print(f"train: {line}")
    for c in result.trainer.diagnosis.constraints:
        print(f"train: feasibility [{c.verdict}] {c.message}")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="[%(levelname)s] %(name)s: %(message)s")
    try:
        return _train(args)
    except _Refused as exc:
        print(f"train: {exc}", file=sys.stderr)
        return 2


def _train(args: argparse.Namespace) -> int:
    system = _load_system(args)
    try:
        resolve_device(args.device)
        spec = load_spec(system, args.spec, args.uniform)
        noise = _parse_noise(args.noise)
        for name in noise:
            system.target.index(name)
        entry = get_entry(system.name)  # the paper's dataset size and epochs
        epochs = args.epochs if args.epochs is not None else entry.paper_epochs
        config = train_config(args, epochs)
    except (SpecError, KeyError, OSError, DeviceError, ValueError) as exc:
        raise _Refused(str(exc)) from None
    n_train = args.samples or entry.paper_samples
    seeds = list(range(args.seed, args.seed + max(1, args.seeds)))
    out = args.out or Path("runs") / f"train-{system.name}-{time.strftime('%Y%m%d-%H%M%S')}"
    (x, u, y), test, source = _training_data(args, system, seeds, n_train, noise)

    print(f"train: {system.name}, {args.kind} model {list(args.hidden or system.paper_hidden)}, "
          f"spec '{spec.raw.get('name')}': {spec.describe()}")
    print(f"train: {source}; {epochs} epochs, batch {config.batch_size}, seeds {seeds}"
          + (f" x {args.restarts} restarts" if args.restarts > 1 else "") + f" -> {out}")
    print(f"train: dual method {config.dual_method}, schedules {config.schedule('primal')} / "
          f"{config.schedule('dual')}, lr {config.primal_lr:g} / {config.dual_lr:g}")
    torch.manual_seed(args.seed)
    try:
        result = train_models(system, spec, x, u, y, config, seeds, args.hidden, args.kind,
                              progress=not args.no_progress, desc=f"{system.name} {spec.raw.get('name')}",
                              restarts=args.restarts, holdout=args.holdout, prelu_init=args.prelu_init)
    except ValueError as exc:
        raise _Refused(str(exc)) from None
    metrics: dict[str, Any] = {"train_seconds": result.train_seconds, "n_train": result.n_train,
                               "prelu_init": args.prelu_init,
                               "updates": result.trainer.steps, "seeds": seeds, "source": source,
                               "train_config": dict(config.__dict__)}
    if result.selection is not None:
        metrics["selection"] = {"rule": "docs/training.md#restarts-and-selection", "restarts": args.restarts,
                                "chosen": result.selection.chosen, "feasible": result.selection.feasible,
                                "heldout_objective": result.selection.objective.tolist(),
                                "heldout_constraints": result.selection.constraints.tolist()}
    ev = None
    if len(test[0]):
        metrics["test"], ev = _test_metrics(result, spec, test)
    diag = result.trainer.diagnosis
    assert diag is not None
    metrics["feasibility"] = diag.to_dict()

    store = CheckpointStore(out)
    fx, fu, fy = (np.asarray(a).reshape(-1, np.shape(a)[-1]) for a in (x, u, y))  # every seed's data
    evidence = DataEvidence.from_data(system, fx, fu, fy, rng=np.random.default_rng(args.seed))
    ckpt, version = save_checkpoint(store, result.trainer, metrics=metrics, evidence=evidence)
    (out / "history.json").write_text(json.dumps(result.history.to_dict()))
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    (out / "spec.yaml").write_text(yaml.safe_dump(spec.to_dict(), sort_keys=False))
    fig = plot_training_curves({spec.raw.get("name", "run"): result.history}, out / "training_curves.png",
                               title=f"{system.name}: {spec.describe()}")
    _print_summary(result, metrics, ev)
    print(f"train: checkpoint {ckpt} (version {version}); curves {fig}; metrics {out / 'metrics.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
