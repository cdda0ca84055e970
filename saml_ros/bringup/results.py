"""What a bringup run observed (ROS-free): episodes cut from the ``state`` stream, their task error, the
learner's model error and the MPC's models, and the before/after summary.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from saml_ros.core.systems import get_entry


def goal_position(system: str, mpc_params: Mapping[str, Any]) -> np.ndarray:
    """The position the task error is measured from (the MPC's ``goal.<goal_position>``, e.g. friction ``[p]``,
    quadrotor ``[x, y, z]``, paddle ``[x, y]``)."""
    entry = get_entry(system)
    return entry.position_goal({k[len("goal."):]: v for k, v in mpc_params.items() if k.startswith("goal.")})


def task_error(system: str, x: np.ndarray, goal: np.ndarray) -> float:
    """Distance (m) of state ``x`` from the goal over the entry's ``goal_fields``: friction |p - p_goal|,
    quadrotor ||p - p_goal||_2 (3-D), paddle ball: the ball's xy at an impact vs the target xy (where the
    previous bounce brought it)."""
    return get_entry(system).task_error(x, goal)


@dataclass
class Episode:
    """One episode as seen on ``state``: from a (re)start to the last state before the next jump."""

    index: int
    t_start: float  #: s (simulated)
    t_end: float
    steps: int  #: states received
    start: np.ndarray
    final: np.ndarray
    error: float  #: task error at the final state (m)
    xy_error: float  #: horizontal distance at the final state (m; = error for 1-D systems)
    model_first: int  #: MPC model version when the episode started
    model_last: int  #: MPC model version at its end


class EpisodeTracker:
    """Splits the ``state`` stream into episodes by stamp jumps (a reset leaves a gap >= 2 dt, see the
    simulator contract) and records the task error at each episode's last state.

    For the event-based paddle ball every impact is one "episode" whose error is measured at the next impact.
    """

    def __init__(self, system: str, dt: float, goal: np.ndarray) -> None:
        self.system, self.dt, self.goal = system, dt, goal
        self.episodes: list[Episode] = []
        self._cur: dict[str, Any] | None = None
        self.first_stamp: int | None = None
        self.last_stamp: int | None = None

    @property
    def sim_time(self) -> float:
        """Simulated seconds covered so far."""
        if self.first_stamp is None or self.last_stamp is None:
            return 0.0
        return (self.last_stamp - self.first_stamp) * 1e-9

    def add(self, x: np.ndarray, stamp: int, model_version: int) -> Episode | None:
        """Feed one state; returns the episode it closed, if any."""
        closed = None
        if self.first_stamp is None:
            self.first_stamp = stamp
        jump = (
            self.last_stamp is not None
            and self.dt > 0
            and (stamp - self.last_stamp > 1.5e9 * self.dt or stamp < self.last_stamp)
        )
        if self.dt == 0 and self._cur is not None:
            self._cur.update(final=x, t_end=stamp * 1e-9, steps=self._cur["steps"] + 1, model_last=model_version)
            closed = self._close()
        elif jump:
            closed = self._close()
        self.last_stamp = stamp if self.last_stamp is None else max(stamp, self.last_stamp)
        if self._cur is None:
            self._cur = {"t_start": stamp * 1e-9, "t_end": stamp * 1e-9, "steps": 1, "start": x, "final": x,
                         "model_first": model_version, "model_last": model_version}
        elif self.dt > 0:
            self._cur.update(final=x, t_end=stamp * 1e-9, steps=self._cur["steps"] + 1, model_last=model_version)
        return closed

    def _close(self) -> Episode | None:
        cur, self._cur = self._cur, None
        if cur is None or (self.dt == 0 and cur["steps"] < 2):
            return None
        final = cur["final"]
        err = task_error(self.system, final, self.goal)
        xy = get_entry(self.system).task_error(final, self.goal, fields=2)
        ep = Episode(len(self.episodes), cur["t_start"], cur["t_end"], cur["steps"], cur["start"], final, err, xy,
                     cur["model_first"], cur["model_last"])
        self.episodes.append(ep)
        return ep


# ------------------------------------------------------------------------------------------ result
@dataclass
class BringupResult:
    """What a bringup run observed (everything the summary prints)."""

    system: str
    run_dir: Path
    sim_time: float = 0.0  #: simulated seconds covered
    wall_time: float = 0.0  #: wall seconds from the first state to the stop
    stop_reason: str = ""  #: "sim_time", "signal SIGINT", "child <name> exited", "startup timeout", ...
    returncodes: dict[str, int] = field(default_factory=dict)
    episodes: list[Episode] = field(default_factory=list)
    #: (updates, in-region error) from learner/model_error, in arrival order
    model_error: list[tuple[float, float]] = field(default_factory=list)
    constraint: str = ""  #: the constraint whose region error is tracked
    model_versions: list[int] = field(default_factory=list)  #: distinct MPC model versions, in order of use
    checkpoints_announced: int = 0
    checkpoints_refused: int = 0
    solve_ms: list[float] = field(default_factory=list)
    step_ms: list[float] = field(default_factory=list)
    deadline_misses: int = 0
    states: int = 0
    ok: bool = False  #: every child exited cleanly and the run was not cut short by a failure
    #: the newest ``guard_*`` counters of ``mpc/status`` (empty when the MPC runs unguarded)
    guard: dict[str, float] = field(default_factory=dict)
    #: one row per ``mpc/status``: (t s of simulated time, model version, live one-step squared errors of the model
    #: in use and of f_hat on the last transition, 1 if planned with the learned model); the live error picture's data
    status_log: list[tuple[float, int, float, float, float]] = field(default_factory=list)

    def add_status(self, stamp_ns: int, values: Mapping[str, float]) -> None:
        """Record one ``mpc/status`` message (see :attr:`status_log`, :attr:`guard`)."""
        self.guard.update({k: v for k, v in values.items() if k.startswith("guard_")})
        self.status_log.append((stamp_ns * 1e-9, int(values.get("model_version", 0)),
                                float(values.get("live_error_model", math.nan)),
                                float(values.get("live_error_base", math.nan)),
                                float(values.get("model_source", math.nan))))

    def error_before_after(self, k: int = 3) -> tuple[float, float]:
        """In-region error of the base model and of the newest model (NaN if unknown).

        Before: the last finite report made before the learner's first update (the zero-initialised residual
        predicts exactly f_hat, and the last such report covers the most transitions); if training started
        before any finite report, the first finite one. After: the median of the last ``k`` finite reports.
        """
        finite = [(u, e) for u, e in self.model_error if math.isfinite(e)]
        if not finite:
            return math.nan, math.nan
        untrained = [e for u, e in finite if u == 0]
        before = untrained[-1] if untrained else finite[0][1]
        return float(before), float(np.median([e for _, e in finite[-k:]]))

    def base_and_last_episodes(self, n: int = 5) -> tuple[list[Episode], list[Episode]]:
        """Episodes flown entirely on the base model, and the last ``n`` flown entirely on learned models."""
        base = [e for e in self.episodes if e.model_last == 0]
        learned = [e for e in self.episodes if e.model_first > 0]
        return base, learned[-n:]


def format_summary(res: BringupResult, n_last: int = 5) -> str:
    """The before/after summary printed at the end of a run."""
    lines = [f"bringup summary ({res.system}): {res.sim_time:.1f} s simulated in {res.wall_time:.1f} s wall "
             f"({res.sim_time / max(res.wall_time, 1e-9):.1f}x real time), {res.states} states; stopped by "
             f"{res.stop_reason}; run dir {res.run_dir}"]
    before, after = res.error_before_after()
    last_upd = res.model_error[-1][0] if res.model_error else 0
    lines.append(f"  in-region one-step model error ({res.constraint or 'n/a'}, learner/model_error): base model "
                 f"{before:.4g} -> {after:.4g} after {last_upd:.0f} learner updates")
    base, learned = res.base_and_last_episodes(n_last)

    def stat(eps: list[Episode], attr: str) -> str:
        if not eps:
            return "n/a (no episode)"
        v = np.array([getattr(e, attr) for e in eps])
        return f"{v.mean():.3f} +- {v.std():.3f} m over {len(v)} episode(s)"

    lines.append(f"  task error, base model f_hat:   {stat(base, 'error')}")
    lines.append(f"  task error, last learned models: {stat(learned, 'error')}")
    if len(get_entry(res.system).goal_fields) > 2:
        lines.append(f"  horizontal landing error: base {stat(base, 'xy_error')}; learned {stat(learned, 'xy_error')}")
    on_learned = [e for e in res.episodes if e.model_first > 0]
    if on_learned:
        worst = max(on_learned, key=lambda e: e.error)
        lines.append(f"  worst episode on a learned model: {worst.error:.3f} m (model v{worst.model_first}, episode "
                     f"{worst.index}); {sum(e.error > 1.0 for e in on_learned)} of {len(on_learned)} ended > 1 m "
                     f"from the target")
    versions = res.model_versions
    lines.append(f"  MPC models used: {len(versions)} ({versions[0] if versions else '-'} -> "
                 f"{versions[-1] if versions else '-'}); checkpoints announced {res.checkpoints_announced}, "
                 f"refused {res.checkpoints_refused}")
    if res.guard:
        g = res.guard
        lines.append(f"  MPC guard: {g.get('guard_fallbacks', 0):.0f} steps on f_hat because the ensemble disagreed, "
                     f"{g.get('guard_base_solves', 0):.0f} steps on f_hat in all, "
                     f"{g.get('guard_rollbacks', 0):.0f} roll back(s) by the live monitor")
    if res.step_ms:
        s = np.asarray(res.step_ms)
        lines.append(f"  MPC control step: median {np.median(s):.2f} ms, p99 {np.percentile(s, 99):.2f} ms, "
                     f"max {s.max():.2f} ms; deadline misses {res.deadline_misses}")
    bad = {k: v for k, v in res.returncodes.items() if v != 0}
    lines.append("  children exited cleanly" if not bad else f"  children with non-zero exit codes: {bad}")
    return "\n".join(lines)
