"""The backup gate: a command passes only if the vehicle can still be stopped clear after it.

The guarantee (stated in full in ARCHITECTURE.md, "The shield's guarantee"):

*Assumptions.* The world is static. Every obstacle that matters has been seen by the scans within
the memory horizon (:class:`~companion.safety.obstacle_memory.ObstacleMemory`). The autopilot
answers within the firmware envelope (:mod:`companion.safety.envelope`): the delay window, the
acceleration and deceleration bounds, the overshoot, and a velocity-estimate error of at most
``estimate_error``. The heading is known (or the commanded yaw rates are flown).

*Promise.* Whatever commands arrive, every command sent keeps a *backup* available: braking to a
stop (a zero setpoint), after which the envelope's worst-case displacement towards every
direction stays below the clearance of the remembered returns that way less ``body_radius +
margin``. So the true vehicle centre stays at least ``body_radius + margin`` from every remembered
return until the vehicle is stopped (to within the estimate error's creep, ``estimate_error`` m/s,
which the shield's keep-out answers from the scans; the gate does not cover that creep).

*Proof sketch.* Let S(x) say "from state x, the backup keeps the worst case clear". A command u
passes only if, starting now, u for one period then the backup keeps the worst case clear, i.e.
S holds at every state the envelope allows one period later. If no command passes, the backup
itself is sent; it is the continuation that the previous step verified, so its worst case is a
subset of the one verified then (the same setpoint sequence, started one period later from a state
inside that worst case). By induction, from a first state where S holds (standstill, clear),
S holds at every step and no verified worst case touches a remembered return.

*Not covered.* Obstacles the scans never saw (below or above the beams, hidden, outside the memory
horizon), anything that moves, an envelope the firmware leaves (a gust, a motor failure, a wrong
heading), and the creep once stopped.

Separation makes it cheap: with ``X_m`` the worst displacement towards direction ``m`` over the
horizon, every reachable position ``d`` has ``d·m <= X_m`` for all ``m``; so for a return ``o``,
``|o - d| >= (o - d)·m >= o·m - X_m`` for any one ``m``. A return is clear when some direction
separates it: ``max_m (o·m - X_m) >= body_radius + margin`` (:func:`separation`). The worst case is
bounded towards 72 directions; a wall beside the course is separated by its normal, a return ahead
by its bearing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.safety.envelope import STEP_S, ResponseEnvelope, worst_closing

#: the directions the worst case is bounded towards, every 5 degrees
N_DIRECTIONS = 72
_DIR_RAD = np.radians(np.arange(N_DIRECTIONS) * (360.0 / N_DIRECTIONS))
_DIR_UNIT = np.stack([np.cos(_DIR_RAD), np.sin(_DIR_RAD)], axis=1)
#: the longest worst case integrated, s (a backup from the highest speed settles well inside it)
MAX_HORIZON_S = 8.0
#: returns searched at once in :func:`separation`
_CHUNK = 64
#: fractions of the asked velocity tried when it does not pass, fastest first
_SCALES = np.linspace(1.0, 0.0, 11)


def separation(points: np.ndarray, inflation: np.ndarray, displacement: np.ndarray) -> np.ndarray:
    """Per candidate, the least over the returns of the best separating direction's room, m.

    :param points: ``(p, 2)`` returns in the body frame (forward, left), m
    :param inflation: ``(p,)`` how far each may truly lie from where it is recorded, m
    :param displacement: ``(m, 72)`` each candidate's worst displacement towards each direction, m
    :return: ``(m,)`` ``min_o max_n (o·n - inflation_o - X_n)``; inf without returns
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    grown = np.asarray(inflation, dtype=np.float64)
    least = np.full(len(displacement), math.inf)
    if len(pts) == 0:
        return least
    # each return's own bearing (within half a sector of a direction) separates it by at least
    # |o| cos(half a sector) - inflation - the farthest reach: take the returns in that order, and
    # stop where that bound cannot go below what the nearer ones left
    reach = float(displacement.max())
    bound = np.hypot(pts[:, 0], pts[:, 1]) * math.cos(math.pi / N_DIRECTIONS) - grown - reach
    order = np.argsort(bound)
    for start in range(0, len(order), _CHUNK):
        chunk = order[start : start + _CHUNK]
        if bound[chunk[0]] >= least.max():
            break
        along = pts[chunk] @ _DIR_UNIT.T - grown[chunk][:, None]  # (c, 72)
        least = np.minimum(least, (along[None, :, :] - displacement[:, None, :]).max(axis=2).min(axis=1))
    return least


