"""Goals and references of a robot's ``mpc:`` task from its topics, without ROS (:class:`GoalTracker`).

* A **goal** message (``mpc.goal.topic``, e.g. ``geometry_msgs/PoseStamped``) sets the goal fields its ``paths``
  name; the other goal fields keep their current value. A goal with a NaN, or outside the goal bounds, is refused
  (:class:`GoalRefused`, the caller counts it) and the last goal is kept.
* A **reference** (``mpc.reference``, a ``nav_msgs/Path``) is tracked instead of the goal while it is fresh. Its
  poses are read by the same field paths (relative to each pose). When the poses carry stamps, the reference of
  x_t is the path interpolated at the time of x_t (the state's stamp + t dt; held at the ends; angle fields the
  short way round); when they carry none (all zero), it starts at the pose nearest the current state (by the
  non-angle goal fields) and advances one pose per step, holding the last. A reference is dropped ``timeout`` s
  after its last pose's time (timed) or after it arrived (untimed, unless a newer one came); its last pose then
  becomes the goal, so the robot stays at the end of the path. A reference with a NaN or a pose outside the goal
  bounds is refused as a whole.

:meth:`GoalTracker.__call__` is what the MPC service passes the planner at each solve: ``(k,)`` or ``(T, k)``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from saml_ros.core.errors import SamlError
from saml_ros.core.mpc.generic.dynamics import wrap_angle
from saml_ros.core.mpc.generic.section import GoalTopic, MPCTask


class GoalRefused(SamlError, ValueError):
    """A goal or reference message that was not used (NaN, out of bounds, malformed); the last goal is kept."""


def _codec(topic: GoalTopic, msg_type: str, units: dict[str, str]) -> Any:
    from msg_schemas.path_codec import FieldPathCodec, PathField

    return FieldPathCodec(msg_type, [PathField(name, units.get(name, ""), path) for name, path in topic.paths])


class GoalTracker:
    """The goal a robot's planner plans for (see the module docstring).

    Args:
        task: the robot's task.
        dt: the planner's step (s).
        units: unit per state field (for the field paths' documentation only).
    """

    def __init__(self, task: MPCTask, dt: float, units: dict[str, str] | None = None) -> None:
        self.task = task
        self.dt = float(dt)
        self.goal = task.goal_default.copy()
        self.fields = task.goal_fields
        self._pos = {name: i for i, name in enumerate(self.fields)}
        self._angle = np.asarray(task.goal_angle, dtype=bool)
        units = units or {}
        self.goal_codec = None if task.goal_topic is None else _codec(task.goal_topic, task.goal_topic.type, units)
        self.ref_codec = None
        if task.reference is not None:
            from msg_schemas.field_path import message_fields

            elem = dict(message_fields(task.reference.type))["poses"][1][0][1]
            self.ref_codec = _codec(task.reference, elem, units)
        self._ref: np.ndarray | None = None  # (P, k) poses
        self._ref_t: np.ndarray | None = None  # (P,) ns, or None: untimed
        self._ref_until = -math.inf  # node clock (ns) after which the reference is dropped
        self._ref_cursor = 0

    # ------------------------------------------------------------------------------------------ input
    def set_goal(self, goal: Any) -> np.ndarray:
        """Replace the whole goal (``(k,)``); :class:`GoalRefused` if it is not finite or outside the bounds."""
        try:
            self.goal = self.task.check_goal(goal)
        except ValueError as exc:
            raise GoalRefused(str(exc)) from None
        self._ref = None
        return self.goal.copy()

    def goal_message(self, msg: Any, topic: str = "") -> np.ndarray:
        """A goal message (the goal topic's type): the new goal, or :class:`GoalRefused` (the last one kept)."""
        if self.goal_codec is None:
            raise GoalRefused("this task has no goal topic")
        vals = self._read(self.goal_codec, msg, topic)
        new = self.goal.copy()
        for (name, _), v in zip(self.task.goal_topic.paths, vals, strict=True):  # type: ignore[union-attr]
            new[self._pos[name]] = v
        return self.set_goal(new)

    def reference_message(self, msg: Any, now_ns: int, topic: str = "") -> int:
        """A reference message (``nav_msgs/Path``) received at ``now_ns`` (node clock): the number of poses, or
        :class:`GoalRefused` (the current goal / reference kept). An empty path drops the reference."""
        assert self.task.reference is not None and self.ref_codec is not None
        poses = list(msg.poses)
        if not poses:
            self._drop()
            return 0
        rows, stamps = [], []
        for i, p in enumerate(poses):
            try:
                vals = self._read(self.ref_codec, p, f"{topic}.poses[{i}]")
            except GoalRefused as exc:
                raise GoalRefused(f"pose {i}: {exc}") from None
            row = self.goal.copy()
            for (name, _), v in zip(self.task.reference.paths, vals, strict=True):
                row[self._pos[name]] = v
            try:
                rows.append(self.task.check_goal(row))
            except ValueError as exc:
                raise GoalRefused(f"pose {i}: {exc}") from None
            st = p.header.stamp
            stamps.append(int(st.sec) * 1_000_000_000 + int(st.nanosec))
        ref = np.array(rows)
        if self._angle.any():  # the short way round between consecutive poses
            a = ref[:, self._angle]
            ref[:, self._angle] = a[0] + np.concatenate([np.zeros((1, a.shape[1])),
                                                         np.cumsum(wrap_angle(np.diff(a, axis=0)), axis=0)])
        t = np.array(stamps, dtype=np.int64)
        timed = bool(np.any(t != 0))
        if timed and np.any(np.diff(t) < 0):
            raise GoalRefused("pose stamps go back in time")
        timeout_ns = int(self.task.reference.timeout * 1e9)
        self._ref, self._ref_t = ref, (t if timed else None)
        self._ref_until = (int(t[-1]) if timed else int(now_ns)) + timeout_ns
        self._ref_cursor = 0
        return len(rows)

    def _read(self, codec: Any, msg: Any, topic: str) -> np.ndarray:
        from msg_schemas.base import SchemaError

        try:
            vals = np.array([p.read(msg, topic) for p in codec.paths], dtype=np.float64)
        except SchemaError as exc:
            raise GoalRefused(str(exc)) from None
        except Exception as exc:  # noqa: BLE001 - a message of another shape: refused, never a crash
            raise GoalRefused(f"{type(exc).__name__}: {exc}") from None
        return vals

    def _drop(self) -> None:
        if self._ref is not None:
            self.goal = self._ref[-1].copy()
            if self._angle.any():
                self.goal[self._angle] = wrap_angle(self.goal[self._angle])
        self._ref = None
        self._ref_t = None

    @property
    def tracking(self) -> bool:
        """Whether a reference is being tracked."""
        return self._ref is not None

    # ------------------------------------------------------------------------------------------ output
    def __call__(self, x0: np.ndarray, stamp_ns: int, horizon: int, now_ns: int | None = None) -> np.ndarray:
        """The goal of the plan from state ``x0`` stamped ``stamp_ns``: ``(k,)`` (a setpoint) or ``(T, k)`` (a
        reference for x_1 .. x_T); ``now_ns`` (default ``stamp_ns``) decides whether the reference has expired."""
        if self._ref is not None and (now_ns if now_ns is not None else stamp_ns) > self._ref_until:
            self._drop()
        if self._ref is None:
            return self.goal.copy()
        ref = self._ref
        if self._ref_t is not None:
            times = stamp_ns + (np.arange(1, horizon + 1) * self.dt * 1e9)
            out = np.empty((horizon, ref.shape[1]))
            for j in range(ref.shape[1]):
                out[:, j] = np.interp(times, self._ref_t.astype(np.float64), ref[:, j])
            return out
        near = ~self._angle
        d = np.linalg.norm(ref[self._ref_cursor:, near] - x0[np.asarray(self.task.goal_idx)[near]], axis=1)
        self._ref_cursor += int(np.argmin(d))  # never back along the path
        idx = np.minimum(self._ref_cursor + np.arange(1, horizon + 1), len(ref) - 1)
        return ref[idx].copy()
