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
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, get_args

from msg_schemas.names import join_topic, normalize_namespace
from saml_ros.core.params import LIVE, Param, Problems, memory_problems, read_params

if TYPE_CHECKING:
    from msg_schemas.base import QosSpec, SystemSchema
    from saml_ros.core.data.plausibility import Plausibility
    from saml_ros.core.dynamics.system import System
    from saml_ros.core.online import LearnerSetup, LoopConfig, TrainingProcess
    from saml_ros.core.online.process import DecoderFactory
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.training import TrainConfig
    from saml_ros.core.training.health import HealthConfig

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


@dataclass(frozen=True)
class LearnerConfig:
    """The learner node's parameters after validation (units in :func:`learner_params`' descriptions).

    ``namespaces`` are normalised (``/name``) and never empty; ``train`` holds the ``train.*`` values by
    TrainConfig field name.
    """

    system: str
    namespaces: list[str]
    spec_file: str
    model_kind: str
    model_hidden: list[int]
    train: dict[str, Any]
    buffer_capacity: int
    buffer_policy: str
    min_transitions: int
    updates_per_second: float
    checkpoint_period: float
    checkpoint_keep: int
    run_dir: str
    resume: bool
    telemetry_rate: float
    telemetry_window: int
    diagnostics_rate: float
    dt: float
    pairing_window: int
    pairing_tolerance: float
    training_niceness: int
    train_threads: int
    training_idle: bool = False
    system_file: str = ""
    model_ensemble: int = 1
    uniform: bool = False
    plausible_bounds: str = ""
    health_explode_ratio: float = 1e4
    health_max_weight: float = 1e6
    health_error_after: int = 100
    refuse_multiple_publishers: bool = False
    normalization_refit: bool = True
    heldout_period: float = 10.0
    heldout_fraction: float = 0.2
    heldout_capacity: int = 25_000
    heldout_eval_period: float = 1.0
    updates_per_transition: float = 0.0
    average_updates: float = 1000.0

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
        from saml_ros.core.model.network import MODEL_KINDS
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
        config = cls(
            system=p["system"], namespaces=nss, spec_file=p["spec_file"], model_kind=p["model.kind"],
            model_hidden=list(p["model.hidden"]),
            train={k[len("train."):]: v for k, v in p.items() if k.startswith("train.")},
            buffer_capacity=p["buffer.capacity"], buffer_policy=p["buffer.policy"],
            min_transitions=p["min_transitions"], updates_per_second=p["updates_per_second"],
            checkpoint_period=p["checkpoint_period"], checkpoint_keep=p["checkpoint_keep"], run_dir=p["run_dir"],
            resume=p["resume"], telemetry_rate=p["telemetry_rate"], telemetry_window=p["telemetry_window"],
            diagnostics_rate=p["diagnostics_rate"], dt=p["dt"], pairing_window=p["pairing.window"],
            pairing_tolerance=p["pairing.tolerance"], training_niceness=p["training_niceness"],
            training_idle=p["training_idle"],
            train_threads=p["train_threads"], system_file=p["system_file"], model_ensemble=p["model.ensemble"],
            uniform=p["uniform"], plausible_bounds=p["plausible_bounds"],
            health_explode_ratio=p["health.explode_ratio"], health_max_weight=p["health.max_weight"],
            health_error_after=p["health.error_after"],
            refuse_multiple_publishers=p["pairing.refuse_multiple_publishers"],
            normalization_refit=p["normalization.refit"],
            heldout_period=p["heldout.period"], heldout_fraction=p["heldout.fraction"],
            heldout_capacity=p["heldout.capacity"], heldout_eval_period=p["heldout.eval_period"],
            updates_per_transition=p["updates_per_transition"], average_updates=p["average_updates"],
        )
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
        hidden = sum(self.model_hidden or system.paper_hidden)
        itemsize = 8 if self.train.get("dtype") == "float64" else 4
        batch = int(self.train.get("batch_size", 1))
        return [
            ("buffer.capacity", f"a replay buffer of {self.buffer_capacity} transitions",
             self.buffer_capacity * (width + 3) * 8),
            ("train.batch_size", f"minibatches of {batch} transitions x {self.model_ensemble} ensemble member(s)",
             batch * self.model_ensemble * (width * (8 + itemsize) + 3 * hidden * itemsize)),
            ("telemetry_window", f"a window of {self.telemetry_window} transitions",
             self.telemetry_window * width * 8),
            ("heldout.capacity", f"a held-out set of {self.heldout_capacity} transitions",
             self.heldout_capacity * (width + 3) * 8),
        ]

    def loop_config(self) -> LoopConfig:
        """The training loop's pacing (``updates_per_second``, ``telemetry_rate``, ``checkpoint_period``: the
        parameters a running learner applies at once, :meth:`TrainingProcess.set_loop
        <saml_ros.core.online.TrainingProcess.set_loop>`)."""
        from saml_ros.core.online import LoopConfig

        return LoopConfig(updates_per_second=self.updates_per_second, telemetry_rate=self.telemetry_rate,
                          checkpoint_period=self.checkpoint_period)

    def health_config(self) -> HealthConfig:
        """The :class:`~saml_ros.core.training.health.HealthConfig` of ``health.*``; ``ValueError`` naming them."""
        from saml_ros.core.training.health import HealthConfig

        problems = Problems()
        check = problems.check
        check(self.health_explode_ratio > 1, "health.explode_ratio", "> 1", self.health_explode_ratio)
        check(self.health_max_weight > 0, "health.max_weight", "> 0", self.health_max_weight)
        check(self.health_error_after >= 1, "health.error_after", ">= 1", self.health_error_after)
        problems.raise_if_any()
        return HealthConfig(explode_ratio=self.health_explode_ratio, max_weight=self.health_max_weight,
                            error_after=self.health_error_after)

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
            ValueError: an invalid setting, a run directory whose checkpoints contradict the configuration, or a
                training process that could not start; the message says which.
            StartCancelled: ``cancelled()`` became true while the training process started.
        """
        from saml_ros.core.online import ResumeError, TrainingProcess

        channels = [(self.namespaces.index(ns), kind, topic) for ns, kind, topic, _ in self.channels(schema)]
        setup = self.training_setup(system, spec, schema.target_pairing, run_dir, channels, decoder)
        trainer = TrainingProcess(dataclasses.replace(setup, paused=paused), **callbacks)
        try:
            trainer.start(launched=launched, cancelled=cancelled)
        except ResumeError as exc:
            raise ValueError(str(exc)) from None
        except RuntimeError as exc:
            raise ValueError(f"the training process could not start: {exc}") from None
        return trainer

    def training_setup(self, system: System, spec: ProblemSpec, target_pairing: str, run_dir: str,
                       channels: list[tuple[int, str, str]], decoder: DecoderFactory) -> LearnerSetup:
        """The :class:`~saml_ros.core.online.LearnerSetup` of the training process (imports torch).

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
                kind=self.model_kind, hidden=tuple(self.model_hidden) or None, train=self.train_config(),
                buffer_capacity=self.buffer_capacity, buffer_policy=self.buffer_policy,
                min_transitions=self.min_transitions, telemetry_window=self.telemetry_window,
                checkpoint_keep=self.checkpoint_keep, n_models=self.model_ensemble,
                plausible_bounds=self.plausible_bounds, health=self.health_config(),
                heldout=HeldoutConfig(period=self.heldout_period, fraction=self.heldout_fraction,
                                      capacity=self.heldout_capacity),
                heldout_period=self.heldout_eval_period, updates_per_transition=self.updates_per_transition,
                renormalize=self.normalization_refit, average_updates=self.average_updates,
            )
            own_pairing = getattr(system, "pairing", None)  # a robot's own topics: resampled onto its period
            pairing = own_pairing() if callable(own_pairing) else PairingConfig.for_system(
                system, target_pairing, tolerance=self.pairing_tolerance, window=self.pairing_window,
                max_slots=max(10_000, 10 * self.pairing_window))
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
            run_dir=run_dir, resume=self.resume, loop=loop, niceness=self.training_niceness,
            idle=self.training_idle,
            threads=self.train_threads, sources=tuple((ns, pairing) for ns in self.namespaces),
            channels=tuple((index, kind) for index, kind, _ in channels), decoder=decoder,
            decoder_args=(self.system, [(kind, topic) for _, kind, topic in channels], definition),
        )
