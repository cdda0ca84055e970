"""Sequences of impacts in the paddle-ball world (:mod:`.world`): a high-level controller keeping the ball bouncing
(:func:`bounce_sequence`) and the collection of impact transitions with random commands.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from saml_ros.systems.paddle_ball.world import Impact, PaddleBallWorld

Controller = Callable[[PaddleBallWorld, np.random.Generator], np.ndarray]


#: a high-level controller of :func:`bounce_sequence`: ``(bounce index k, predicted pre-impact state (6,)) ->
#: (command u (6,), target landing point (2,) m)``
BounceChooser = Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]]


#: why :func:`bounce_sequence` ended early (besides the world's own ``"fell"``, ``"out_of_reach"``, ``"timeout"``)
REHIT = "hit again while rising"


OFF_PLAN = "impact not as planned"


NOT_UP = "ball not sent up"


LANDS_OUT = "lands out of reach"


@dataclass
class BounceRecord:
    """The outcome of :func:`bounce_sequence`.

    Attributes:
        bounces: consecutive successful bounces (the ball left the paddle upwards, on plan, towards a landing
            point within the paddle's reach); ``bounces == n`` for a completed sequence.
        failure: why the sequence ended early, ``None`` when all ``n`` bounces succeeded.
        targets, landings: per successful bounce, the target and the predicted landing point (m, xy) of the
            ball's free flight where it next descends through the impact plane.
        errors: per successful bounce, ``||landing - target||`` (m).
        impacts: every impact of the sequence (the failing one included).
    """

    bounces: int
    failure: str | None
    targets: list[np.ndarray] = field(default_factory=list)
    landings: list[np.ndarray] = field(default_factory=list)
    errors: list[float] = field(default_factory=list)
    impacts: list[Impact] = field(default_factory=list)

    @property
    def completed(self) -> bool:
        return self.failure is None


def bounce_sequence(world: PaddleBallWorld, choose: BounceChooser, n: int) -> BounceRecord:
    """Keep the ball bouncing for ``n`` consecutive impacts from the world's current state (after
    :meth:`PaddleBallWorld.reset`): before each impact ``choose(k, x_pre)`` gives the command for the predicted
    pre-impact state and the bounce's target.

    The sequence fails (and stops) when the ball is not kept bouncing: the world loses the ball, no impact comes
    within ``impact_timeout``, the paddle meets the ball while it still rises (:data:`REHIT`), the impact was not
    the planned one (:data:`OFF_PLAN`), the ball does not leave upwards (:data:`NOT_UP`) or its free flight comes
    down outside the paddle's reach (:data:`LANDS_OUT`).
    """
    rec = BounceRecord(0, None)
    o = world.options
    reach = o.reach + o.paddle_half_size
    for k in range(n):
        _, x_pre = world.next_impact()
        u, target = choose(k, x_pre)
        try:
            world.set_command(u)
        except ValueError as exc:
            rec.failure = f"invalid command: {exc}"
            return rec
        imp = None
        for _ in range(int(o.impact_timeout / world.timestep) + 1):
            got = world.step(1)
            if got:
                imp = got[0]
                break
            if world.failed():
                break
        if imp is None:
            rec.failure = world.failure_reason or "timeout"
            return rec
        rec.impacts.append(imp)
        if imp.pre[5] >= 0.0:
            rec.failure = REHIT
        elif not imp.on_plan:
            rec.failure = OFF_PLAN
        elif imp.post_velocity[2] <= 0.0:
            rec.failure = NOT_UP
        if rec.failure is not None:
            return rec
        _, nxt = world.predict_impact(t_min=0.0)  # the free flight's descent through the impact plane
        landing = nxt[:2].copy()
        if max(abs(float(landing[0])), abs(float(landing[1]))) > reach:
            rec.failure = LANDS_OUT
            return rec
        target = np.asarray(target, dtype=np.float64)
        rec.targets.append(target)
        rec.landings.append(landing)
        rec.errors.append(float(np.linalg.norm(landing - target)))
        rec.bounces += 1
    return rec


#: impact speed (m/s) below which :func:`random_commands` cushions the ball (sample_inputs' slow balls: <= 0.51)
SLOW_BALL_SPEED = 0.6


def random_commands(world: PaddleBallWorld, rng: np.random.Generator) -> np.ndarray:
    """A random command drawn like ``PaddleBall.sample_inputs``'s control distribution, ``(6,)``.

    As there, the mode follows the ball: for a slow ball (predicted impact speed below
    :data:`SLOW_BALL_SPEED`) a cushioned catch, paddle velocity ``k`` times the ball's predicted velocity at the
    impact, ``k ~ U[0.3, 0.6]``; otherwise a bounce, ``pvx, pvy ~ U[-0.5, 0.5]``, ``pvz ~ U[0, 2]`` m/s.
    Normals uniform on the cap within 0.35 rad of vertical.
    """
    _, ball = world.next_impact()
    if np.linalg.norm(ball[3:]) < SLOW_BALL_SPEED:
        pv = rng.uniform(0.3, 0.6) * ball[3:]
    else:
        pv = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(0.0, 2.0)])
    cos_tilt = rng.uniform(math.cos(0.35), 1.0)
    sin_tilt = math.sqrt(1.0 - cos_tilt**2)
    phi = rng.uniform(0.0, 2 * math.pi)
    return np.concatenate((pv, (sin_tilt * math.cos(phi), sin_tilt * math.sin(phi), cos_tilt)))


@dataclass
class CollectStats:
    """Book-keeping of :func:`collect_impacts`: impacts kept/dropped (off plan), resets, simulated seconds."""

    kept: int = 0
    off_plan: int = 0
    resets: int = 0
    sim_time: float = 0.0


def collect_impacts(world: PaddleBallWorld, n: int, rng: np.random.Generator,
                    controller: Controller = random_commands, *, only_on_plan: bool = True,
                    stats: CollectStats | None = None) -> list[Impact]:
    """Gather ``n`` impacts, a new ``controller(world, rng)`` command before each; a lost ball is reset with
    :meth:`PaddleBallWorld.reset_random`. With ``only_on_plan`` impacts the controller did not realise
    (``Impact.on_plan`` False) are dropped (counted in ``stats``).
    """
    stats = stats if stats is not None else CollectStats()
    out: list[Impact] = []
    world.reset_random(rng)
    stats.resets += 1
    world.set_command(controller(world, rng))
    while len(out) < n:
        t0 = world.time
        imp = world.run_until_impact(max_time=world.options.impact_timeout)
        stats.sim_time += world.time - t0
        if imp is not None:
            if imp.on_plan or not only_on_plan:
                out.append(imp)
                stats.kept += 1
            else:
                stats.off_plan += 1
        if imp is None or world.failed():
            world.reset_random(rng)
            stats.resets += 1
        world.set_command(controller(world, rng))
    return out


def impacts_to_arrays(impacts: list[Impact]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(x (N, 6), u (N, 6), y (N, 3))`` float64 training arrays: pre state, commanded control, post velocity."""
    if not impacts:
        return np.zeros((0, 6)), np.zeros((0, 6)), np.zeros((0, 3))
    x = np.stack([i.pre for i in impacts])
    u = np.stack([i.u_cmd for i in impacts])
    y = np.stack([i.post_velocity for i in impacts])
    return x, u, y
