"""Giving way to what moves, on the tracker's movers as the shield gets them
(:class:`companion.perception.tracking.Mover`, body axes at the scan's time). Two users:

- the goal baseline ``goal_follower_tracks`` (:class:`training.baselines.GoalFollowerTracks`)
  flies the whole rule below (:meth:`GiveWay.decide`);
- the shield, behind its backup gate (``[shield] give_way``), steps aside where a mover would run
  into the stop the gate falls back to (:meth:`GiveWay.closest`, :meth:`GiveWay.step_aside`).

Each mover is predicted at constant velocity. A velocity the vehicle might fly is predicted as the
autopilot flies it: from the true velocity now towards that velocity with a first-order lag of
``response_time``. The two conflict when, within the horizon, they come closer than the vehicle's
radius + the mover's radius + ``margin`` while closing: a mover that close but drawing apart has
passed.

The whole rule, every frame, the first of these that holds:

1. go: the goal follower's intended velocity is clear for ``course_time`` (after a wait or a
   sidestep, clear ``resume_steps`` frames in a row, so that a wait does not flicker into a go,
   and a sidestep goes on meanwhile: a close mover may drop out of the tracks for a scan or two);
2. wait: a stop is clear for ``wait_time`` (the vehicle keeps facing where it was going);
3. step aside: of the velocities of ``sidestep_speed`` in ``directions`` directions that the action
   can fly and the static scan leaves room for, one clear for ``wait_time``, nearest the intended
   direction (the sidestep's own, once stepping); with none clear, the one that meets a mover
   latest, then least deep (a head-on drone, a walker whose path runs through the waiting vehicle). With
   no room anywhere: wait.

Pure logic: velocities, movers and the scan's clearances in, a decision out.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from companion.perception.scan import N_BINS
from companion.perception.tracking import Mover


@dataclass(frozen=True)
class GiveWayConfig:
    """Tuning of :class:`GiveWay` (metres, seconds, m/s).

    :param vehicle_radius: the vehicle's radius, m
    :param margin: distance kept beyond both radii, m
    :param course_time: seconds of the intended course that must be clear to go
    :param wait_time: seconds a stop (or a sidestep) must stay clear for
    :param response_time: time constant of the autopilot's velocity following a command, s
    :param step_s: time step of the prediction, s
    :param sidestep_speed: speed of a sidestep, m/s
    :param directions: sidestep directions tried, evenly spaced round the vehicle (even: straight
        back is one)
    :param room: static clearance a sidestep's direction needs beyond its travel in ``course_time``, m
    :param resume_steps: frames in a row the intended course must be clear before going again
    """

    vehicle_radius: float = 0.25
    margin: float = 0.4
    course_time: float = 2.0
    wait_time: float = 3.0
    response_time: float = 0.5
    step_s: float = 0.1
    sidestep_speed: float = 1.0
    directions: int = 16
    room: float = 0.3
    resume_steps: int = 5


@dataclass(frozen=True)
class Decision:
    """What to fly this frame.

    :param mode: ``go`` (the intended velocity), ``wait`` (stop) or ``step`` (aside)
    :param velocity: body velocity (forward, left) to fly, m/s
    """

    mode: Literal["go", "wait", "step"]
    velocity: tuple[float, float]


class GiveWay:
    """The wait-and-go rule with a sidestep (see the module docstring); one instance per flight.

    :param config: tuning
    """

    def __init__(self, config: GiveWayConfig | None = None) -> None:
        self.config = config or GiveWayConfig()
        c = self.config
        self._times = np.arange(0.0, max(c.course_time, c.wait_time) + 1e-9, c.step_s)
        #: the sidesteps' directions, rad counter-clockwise from the nose
        self._angles = [2.0 * math.pi * k / c.directions for k in range(c.directions)]
        self.reset()

    def reset(self) -> None:
        """A new flight: nothing waited for."""
        self._clear_run = self.config.resume_steps
        self._stepping: tuple[float, float] | None = None  # the sidestep being flown

    def decide(
        self,
        intended: Sequence[float],
        velocity: Sequence[float],
        movers: Sequence[Mover],
        clear: np.ndarray,
        max_left: float,
    ) -> Decision:
        """This frame's decision.

        :param intended: body velocity (forward, left) the goal follower means to fly, m/s
        :param velocity: the vehicle's true body velocity now, m/s
        :param movers: what moves, as the tracker gives it
        :param clear: ``(360,)`` static corridor clearance per heading (bin centres CCW from the
            nose), m: where a sidestep has room
        :param max_left: the largest sideways speed the action can ask, m/s (0: along the nose only)
        """
        c = self.config
        go = (float(intended[0]), float(intended[1]))
        course_clear = self.closest(go, velocity, movers, c.course_time) >= 0.0
        self._clear_run = self._clear_run + 1 if course_clear else 0
        if self._clear_run >= c.resume_steps:
            self._stepping = None
            return Decision("go", go)
        if course_clear and self._stepping is not None:  # a mover lost from sight: finish the step
            return Decision("step", self._stepping)
        if self.closest((0.0, 0.0), velocity, movers, c.wait_time) >= 0.0:
            self._stepping = None
            return Decision("wait", (0.0, 0.0))
        decision = self._sidestep(go, velocity, movers, clear, max_left)
        self._stepping = decision.velocity if decision.mode == "step" else None
        return decision

    def closest(
        self, command: Sequence[float], velocity: Sequence[float], movers: Sequence[Mover], horizon: float
    ) -> float:
        """How far beyond the keep-apart distance (radii + ``margin``) the nearest closing mover
        passes within ``horizon`` when the vehicle is commanded ``command``, m: negative is a
        conflict, ``inf`` none closes.

        :param command: body velocity commanded from now on, m/s
        :param velocity: the true body velocity now, m/s
        """
        return self.encounter(command, velocity, movers, horizon)[0]

    def encounter(
        self, command: Sequence[float], velocity: Sequence[float], movers: Sequence[Mover], horizon: float
    ) -> tuple[float, float]:
        """(:meth:`closest`'s distance, seconds until the first conflict: ``inf`` with none)."""
        nearest, first = self.encounters(
            np.asarray(command, dtype=np.float64)[None], velocity, movers, horizon
        )
        return float(nearest[0]), float(first[0])

    def encounters(
        self, commands: np.ndarray, velocity: Sequence[float], movers: Sequence[Mover], horizon: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`encounter` of each of ``commands`` (``(n, 2)`` body velocities, m/s) at once:
        ``(n,)`` distances and ``(n,)`` seconds."""
        c = self.config
        t = self._times[self._times <= horizon + 1e-9]
        if not movers:
            return np.full(len(commands), math.inf), np.full(len(commands), math.inf)
        cmd, now = np.asarray(commands, dtype=np.float64), np.asarray(velocity, dtype=np.float64)
        lag = c.response_time * (1.0 - np.exp(-t / c.response_time))
        path = t[None, :, None] * cmd[:, None, :] + lag[None, :, None] * (now - cmd)[:, None, :]  # (n, T, 2)
        position = np.array([m.position for m in movers], dtype=np.float64)
        motion = np.array([m.velocity for m in movers], dtype=np.float64)
        keep = c.vehicle_radius + np.array([m.radius for m in movers], dtype=np.float64) + c.margin
        ahead = position[:, None, :] + t[None, :, None] * motion[:, None, :]  # (k, T, 2)
        rel = ahead[None] - path[:, None]  # (n, k, T, 2)
        gap = np.hypot(rel[..., 0], rel[..., 1]) - keep[None, :, None]  # (n, k, T)
        k = np.argmin(gap, axis=2)
        least = np.take_along_axis(gap, k[..., None], axis=2)[..., 0]  # (n, k)
        closing = k > 0  # closing at some time ahead; drawing apart from now on is no conflict
        met = closing & (least < 0.0)
        first = np.where(met, t[np.argmax(gap < 0.0, axis=2)], math.inf).min(axis=1)
        return np.where(closing, least, math.inf).min(axis=1), first

    def sidesteps(self, max_back: float = math.inf) -> np.ndarray:
        """``(directions, 2)`` the sidestep velocities (body forward, left), m/s: ``sidestep_speed``
        towards each direction, slowed where its backward part would exceed ``max_back``."""
        speed = self.config.sidestep_speed
        rows = []
        for angle in self._angles:
            c, s = math.cos(angle), math.sin(angle)
            v = min(speed, max_back / -c) if c < 0.0 else speed
            rows.append((v * c, v * s))
        return np.array(rows)

    def preference(
        self,
        candidates: np.ndarray,
        nearest: np.ndarray,
        first: np.ndarray,
        current: tuple[float, float] | None,
    ) -> np.ndarray:
        """The shield's order of sidesteps, best first: those no mover meets within ``wait_time``,
        nearest ``current``'s direction first (the nose's without one); then the others, met latest,
        then least deep, ``current`` first among equals.

        :param candidates: ``(n, 2)`` body velocities, m/s (:meth:`sidesteps`)
        :param nearest: ``(n,)`` and ``first``, ``(n,)``: their :meth:`encounters`
        :param current: the sidestep sent last, if the vehicle is stepping aside
        :return: ``(n,)`` indices into ``candidates``
        """
        ahead = math.atan2(current[1], current[0]) if current is not None else 0.0
        turn = np.abs(_wrap(np.arctan2(candidates[:, 1], candidates[:, 0]) - ahead))
        other = np.array([tuple(v) != current for v in candidates.tolist()])
        clear = np.isinf(first)
        # np.lexsort sorts by its last key first
        return np.lexsort((other, np.where(clear, turn, -nearest), np.where(clear, 0.0, -first), ~clear))

    def _sidestep(
        self,
        go: tuple[float, float],
        velocity: Sequence[float],
        movers: Sequence[Mover],
        clear: np.ndarray,
        max_left: float,
    ) -> Decision:
        """The sidestep of the module docstring's third rule."""
        c = self.config
        candidates = self.sidesteps()
        bins = [int(math.degrees(angle)) % N_BINS for angle in self._angles]
        usable = (np.abs(candidates[:, 1]) <= max_left + 1e-9) & (
            clear[bins] >= c.sidestep_speed * c.course_time + c.room
        )
        toward = self._stepping or go  # a sidestep keeps its direction while it stays clear
        want = math.atan2(toward[1], toward[0]) if toward != (0.0, 0.0) else 0.0
        best: tuple[float, float, float, tuple[float, float]] | None = None
        for angle, v, ok in zip(self._angles, candidates, usable, strict=True):
            if not ok:
                continue
            step = (float(v[0]), float(v[1]))
            gap, first = self.encounter(step, velocity, movers, c.wait_time)
            turn = abs((angle - want + math.pi) % (2.0 * math.pi) - math.pi)
            # any clear one is as good; of the others, the latest to conflict, then the shallowest
            key = (first, min(gap, 0.0), -turn, step)
            if best is None or key[:3] > best[:3]:
                best = key
        return Decision("wait", (0.0, 0.0)) if best is None else Decision("step", best[3])


def _wrap(angle: np.ndarray) -> np.ndarray:
    """``angle`` wrapped into [-pi, pi), rad."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi
