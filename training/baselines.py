"""Baselines the learned policy is measured against, on the same observation it sees.

Avoidance task (LidarAvoid-v0, a 360-bin scan):

* :class:`RandomController` — uniform random actions: the floor.
* :class:`GapFollower` — a classical reactive controller (follow-the-gap with the vehicle's width,
  as in VFH's "enlarged obstacles"): for every heading it computes how far the vehicle could fly
  straight before its body touches a return, steers towards the freest heading near straight
  ahead, and slows down as the clearance ahead shrinks. No learning, no memory.

Goal task (LidarNav-v0, the scan + goal bearing/distance + measured velocity frame of
:class:`companion.perception.observation.ObservationLayout`):

* :class:`StraightLine` — turn to the goal and fly at it, no avoidance: how hard a world is.
* :class:`GoalFollower` — the classical goal-directed controller (see its docstring).
* :class:`GoalFollowerTracks` — the goal follower giving way to the tracker's movers
  (:mod:`companion.safety.give_way`).

All implement the controller interface the evaluator uses: ``reset(obs)`` at an episode start,
then ``act(obs) -> (2,)`` per step, actions in ``[-1, 1]`` (a0 forward speed, a1 yaw rate,
counter-clockwise positive).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

from companion.perception.drift import DriftConfig, DriftEstimator, DriftHoldConfig, held_drift
from companion.perception.observation import ObservationLayout
from companion.perception.scan import N_BINS
from companion.perception.tracking import Mover
from companion.safety.give_way import GiveWay, GiveWayConfig

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


def _goal(obs: np.ndarray, layout: ObservationLayout) -> tuple[np.ndarray, float, float]:
    """(scan, goal bearing rad CCW from the nose, goal distance m) of one goal-layout frame."""
    o = np.asarray(obs, dtype=np.float64).reshape(layout.frame_size)
    n = layout.n_bins
    return o[:n], math.atan2(o[n + 1], o[n]), float(o[n + 2]) * layout.goal_range


def _velocity(obs: np.ndarray, layout: ObservationLayout) -> tuple[float, float]:
    """(forward, left) measured body velocity, m/s, of one goal-layout frame."""
    o = np.asarray(obs, dtype=np.float64).reshape(layout.frame_size)
    n = layout.n_bins
    return float(o[n + 3]) * layout.velocity_scale, float(o[n + 4]) * layout.velocity_scale


def _drift(obs: np.ndarray, layout: ObservationLayout) -> np.ndarray:
    """(forward, left) drift estimate, m/s, of one drift-layout frame (what the env's estimator,
    and so its ``drift_hold``, saw)."""
    o = np.asarray(obs, dtype=np.float64).reshape(layout.frame_size)
    return o[layout.slices()["drift"]] * layout.velocity_scale


def _wrap(angle: float | np.ndarray) -> float | np.ndarray:
    return (angle + np.pi) % (2 * np.pi) - np.pi


def _bin(angle: float) -> int:
    """The scan bin a direction (rad, CCW from the nose) falls in. ``x % 360.0`` is 360.0 for a
    tiny negative ``x`` (-1e-15 rounds to it), one past the last bin: the second ``%`` folds it."""
    return int(math.degrees(angle) % 360.0) % N_BINS


@dataclass(frozen=True)
class StraightLineConfig:
    """:param cruise: forward action once facing the goal
    :param turn_gain: yaw-rate action per radian of bearing"""

    cruise: float = 1.0
    turn_gain: float = 2.0


class StraightLine:
    """Turn to the goal and fly straight at it, blind to obstacles (a world's difficulty gauge)."""

    def __init__(self, layout: ObservationLayout, config: StraightLineConfig | None = None) -> None:
        self.layout, self.config = layout, config or StraightLineConfig()

    def reset(self, obs: np.ndarray) -> np.ndarray:
        return self.act(obs)

    def act(self, obs: np.ndarray) -> np.ndarray:
        _, bearing, _ = _goal(obs, self.layout)
        c = self.config
        speed = c.cruise * max(0.0, math.cos(bearing)) ** 2
        return np.array([speed, np.clip(c.turn_gain * bearing, -1.0, 1.0)], dtype=np.float32)


@dataclass(frozen=True)
class GoalFollowerConfig:
    """Tuning of :class:`GoalFollower` (metres, radians, steps of 0.1 s, fractions of the action range).

    :param max_range: range of a scan value of 1.0
    :param body_radius: half-width of the corridor a heading must keep clear (radius 0.25 + margin)
    :param lookahead: a heading is admissible when its corridor is clear this far (or to the goal)
    :param hysteresis: cost per radian of changing the chosen heading's offset from the goal,
        so the choice does not flip between two gaps around an obstacle on the goal line
    :param horizon: metres of clearance beyond which a heading counts as open (a subgoal candidate)
    :param jump: metres between neighbouring bins' ranges that mark an obstacle's edge
    :param edge_margin: metres beyond an edge the subgoal direction passes (on top of ``body_radius``)
    :param subgoal_hysteresis: metres of heuristic per radian of change in the subgoal direction
    :param swept_margin: the speed also follows the clearance along the chosen heading of a corridor
        this much wider on each side (a vehicle turning at speed drifts off its heading), but not
        below ``creep`` (a gap narrower than the wide corridor is passed slowly, not refused)
    :param creep: see ``swept_margin``

    :param cruise: forward action with a clear path ahead
    :param stop_distance: forward action is 0 at or below this clearance along the chosen heading
    :param slow_distance: forward action reaches ``cruise`` at this clearance
    :param turn_gain: yaw-rate action per radian of heading error
    :param stall_steps: no progress of ``stall_progress`` toward the goal for this long → escape
    :param stall_progress: metres of progress that count as progress
    :param escape_steps: longest escape (boundary following) before trying the goal again
    :param wall_lookahead: clearance a heading needs to count as free while following a boundary
    :param boundary_range: a boundary is followed only while a return on its side lies this close

    What the autopilot really does (:mod:`flightsim.vehicle.autopilot_response`: lag, overshoot, a capped
    yaw rate, and a velocity loop closed on an estimate that may be 0.2–0.4 m/s off):

    :param keep_out: returns closer than this (vehicle centre, m) are left first: only headings
        that do not close on them are admissible, and the forward action gets a push away from them
    :param push_gain: forward action per unit of that push (depth inside ``keep_out``), at most ``creep``
    :param stop_time: seconds of travel at a speed that the slowest response needs to stop from it
        (the randomised PX4-like responses' stopping distance is 1.1–1.7 s × speed; ideal 0.33 s):
        no forward command the vehicle could not stop from within the clearance ahead, and a stop
        when the measured course runs into something within that distance
    :param course_min_speed: m/s below which the measured course is too uncertain to check
    :param step_s: seconds between two frames (the env's 10 Hz)
    :param crab_min_speed: m/s of wanted travel from which the nose leads into the estimate's
        error (below it the vehicle turns to its heading and only the along-nose part is compensated)
    :param crab_max: the largest such lead, rad
    :param gain_steady: steps a forward command must hold (within 10 %) before the measured speed
        is compared with it; the forward command is divided by the learnt ratio
    :param gain_min_speed: m/s below which a command is not compared
    :param gain_range: bounds of that ratio
    :param gain_time: time constant, s, of the filter on that ratio
    """

    max_range: float = 10.0
    body_radius: float = 0.42
    lookahead: float = 2.5
    hysteresis: float = 0.5
    horizon: float = 8.0
    jump: float = 1.0
    edge_margin: float = 0.3
    subgoal_hysteresis: float = 1.0
    swept_margin: float = 0.2
    creep: float = 0.3
    cruise: float = 0.7
    stop_distance: float = 0.6
    slow_distance: float = 3.5
    turn_gain: float = 2.0
    stall_steps: int = 40
    stall_progress: float = 0.5
    escape_steps: int = 200
    wall_lookahead: float = 1.5
    boundary_range: float = 3.0
    keep_out: float = 0.55
    push_gain: float = 1.0
    stop_time: float = 1.2
    course_min_speed: float = 0.2
    step_s: float = 0.1
    crab_min_speed: float = 0.2
    crab_max: float = 0.6
    gain_steady: int = 5
    gain_min_speed: float = 0.3
    gain_range: tuple[float, float] = (0.6, 1.1)
    gain_time: float = 2.0


@dataclass(frozen=True)
class GoalStep:
    """What :class:`GoalFollower` decided for one frame, before its command.

    :param speed: forward action along ``heading`` (its fraction of the velocity scale)
    :param heading: direction to travel, rad CCW from the nose
    :param bearing: the goal's direction, rad CCW from the nose
    :param ranges: ``(360,)`` the scan in metres (``inf``: nothing seen)
    :param clear: ``(360,)`` corridor clearance per heading, metres (:func:`corridor_clearance`)
    :param velocity: true body velocity (forward, left), m/s: measured less the estimate's error
    """

    speed: float
    heading: float
    bearing: float
    ranges: np.ndarray
    clear: np.ndarray
    velocity: np.ndarray


class GoalFollower:
    """Tangent Bug on the scan: steer for the goal or the obstacle edge that promises the shortest way,
    through the admissible heading nearest to it, with hysteresis and a boundary-following escape.

    Every step, as Tangent Bug (Kamon, Rivlin & Rimon 1998) does with a range sensor: the subgoal
    is the goal itself when its heading is clear (to the goal or for ``horizon``), else the edge of
    an obstacle (a jump of ``jump`` between neighbouring bins, the direction passing it by
    ``body_radius + edge_margin``) that minimises ``|edge| + |goal - edge|``; changing the
    subgoal's direction costs ``subgoal_hysteresis`` metres per radian (offsets are measured from
    the goal bearing, so the vehicle's own turning is no change). For each heading the distance the
    vehicle's body could fly straight before touching a return (:func:`corridor_clearance`);
    headings clear for ``lookahead`` (or up to the goal) are admissible, and the one nearest the
    subgoal is flown (``hysteresis`` against changes); with none admissible, the freest heading.
    Speed falls with the clearance along the chosen heading (also of a wider, swept corridor) and
    with the heading error (turn first, then go).

    Concave obstacles (a U between start and goal) trap any such greedy rule, so when the goal has
    come no ``stall_progress`` closer for ``stall_steps``, the controller follows the obstacle's
    boundary (as Bug algorithms do), keeping it on the side it was already turning toward, until the
    goal's bearing is admissible again from closer than where it got stuck, or ``escape_steps``
    pass, or nothing is left beside to follow.

    A real autopilot does not fly the command as given (:mod:`flightsim.vehicle.autopilot_response`), and
    geometry alone crashed in 43 % of the test worlds through the randomised response. So:

    * **Drift the estimate hides.** PX4 closes its velocity loop on an estimate up to 0.2–0.4 m/s
      off, so a vehicle told to hover drifts at that error while reporting zero. The controller
      measures its true motion from the previous and the current scan
      (:class:`companion.perception.drift.DriftEstimator`), keeps the difference to the reported velocity
      (the estimate's error, low-pass filtered) and commands the wanted velocity *plus*
      that error: the along-nose part directly, the sideways part by leading with the nose
      (a crab angle up to ``crab_max``).
    * **Lag and overshoot.** No forward command faster than the vehicle can stop from within the
      clearance along its heading (``stop_time`` s of travel), and a stop when the true course
      (reported velocity less the error) runs into something within that stopping distance: in a
      turn the vehicle slides outward, not along its nose.
    * **Keep-out.** Within ``keep_out`` of a return, only headings that leave it are flown, and
      the forward action is pushed away from it (backward when it is ahead): the one escape that
      needs no turn first, for a capped yaw rate makes turns slow.

    Where the setpoint already carries part of the error (the env's ``drift_hold``, the
    companion's ``[drift_hold]``), the controller makes up only for the rest: that part, computed
    from the frame's own drift estimate as the env does, is taken off its command.

    Memory: the previous frame, the estimate's error and the few numbers of the escape; no map.
    The policy sees the same (four stacked frames carry the scan-to-scan motion too).

    :param layout: the frame layout (a goal layout)
    :param config: tuning
    :param hold: the limits of the drift the setpoint carries on top of every action, or None when
        it carries none (then a drift layout is not needed)
    :raises ValueError: ``hold`` with a layout without drift features
    """

    def __init__(
        self,
        layout: ObservationLayout,
        config: GoalFollowerConfig | None = None,
        hold: DriftHoldConfig | None = None,
    ) -> None:
        if hold is not None and not layout.drift:
            raise ValueError(f"a drift hold needs the drift estimate in the frame: layout {layout.name}")
        self.layout, self.config, self.hold = layout, config or GoalFollowerConfig(), hold

    def reset(self, obs: np.ndarray) -> np.ndarray:
        self._offset = 0.0  # last chosen heading minus the goal bearing
        self._subgoal_offset = 0.0  # last subgoal direction minus the goal bearing
        self._best = math.inf  # closest to the goal since the last progress
        self._since_progress = 0
        self._escape_side = 0  # +1: boundary on the right (turning left), -1: on the left; 0: no escape
        self._escape_left = 0
        self._stuck_at = math.inf
        self._last_distance = math.inf
        # the scan's max_range is the matcher's too: returns there are saturation, not walls
        self._drift = DriftEstimator(DriftConfig(max_range=self.config.max_range))
        self._bias = np.zeros(2)  # velocity estimate minus true velocity, body frame, m/s
        self._held = np.zeros(2)  # what the setpoint carries of it on top of the action, m/s
        self._speed_gain = 1.0  # measured / commanded forward speed, steady state
        self._commands: deque[float] = deque(maxlen=self.config.gain_steady)  # forward m/s sent
        return self.act(obs)

    def act(self, obs: np.ndarray) -> np.ndarray:
        step = self._plan(obs)
        action = self._command(step.speed, step.heading)
        action[0] = np.clip(action[0] + self._push_off(step.ranges), -1.0, 1.0)
        return action

    def _plan(self, obs: np.ndarray) -> GoalStep:
        """This frame's heading and speed (and what they were judged on), before the command that
        makes the autopilot fly them."""
        c = self.config
        scan, bearing, distance = _goal(obs, self.layout)
        ranges = np.where(scan >= 1.0, np.inf, scan * c.max_range)
        clear = corridor_clearance(ranges, c.body_radius)
        measured = np.array(_velocity(obs, self.layout))
        velocity = self._true_velocity(ranges, measured, bearing, distance)
        if self.hold is not None:
            self._held = np.array(held_drift(_drift(obs, self.layout), self.hold))
        self._learn_speed_gain(float(measured[0]))
        self._track_progress(distance)
        heading = self._heading(ranges, clear, bearing, distance)
        self._offset = float(_wrap(heading - bearing))
        k = _bin(heading)
        wide = corridor_clearance(ranges, c.body_radius + c.swept_margin)
        speed = self._ramp(float(clear[k]), distance) * max(0.0, math.cos(heading)) ** 2
        speed = min(speed, max(c.creep, self._ramp(float(wide[k]), distance)))

        ahead = float(min(clear[0], clear[-1]))
        if ahead < c.stop_distance:
            speed = 0.0
        speed = min(speed, self._stoppable(float(clear[k])))
        if self._cannot_stop_along_course(clear, *velocity):
            speed = 0.0
        return GoalStep(speed, heading, bearing, ranges, clear, velocity)

    def _heading(self, ranges: np.ndarray, clear: np.ndarray, bearing: float, distance: float) -> float:
        """The heading to fly (rad CCW from the nose): along the boundary while escaping, else
        the admissible heading nearest the subgoal, else the freest."""
        c = self.config
        admissible = clear >= np.minimum(c.lookahead, distance)
        away = self._away_from(ranges)
        if (admissible & away).any():
            admissible &= away
        if self._escape_side:
            self._escape_left -= 1
            goal_bin = _bin(bearing)
            goal_free = bool(admissible[goal_bin]) and distance < self._stuck_at - c.stall_progress
            if goal_free or self._escape_left <= 0:
                self._escape_side = 0
                self._best, self._since_progress = distance, 0
        boundary = self._follow_boundary(ranges, clear, away) if self._escape_side else None
        if self._escape_side and boundary is None:  # nothing beside to follow: the trap is behind
            self._escape_side = 0
            self._best, self._since_progress = distance, 0
        if boundary is not None:
            return boundary
        if not admissible.any():
            return float(_SIGNED[int(np.argmax(np.minimum(clear, c.max_range)))])
        target = self._subgoal(ranges, clear, bearing, distance)
        self._subgoal_offset = float(_wrap(target - bearing))
        change = np.abs(_wrap(_SIGNED - bearing) - self._offset)
        cost = np.abs(_wrap(_SIGNED - target)) + c.hysteresis * change
        return float(_SIGNED[int(np.argmin(np.where(admissible, cost, np.inf)))])

    def _command(self, speed: float, heading: float) -> np.ndarray:
        """The action that makes the vehicle really travel at ``speed`` (action units) along
        ``heading``: the autopilot flies its *estimate* to the command, so the true velocity falls
        short of it by the estimate's error; command the wanted velocity plus that error (less
        what the setpoint already holds of it) instead. Only its along-nose part can be commanded,
        so the nose leads by the crab angle too."""
        c = self.config
        scale = self.layout.velocity_scale
        want = speed * scale * np.array([math.cos(heading), math.sin(heading)])
        command = want + self._bias - self._held
        steer = heading
        if speed * scale >= c.crab_min_speed:
            crab = float(_wrap(math.atan2(command[1], command[0]) - heading))
            steer = heading + float(np.clip(crab, -c.crab_max, c.crab_max))
        forward = float(command[0] / scale)
        if speed <= 0.0:  # stopping: only hold against the error, never fly on
            forward = float(np.clip(forward, -c.creep, c.creep))
        elif forward > 0.0:  # an autopilot that falls short of the command is asked for more
            forward /= self._speed_gain
        self._commands.append(forward * scale)
        yaw = c.turn_gain * steer
        return np.array([np.clip(forward, -1.0, 1.0), np.clip(yaw, -1.0, 1.0)], dtype=np.float32)

    def _learn_speed_gain(self, measured_forward: float) -> None:
        """How much of a steady forward command the autopilot delivers (PX4's drag-limited loop
        settles 10–35 % short), from the measured speed after ``gain_steady`` unchanged commands."""
        c = self.config
        recent = list(self._commands)[-c.gain_steady :]
        if len(recent) < c.gain_steady or min(recent) < c.gain_min_speed:
            return
        if max(recent) - min(recent) > 0.1 * max(recent):
            return
        ratio = float(np.clip(measured_forward / recent[-1], c.gain_range[0], c.gain_range[1]))
        self._speed_gain += (c.step_s / c.gain_time) * (ratio - self._speed_gain)

    def _true_velocity(
        self, ranges: np.ndarray, measured: np.ndarray, bearing: float, distance: float
    ) -> np.ndarray:
        """The vehicle's true body velocity (m/s): the measured one less the estimate's error
        (:class:`companion.perception.drift.DriftEstimator`)."""
        self._bias = self._drift.update(ranges, measured, bearing, distance, self.config.step_s)
        return measured - self._bias

    def _ramp(self, clearance: float, distance: float) -> float:
        """Forward action for a clearance along the heading: 0 at ``stop_distance``, ``cruise`` at
        ``slow_distance`` (the goal counts as clearance: no braking for a waypoint to fly through)."""
        c = self.config
        free = min(clearance, distance + c.stop_distance) - c.stop_distance
        return c.cruise * float(np.clip(free / (c.slow_distance - c.stop_distance), 0.0, 1.0))

    def _away_from(self, ranges: np.ndarray) -> np.ndarray:
        """Headings that do not close on any return inside ``keep_out``: near something, the
        vehicle leaves it before anything else (a drift the estimate hides acts there first)."""
        close = _SIGNED[ranges < self.config.keep_out]
        if close.size == 0:
            return np.ones(N_BINS, dtype=bool)
        return (np.cos(_SIGNED[:, None] - close[None, :]) <= 0.0).all(axis=1)

    def _push_off(self, ranges: np.ndarray) -> float:
        """Forward action (negative: backward) away from returns inside ``keep_out``, in
        proportion to how deep inside they are: the one escape that needs no turn first."""
        c = self.config
        close = ranges < c.keep_out
        if not close.any():
            return 0.0
        depth = (c.keep_out - ranges[close]) / c.keep_out
        push = -float(np.sum(depth * np.cos(_SIGNED[close])) / max(1, close.sum()) ** 0.5)
        return float(np.clip(c.push_gain * push, -c.creep, c.creep))

    def _stoppable(self, clearance: float) -> float:
        """The fastest forward action the vehicle can still stop from within ``clearance``
        (``stop_time`` s of travel at that speed, ``stop_distance`` kept)."""
        c = self.config
        return max(0.0, clearance - c.stop_distance) / (c.stop_time * self.layout.velocity_scale)

    def _cannot_stop_along_course(self, clear: np.ndarray, forward: float, left: float) -> bool:
        """The measured motion runs into something before the vehicle could stop: brake.

        The vehicle does not go where its nose points: the autopilot's velocity lags the command
        (it overshoots a lowered speed, and slides outward in a turn). So the corridor along the
        measured course must be clear for the stopping distance at the measured speed."""
        c = self.config
        speed = math.hypot(forward, left)
        if speed < c.course_min_speed:
            return False
        course = _bin(math.atan2(left, forward))
        return float(clear[course]) - c.stop_distance < c.stop_time * speed

    def _subgoal(self, ranges: np.ndarray, clear: np.ndarray, bearing: float, distance: float) -> float:
        """The direction to fly for: the goal's bearing if clear, else the best obstacle edge's."""
        c = self.config
        goal_bin = _bin(bearing)
        if clear[goal_bin] >= min(distance, c.horizon):
            return bearing
        r = np.minimum(ranges, c.max_range)
        following = np.roll(r, -1)
        edges = np.nonzero(np.abs(following - r) > c.jump)[0]
        if edges.size == 0:
            return bearing
        # the edge is the nearer of the two bins; the way round it lies toward the farther one
        near_is_first = r[edges] < following[edges]
        near_bin = np.where(near_is_first, edges, (edges + 1) % N_BINS)
        side = np.where(near_is_first, 1.0, -1.0)  # +1: pass counter-clockwise of the edge
        near_r = r[near_bin]
        passing = np.arcsin(np.minimum(1.0, (c.body_radius + c.edge_margin) / np.maximum(near_r, 1e-6)))
        direction = _wrap(_SIGNED[near_bin] + side * passing)
        ex, ey = near_r * np.cos(_SIGNED[near_bin]), near_r * np.sin(_SIGNED[near_bin])
        gx, gy = distance * math.cos(bearing), distance * math.sin(bearing)
        heuristic = near_r + np.hypot(gx - ex, gy - ey)
        heuristic += c.subgoal_hysteresis * np.abs(_wrap(direction - bearing) - self._subgoal_offset)
        return float(direction[int(np.argmin(heuristic))])

    def _track_progress(self, distance: float) -> None:
        """Stall detection; a jump in distance is a new waypoint and starts over."""
        c = self.config
        if distance > self._last_distance + 1.0:
            self._best, self._since_progress, self._escape_side = distance, 0, 0
        self._last_distance = distance
        if distance < self._best - c.stall_progress:
            self._best, self._since_progress = distance, 0
            return
        self._since_progress += 1
        if not self._escape_side and self._since_progress >= c.stall_steps:
            self._escape_side = 1 if self._offset >= 0.0 else -1
            self._escape_left = c.escape_steps
            self._stuck_at = distance

    def _follow_boundary(self, ranges: np.ndarray, clear: np.ndarray, away: np.ndarray) -> float | None:
        """The first free heading sweeping round from the nearest return on the boundary side, away
        from it: the boundary stays beside (but no closer than ``keep_out``: ``away``). None when
        nothing lies within ``boundary_range`` on that side (sweeping from a fixed bearing there
        only spins the vehicle on the spot)."""
        c = self.config
        side = self._escape_side
        beside = (side * _SIGNED < 0.0) & (ranges < c.boundary_range)  # +1: the right half
        if not beside.any():
            return None
        wall = int(np.degrees(_SIGNED[np.argmin(np.where(beside, ranges, np.inf))]))
        sweep = wall + side * np.arange(0, 360)  # degrees, from the wall round, away from it
        free = (clear >= c.wall_lookahead)[sweep % 360]
        if (free & away[sweep % 360]).any():
            free &= away[sweep % 360]
        if not free.any():
            return float(_wrap(np.radians(wall) + side * np.pi / 2))
        return float(_wrap(np.radians(sweep[int(np.argmax(free))])))


class GoalFollowerTracks(GoalFollower):
    """The goal follower giving way to what moves (:mod:`companion.safety.give_way`): it waits for a mover
    whose predicted path crosses its intended course, and steps aside from one that would meet it
    where it waits. The movers are the tracker's (as the shield gets them), never the simulator's.

    While it waits (facing the goal) or steps aside (the nose held), the stall clock stands: waiting
    for a walker is no trap to escape.

    :param layout: the frame layout (a goal layout)
    :param movers: the tracker's movers for the newest frame (body axes at the scan's time)
    :param config: the goal follower's tuning
    :param hold: as :class:`GoalFollower`'s
    :param give_way: the rule's tuning
    :param max_sideways_speed: m/s a third action part stands for (the env's ``sideways``): a
        sidestep flies it, and every action has three parts; 0: two parts, sidesteps along the nose
    """

    def __init__(
        self,
        layout: ObservationLayout,
        movers: Callable[[], Sequence[Mover]],
        config: GoalFollowerConfig | None = None,
        hold: DriftHoldConfig | None = None,
        give_way: GiveWayConfig | None = None,
        max_sideways_speed: float = 0.0,
    ) -> None:
        super().__init__(layout, config, hold)
        self.rule = GiveWay(give_way)
        self._movers = movers
        self._sideways = float(max_sideways_speed)
        #: the last frame's decision (``go``, ``wait`` or ``step``)
        self.mode = "go"

    def reset(self, obs: np.ndarray) -> np.ndarray:
        self.rule.reset()
        return super().reset(obs)

    def act(self, obs: np.ndarray) -> np.ndarray:
        step = self._plan(obs)
        scale = self.layout.velocity_scale
        intended = step.speed * scale * np.array([math.cos(step.heading), math.sin(step.heading)])
        decision = self.rule.decide(intended, step.velocity, self._movers(), step.clear, self._sideways)
        self.mode = decision.mode
        left = 0.0
        if decision.mode == "go":
            action = self._command(step.speed, step.heading)
        else:
            self._since_progress = 0
            if decision.mode == "wait":
                action = self._command(0.0, step.bearing)
            else:
                action, left = self._sidestep(np.asarray(decision.velocity))
        action[0] = np.clip(action[0] + self._push_off(step.ranges), -1.0, 1.0)
        return np.append(action, np.float32(left)) if self._sideways else action

    def _sidestep(self, velocity: np.ndarray) -> tuple[np.ndarray, float]:
        """The action (two parts) and the sideways part that fly ``velocity`` (body, m/s) with the
        nose held (a turning body would turn the step with it): the estimate's error made up as
        :meth:`GoalFollower._command` does."""
        command = velocity + self._bias - self._held
        forward = float(np.clip(command[0] / self.layout.velocity_scale, -1.0, 1.0))
        self._commands.append(forward * self.layout.velocity_scale)
        left = float(np.clip(command[1] / self._sideways, -1.0, 1.0)) if self._sideways else 0.0
        return np.array([forward, 0.0], dtype=np.float32), left
