"""The learner node's configuration without ROS: its parameter table and the validated :class:`LearnerConfig`.

The node declares :func:`learner_params` (names, defaults, descriptions; ``train.*`` are the fields of
:class:`~saml_ros.core.training.TrainConfig`) and builds the configuration with :meth:`LearnerConfig.from_params`,
which raises ``ValueError`` naming the bad parameter; :meth:`LearnerConfig.training_setup` turns it into what
the training process is started with. See docs/learner.md.

Importing this module imports no torch: the learner node imports it before its training interpreter has started
(the functions that need the trainer or a system import them when called).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, get_args

from msg_schemas.names import join_topic, normalize_namespace
from saml_ros.core.errors import SamlError
from saml_ros.core.params import LIVE, Param, Problems, memory_problems, read_params

if TYPE_CHECKING:
    from msg_schemas.base import QosSpec, SystemSchema
    from saml_ros.core.data.plausibility import Plausibility
    from saml_ros.core.dynamics.system import System
    from saml_ros.core.online import LearnerSetup, LoopConfig, TrainingProcess
    from saml_ros.core.online.process import DecoderFactory
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.training import TrainConfig
    from saml_ros.core.training.config import HealthConfig

class TrainingStartError(SamlError, ValueError):
    """The learner's training process could not be set up or started as configured
    (:meth:`LearnerConfig.start_training`); the message says which setting, run directory or start-up failed."""


#: one subscription of the learner: namespace, kind (state, applied_cmd, target), topic, message type
Channel = tuple[str, str, str, str]
#: ``train.*`` parameters: TrainConfig field -> description (``epochs`` is an offline-only field)
TRAIN_PARAM_DOCS: dict[str, str] = {
    "batch_size": "minibatch size M sampled from the replay buffer per update",
    "primal_lr": "learning rate alpha_theta of the model parameters",
    "dual_lr": "learning rate alpha_lambda of the dual variables (ascent on the constraint estimates; not used by "
               "'augmented', whose step is its penalty)",
    "primal_optimizer": "'adam' (the paper) or 'sgd'",
    "dual_optimizer": "'adam' (the paper) or 'sgd'",
    "log_every": "updates between training-history rows kept in memory (0 = 100)",
    "seed": "seed of the model initialisation and the minibatch sampling",
    "dtype": "'float32' or 'float64' for the model and the minibatches",
    "engine": "offline training engine (not used by the online step loop)",
    "dual_method": "how the multipliers move: 'paper' (Algorithm 1), 'lagrangian' (the same with cosine rates: the "
                   "default), 'nupi' (PI controller), 'augmented' (augmented Lagrangian method: lambda <- relu(lambda "
                   "+ rho g)) or 'resilient' (constraints relaxed at a price); docs/training.md",
    "nupi_kp": "nupi: proportional gain K_P (integral gain 1, step train.dual_lr, error g / eps)",
    "nupi_ema": "nupi: smoothing nu of the error signal, in [0, 1)",
    "penalty": "augmented: penalty c (objective units); rho_k = c / eps_k, the penalty's weight and lambda's step",
    "relax_cost": "resilient: price alpha (dimensionless): relaxing eps by a fraction r costs alpha r^2 / 2 times "
                  "the objective",
    "primal_schedule": "learning-rate schedule of the model: 'auto', 'constant', 'step' or 'cosine' (online, 'auto' "
                       "is constant unless train.schedule_steps > 0)",
    "dual_schedule": "learning-rate schedule of the multipliers (as train.primal_schedule)",
    "schedule_steps": "horizon T of the step / cosine schedules in updates (online: needed for either; 0 = none)",
    "lr_gamma": "step schedule: factor of each drop, in (0, 1]",
    "lr_drops": "step schedule: number of evenly spaced drops over the horizon",
    "lr_floor": "cosine schedule: final learning rate as a fraction of the first, in [0, 1]",
    "device": "training device: cpu | cuda | cuda:N (checked at start-up; a device that cannot be used is a "
              "configuration error)",
}

_HEAD: tuple[Param, ...] = (
    Param("system", "friction", "system name: friction | quadrotor | paddle_ball (set from system_file when given)"),
    Param("system_file", "", "a robot described by a system file (YAML, docs/your_robot.md): its own topics, field "
                             "paths, units, base model and spec; empty = the registered 'system'"),
    Param("namespaces", [], "namespaces whose state/applied_cmd are paired (each separately, one shared buffer); "
                            "empty = this node's namespace", item_type=str),
    Param("spec_file", "", "problem spec YAML (docs/spec.md); empty = the paper's spec"),
    Param("model.kind", "residual", "'residual' (f_hat + network) or 'full' (network only)"),
    Param("model.hidden", [], "hidden layer sizes; empty = the paper's sizes for the system", item_type=int),
    Param("model.ensemble", 1, "ensemble members trained side by side (own initialisation and minibatches, one "
                               "buffer); > 1 lets the MPC's guard use their disagreement (guard.max_disagreement)"),
    Param("uniform", False, "train the Uniformly Accurate baseline: the spec's objective without its constraints"),
)
_TAIL: tuple[Param, ...] = (
    Param("buffer.capacity", 100_000, "replay buffer capacity (transitions)"),
    Param("buffer.policy", "fifo", "eviction when full: 'fifo' (keep the newest) or 'reservoir'"),
    Param("min_transitions", 1000, "training transitions before training starts; the input/output normalisation is "
                                   "fitted on them (and refitted when the data drifts, normalization.refit)"),
    Param("normalization.refit", True, "refit the input/output normalisation on the replay buffer when a spread grew "
                                       "by more than a factor 2 or a centre moved by more than one spread, keeping "
                                       "the model's function; false: fitted once on the first min_transitions and "
                                       "frozen"),
    Param("heldout.period", 10.0, "s of stream time per held-out cycle: the last heldout.fraction of every cycle "
                                  "is held out (never trained on) and the verdicts are read on it"),
    Param("heldout.fraction", 0.2, "share of every heldout.period held out, in [0, 0.5]; 0 = none (no held-out "
                                   "verdict)"),
    Param("heldout.capacity", 25_000, "held-out transitions kept (the newest)"),
    Param("heldout.eval_period", 1.0, "s (wall clock) between two evaluations on the held-out stretches (telemetry, "
                                      "/diagnostics); every checkpoint is evaluated when written"),
    Param("average_updates", 1000.0, "time constant (updates) of an exponential average of the weights kept beside "
                                     "the trainer's; the one that does better on the held-out stretches is published "
                                     "in checkpoints (0 = no average: the trainer's weights)"),
    Param("updates_per_transition", 0.0, "at most this many primal-dual updates per training transition received "
                                         "since training started (0 = no limit): training waits for new data "
                                         "instead of memorising the buffer"),
    Param("updates_per_second", 0.0, "primal-dual updates per wall-clock second (0 = as fast as possible)",
          when=LIVE),
    Param("checkpoint_period", 10.0, "wall-clock seconds between checkpoints (only when there are new updates)",
          when=LIVE),
    Param("checkpoint_keep", 5, "checkpoint files kept in run_dir (older ones are pruned)"),
    Param("run_dir", "", "checkpoint directory; empty = runs/<system> in the working directory"),
    Param("resume", True, "load the newest valid checkpoint of run_dir (weights, normalisation, lambda, optimizer "
                          "state, update count)"),
    Param("telemetry_rate", 5.0, "learner/model_error messages per second (Hz)", when=LIVE),
    Param("telemetry_window", 1000, "most recent transitions the live model error is computed on"),
    Param("diagnostics_rate", 1.0, "/diagnostics messages per second (Hz)", when=LIVE),
    Param("dt", 0.0, "sampling period of the simulator / robot in s (0 = the system's default); pairs x_t with "
                     "x_{t+dt} and sets the base model's step"),
    Param("pairing.window", 1000, "newest states (per namespace) whose stamps are remembered for pairing; older "
                                  "incomplete entries are dropped (counted)"),
    Param("pairing.tolerance", 1e-6, "s: stamps closer than this are the same stamp"),
    Param("pairing.refuse_multiple_publishers", False,
          "refuse (count, do not pair) a namespace's messages while its state or command topic has more than one "
          "publisher (two robots in one namespace); off: paired, and only named on /diagnostics (WARN)"),
    Param("training_niceness", 10, "nice increment of the training process (0-19): the OS runs ingest, simulators "
                                   "and the MPC first when CPUs are short"),
    Param("training_idle", False, "run the training process under Linux's SCHED_IDLE policy: it gets only CPU time "
                                  "no other process wants, so the control loop (simulator, MPC), ingest and any "
                                  "other work always go first and a waking controller never waits for it; "
                                  "stronger than any training_niceness (ignored then)"),
    Param("train_threads", 1, "torch intra-op threads of the training process (0 = torch's default, one per "
                              "core); 1 is fastest for these small networks on a shared machine"),
    Param("plausible_bounds", "", "overrides of the system's plausible ranges as a YAML mapping, e.g. "
                                  "'{x.pz: [-1.0, 2000.0], u.f1: [0.0, 40.0]}' (fields x.<state>, u.<control>, "
                                  "next.<target>; .inf = open); messages outside are rejected (rejected/bounds)"),
    Param("health.explode_ratio", 1e4, "a minibatch objective or gradient norm this many times its running mean "
                                       "is exploding: the training step is skipped"),
    Param("health.max_weight", 1e6, "a network weight or multiplier larger than this after an update is exploding: "
                                    "the last healthy state is restored"),
    Param("health.error_after", 100, "consecutive skipped training steps from which /diagnostics reports ERROR "
                                     "(WARN once any step was skipped)"),
)


def learner_params() -> list[Param]:
    """The learner node's parameter table, in declaration order (imports the trainer for ``train.*``)."""
    from saml_ros.core.training import TrainConfig

    defaults = TrainConfig()
    train = [Param(f"train.{f.name}", getattr(defaults, f.name), TRAIN_PARAM_DOCS.get(f.name, f"TrainConfig.{f.name}"))
             for f in dataclasses.fields(TrainConfig) if f.name != "epochs"]
    return [*_HEAD, *train, *_TAIL]