@dataclass
class _Sent:
    """Setpoints sent so far (world frame by the heading at sending), newest last."""

    times: list[float]
    vectors: list[np.ndarray]


class BackupGate:
    """Passes the command closest to the asked one whose backup stays clear (see the module doc).

    :param envelope: the firmware envelope
    :param clearance: how far the vehicle centre must stay from every return: body radius + margin, m
    :param period: the control period: how long a command is flown before the next can be the backup, s
    :param unknown_speed: the speed assumed in every direction when the velocity is not known, m/s
    """

    def __init__(
        self, envelope: ResponseEnvelope, clearance: float, period: float = 0.1, unknown_speed: float = 2.0
    ) -> None:
        self.envelope = envelope
        self.clearance = float(clearance)
        self.period = float(period)
        self.unknown_speed = float(unknown_speed)
        self._sent = _Sent([], [])
        self._time = 0.0
        self._heading = 0.0

    def reset(self) -> None:
        """Forget the setpoints sent (a new engagement starts from a zero setpoint held long)."""
        self._sent = _Sent([], [])

    def advance(self, dt: float, heading: float | None, yaw_rate: float) -> None:
        """Move the gate's clock by ``dt`` and its heading to ``heading`` (rad, counter-clockwise),
        or by ``yaw_rate`` flown for ``dt`` when the heading is not known."""
        step = dt if math.isfinite(dt) and dt > 0.0 else 0.0
        self._time += step
        self._heading = (
            float(heading)
            if heading is not None and math.isfinite(heading)
            else (self._heading + yaw_rate * step)
        )
        keep = self._time - self.envelope.max_delay - self.period
        while len(self._sent.times) > 1 and self._sent.times[1] <= keep:
            del self._sent.times[0]
            del self._sent.vectors[0]

    def record(self, body: tuple[float, float]) -> None:
        """The setpoint (body forward, left, m/s) that was sent now."""
        c, s = math.cos(self._heading), math.sin(self._heading)
        self._sent.times.append(self._time)
        self._sent.vectors.append(np.array([c * body[0] - s * body[1], s * body[0] + c * body[1]]))

    def passes(
        self,
        candidates: np.ndarray,
        velocity: tuple[float, float] | None,
        points: np.ndarray,
        inflation: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Which candidate body setpoints keep their backup clear, and by how much.

        :param candidates: ``(m, 2)`` body setpoints (forward, left), m/s
        :param velocity: the measured body velocity less the drift estimate, m/s (None: not known)
        :param points: ``(p, 2)`` the remembered returns, body frame, m
        :param inflation: ``(p,)`` their inflation, m
        :return: ``(m,)`` bools and ``(m,)`` the least room left, m
        """
        env = self.envelope
        heading = self._heading
        c, s = math.cos(heading), math.sin(heading)
        units_world = _DIR_UNIT @ np.array([[c, s], [-s, c]])  # body directions turned into the world
        cand = np.atleast_2d(np.asarray(candidates, dtype=np.float64))
        cand_world = np.stack([c * cand[:, 0] - s * cand[:, 1], s * cand[:, 0] + c * cand[:, 1]], axis=1)
        cand_comp = cand_world @ units_world.T  # (m, 72)
        if velocity is None:
            closing = np.full(N_DIRECTIONS, self.unknown_speed)
        else:
            closing = _DIR_UNIT @ np.asarray(velocity, dtype=np.float64)
        # the history's highest component in force at each future time, and the candidate's window
        peak = max(float(np.max(closing)) + env.estimate_error, float(np.max(env.target(cand_comp))))
        horizon = min(self.period + env.max_delay + max(peak, 0.0) / env.decel + STEP_S, MAX_HORIZON_S)
        times = STEP_S * np.arange(math.ceil(horizon / STEP_S))
        history = self._history_components(units_world, times)  # (k, 72), -inf where none in force
        # a setpoint counts over every step its span touches (see envelope.window_targets)
        cand_on = (times + STEP_S > env.min_delay) & (times <= self.period + env.max_delay)
        backup_on = times + STEP_S > self.period + env.min_delay
        highest = np.where(
            cand_on[:, None, None], np.maximum(history[:, None, :], cand_comp[None]), history[:, None, :]
        )
        highest = np.where(backup_on[:, None, None], np.maximum(highest, 0.0), highest)
        targets = env.target(highest)
        closing_bound, displacement = worst_closing(np.broadcast_to(closing, cand_comp.shape), targets, env)
        # up to the stop: once only the backup is flown and the worst case has come down to its
        # creep, the gate's promise is kept (what creeps on is the keep-out's, see the module doc)
        stopped = (np.append(0.0, times + STEP_S) >= self.period + env.max_delay)[:, None, None] & (
            closing_bound <= env.target(np.zeros(())) + 1e-9
        )
        settled = np.where(stopped.any(axis=0), stopped.argmax(axis=0), len(times))
        upto = np.arange(len(times) + 1)[:, None, None] <= settled[None]
        reach = np.where(upto, displacement, -np.inf).max(axis=0)
        least = separation(points, inflation, reach) - self.clearance
        return least >= 0.0, least

    def _history_components(self, units_world: np.ndarray, times: np.ndarray) -> np.ndarray:
        """``(k, 72)``: the highest component of the setpoints sent before now that may still be
        flown at each future time (``-inf`` when none: only the candidate and the backup)."""
        env = self.envelope
        out = np.full((len(times), N_DIRECTIONS), -np.inf)
        sent_times = np.asarray(self._sent.times) - self._time  # <= 0
        if len(sent_times) == 0:
            return np.maximum(out, 0.0)  # a fresh gate: the vehicle was held still
        comps = np.stack(self._sent.vectors) @ units_world.T
        # setpoint j is flown over [t_j + min_delay, t_{j+1} + max_delay]; the newest until the candidate
        ends = np.append(sent_times[1:], 0.0) + env.max_delay
        for j, (start, end) in enumerate(zip(sent_times + env.min_delay, ends, strict=True)):
            on = (times + STEP_S > start) & (times <= end)
            out[on] = np.maximum(out[on], comps[j])
        return out

    def choose(
        self,
        asked: tuple[float, float],
        velocity: tuple[float, float] | None,
        points: np.ndarray,
        inflation: np.ndarray,
    ) -> tuple[tuple[float, float], str | None]:
        """The setpoint to send: ``asked`` when it passes; else the passing candidate closest to it
        (scaled down, or with its part towards the nearest return removed, then scaled); else, when
        none passes (the assumptions were left: a return seen late, or closer than the creep allows),
        whichever of them leaves the most room, the stop and ``asked`` included. The reason is None,
        ``"gate_slowed"``, ``"gate_backup"`` (the stop) or ``"gate_best_effort"``."""
        want = np.asarray(asked, dtype=np.float64)
        ok, _ = self.passes(want[None], velocity, points, inflation)
        if ok[0]:
            return (float(want[0]), float(want[1])), None
        nearest = points[int(np.argmin(np.hypot(points[:, 0], points[:, 1]) - inflation))]
        towards = nearest / max(float(np.hypot(*nearest)), 1e-9)
        slide = want - max(float(want @ towards), 0.0) * towards
        candidates = np.concatenate([want[None], _SCALES[1:, None] * want, _SCALES[:-1, None] * slide])
        ok, room = self.passes(candidates, velocity, points, inflation)
        if ok.any():
            distance = np.where(ok, np.hypot(*(candidates - want).T), np.inf)
            pick = int(np.argmin(distance))
            reason = "gate_slowed" if np.any(candidates[pick]) else "gate_backup"
        else:
            pick = int(np.argmax(room))
            reason = "gate_best_effort"
        best = candidates[pick]
        return (float(best[0]), float(best[1])), reason
