"""Does a flown vehicle stay inside the firmware envelope? Checked on recorded flights.

:func:`memory_margins` checks the shield's obstacle memory the same way: does its odometry carry a
return to within the inflation it gives it?

From each shield step of a recording (the measured velocity the shield saw, and the setpoint it
let through), the envelope's worst case (:mod:`companion.safety.envelope`) is flown forward with
the setpoints that really followed, and the vehicle's true displacement (the SITL's ground truth)
is compared with it along 36 directions, over ``horizon`` seconds. A positive margin everywhere
means the real vehicle never moved farther towards any direction than the envelope allowed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.recording.reader import read_recording
from companion.safety.envelope import STEP_S, ResponseEnvelope, window_targets, worst_closing
from companion.safety.obstacle_memory import RANGE_ACCURACY_M, ObstacleMemory

#: the directions checked: every 10 degrees
DIRECTIONS = np.radians(np.arange(0.0, 360.0, 10.0))
#: a longer pause between shield steps means the companion was not commanding (HOLD), s
MAX_GAP_S = 0.5
_UNITS = np.stack([np.cos(DIRECTIONS), np.sin(DIRECTIONS)], axis=1)


@dataclass(frozen=True)
class RecordedFlight:
    """What the check needs of one recording (world ENU, seconds of log time).

    :param truth_time: ``(n,)`` ground-truth times
    :param truth_xy: ``(n, 2)`` true horizontal positions, m
    :param truth_yaw: ``(n,)`` true heading, rad counter-clockwise from East (unwrapped)
    :param step_time: ``(k,)`` shield step times
    :param measured: ``(k, 2)`` the body velocity each step's shield judged (forward, left), m/s
    :param output: ``(k, 2)`` the body setpoint each step let through (forward, left), m/s
    :param truth_velocity: ``(n, 2)`` true horizontal velocity (East, North), m/s (None: not read)
    """

    truth_time: np.ndarray
    truth_xy: np.ndarray
    truth_yaw: np.ndarray
    step_time: np.ndarray
    measured: np.ndarray
    output: np.ndarray
    truth_velocity: np.ndarray | None = None


def load_flight(path: str | Path) -> RecordedFlight:
    """The ground truth and shield steps of a recording (``/truth/state``, ``/shield``)."""
    rec = read_recording(path)
    truth = rec.topic("/truth/state")
    steps = [(t, m) for t, m in rec.topic("/shield") if (m.get("extra") or {}).get("arg3") is not None]
    if not truth or not steps:
        raise ValueError(f"{path}: no ground truth or no shield steps with a measured velocity")
    return RecordedFlight(
        truth_time=np.array([t for t, _ in truth]),
        truth_xy=np.array([[m["position"]["x"], m["position"]["y"]] for _, m in truth]),
        truth_yaw=np.unwrap(np.array([m["yaw"] for _, m in truth])),
        step_time=np.array([t for t, _ in steps]),
        measured=np.array([m["extra"]["arg3"] for _, m in steps], dtype=float),
        output=np.array([[m["output"]["forward"], m["output"]["lateral"]] for _, m in steps], dtype=float),
        truth_velocity=np.array([[m["velocity"]["x"], m["velocity"]["y"]] for _, m in truth], dtype=float),
    )


def to_world(body: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """``(k, 2)`` body (forward, left) vectors rotated into the world (East, North) by ``(k,)`` headings."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([c * body[:, 0] - s * body[:, 1], s * body[:, 0] + c * body[:, 1]], axis=1)


def containment_margins(
    flight: RecordedFlight, envelope: ResponseEnvelope, horizon: float = 2.5
) -> np.ndarray:
    """Per shield step, the least margin (m) between the envelope's bound and the true displacement
    over the next ``horizon`` seconds, along the worst direction; negative: outside the envelope.
    Only horizons the companion commanded throughout count: none that runs past the ground truth
    or the last shield step, or across a gap of more than :data:`MAX_GAP_S` between steps (the
    autopilot held its own position there)."""
    yaw_at_steps = np.interp(flight.step_time, flight.truth_time, flight.truth_yaw)
    components = to_world(flight.output, yaw_at_steps) @ _UNITS.T  # (k, 36)
    measured = to_world(flight.measured, yaw_at_steps) @ _UNITS.T
    n_steps = round(horizon / STEP_S)
    gaps = np.flatnonzero(np.diff(flight.step_time) > MAX_GAP_S)
    # each step's commanded span ends at the next gap or the last step
    span_end = flight.step_time[
        np.append(gaps, len(flight.step_time) - 1)[np.searchsorted(gaps, np.arange(len(flight.step_time)))]
    ]
    margins = []
    for i, t in enumerate(flight.step_time):
        if t + horizon > min(flight.truth_time[-1], span_end[i]):
            continue
        times = t + STEP_S * np.arange(n_steps)
        targets = window_targets(flight.step_time, components, times, envelope)
        _, bound = worst_closing(measured[i], targets, envelope)
        when = t + STEP_S * np.arange(n_steps + 1)
        xy = np.stack([np.interp(when, flight.truth_time, flight.truth_xy[:, k]) for k in range(2)], axis=1)
        true = (xy - xy[0]) @ _UNITS.T
        margins.append(float((bound - true).min()))
    return np.array(margins)


def memory_margins(
    flight: RecordedFlight, envelope: ResponseEnvelope, memory_time: float = 0.5
) -> np.ndarray:
    """Per remembered return and step, the memory's inflation less how far its odometry carried the
    return from where it truly lies, m; negative: the memory put it farther off than it allowed.

    The shield's :class:`~companion.safety.obstacle_memory.ObstacleMemory` is fed each shield step's
    measured velocity and the true heading, and at each step a return where the vehicle truly is;
    at every later step each is compared with that place in the true body frame then. Spans of
    steps apart by more than :data:`MAX_GAP_S` are checked each from a fresh memory."""
    memory = ObstacleMemory(memory_time, envelope.estimate_error, envelope.velocity_lag)
    yaw = np.interp(flight.step_time, flight.truth_time, flight.truth_yaw)
    xy = np.stack(
        [np.interp(flight.step_time, flight.truth_time, flight.truth_xy[:, k]) for k in range(2)], 1
    )
    margins: list[np.ndarray] = []
    placed: list[int] = []  # the step each remembered return was placed at, oldest first
    for k, t in enumerate(flight.step_time):
        dt = t - flight.step_time[k - 1] if k else 0.0
        if dt > MAX_GAP_S:
            memory.reset()
            placed.clear()
        points, inflation = memory.update(np.zeros((1, 2)), dt, tuple(flight.measured[k]), float(yaw[k]), 0.0)
        placed = [*placed, k][-len(points) :]
        c, s = np.cos(yaw[k]), np.sin(yaw[k])
        offset = xy[placed] - xy[k]
        truth = np.stack([c * offset[:, 0] + s * offset[:, 1], -s * offset[:, 0] + c * offset[:, 1]], axis=1)
        margins.append(inflation - RANGE_ACCURACY_M - np.hypot(*(points - truth).T))
    return np.concatenate(margins)