def _from(param: str) -> dict[str, Any]:
    """The metadata of a configuration field holding the value of the parameter ``param`` (read by
    :meth:`LearnerConfig._build`)."""
    return {"param": param}


def _part(cls: type) -> dict[str, Any]:
    """The metadata of a configuration field holding a part (``cls``, whose fields are each :func:`_from` a
    parameter)."""
    return {"part": cls}


@dataclass(frozen=True)
class ModelSettings:
    """``model.*``: the network (``kind`` 'residual' or 'full', ``hidden`` sizes, empty = the paper's; ``ensemble``
    members)."""

    kind: str = field(metadata=_from("model.kind"))
    hidden: list[int] = field(metadata=_from("model.hidden"))
    ensemble: int = field(metadata=_from("model.ensemble"))


@dataclass(frozen=True)
class BufferSettings:
    """``buffer.*``: the replay buffer's ``capacity`` (transitions) and eviction ``policy``."""

    capacity: int = field(metadata=_from("buffer.capacity"))
    policy: str = field(metadata=_from("buffer.policy"))


@dataclass(frozen=True)
class PairingSettings:
    """``pairing.*``: states remembered for pairing (``window``), the stamp ``tolerance`` (s) and whether a topic
    with several publishers is refused (``refuse_multiple_publishers``)."""

    window: int = field(metadata=_from("pairing.window"))
    tolerance: float = field(metadata=_from("pairing.tolerance"))
    refuse_multiple_publishers: bool = field(metadata=_from("pairing.refuse_multiple_publishers"))


