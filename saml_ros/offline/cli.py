"""``ros2 run saml_ros train`` / ``./dev train``: train a Sufficiently (or Uniformly) Accurate model offline.

Data comes from the system's paper sampling distribution (default) or from recorded bags (``--bag``).
Writes into ``--out``: ``ckpt-000001.saml`` + ``latest`` (usable by the MPC node), ``history.json``,
``training_curves.png`` and ``metrics.json`` (held-out evaluation per constraint region, and the verdict on each
constraint read on held-out data: docs/training.md#held-out-verdicts).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from saml_ros.core.model.checkpoint import CheckpointStore
from saml_ros.core.model.evidence import DataEvidence
from saml_ros.core.runtime.device import DeviceError, check_device
from saml_ros.core.spec import ProblemSpec, SpecError
from saml_ros.core.systems import get_entry, get_system, system_names
from saml_ros.core.training.config import DUAL_METHODS, TrainConfig, parse_margin

if TYPE_CHECKING:  # torch, the trainer and matplotlib are imported once the data is read (a refused run needs none)
    from saml_ros.core.training.verdict import Verdicts
    from saml_ros.offline.pipelines import TrainedModels


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
    p.add_argument("--test-samples", type=int,
                   help="held-out transitions (freshly generated) for the verdicts and metrics.json (default: 10x "
                        "--samples, at least 10000; with --bag the held-out data are stretches of the recordings)")
    p.add_argument("--margin", default=None,
                   help="what training aims at below each eps: 'auto' (sized by the standard errors measured half-way "
                        "through the run, docs/training.md#the-margin), a fraction of eps (e.g. 0.1), or 'none'; "
                        "default auto, none for --dual-method paper")
    p.add_argument("--require-met", action="store_true",
                   help="exit with status 1 unless every constraint is met on the held-out data")
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
    p.add_argument("--holdout", type=float, default=0.2,
                   help="with --restarts and --bag: the fraction of the training recordings (whole stretches of "
                        "time) held out to select on; generated data select on fresh data (--test-samples of them)")
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
    from saml_ros.systems.system_file import SystemFileError
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


@dataclass
class Data:
    """The data of a run: ``train`` (``(E, N, .)`` generated per seed, or ``(N, .)`` from bags in time order),
    ``test`` (the held-out data the verdicts are read on), ``select`` (restarts select on it; None: no restarts),
    ``stream`` (recordings: batch-means standard errors), ``source`` and ``heldout`` (what they are, in words)."""

    train: Arrays
    test: Arrays
    select: Arrays | None
    stream: bool
    source: str
    heldout: str


def _take(a: Arrays, idx: np.ndarray) -> Arrays:
    return (a[0][idx], a[1][idx], a[2][idx])


def _training_data(args: argparse.Namespace, system: Any, seeds: list[int], n_train: int,
                   noise: dict[str, float]) -> Data:
    """Generated: ``n_train`` transitions per seed from the paper's sampling distribution; the verdicts' held-out
    set and the restarts' selection set are fresh draws (``--test-samples`` each, default 10x ``n_train``, at least
    10000). ``--bag``: a fifth of every recording is held out for the verdicts in two whole stretches of time
    (:func:`~saml_ros.offline.pipelines.stretch_split`), and with ``--restarts`` ``--holdout`` of the rest, also in
    stretches, to select on."""
    if not args.bag:
        n_test = args.test_samples if args.test_samples is not None else max(10_000, 10 * n_train)
        if n_test < 1:
            raise _Refused(f"--test-samples must be >= 1, got {n_test}")
        from saml_ros.offline.pipelines import generate_datasets

        x, u, y = generate_datasets(system, n_train, seeds, noise)
        test = system.make_dataset(n_test, np.random.default_rng(10_000 + args.seed), noise)
        select = (system.make_dataset(n_test, np.random.default_rng(20_000 + args.seed), noise)
                  if args.restarts > 1 else None)
        return Data((x, u, y), test, select, False,
                    f"{n_train} generated transitions per seed (paper sampling distribution)",
                    f"{n_test} fresh transitions (paper sampling distribution)")
    from saml_ros.bags.transitions import extract_transitions

    try:
        bt = extract_transitions(args.bag, system)
    except Exception as exc:  # bag errors carry a message naming the bag and the problem
        raise _Refused(str(exc)) from None
    from saml_ros.offline.pipelines import stretch_split

    everything = (bt.x, bt.u, bt.y)
    source = f"{len(bt)} transitions from {len(args.bag)} bag(s)"
    if not 0 < args.holdout < 1:
        raise _Refused(f"--holdout must be in (0, 1), got {args.holdout}")
    if len(bt) >= 10:
        kept, held = stretch_split(bt.stamps, bt.source, 0.2)
    else:  # too few to hold any out: trained on all of it, no held-out verdict
        kept, held = np.arange(len(bt)), np.zeros(0, dtype=np.int64)
    select = None
    if args.restarts > 1:
        fit, sel = stretch_split(bt.stamps[kept], bt.source[kept], args.holdout)
        select, kept = _take(everything, kept[sel]), kept[fit]
    if len(kept) < 2:
        raise _Refused(f"only {len(kept)} training transitions in the bag(s); need at least 2")
    n_src = len(np.unique(bt.source))
    heldout = (f"{len(held)} transitions of the recordings never trained on (two whole stretches of time per bag "
               f"and namespace, {n_src} of them; a fifth of the data)" if len(held) else
               f"none: {len(bt)} transitions are too few to hold any out")
    return Data(_take(everything, kept), _take(everything, held), select, True, source, heldout)


def _test_metrics(result: Any, spec: ProblemSpec, test: Arrays) -> tuple[dict[str, Any], Any]:
    """The held-out metrics of ``metrics.json`` and the evaluation they come from."""
    from saml_ros.offline.pipelines import evaluate_models

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


def heldout_verdicts(result: TrainedModels, spec: ProblemSpec, test: Arrays, stream: bool,
                     description: str) -> Verdicts:
    """The verdict on every constraint of ``result``'s members, read on ``test`` (:mod:`saml_ros.core.training.
    verdict`), with the training values, the aim and the training's convergence diagnosis beside it."""
    from saml_ros.core.training import Transitions
    from saml_ros.core.training.verdict import read_verdicts, spec_estimates

    held = None
    if len(test[0]):
        _, held = spec_estimates(result.model, spec, Transitions(result.model, spec, *test), stream)
    assert result.training is not None
    return read_verdicts(spec, held, result.training, result.aimed, result.trainer.diagnosis, description)


def _print_summary(result: Any, metrics: dict[str, Any], ev: Any, verdicts: Verdicts) -> None:
    """The run's closing lines: time, held-out errors per region, lambda, selection, the verdict per constraint."""
    from saml_ros.offline.pipelines import mean_std

    print(f"train: done in {result.train_seconds:.1f} s ({result.trainer.steps} updates)")
    if result.aim is not None:
        print(f"train: {result.aim.describe()}")
    if ev is not None:
        print(f"train: held-out objective {mean_std(np.asarray(metrics['test']['objective']))}")
        for r in ev.regions:
            print(f"train: constraint '{r.name}': error inside {mean_std(r.inside)}, "
                  f"outside {mean_std(r.outside)} ({100 * r.frac_inside:.1f}% of test data inside)")
    print(f"train: lambda = {np.round(result.trainer.lam.double().numpy() + 0.0, 4).tolist()}")  # + 0.0: no "-0.0"
    if result.selection is not None:
        for line in result.selection.describe():
            print(f"train: {line}")
    print(f"train: held-out data: {verdicts.heldout}")
    for c in verdicts.constraints:
        print(f"train: verdict [{c.verdict}] {c.message}")
        if c.verdict != "met" and c.convergence_message:
            print(f"train:   training diagnosis [{c.convergence}] (against the aim): {c.convergence_message}")
    level = ("OK", "WARN", "ERROR")[verdicts.level]
    n_met = sum(c.verdict == "met" for c in verdicts.constraints)
    print(f"train: {n_met}/{len(verdicts.constraints)} constraints met on held-out data (level {level})")


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
        check_device(args.device)
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
    try:
        margin = parse_margin(args.margin if args.margin is not None else
                              ("none" if config.dual_method == "paper" else "auto"))
    except ValueError as exc:
        raise _Refused(str(exc)) from None
    data = _training_data(args, system, seeds, n_train, noise)
    import torch

    from saml_ros.core.training import save_checkpoint
    from saml_ros.offline.pipelines import train_models
    from saml_ros.offline.plots import plot_training_curves

    (x, u, y), test, source = data.train, data.test, data.source
    held_in = [len(test[0]) if m is None else int(m.sum())  # samples in each constraint's region, held out
               for m in spec.masks(*(torch.as_tensor(a, dtype=torch.float64) for a in test))[1:]]

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
                              restarts=args.restarts, holdout=args.holdout, prelu_init=args.prelu_init,
                              margin=margin, heldout_n=held_in, stream=data.stream, select=data.select)
    except ValueError as exc:
        raise _Refused(str(exc)) from None
    metrics: dict[str, Any] = {"train_seconds": result.train_seconds, "n_train": result.n_train,
                               "prelu_init": args.prelu_init,
                               "updates": result.trainer.steps, "seeds": seeds, "source": source,
                               "train_config": dict(config.__dict__)}
    if result.selection is not None:
        metrics["selection"] = {"rule": "docs/training.md#restarts-and-selection", "restarts": args.restarts,
                                "n": int(len(data.select[0])) if data.select is not None else None,
                                **result.selection.to_dict()}
    ev = None
    if len(test[0]):
        metrics["test"], ev = _test_metrics(result, spec, test)
    diag = result.trainer.diagnosis
    assert diag is not None
    verdicts = heldout_verdicts(result, spec, test, data.stream, data.heldout)
    metrics["verdict"] = verdicts.to_dict()
    metrics["aim"] = result.aim.to_dict() if result.aim is not None else {"margin": "none"}
    metrics["feasibility"] = diag.to_dict()  # the training's convergence diagnosis, against the aim

    store = CheckpointStore(out)
    fx, fu, fy = (np.asarray(a).reshape(-1, np.shape(a)[-1]) for a in (x, u, y))  # every seed's data
    evidence = DataEvidence.from_data(system, fx, fu, fy, rng=np.random.default_rng(args.seed))
    ckpt, version = save_checkpoint(store, result.trainer, metrics=metrics, evidence=evidence,
                                    extra={"heldout_verdict": metrics["verdict"], "aim": metrics["aim"]})
    (out / "history.json").write_text(json.dumps(result.history.to_dict()))
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    (out / "spec.yaml").write_text(yaml.safe_dump(spec.to_dict(), sort_keys=False))
    marks = ({"aimed below eps from here (g against the aim)": result.aim.epoch}
             if result.aim is not None and result.aim.margin == "auto" else None)
    fig = plot_training_curves({spec.raw.get("name", "run"): result.history}, out / "training_curves.png",
                               title=f"{system.name}: {spec.describe()}", marks=marks)
    _print_summary(result, metrics, ev, verdicts)
    print(f"train: checkpoint {ckpt} (version {version}); curves {fig}; metrics {out / 'metrics.json'}")
    return 1 if args.require_met and not verdicts.all_met else 0


if __name__ == "__main__":
    raise SystemExit(main())
