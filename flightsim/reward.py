"""Rewards of the LidarAvoid environment: pure functions of one step's outcome, chosen by name.

``"tutorial"`` is the seed tutorial's reward, kept exactly so results compare with it.
``"progress"`` (the default) is what the project trains with, because the tutorial's reward pays
+1 a step for merely staying alive: a policy that hovers in place scores almost as well as one
that flies, and PPO finds hovering first and stays there. Success here means flying (at least
40 m in 100 s without a collision), so "progress" pays for forward speed actually achieved and
makes standing still cost something.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

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