@dataclass(frozen=True)
class CheckpointSettings:
    """Where and how often checkpoints are written: ``period`` (s, ``checkpoint_period``), files kept (``keep``,
    ``checkpoint_keep``), the directory (``run_dir``, empty = runs/<system>) and ``resume``."""

    period: float = field(metadata=_from("checkpoint_period"))
    keep: int = field(metadata=_from("checkpoint_keep"))
    run_dir: str = field(metadata=_from("run_dir"))
    resume: bool = field(metadata=_from("resume"))


@dataclass(frozen=True)
class TelemetrySettings:
    """What the node reports: ``learner/model_error`` per second (``rate``, Hz, ``telemetry_rate``) on the newest
    ``window`` transitions (``telemetry_window``), and ``/diagnostics`` per second (``diagnostics_rate``, Hz)."""

    rate: float = field(metadata=_from("telemetry_rate"))
    window: int = field(metadata=_from("telemetry_window"))
    diagnostics_rate: float = field(metadata=_from("diagnostics_rate"))


@dataclass(frozen=True)
class HealthSettings:
    """``health.*``: the limits of :class:`~saml_ros.core.training.health.HealthConfig` a user sets
    (:meth:`LearnerConfig.health_config`)."""

    explode_ratio: float = field(metadata=_from("health.explode_ratio"))
    max_weight: float = field(metadata=_from("health.max_weight"))
    error_after: int = field(metadata=_from("health.error_after"))


