"""Training speed of the learner's training process under its compute settings (part of ``bench.bench_learner``).

For each system, one :class:`~saml_ros.core.online.TrainingProcess` per setting (torch intra-op threads,
subnormal flushing) gets 2000 transitions of the system's training distribution and trains the paper's
network on the paper's spec as fast as it can (``updates_per_second: 0``, niceness 0, no checkpoints); its
primal-dual updates per second are read from its status reports over ``seconds`` wall seconds, after one
second of warm-up. The settings are measured in alternating order over ``rounds`` rounds; each one's best
round counts (load on a shared machine only slows a round down). No ROS is involved.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from saml_ros.core.systems import SYSTEM_NAMES

#: ``(label, threads, flush_denormal)``: the first is the training process before subnormal flushing was
#: added (it always ran one thread), the second today's default, the third torch's own thread default
SETTINGS: tuple[tuple[str, int, bool], ...] = (
    ("1 thread, subnormals kept (before)", 1, False),
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
    from saml_ros.core.online import LearnerSetup, LoopConfig, OnlineConfig, TrainingProcess
    from saml_ros.core.pairing import Transition
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
        deadline = time.monotonic() + 60.0
        while not (seen and seen[-1][1] > 0):
            if time.monotonic() > deadline:
                raise RuntimeError(f"{system_name}: the training process did not start training within 60 s")
            time.sleep(0.05)
        time.sleep(1.0)  # warm-up
        t0, u0 = seen[-1]
        time.sleep(seconds)
        t1, u1 = seen[-1]
    finally:
        proc.stop()
    return Rate((u1 - u0) / (t1 - t0), ready.threads)


def run(systems: Sequence[str] = SYSTEMS, seconds: float = 3.0, rounds: int = 2) -> dict[str, list[Rate]]:
    """Measure every setting of :data:`SETTINGS` for every system; prints one line per system and returns
    ``{system: [best Rate per setting]}``."""
    print(f"\ntraining process speed (paper networks and specs, {N_DATA} transitions, as fast as it can; best of "
          f"{rounds} round(s) of {seconds:g} s; updates/s)", flush=True)
    out: dict[str, list[Rate]] = {}
    for name in systems:
        best: list[Rate | None] = [None] * len(SETTINGS)
        for r in range(rounds):
            order = range(len(SETTINGS)) if r % 2 == 0 else reversed(range(len(SETTINGS)))
            for i in order:
                _, threads, flush = SETTINGS[i]
                rate = training_rate(name, threads, flush, seconds)
                old = best[i]
                if old is None or rate.updates_per_s > old.updates_per_s:
                    best[i] = rate
        rates = [b for b in best if b is not None]
        out[name] = rates
        base = rates[0].updates_per_s
        cells = [f"{label} [{b.threads}]: {b.updates_per_s:7.0f} ({b.updates_per_s / base:.2f}x)"
                 for (label, _, _), b in zip(SETTINGS, rates, strict=True)]
        print(f"  {name:12s} " + "; ".join(cells), flush=True)
    return out
