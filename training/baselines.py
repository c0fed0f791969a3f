"""Baselines the learned policy is measured against, on the same 360-bin scan it sees.

* :class:`RandomController` — uniform random actions: the floor.
* :class:`GapFollower` — a classical reactive controller (follow-the-gap with the vehicle's width,
  as in VFH's "enlarged obstacles"): for every heading it computes how far the vehicle could fly
  straight before its body touches a return, steers towards the freest heading near straight
  ahead, and slows down as the clearance ahead shrinks. No learning, no memory.

Both implement the controller interface the evaluator uses: ``reset(scan)`` at an episode start,
then ``act(scan) -> (2,)`` per scan, actions in ``[-1, 1]`` (a0 forward speed, a1 yaw rate,
counter-clockwise positive).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from companion.scan import N_BINS

_ANGLES = np.deg2rad(np.arange(N_BINS) + 0.5)  # bin centres, counter-clockwise from straight ahead
_SIGNED = np.where(np.pi < _ANGLES, _ANGLES - 2 * np.pi, _ANGLES)  # in (-pi, pi]


class RandomController:
    """Uniformly random actions (seeded, so an evaluation is repeatable)."""

    def __init__(self, seed: int = 0) -> None:
        self._rng = np.random.default_rng(seed)

    def reset(self, scan: np.ndarray) -> np.ndarray:
        return self.act(scan)

    def act(self, scan: np.ndarray) -> np.ndarray:
        return self._rng.uniform(-1.0, 1.0, size=2).astype(np.float32)


@dataclass(frozen=True)
class GapFollowerConfig:
    """Tuning of :class:`GapFollower` (metres, radians, and fractions of the action range).

    :param max_range: range of a scan value of 1.0 (the scan's ``max_range``)
    :param body_radius: half-width of the corridor a heading must keep clear (vehicle radius + margin)
    :param horizon: clearances beyond this are "free enough"; caps the score so near-straight wins
    :param straight_bias: score penalty per radian of turn, metres (prefers holding course)
    :param sector_deg: candidate headings within this many degrees of straight ahead
    :param cruise: forward action with a clear path ahead
    :param stop_distance: forward action is 0 at or below this clearance straight ahead
    :param slow_distance: forward action reaches ``cruise`` at this clearance straight ahead
    :param turn_gain: yaw-rate action per radian of heading error
    """

    max_range: float = 10.0
    body_radius: float = 0.55
    horizon: float = 4.0
    straight_bias: float = 0.8
    sector_deg: float = 150.0
    cruise: float = 0.8
    stop_distance: float = 0.6
    slow_distance: float = 2.5
    turn_gain: float = 1.5


def corridor_clearance(ranges: np.ndarray, body_radius: float) -> np.ndarray:
    """For each bin's heading, the distance the vehicle can fly straight before its body meets a return.

    A return at range ``r`` and angle offset ``d`` from the heading blocks it when it lies ahead
    (``cos d > 0``) and within ``body_radius`` sideways (``r |sin d| < body_radius``); it then
    limits travel to ``r cos d``. Returns closer than ``body_radius`` block every heading they are
    in front of.

    :param ranges: ``(360,)`` ranges in metres (``inf`` where nothing was seen)
    :param body_radius: corridor half-width, metres
    :return: ``(360,)`` clearance per heading, metres (``inf`` when nothing blocks it)
    """
    return _corridor_kernel(np.ascontiguousarray(ranges, dtype=np.float64), float(body_radius))


@njit(cache=True)
def _corridor_kernel(ranges: np.ndarray, body_radius: float) -> np.ndarray:  # pragma: no cover - compiled
    """Each return only touches the headings within ``asin(body_radius / r)`` of it: O(bins × window)."""
    n = ranges.shape[0]
    step = 2.0 * np.pi / n
    out = np.full(n, np.inf)
    for j in range(n):
        r = ranges[j]
        if not np.isfinite(r):
            continue
        half = np.pi / 2.0 if r <= body_radius else np.arcsin(body_radius / r)
        w = int(half / step) + 1
        for k in range(-w, w + 1):
            d = k * step
            along = r * np.cos(d)
            if along <= 1e-9 or abs(r * np.sin(d)) >= body_radius:  # exactly abeam is not ahead
                continue
            i = (j - k) % n  # heading i sees return j at offset j - i = k
            if along < out[i]:
                out[i] = along
    return out


class GapFollower:
    """Follow-the-gap with the vehicle's width (see the module docstring).

    :param config: tuning
    """

    def __init__(self, config: GapFollowerConfig | None = None) -> None:
        self.config = config or GapFollowerConfig()
        self._candidates = np.abs(_SIGNED) <= np.deg2rad(self.config.sector_deg)

    def reset(self, scan: np.ndarray) -> np.ndarray:
        return self.act(scan)

    def act(self, scan: np.ndarray) -> np.ndarray:
        """One action for one scan (``(360,)`` normalised ranges, 1.0 = nothing seen)."""
        c = self.config
        s = np.asarray(scan, dtype=np.float64).reshape(N_BINS)
        ranges = np.where(s >= 1.0, np.inf, s * c.max_range)
        clearance = corridor_clearance(ranges, c.body_radius)
        score = np.minimum(clearance, c.horizon) - c.straight_bias * np.abs(_SIGNED)
        score = np.where(self._candidates, score, -np.inf)
        heading = float(_SIGNED[int(np.argmax(score))])
        ahead = float(min(clearance[0], clearance[-1]))
        speed = c.cruise * np.clip((ahead - c.stop_distance) / (c.slow_distance - c.stop_distance), 0.0, 1.0)
        speed *= max(0.0, float(np.cos(heading)))  # turn first, then go
        yaw = np.clip(c.turn_gain * heading, -1.0, 1.0)
        return np.array([speed, yaw], dtype=np.float32)