@dataclass(frozen=True)
class HeldoutSettings:
    """``heldout.*``: the held-out stretches of the stream (``period`` s, ``fraction``, ``capacity`` transitions)
    and the wall-clock seconds between two evaluations on them (``eval_period``)."""

    period: float = field(metadata=_from("heldout.period"))
    fraction: float = field(metadata=_from("heldout.fraction"))
    capacity: int = field(metadata=_from("heldout.capacity"))
    eval_period: float = field(metadata=_from("heldout.eval_period"))


@dataclass(frozen=True)
class ProcessSettings:
    """How the training process runs: its nice increment (``niceness``, ``training_niceness``), ``SCHED_IDLE``
    (``idle``, ``training_idle``) and torch intra-op ``threads`` (``train_threads``)."""

    niceness: int = field(metadata=_from("training_niceness"))
    idle: bool = field(metadata=_from("training_idle"))
    threads: int = field(metadata=_from("train_threads"))


def param_fields() -> dict[str, tuple[str | None, str]]:
    """Where each parameter of :func:`learner_params` but ``train.*`` lives in :class:`LearnerConfig`: ``{name:
    (part, field)}``, ``part`` None for a field of the configuration itself (``"checkpoint_period": ("checkpoint",
    "period")``, ``"system": (None, "system")``)."""
    out: dict[str, tuple[str | None, str]] = {}
    for f in dataclasses.fields(LearnerConfig):
        if "part" in f.metadata:
            out.update({g.metadata["param"]: (f.name, g.name) for g in dataclasses.fields(f.metadata["part"])})
        elif "param" in f.metadata:
            out[f.metadata["param"]] = (None, f.name)
    return out


