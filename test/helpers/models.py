"""Models and checkpoints the model-acceptance, model-in-use, guard, demo and MPC-node tests share: residual
quadrotor models near f_hat (optionally biased), the evidence of their training data, checkpoints of them (optionally
poisoned), models that are f_hat except beyond a trap, and the online learner's checkpoint after hovering only."""

from __future__ import annotations

import fcntl
from pathlib import Path

import numpy as np
import torch

from saml_ros.core.model.checkpoint import CheckpointStore, read_checkpoint
from saml_ros.core.model.evidence import DataEvidence
from saml_ros.core.model.network import DynamicsModel
from saml_ros.core.mpc import make_controller
from saml_ros.core.online import OnlineConfig, OnlineLearner
from saml_ros.core.spec import ProblemSpec
from saml_ros.core.systems import get_system
from saml_ros.core.training import PrimalDualTrainer, TrainConfig, checkpoint_payload
from saml_ros.demo.landing import LandingTask, plant
from saml_ros.systems.quadrotor.model import Quadrotor

_QUAD = get_system("quadrotor")
assert isinstance(_QUAD, Quadrotor)
QUAD: Quadrotor = _QUAD
#: the demo's landing task
TASK = LandingTask()


def quad_model(seed: int = 0, bias: dict[str, float] | None = None,
               hidden: tuple[int, ...] | None = None) -> DynamicsModel:
    """A residual quadrotor model close to f_hat (tiny random output weights), with an output ``bias`` (in the
    target's units, per field) added everywhere."""
    x, u, y = QUAD.make_dataset(500, np.random.default_rng(seed))
    model = DynamicsModel(QUAD, hidden, seed=seed)
    model.fit_normalization(x, u, y)
    with torch.no_grad():
        model.net.weights[-1].normal_(0.0, 1e-3, generator=torch.Generator().manual_seed(seed))
        for field, value in (bias or {}).items():
            j = QUAD.target.index(field)
            model.net.biases[-1][0, 0, j] = value / float(model.out_std[0, 0, j])
    return model


def quad_evidence(seed: int = 0, **box: float) -> DataEvidence:
    """The evidence of 3000 transitions of the paper's distribution, limited to ``|field| <= limit`` per ``box``."""
    x, u, y = QUAD.make_dataset(3000, np.random.default_rng(100 + seed))
    for field, limit in box.items():  # training data limited to |field| <= limit
        keep = np.abs(x[:, QUAD.state.index(field)]) <= limit
        x, u, y = x[keep], u[keep], y[keep]
    ev = DataEvidence.from_data(QUAD, x, u, y, np.random.default_rng(seed))
    assert ev is not None
    return ev


def save_quad_checkpoint(store: CheckpointStore, model: DynamicsModel, evidence: DataEvidence | None,
                         poison: str | None = None) -> tuple[Path, int]:
    """A checkpoint of ``model`` (with the training data's ``evidence``); ``poison`` names model arrays to fill
    with NaN, as a broken or hostile writer would (saml_ros's own writers refuse to)."""
    trainer = PrimalDualTrainer(model, ProblemSpec.for_system(QUAD.paper_spec(), QUAD), TrainConfig())
    arrays, meta = checkpoint_payload(trainer, evidence=evidence)
    if poison:
        for k in arrays:
            if k.startswith("model/") and poison in k:
                arrays[k] = np.full_like(arrays[k], np.nan)
    return store.save(arrays, meta)


def trap_model(system_name: str, field: str, above: float, weight: float, dtype: torch.dtype) -> DynamicsModel:
    """A residual model equal to f_hat except where state ``field`` exceeds ``above``: there one PReLU unit switches
    on and its output ``weight`` drives every predicted target field to ``weight * (field - above)``."""
    system = get_system(system_name)
    model = DynamicsModel(system, hidden=(4,), seed=0).to(dtype)
    with torch.no_grad():
        for p in model.net.parameters():
            p.zero_()
        model.net.weights[0][0, system.state.index(field), 0] = 1.0  # the input is not normalised (mean 0, std 1)
        model.net.biases[0][0, 0, 0] = -above
        model.net.weights[1][0, 0, :] = weight
    return model


def hover_only_checkpoint(tmp_path: Path, z: float = 0.5, updates: int = 1500, n_models: int = 5) -> Path:
    """The online learner (an ``n_models``-member SA ensemble) fed only hovering at ``z`` m (motor noise 0.3 N):
    its checkpoint, the next version in ``tmp_path / "hover"``.

    The learner runs once per test run and argument set (up to a minute of training under load), in a folder every
    pytest-xdist worker of the run shares (next to the workers' temporary folders, removed with them); later calls
    save that checkpoint's arrays and metadata as the next version of their own store, as the learner would."""
    root = tmp_path.parent.parent if tmp_path.parent.name.startswith("popen-gw") else tmp_path.parent
    cache = root / "hover_only_checkpoints" / f"z{z:g}-updates{updates}-models{n_models}"
    cache.mkdir(parents=True, exist_ok=True)
    with open(cache.parent / f"{cache.name}.lock", "wb") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # one worker trains, the others wait for its checkpoint
        if CheckpointStore(cache).latest() is None:
            _train_hover_only(cache, _hover_data(cache.parent, z), updates, n_models)
    arrays, meta = read_checkpoint(CheckpointStore(cache).path_for(1))
    return CheckpointStore(tmp_path / "hover").save(arrays, {k: v for k, v in meta.items()
                                                             if k not in ("version", "time")})[0]


def _hover_data(root: Path, z: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The hovering flights at ``z`` m (``x, u, next x``), flown once per test run into ``root`` (the learners of
    every argument set train on them: 600 MPC solves, about 2.5 CPU-s each time otherwise)."""
    path = root / f"hover-data-z{z:g}.npz"
    with open(root / f"{path.name}.lock", "wb") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not path.exists():
            tmp = path.with_suffix(".tmp.npz")
            np.savez(tmp, *_fly_hover(z))
            tmp.rename(path)
    with np.load(path) as data:
        return data["arr_0"], data["arr_1"], data["arr_2"]


def _fly_hover(z: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """20 flights of 30 steps hovering at ``z`` m from random (x, y), motor noise 0.3 N: ``x, u, next x``."""
    f = plant(QUAD, TASK.landing_height)
    rng = np.random.default_rng(0)
    ctrl = make_controller(QUAD, None, **TASK.mpc_options())
    xs, us, ys = [], [], []
    for _ in range(20):
        p = np.array([rng.uniform(-2, 2), rng.uniform(-2, 2), z])
        x = QUAD.hover_state(p.tolist())
        ctrl.reset()
        for _ in range(30):
            u = np.clip(ctrl.solve(x, p).u + rng.normal(0, 0.3, 4), 0.0, 10.0)
            xn = f(x, u)
            xs.append(x)
            us.append(u)
            ys.append(xn)
            x = xn
    return np.array(xs), np.array(us), np.array(ys)


def _train_hover_only(run_dir: Path, data: tuple[np.ndarray, np.ndarray, np.ndarray], updates: int,
                      n_models: int) -> Path:
    """:func:`hover_only_checkpoint`'s training on the hovering ``data``: its checkpoint, version 1 of ``run_dir``."""
    spec = ProblemSpec.for_system(QUAD.paper_spec(), QUAD)
    store = CheckpointStore(run_dir)
    learner = OnlineLearner(QUAD, spec, OnlineConfig(train=TrainConfig(batch_size=128), min_transitions=200,
                                                     n_models=n_models), store=store, resume=False)
    learner.add_batch(*data)
    learner.update(updates)
    saved = learner.save_checkpoint()
    assert saved is not None
    return saved[0]
