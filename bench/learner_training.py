"""Training speed of the learner's training process under its compute settings (part of ``bench.bench_learner``).

For each system, one :class:`~saml_ros.core.online.TrainingProcess` per setting (torch intra-op threads,
subnormal flushing) gets 2000 transitions of the system's training distribution and trains the paper's
network on the paper's spec as fast as it can (``updates_per_second: 0``, niceness 0, no checkpoints); its
primal-dual updates per second are read from its status reports over ``seconds`` wall seconds, after one
second of warm-up. Beside them, in this process (one thread, subnormals flushed), the offline engine's steps per
second for the same network, spec, training configuration, batch and data (:meth:`PrimalDualTrainer.fit` on the
2000 transitions, the fast engine): what an online update can at best cost. The settings and the offline engine
are measured in alternating order over ``rounds`` rounds; each one's best round counts (load on a shared machine
only slows a round down). No ROS is involved. Target (issue 15): the default setting's updates/s >= 50 % of the
offline engine's steps/s.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from saml_ros.core.systems import SYSTEM_NAMES

#: ``(label, threads, flush_denormal)``: the first is the training process without subnormal flushing (as it was
#: before flushing was added), the second the default, the third torch's own thread default
SETTINGS: tuple[tuple[str, int, bool], ...] = (
    ("1 thread, subnormals kept", 1, False),
    ("1 thread, subnormals flushed (default)", 1, True),
    ("torch default threads, flushed", 0, True),
)
SYSTEMS = SYSTEM_NAMES
N_DATA = 2000
MIN_TRANSITIONS = 1000


@dataclass
class Rate:
    """One measurement: primal-dual updates per second and the threads the process reported."""

    updates_per_s: float
    threads: int


def training_rate(system_name: str, threads: int, flush_denormal: bool, seconds: float) -> Rate:
    """Updates per second of one training process of ``system_name`` with the given settings."""
    from saml_ros.core.data.pairing import Transition
    from saml_ros.core.online import LearnerSetup, LoopConfig, OnlineConfig, TrainingProcess
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.systems import get_system

    system = get_system(system_name)
    setup = LearnerSetup(
        system=system_name, system_params={},
        spec=ProblemSpec.for_system(system.paper_spec(), system).to_dict(),
        config=OnlineConfig(min_transitions=MIN_TRANSITIONS, buffer_capacity=N_DATA), run_dir=None,
        loop=LoopConfig(updates_per_second=0.0, telemetry_rate=10.0), niceness=0, threads=threads,
        flush_denormal=flush_denormal,
    )
    seen: list[tuple[float, float]] = []
    proc = TrainingProcess(setup, on_status=lambda st: seen.append((time.monotonic(), st.get("updates", 0.0))),
                           on_log=lambda level, text: None)
    ready = proc.start()
    try:
        x, u = system.sample_inputs(N_DATA, np.random.default_rng(0))
        y = system.true_step_np(x, u)
        for i in range(N_DATA):
            proc.submit(Transition(x[i], u[i], y[i], 10**9 + i * 10**8, 0))
        deadline = time.monotonic() + 180.0
        while not (seen and seen[-1][1] > 0):
            if time.monotonic() > deadline:
                raise RuntimeError(f"{system_name}: the training process did not start training within 180 s")
            time.sleep(0.05)
        time.sleep(1.0)  # warm-up
        t0, u0 = seen[-1]
        time.sleep(seconds)
        t1, u1 = seen[-1]
    finally:
        proc.stop()
    return Rate((u1 - u0) / (t1 - t0), ready.threads)


def _problem(system_name: str) -> tuple[Any, Any, Any, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """What the in-process measurements share: one torch thread and subnormals flushed (the training process's
    settings), the system, its paper spec, the training process's configuration and :data:`N_DATA` transitions
    of the true dynamics."""
    from saml_ros.core.online import OnlineConfig
    from saml_ros.core.online.child import apply_compute_settings
    from saml_ros.core.spec import ProblemSpec
    from saml_ros.core.systems import get_system

    apply_compute_settings(1, True)
    system = get_system(system_name)
    spec = ProblemSpec.for_system(system.paper_spec(), system)
    cfg = OnlineConfig(min_transitions=MIN_TRANSITIONS, buffer_capacity=N_DATA)
    x, u = system.sample_inputs(N_DATA, np.random.default_rng(0))
    return system, spec, cfg, (x, u, system.true_step_np(x, u))


def offline_rate(system_name: str, seconds: float) -> float:
    """Steps per second of the offline engine (``fit``) on the training process's network, spec, configuration
    and data (:func:`training_rate`), in this process with one torch thread and subnormals flushed."""
    import logging

    import torch

    from saml_ros.core.model.network import DynamicsModel
    from saml_ros.core.training import PrimalDualTrainer
    from saml_ros.core.training.dataset import Transitions

    threads = torch.get_num_threads()
    system, spec, cfg, (x, u, y) = _problem(system_name)
    model = DynamicsModel(system, cfg.hidden, cfg.kind, n_models=1, seed=cfg.train.seed)
    model.to(cfg.train.torch_dtype)
    model.fit_normalization(x[:MIN_TRANSITIONS], u[:MIN_TRANSITIONS], y[:MIN_TRANSITIONS])
    trainer = PrimalDualTrainer(model, spec, cfg.train, cfg.health)
    data = Transitions(model, spec, x, u, y)
    quiet = logging.getLogger("saml_ros.trainer")
    level, quiet.level = quiet.level, logging.ERROR  # the short fits' feasibility warnings
    try:
        trainer.fit(data, epochs=2)  # warm-up
        assert trainer.engine_used == "fast", trainer.engine_used
        steps0, t0 = trainer.steps, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            trainer.fit(data, epochs=50)  # 750 steps per fit: its set-up and final evaluation add < 2 %
        return (trainer.steps - steps0) / (time.perf_counter() - t0)
    finally:
        quiet.level = level
        torch.set_num_threads(threads)


def cpu_shares(system_name: str, seconds: float, chunks: Sequence[int] = (10, 50)) -> dict[int, float]:
    """In this process, by CPU time (``time.process_time``, less sensitive to other jobs than wall time):
    ``OnlineLearner.update(k)`` updates per CPU second for each chunk size ``k``, as a share of the offline
    engine's steps per CPU second on the same data (:func:`offline_rate`'s set-up); the best of 3 alternating
    rounds of ``seconds`` each."""
    import logging

    import torch

    from saml_ros.core.online import OnlineLearner
    from saml_ros.core.training import PrimalDualTrainer
    from saml_ros.core.training.dataset import Transitions

    threads = torch.get_num_threads()
    system, spec, cfg, (x, u, y) = _problem(system_name)
    learner = OnlineLearner(system, spec, cfg)
    learner.add_batch(x, u, y)
    learner.update(1)
    assert learner.trainer is not None
    model = learner.trainer.model
    trainer = PrimalDualTrainer(type(model)(system, cfg.hidden, cfg.kind, n_models=1, seed=0), spec, cfg.train)
    trainer.model.load_state_dict(model.state_dict())
    data = Transitions(trainer.model, spec, x, u, y)
    quiet = logging.getLogger("saml_ros.trainer")
    level, quiet.level = quiet.level, logging.ERROR
    best: dict[int, float] = {}
    try:
        trainer.fit(data, epochs=2)
        for _ in range(3):
            for k in (*chunks, 0):  # 0: the offline engine
                t0, n = time.process_time(), 0
                while time.process_time() - t0 < seconds:
                    if k == 0:
                        s0 = trainer.steps
                        trainer.fit(data, epochs=50)
                        n += trainer.steps - s0
                    else:
                        n += learner.update(k)
                best[k] = max(best.get(k, 0.0), n / (time.process_time() - t0))
    finally:
        quiet.level = level
        torch.set_num_threads(threads)
    return {k: best[k] / best[0] for k in chunks}


def run(systems: Sequence[str] = SYSTEMS, seconds: float = 3.0, rounds: int = 2) -> dict[str, list[Rate]]:
    """Measure every setting of :data:`SETTINGS` and the offline engine for every system; prints one line per
    system and returns ``{system: [best Rate per setting] + [offline Rate]}``."""
    print(f"\ntraining process speed (paper networks and specs, {N_DATA} transitions, as fast as it can; best of "
          f"{rounds} round(s) of {seconds:g} s; updates/s)", flush=True)
    from saml_ros.core.online import OnlineConfig

    batch = OnlineConfig().train.batch_size
    out: dict[str, list[Rate]] = {}
    for name in systems:
        best: list[Rate | None] = [None] * (len(SETTINGS) + 1)
        for r in range(rounds):
            order = range(len(SETTINGS) + 1) if r % 2 == 0 else reversed(range(len(SETTINGS) + 1))
            for i in order:
                if i == len(SETTINGS):
                    rate = Rate(offline_rate(name, seconds), 1)
                else:
                    _, threads, flush = SETTINGS[i]
                    rate = training_rate(name, threads, flush, seconds)
                old = best[i]
                if old is None or rate.updates_per_s > old.updates_per_s:
                    best[i] = rate
        rates = [b for b in best if b is not None]
        out[name] = rates
        base = rates[0].updates_per_s
        cells = [f"{label} [{b.threads}]: {b.updates_per_s:7.0f} ({b.updates_per_s / base:.2f}x)"
                 for (label, _, _), b in zip(SETTINGS, rates, strict=False)]
        print(f"  {name:12s} " + "; ".join(cells), flush=True)
        online, offline = rates[1].updates_per_s, rates[-1].updates_per_s
        share = online / offline
        print(f"  {'':12s} offline engine (fit, same net, spec, batch {batch} and data) [1]: {offline:7.0f} steps/s; "
              f"online (default setting) = {100 * share:.0f} % of it (target >= 50 %: "
              f"{'met' if share >= 0.5 else 'NOT met'})", flush=True)
        cpu = cpu_shares(name, 1.0)
        print(f"  {'':12s} in-process by CPU time, OnlineLearner.update(k) / offline engine: "
              + ", ".join(f"k = {k}: {100 * v:.0f} %" for k, v in cpu.items()), flush=True)
    return out