@dataclass(frozen=True)
class LearnerConfig:
    """The learner node's parameters after validation (units in :func:`learner_params`' descriptions), in parts.

    Every field but ``train`` holds one parameter's value or is a part of several (:func:`param_fields` says
    which); ``namespaces`` are normalised (``/name``) and never empty; ``train`` holds the ``train.*`` values by
    TrainConfig field name. Built only from parameter values (:meth:`from_params`, :meth:`validated`), changed by
    parameter name (:meth:`with_params`).
    """

    system: str = field(metadata=_from("system"))
    system_file: str = field(metadata=_from("system_file"))
    namespaces: list[str] = field(metadata=_from("namespaces"))
    spec_file: str = field(metadata=_from("spec_file"))
    uniform: bool = field(metadata=_from("uniform"))
    model: ModelSettings = field(metadata=_part(ModelSettings))
    train: dict[str, Any] = field()
    buffer: BufferSettings = field(metadata=_part(BufferSettings))
    min_transitions: int = field(metadata=_from("min_transitions"))
    normalization_refit: bool = field(metadata=_from("normalization.refit"))
    heldout: HeldoutSettings = field(metadata=_part(HeldoutSettings))
    average_updates: float = field(metadata=_from("average_updates"))
    updates_per_transition: float = field(metadata=_from("updates_per_transition"))
    updates_per_second: float = field(metadata=_from("updates_per_second"))
    checkpoint: CheckpointSettings = field(metadata=_part(CheckpointSettings))
    telemetry: TelemetrySettings = field(metadata=_part(TelemetrySettings))
    dt: float = field(metadata=_from("dt"))
    pairing: PairingSettings = field(metadata=_part(PairingSettings))
    process: ProcessSettings = field(metadata=_part(ProcessSettings))
    plausible_bounds: str = field(metadata=_from("plausible_bounds"))
    health: HealthSettings = field(metadata=_part(HealthSettings))

    @classmethod
    def _build(cls, p: Mapping[str, Any]) -> LearnerConfig:
        """The configuration of checked parameter values ``p`` by name (every parameter of :func:`learner_params`):
        the one place where parameters become fields."""
        kwargs: dict[str, Any] = {"train": {k[len("train."):]: v for k, v in p.items() if k.startswith("train.")}}
        for f in dataclasses.fields(cls):
            if "part" in f.metadata:
                part = f.metadata["part"]
                kwargs[f.name] = part(**{g.name: p[g.metadata["param"]] for g in dataclasses.fields(part)})
            elif "param" in f.metadata:
                kwargs[f.name] = p[f.metadata["param"]]
        return cls(**kwargs)

    def with_params(self, values: Mapping[str, Any]) -> LearnerConfig:
        """This configuration with the parameters ``values`` (by name, already checked) changed: a running
        node's live parameters."""
        where = param_fields()
        flat: dict[str, Any] = {}
        parts: dict[str, Any] = {}
        for name, value in values.items():
            if name.startswith("train."):
                flat["train"] = {**flat.get("train", self.train), name[len("train."):]: value}
                continue
            part, attr = where[name]
            if part is None:
                flat[attr] = value
            else:
                parts[part] = dataclasses.replace(parts.get(part, getattr(self, part)), **{attr: value})
        return dataclasses.replace(self, **flat, **parts)

    @classmethod
    def from_params(cls, values: Mapping[str, Any], node_namespace: str = "/") -> LearnerConfig:
        """The configuration from parameter values by name (missing ones take their defaults); an empty
        ``namespaces`` means the node's own namespace ``node_namespace``.

        Raises:
            ParamErrors (a ValueError): an unknown system or parameter, values of the wrong type or out of range; every bad
                parameter is named.
        """
        problems = Problems()
        config = cls._read(values, node_namespace, problems)
        problems.raise_if_any()
        return config

    @classmethod
    def validated(cls, values: Mapping[str, Any], node_namespace: str = "/",
                  load_file: Callable[[str], str] | None = None) -> tuple[LearnerConfig, System, ProblemSpec]:
        """Every check of the parameter values the learner node makes at configure before it starts training:
        :meth:`from_params`, :meth:`make_system`, :meth:`load_spec`, :meth:`plausibility` and the memory the
        buffer, the minibatches and the telemetry window need (:meth:`memory_needs`). ``load_file(path)``: the
        system name of a ``system_file`` (the node loads the file; the core imports no user code).

        Raises:
            ParamErrors: every problem found, each naming its parameter.
        """
        problems = Problems()
        values = dict(values)
        if values.get("system_file") and load_file is not None:
            with problems.capture("system_file", "system"):
                values["system"] = load_file(str(values["system_file"]))
        config = cls._read(values, node_namespace, problems)
        system: Any = None
        spec: Any = None
        if not problems.has("system", "dt"):
            with problems.capture("system", "dt"):
                system = config.make_system()
        if system is not None:
            with problems.capture("spec_file"):
                spec = config.load_spec(system)
            with problems.capture("plausible_bounds"):
                config.plausibility(system)
            if not problems.has("buffer.capacity", "train.batch_size", "model.ensemble", "model.hidden",
                                "telemetry_window", "train.dtype", "heldout.capacity"):
                for message in memory_problems(config.memory_needs(system)):
                    problems.add(message)
        problems.raise_if_any()
        return config, system, spec

    @classmethod
    def _read(cls, values: Mapping[str, Any], node_namespace: str, problems: Problems) -> LearnerConfig:
        """:meth:`from_params`, its problems recorded in ``problems`` (a bad value is replaced by its default)."""
        from saml_ros.core.data.buffer import Policy
        from saml_ros.core.model.inputs import MODEL_KINDS
        from saml_ros.core.systems.registry import get_entry

        check = problems.check
        table = learner_params()
        unknown = sorted(set(values) - {p.name for p in table})
        if unknown:
            problems.add(f"unknown learner parameter(s) {unknown}", *unknown)
        p = read_params(table, values, problems)
        with problems.capture("system", prefix="parameter 'system': "):
            get_entry(p["system"])
        for name in ("telemetry_rate", "diagnostics_rate", "checkpoint_period"):
            check(p[name] > 0, name, "> 0", p[name])
        for name in ("updates_per_second", "dt", "pairing.tolerance", "train_threads"):
            check(p[name] >= 0, name, ">= 0", p[name])
        check(p["checkpoint_keep"] >= 1, "checkpoint_keep", ">= 1", p["checkpoint_keep"])
        check(p["pairing.window"] >= 2, "pairing.window", ">= 2", p["pairing.window"])
        check(1 <= p["model.ensemble"] <= 64, "model.ensemble", "in 1..64", p["model.ensemble"])
        check(0 <= p["training_niceness"] <= 19, "training_niceness", "in 0..19", p["training_niceness"])
        # what the training process's OnlineConfig refuses, named here as parameters
        check(p["model.kind"] in MODEL_KINDS, "model.kind", f"one of {list(MODEL_KINDS)}", p["model.kind"])
        check(all(h >= 1 for h in p["model.hidden"]), "model.hidden", "a list of sizes >= 1", p["model.hidden"])
        policies = list(get_args(Policy))
        check(p["buffer.policy"] in policies, "buffer.policy", f"one of {policies}", p["buffer.policy"])
        check(p["min_transitions"] >= 2, "min_transitions", ">= 2 (the normalisation needs a spread)",
              p["min_transitions"])
        check(p["buffer.capacity"] >= p["min_transitions"], "buffer.capacity",
              f">= min_transitions ({p['min_transitions']})", p["buffer.capacity"])
        check(p["telemetry_window"] >= 1, "telemetry_window", ">= 1", p["telemetry_window"])
        for name in ("heldout.period", "heldout.eval_period"):
            check(math.isfinite(p[name]) and p[name] > 0, name, "> 0 s", p[name])
        check(0 <= p["heldout.fraction"] <= 0.5, "heldout.fraction", "in [0, 0.5]", p["heldout.fraction"])
        check(p["heldout.capacity"] >= 1, "heldout.capacity", ">= 1", p["heldout.capacity"])
        check(math.isfinite(p["average_updates"]) and p["average_updates"] >= 0, "average_updates",
              ">= 0 (0 = no average)", p["average_updates"])
        check(math.isfinite(p["updates_per_transition"]) and p["updates_per_transition"] >= 0,
              "updates_per_transition", ">= 0 (0 = no limit)", p["updates_per_transition"])
        nss = [normalize_namespace(n) for n in p["namespaces"]] or [normalize_namespace(node_namespace)]
        check(len(set(nss)) == len(nss), "namespaces", "a list without repetitions", nss)
        config = cls._build({**p, "namespaces": nss, "model.hidden": list(p["model.hidden"])})
        if p["system_file"]:
            check(p["dt"] == 0, "dt", "0 with system_file (a robot's period is the file's 'dt')", p["dt"])
        with problems.capture(*(n for n in p if n.startswith("train."))):
            config.train_config()  # validates train.*
        with problems.capture("health.explode_ratio", "health.max_weight", "health.error_after"):
            config.health_config()
        return config

    def memory_needs(self, system: System) -> list[tuple[str, str, int]]:
        """``(parameter, what, bytes)`` of the learner's allocations that grow with a parameter (lower bounds):
        the replay buffer (``buffer.capacity`` rows of x, u, y, stamp, source, sequence in float64 / int64), the
        minibatches of one update (``train.batch_size`` x ``model.ensemble`` rows, drawn in float64 and converted,
        with the network's activations and their gradients) and the telemetry window."""
        width = system.state.size + system.control.size + system.target.size
        hidden = sum(self.model.hidden or system.paper_hidden)
        itemsize = 8 if self.train.get("dtype") == "float64" else 4
        batch = int(self.train.get("batch_size", 1))
        return [
            ("buffer.capacity", f"a replay buffer of {self.buffer.capacity} transitions",
             self.buffer.capacity * (width + 3) * 8),
            ("train.batch_size", f"minibatches of {batch} transitions x {self.model.ensemble} ensemble member(s)",
             batch * self.model.ensemble * (width * (8 + itemsize) + 3 * hidden * itemsize)),
            ("telemetry_window", f"a window of {self.telemetry.window} transitions",
             self.telemetry.window * width * 8),
            ("heldout.capacity", f"a held-out set of {self.heldout.capacity} transitions",
             self.heldout.capacity * (width + 3) * 8),
        ]

    def loop_config(self) -> LoopConfig:
        """The training loop's pacing (``updates_per_second``, ``telemetry_rate``, ``checkpoint_period``: the
        parameters a running learner applies at once, :meth:`TrainingProcess.set_loop
        <saml_ros.core.online.TrainingProcess.set_loop>`)."""
        from saml_ros.core.online import LoopConfig

        return LoopConfig(updates_per_second=self.updates_per_second, telemetry_rate=self.telemetry.rate,
                          checkpoint_period=self.checkpoint.period)

    def health_config(self) -> HealthConfig:
        """The :class:`~saml_ros.core.training.health.HealthConfig` of ``health.*``; ``ValueError`` naming them."""
        from saml_ros.core.training.config import HealthConfig

        problems = Problems()
        check = problems.check
        check(self.health.explode_ratio > 1, "health.explode_ratio", "> 1", self.health.explode_ratio)
        check(self.health.max_weight > 0, "health.max_weight", "> 0", self.health.max_weight)
        check(self.health.error_after >= 1, "health.error_after", ">= 1", self.health.error_after)
        problems.raise_if_any()
        return HealthConfig(explode_ratio=self.health.explode_ratio, max_weight=self.health.max_weight,
                            error_after=self.health.error_after)

    def plausibility(self, system: System) -> Plausibility:
        """The system's plausible ranges with ``plausible_bounds``; ``ValueError`` naming the parameter."""
        from saml_ros.core.data.plausibility import Plausibility

        try:
            return Plausibility.for_system(system, self.plausible_bounds)
        except (ValueError, TypeError) as exc:
            raise ValueError(f"parameter 'plausible_bounds': {exc}") from None

    def train_config(self) -> TrainConfig:
        """The :class:`~saml_ros.core.training.TrainConfig` of ``train.*``; :class:`ParamErrors` naming every field
        TrainConfig refuses on its own (``parameter 'train.<field>': ...``), else ``ValueError`` about their
        combination (``parameters 'train.*': ...``)."""
        from saml_ros.core.training import TrainConfig
        from saml_ros.core.training.schedule import schedules_for

        defaults = TrainConfig()
        problems = Problems()
        for name, value in self.train.items():  # each field alone: TrainConfig reports only its first problem
            if name in TrainConfig.__dataclass_fields__ and value != getattr(defaults, name):
                with problems.capture(f"train.{name}", prefix=f"parameter 'train.{name}': "):
                    TrainConfig.from_dict({name: value})
        problems.raise_if_any()
        try:
            config = TrainConfig.from_dict(self.train)
            schedules_for(config, 0)  # online: a step / cosine schedule needs train.schedule_steps
        except (ValueError, TypeError) as exc:
            raise ValueError(f"parameters 'train.*': {exc}") from None
        return config

    def make_system(self) -> System:
        """The system, with ``dt`` when it is set (> 0); ``ValueError`` naming ``system`` / ``dt``."""
        from saml_ros.core.systems.registry import get_entry

        try:
            return get_entry(self.system).make_system(**({"dt": self.dt} if self.dt > 0 else {}))
        except (ValueError, TypeError) as exc:
            raise ValueError(f"parameter 'system' / 'dt': {exc}") from None

    def load_spec(self, system: System) -> ProblemSpec:
        """``spec_file``'s problem, or the system's paper spec when it is empty, without its constraints when
        ``uniform``; ``ValueError`` naming ``spec_file``."""
        from saml_ros.core.spec import ProblemSpec, SpecError

        try:
            if self.spec_file:
                spec = ProblemSpec.from_yaml(self.spec_file, system)
            else:
                spec = ProblemSpec.for_system(system.paper_spec(), system)
            return spec.uniform() if self.uniform else spec
        except FileNotFoundError:
            raise ValueError(f"parameter 'spec_file': no such file {self.spec_file!r}") from None
        except (SpecError, OSError) as exc:
            raise ValueError(f"parameter 'spec_file': {exc}") from None

    def channels(self, schema: SystemSchema) -> list[Channel]:
        """One :data:`Channel` per (namespace, kind) the learner subscribes: ``state``, ``applied_cmd`` and, where
        the schema pairs the target with the state of the same stamp (paddle ball), ``target``."""
        kinds = [("state", schema.state_topic, schema.state.msg_type),
                 ("applied_cmd", schema.applied_cmd_topic, schema.control.msg_type)]
        if schema.target_pairing == "same":
            kinds.append(("target", schema.target_topic, schema.target.msg_type))
        return [(ns, kind, join_topic(ns, name), msg_type) for ns in self.namespaces for kind, name, msg_type in kinds]

    def channel_traits(self, schema: SystemSchema) -> tuple[list[bool], list[QosSpec]]:
        """Per :meth:`channels` entry: whether its messages carry no header (a robot's ``cmd_vel``: stamped on
        receipt) and the topic's QoS (a robot's system file may make it best effort)."""
        kinds = {"state": (schema.state_topic, schema.state), "applied_cmd": (schema.applied_cmd_topic, schema.control),
                 "target": (schema.target_topic, schema.target)}
        chans = self.channels(schema)
        unstamped = [getattr(kinds[kind][1], "stamped", True) is False for _, kind, _, _ in chans]
        return unstamped, [schema.topic(kinds[kind][0]).qos for _, kind, _, _ in chans]

    def start_training(self, system: System, spec: ProblemSpec, schema: SystemSchema, run_dir: str,
                       decoder: DecoderFactory, *, paused: bool = False, launched: Any = None,
                       cancelled: Callable[[], bool] | None = None, **callbacks: Any) -> TrainingProcess:
        """The training process of :meth:`training_setup` for ``schema``'s :meth:`channels`, started (``paused``:
        not training until ``resume()``; ``launched``: a pre-started interpreter; ``cancelled``: give up the start
        when it returns True, see :meth:`~saml_ros.core.online.TrainingProcess.start`; ``callbacks``: the
        ``on_*`` arguments of :class:`~saml_ros.core.online.TrainingProcess`).

        Raises:
            TrainingStartError: an invalid setting, a run directory whose checkpoints contradict the
                configuration, or a training process that could not start; the message says which.
            StartCancelled: ``cancelled()`` became true while the training process started.
        """
        from saml_ros.core.online import ResumeError, TrainingProcess

        channels = [(self.namespaces.index(ns), kind, topic) for ns, kind, topic, _ in self.channels(schema)]
        try:
            setup = self.training_setup(system, spec, schema.target_pairing, run_dir, channels, decoder)
        except ValueError as exc:
            raise TrainingStartError(str(exc)) from None
        trainer = TrainingProcess(dataclasses.replace(setup, paused=paused), **callbacks)
        try:
            trainer.start(launched=launched, cancelled=cancelled)
        except ResumeError as exc:
            raise TrainingStartError(str(exc)) from None
        except RuntimeError as exc:
            raise TrainingStartError(f"the training process could not start: {exc}") from None
        return trainer

    def training_setup(self, system: System, spec: ProblemSpec, target_pairing: str, run_dir: str,
                       channels: list[tuple[int, str, str]], decoder: DecoderFactory) -> LearnerSetup:
        """The :class:`~saml_ros.core.online.LearnerSetup` of the training process (without torch: the training
        process imports it).

        Args:
            system, spec: from :meth:`make_system` and :meth:`load_spec`.
            target_pairing: the schema's ``"next"`` or ``"same"``.
            run_dir: checkpoint directory.
            channels: ``(namespace index, kind, topic)`` of each raw-message channel.
            decoder: the factory of the channels' message decoder, called in the training process with
                ``(system, [(kind, topic), ...])`` (a module-level function, e.g.
                :func:`msg_schemas.decode.make_decoder`).

        Raises:
            ValueError: an invalid learner, buffer, pairing or loop setting.
        """
        from saml_ros.core.data.pairing import PairingConfig
        from saml_ros.core.model.io import system_params
        from saml_ros.core.online import HeldoutConfig, LearnerSetup, OnlineConfig

        bounds = self.plausibility(system)
        try:
            config = OnlineConfig(
                kind=self.model.kind, hidden=tuple(self.model.hidden) or None, train=self.train_config(),
                buffer_capacity=self.buffer.capacity, buffer_policy=self.buffer.policy,
                min_transitions=self.min_transitions, telemetry_window=self.telemetry.window,
                checkpoint_keep=self.checkpoint.keep, n_models=self.model.ensemble,
                plausible_bounds=self.plausible_bounds, health=self.health_config(),
                heldout=HeldoutConfig(period=self.heldout.period, fraction=self.heldout.fraction,
                                      capacity=self.heldout.capacity),
                heldout_period=self.heldout.eval_period, updates_per_transition=self.updates_per_transition,
                renormalize=self.normalization_refit, average_updates=self.average_updates,
            )
            own_pairing = getattr(system, "pairing", None)  # a robot's own topics: resampled onto its period
            pairing = own_pairing() if callable(own_pairing) else PairingConfig.for_system(
                system, target_pairing, tolerance=self.pairing.tolerance, window=self.pairing.window,
                max_slots=max(10_000, 10 * self.pairing.window))
            pairing = dataclasses.replace(pairing, bounds=bounds)
            loop = self.loop_config()
        except TypeError as exc:
            raise ValueError(str(exc)) from None
        params = system_params(system)
        function = getattr(system, "user_function", None)
        if function is not None:  # a robot's base model is user code: it travels pickled by reference
            params = {**params, "base_function": function}
        definition = getattr(system, "definition", None)  # a robot's field paths, for the decoder
        return LearnerSetup(
            system=self.system, system_params=params, spec=spec.to_dict(), config=config,
            run_dir=run_dir, resume=self.checkpoint.resume, loop=loop, niceness=self.process.niceness,
            idle=self.process.idle,
            threads=self.process.threads, sources=tuple((ns, pairing) for ns in self.namespaces),
            channels=tuple((index, kind) for index, kind, _ in channels), decoder=decoder,
            decoder_args=(self.system, [(kind, topic) for _, kind, topic in channels], definition),
        )
