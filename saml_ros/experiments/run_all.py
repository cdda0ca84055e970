"""``experiment all`` on several cores: each experiment in its own process, longest first.

The experiments are independent and every runner is single-threaded (:func:`.common.compute_settings`), so on a
machine with J cores ``all`` runs J of them at once. Each child is ``python -m saml_ros.experiments.cli NAME
--out PARENT/NAME ...`` with the parent's options; its output goes to ``PARENT/NAME/run.log`` and is printed when
it ends. The order (longest first, by the CPU times measured in docs/experiments.md) keeps the two lanes of a
2-core machine about equally long.
"""

from __future__ import annotations

import os
import resource
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

#: measured CPU seconds of each full experiment (docs/experiments.md, "Run time"): the order, and the rough
#: estimate of the time left in the status lines
CPU_SECONDS: dict[str, float] = {"paddle_ball": 250.0, "quadrotor": 290.0, "friction": 175.0, "convergence": 130.0}


@dataclass
class Child:
    """One running experiment."""

    name: str
    proc: subprocess.Popen[bytes]
    log: Path
    t0: float


def default_jobs() -> int:
    """Cores this process may use (``os.sched_getaffinity`` where it exists)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not on Linux
        return max(1, os.cpu_count() or 1)


#: the children's environment: one BLAS / OpenMP thread each (torch is pinned by the runners themselves)
CHILD_THREADS = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def child_command(name: str, out: Path, options: list[str]) -> list[str]:
    """The command line of the child that runs experiment ``name`` into ``out``."""
    return [sys.executable, "-m", "saml_ros.experiments.cli", name, "--out", str(out), "--no-progress", *options]


def run_parallel(names: list[str], parent: Path, options: list[str] | dict[str, list[str]], jobs: int,
                 status_every: float = 60.0) -> tuple[list[str], float]:
    """Run experiments ``names`` into ``parent/<name>`` with at most ``jobs`` at once; every ``status_every``
    seconds (0: never) a line says what runs, for how long, and roughly how long it has left. ``options``: the
    children's extra command-line options, the same for all or per name. A child's earlier ``results.json`` and
    ``results.md`` are removed before it starts (a failed run leaves none to be mistaken for its results); on
    SIGTERM or Ctrl-C the running children are terminated.

    Returns the names that failed (non-zero exit; their log's tail is printed) and the children's CPU seconds.
    """
    per_name = options if isinstance(options, dict) else {n: list(options) for n in names}
    pending = sorted(names, key=lambda n: -CPU_SECONDS.get(n, 0.0))  # longest first
    running: list[Child] = []
    failed: list[str] = []
    cpu0 = _children_cpu()
    previous = signal.signal(signal.SIGTERM, _raise_exit)
    try:
        _loop(pending, running, failed, parent, per_name, jobs, status_every)
    finally:
        for child in running:  # interrupted: no orphaned experiments
            child.proc.terminate()
            child.proc.wait()
        signal.signal(signal.SIGTERM, previous)
    return failed, _children_cpu() - cpu0


def _raise_exit(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)


def _loop(pending: list[str], running: list[Child], failed: list[str], parent: Path,
          options: dict[str, list[str]], jobs: int, status_every: float) -> None:
    t0 = last_status = time.perf_counter()
    while pending or running:
        while pending and len(running) < jobs:
            name = pending.pop(0)
            out = parent / name
            out.mkdir(parents=True, exist_ok=True)
            log = out / "run.log"
            for stale in ("results.json", "results.md"):
                (out / stale).unlink(missing_ok=True)
            with log.open("wb") as fh:
                running.append(Child(name, subprocess.Popen(
                    child_command(name, out, options.get(name, [])), stdout=fh, stderr=subprocess.STDOUT,
                    env={**os.environ, **CHILD_THREADS}), log, time.perf_counter()))
            print(f"experiment {name} -> {out} (running: {', '.join(c.name for c in running)}; log {log})",
                  flush=True)
        time.sleep(0.5)
        now = time.perf_counter()
        if status_every > 0 and now - last_status >= status_every:
            last_status = now
            print(f"experiment all: {now - t0:.0f} s; " + status_line(running, pending, now), flush=True)
        for child in [c for c in running if c.proc.poll() is not None]:
            running.remove(child)
            text = child.log.read_text(errors="replace")
            wall = time.perf_counter() - child.t0
            if child.proc.returncode != 0:
                failed.append(child.name)
                tail = "\n".join(text.splitlines()[-30:])
                print(f"experiment {child.name}: FAILED (exit {child.proc.returncode}) after {wall:.0f} s; the end "
                      f"of {child.log}:\n{tail}", file=sys.stderr, flush=True)
            else:
                results = child.log.parent / "results.md"
                print(results.read_text() if results.exists() else text, flush=True)
                print(f"experiment {child.name}: done in {wall:.1f} s wall; results in {child.log.parent}",
                      flush=True)


def status_line(running: list[Child], pending: list[str], now: float) -> str:
    """``running: quadrotor 120 s (about 170 s left), ...; waiting: friction`` (estimates from
    :data:`CPU_SECONDS`)."""
    parts = []
    for c in running:
        left = CPU_SECONDS.get(c.name, 0.0) - (now - c.t0)
        parts.append(f"{c.name} {now - c.t0:.0f} s" + (f" (about {left:.0f} s left)" if left > 0 else ""))
    return "running: " + ", ".join(parts) + (f"; waiting: {', '.join(pending)}" if pending else "")


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime
