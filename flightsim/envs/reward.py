"""Rewards of the environments: pure functions of one step's outcome.

LidarAvoid-v0 chooses one of :data:`REWARDS` by name; LidarNav-v0 pays :func:`goal_reward`.

``"tutorial"`` is the seed tutorial's reward, kept exactly so results compare with it.
``"progress"`` (the default) is what the project trains with, because the tutorial's reward pays
+1 a step for merely staying alive: a policy that hovers in place scores almost as well as one
that flies, and PPO finds hovering first and stays there. Success here means flying (at least
40 m in 100 s without a collision), so "progress" pays for forward speed actually achieved and
makes standing still cost something.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class StepOutcome:
    """What a reward may look at after one control step.

    :param action: the clipped action ``(a0 forward, a1 yaw rate)`` in ``[-1, 1]``
    :param scan_min: smallest value of the current (fresh) scan, normalised (0.1 = 1 m at 10 m range)
    :param forward_speed: velocity along the nose actually flown, m/s
    :param max_speed: forward speed that ``a0 = 1`` commands, m/s
    :param collision: the vehicle touched geometry this step
    """

    action: np.ndarray
    scan_min: float
    forward_speed: float
    max_speed: float
    collision: bool


PROXIMITY_THRESHOLD = 0.1  # normalised scan value: 1 m at the default 10 m range


def _proximity_penalty(scan_min: float) -> float:
    """The tutorial's: inside 1 m, ``(0.1 - min(scan)) * 10`` (up to 1.0 when touching)."""
    return (PROXIMITY_THRESHOLD - scan_min) * 10.0 if scan_min < PROXIMITY_THRESHOLD else 0.0


def tutorial_reward(o: StepOutcome) -> float:
    """The seed tutorial's reward, exactly.

    Collision −200 (the episode ends); otherwise +1 survival, +0.5·a0 when a0 > 0, the proximity
    penalty inside 1 m, and −0.2 for a sharp turn (|a0| > 0.5 and |a1| > 0.5).
    """
    if o.collision:
        return -200.0
    a0, a1 = float(o.action[0]), float(o.action[1])
    reward = 1.0
    if a0 > 0.0:
        reward += 0.5 * a0
    reward -= _proximity_penalty(o.scan_min)
    if abs(a0) > 0.5 and abs(a1) > 0.5:
        reward -= 0.2
    return reward


def progress_reward(o: StepOutcome) -> float:
    """Pay for flying, not for existing.

    Per step: forward speed flown / max speed (so up to +1 at full speed, negative backwards),
    minus the tutorial's proximity penalty inside 1 m, minus ``0.05·|a1|`` (turning in place is not
    progress), minus 0.1 while slower than 0.2 m/s (hovering is not success). Collision −100.
    A hovering policy earns −0.1 a step; one cruising at 1 m/s earns about +0.5.
    """
    if o.collision:
        return -100.0
    reward = o.forward_speed / o.max_speed
    reward -= _proximity_penalty(o.scan_min)
    reward -= 0.05 * abs(float(o.action[1]))
    if o.forward_speed < 0.2:
        reward -= 0.1
    return reward


REWARDS: dict[str, Callable[[StepOutcome], float]] = {
    "tutorial": tutorial_reward,
    "progress": progress_reward,
}


# --- the goal task (LidarNav-v0) -------------------------------------------------------------------


@dataclass(frozen=True)
class GoalRewardConfig:
    """Weights of :func:`goal_reward` (strict-loadable as ``[env.goal_reward]``).

    :param progress: per metre flown closer to the current waypoint (negative when moving away)
    :param waypoint_bonus: on reaching a waypoint (the last one included)
    :param finish_bonus: on reaching the last waypoint, on top of ``waypoint_bonus``
    :param collision: paid once, on the colliding step (the episode ends)
    :param time_cost: per step (0.1 s): a slow or hovering pilot pays for it
    :param proximity: times the tutorial's proximity penalty (up to 1.0 a step inside 1 m)
    """

    progress: float = field(default=1.0, metadata={"min": 0.0, "max": 100.0})
    waypoint_bonus: float = field(default=10.0, metadata={"min": 0.0, "max": 1000.0})
    finish_bonus: float = field(default=10.0, metadata={"min": 0.0, "max": 1000.0})
    collision: float = field(default=50.0, metadata={"min": 0.0, "max": 1000.0})
    time_cost: float = field(default=0.02, metadata={"min": 0.0, "max": 10.0})
    proximity: float = field(default=0.25, metadata={"min": 0.0, "max": 10.0})


@dataclass(frozen=True)
class GoalStep:
    """What the goal reward looks at after one control step, beside :class:`StepOutcome`.

    :param progress_m: metres the vehicle came closer to the waypoint it was flying to
    :param reached: it reached that waypoint this step
    :param finished: that waypoint was the last one
    """

    progress_m: float
    reached: bool
    finished: bool


def goal_reward(o: StepOutcome, g: GoalStep, w: GoalRewardConfig) -> float:
    """Fly to the waypoints, in order, soon, without touching anything.

    Per step: ``progress·progress_m`` (potential-based: circling or flying back and forth earns
    nothing), ``− time_cost``, ``− proximity ×`` the tutorial's proximity penalty inside 1 m;
    ``+ waypoint_bonus`` on reaching a waypoint and ``+ finish_bonus`` more on the last one;
    a collision costs ``collision`` and nothing else counts on that step. With the defaults a
    straight 20 m leg flown at 2 m/s earns about +28 (20 progress, 10 bonus, −2 time).
    """
    if o.collision:
        return -w.collision
    reward = w.progress * g.progress_m - w.time_cost - w.proximity * _proximity_penalty(o.scan_min)
    if g.reached:
        reward += w.waypoint_bonus + (w.finish_bonus if g.finished else 0.0)
    return reward
