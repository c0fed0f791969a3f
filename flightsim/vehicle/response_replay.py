"""Replay recorded autopilot command sequences on the simulated vehicle and score the match.

The recordings (``tests/fixtures/autopilot-response/``, made from real PX4 SIH and ArduCopter SITL;
see its README) hold the 10 Hz command in force and the true motion. :func:`replay` flies the same
commands on the JSBSim vehicle through a response model (or the ideal autopilot), :func:`compare`
gives the RMS error of ground speed, yaw rate and sideslip against the recording's ground truth.
:func:`replay_flight` does the same with a whole recorded flight of the companion on a real SITL
(``../shared/fixtures/real-sitl-flights``, read by :func:`flightsim.vehicle.envelope_check.load_flight`):
the setpoints its shield let through, flown per commanded segment.
Used by ``bench/bench_response.py`` and ``tests/flightsim/test_autopilot_response.py``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flightsim.vehicle.autopilot_response import CHUNK_S, AutopilotResponse, ResponseParams
from flightsim.vehicle.control import Setpoint
from flightsim.vehicle.envelope_check import MAX_GAP_S, RecordedFlight, to_world
from flightsim.vehicle.quadrotor import Vehicle

FIXTURES = Path(__file__).resolve().parents[2] / "tests" / "fixtures" / "autopilot-response"
SEQUENCES = ("forward", "forward-rep2", "yaw", "turn", "turn-rep2", "reverse", "random")
FIRMWARES = {"px4": "px4-sih", "ardupilot": "ardupilot-sitl"}
SLIP_MIN_SPEED = 0.5
"""Sideslip is compared only where both trajectories move faster than this, m/s."""
_ALTITUDE = 1.5


@dataclass
class Trajectory:
    """Motion sampled at times ``t`` (s from the sequence start): world velocity (ENU, m/s),
    heading (rad, CCW from East) and yaw rate (rad/s, CCW)."""

    t: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    yaw: np.ndarray
    yaw_rate: np.ndarray

    def at(self, t: np.ndarray) -> Trajectory:
        """Linearly interpolated at ``t`` (heading unwrapped first)."""
        yaw = np.interp(t, self.t, np.unwrap(self.yaw))
        return Trajectory(t, *(np.interp(t, self.t, a) for a in (self.vx, self.vy)), yaw,
                          np.interp(t, self.t, self.yaw_rate))  # fmt: skip

    @property
    def speed(self) -> np.ndarray:
        return np.hypot(self.vx, self.vy)

    @property
    def forward_speed(self) -> np.ndarray:
        return self.vx * np.cos(self.yaw) + self.vy * np.sin(self.yaw)

    @property
    def slip(self) -> np.ndarray:
        """Course minus heading, rad, + = moving to the left of the nose."""
        return np.angle(np.exp(1j * (np.arctan2(self.vy, self.vx) - self.yaw)))


@dataclass
class Recording:
    """One recorded sequence: the commands (10 Hz, FLU) and the true motion."""

    name: str
    command_t: np.ndarray
    command_v: np.ndarray
    command_r: np.ndarray
    truth: Trajectory
    estimate: Trajectory
    duration: float


def load_recording(path: Path) -> Recording:
    """Read one CSV of the fixture (NED columns turned into ENU/FLU)."""
    d = np.genfromtxt(path, delimiter=",", names=True)
    t = d["t"]
    ticks = np.arange(0.0, t[-1] - 1.0 + 1e-9, 0.1)  # the sequence ends 1 s before the last row
    idx = np.clip(np.searchsorted(t, ticks + 0.005), 0, len(t) - 1)  # the command in force just after a tick

    def trajectory(prefix: str) -> Trajectory:
        # NED (north, east) -> ENU (east, north); NED yaw (CW from North) -> ENU yaw; FRD rate -> FLU
        return Trajectory(t, d[f"{prefix}_vy"], d[f"{prefix}_vx"], math.pi / 2 - d[f"{prefix}_yaw"],
                          -d[f"{prefix}_yawspeed"])  # fmt: skip

    return Recording(path.stem, ticks, d["cmd_v"][idx], d["cmd_r"][idx], trajectory("true"),
                     trajectory("est"), float(ticks[-1] + 0.1))  # fmt: skip


def recording_path(firmware: str, sequence: str, root: Path = FIXTURES) -> Path:
    """The fixture CSV of a firmware (``"px4"``/``"ardupilot"``) and sequence."""
    return root / f"{FIRMWARES[firmware]}-{sequence}.csv"


def replay(
    vehicle: Vehicle, params: ResponseParams | None, recording: Recording, tail_s: float = 1.0
) -> Trajectory:
    """Fly the recording's commands (then ``tail_s`` of zeros) and sample the motion every chunk.

    Starts hovering at rest, heading East. ``params`` None flies the ideal autopilot; the estimate
    error is left out (a random walk cannot be replayed against one recorded realisation).

    :param vehicle: the JSBSim vehicle (reset here)
    :param params: the response, or None for the ideal autopilot
    :param recording: what to replay
    :param tail_s: zero commands flown after the sequence (the recordings have 1 s)
    """
    state = vehicle.reset((0.0, 0.0, _ALTITUDE), 0.0)
    response = None if params is None else AutopilotResponse(params.without_estimate_error())
    commands = list(zip(recording.command_v.tolist(), recording.command_r.tolist(), strict=True))
    commands += [(0.0, 0.0)] * round(tail_s / 0.1)
    rows = [(0.0, *state.velocity[:2], state.yaw, state.angular_rate[2])]
    for v, r in commands:
        # the same as fly(vehicle, response, v, r, ...) for 0.1 s, sampled every chunk
        held = Setpoint.from_body(v, 0.0, state.yaw, yaw_rate=r, altitude=_ALTITUDE)  # the ideal autopilot's
        if response is not None:
            response.command(v, 0.0, r, state.yaw)
        for _ in range(4):
            sp = held if response is None else response.setpoint(state, altitude=_ALTITUDE)
            state = vehicle.step(sp, CHUNK_S)
            rows.append((state.time, *state.velocity[:2], state.yaw, state.angular_rate[2]))
    a = np.array(rows)
    return Trajectory(a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4])


@dataclass(frozen=True)
class Errors:
    """RMS differences between a simulated and a recorded trajectory over the sequence."""

    speed: float  # ground speed, m/s
    yaw_rate: float  # rad/s
    slip_deg: float  # sideslip where both move faster than SLIP_MIN_SPEED, degrees (NaN: never)


def compare(sim: Trajectory, real: Trajectory, duration: float, step: float = 0.05) -> Errors:
    """RMS errors of ``sim`` against ``real`` on a common grid over [0, duration].

    :param sim: the simulated motion
    :param real: the recorded motion (ground truth)
    :param duration: s, the part to score (commands plus the 1 s of zeros)
    :param step: grid spacing, s
    """
    t = np.arange(0.0, duration + 1e-9, step)
    a, b = sim.at(t), real.at(t)
    moving = (a.speed > SLIP_MIN_SPEED) & (b.speed > SLIP_MIN_SPEED)
    slip = np.angle(np.exp(1j * (a.slip[moving] - b.slip[moving])))
    return Errors(
        speed=float(np.sqrt(np.mean((a.speed - b.speed) ** 2))),
        yaw_rate=float(np.sqrt(np.mean((a.yaw_rate - b.yaw_rate) ** 2))),
        slip_deg=float(np.degrees(np.sqrt(np.mean(slip**2)))) if moving.any() else math.nan,
    )


@dataclass(frozen=True)
class Hardness:
    """How hard a response is to fly, the figures the recordings' analysis uses (truth).

    :param t90_s: forward step 0 -> 1 m/s at t = 2 s: time to 90 %, s (inf: not within the 4 s hold)
    :param steady_speed: mean forward speed over the last second of that 1 m/s hold, m/s
    :param yaw_cap: mean yaw rate over the last second of the 1.5 rad/s yaw command (t = 10-13 s), rad/s
    :param turn_speed: median ground speed in the 2 m/s, +-1 rad/s turn (t = 3-11 s), m/s
    :param turn_slip_deg: median |sideslip| there where faster than SLIP_MIN_SPEED, degrees
    """

    t90_s: float
    steady_speed: float
    yaw_cap: float
    turn_speed: float
    turn_slip_deg: float


def hardness(forward: Trajectory, yaw: Trajectory, turn: Trajectory) -> Hardness:
    """The :class:`Hardness` figures of three trajectories flown on the ``forward``, ``yaw`` and
    ``turn`` sequences (simulated or recorded).

    :param forward: motion on the forward sequence
    :param yaw: motion on the yaw sequence
    :param turn: motion on the turn sequence
    """
    t = np.arange(1.8, 6.0, 0.01)
    f = forward.at(t)
    u = f.forward_speed
    y0 = float(np.mean(u[t < 2.0]))
    reached = np.nonzero((t >= 2.0) & ((u - y0) / (1.0 - y0) >= 0.9))[0]
    t90 = float(t[reached[0]] - 2.0) if reached.size else math.inf
    steady = float(np.mean(u[t >= 5.0]))
    yaw_cap = float(np.mean(yaw.at(np.arange(12.0, 13.0, 0.01)).yaw_rate))
    g = turn.at(np.arange(3.0, 11.0, 0.01))
    moving = g.speed > SLIP_MIN_SPEED
    return Hardness(
        t90_s=t90,
        steady_speed=steady,
        yaw_cap=yaw_cap,
        turn_speed=float(np.median(g.speed)),
        turn_slip_deg=float(np.degrees(np.median(np.abs(g.slip[moving])))),
    )


@dataclass(frozen=True)
class FlightErrors:
    """How a response flew a recorded flight's setpoints, against the flight's ground truth.

    :param speed: RMS ground-speed error, m/s
    :param bias: mean ground-speed error (simulated minus real; negative: slower), m/s
    :param course_deg: RMS course error where both move faster than :data:`SLIP_MIN_SPEED`, degrees
    :param samples: the 0.1 s samples scored
    """

    speed: float
    bias: float
    course_deg: float
    samples: int


def replay_flight(
    vehicle: Vehicle, params: ResponseParams, flight: RecordedFlight, min_steps: int = 20
) -> FlightErrors:
    """Fly a recorded flight's setpoints through ``params`` on the vehicle and score its speed and
    course against the flight's ground truth, every 0.1 s.

    Each commanded segment (shield steps no more than :data:`MAX_GAP_S` apart; shorter than
    ``min_steps`` steps: skipped) starts at rest where the real vehicle was, heading as it did; each
    setpoint is rotated into the world by the real heading when it was sent (the recordings hold
    the shield's body setpoints, not the autopilot's yaw) and takes effect from then on, with no yaw
    rate. The estimate error is left out, as in :func:`replay`.

    :param vehicle: the JSBSim vehicle (reset per segment)
    :param params: the response flown
    :param flight: the recording (its ``truth_velocity`` is required)
    :param min_steps: shortest segment scored, shield steps
    """
    if flight.truth_velocity is None:
        raise ValueError("the flight has no ground-truth velocity")
    tt, tv = flight.truth_time, flight.truth_velocity
    yaw = np.interp(flight.step_time, tt, flight.truth_yaw)
    setpoints = to_world(flight.output, yaw)
    gaps = np.flatnonzero(np.diff(flight.step_time) > MAX_GAP_S) + 1
    speed_errors: list[float] = []
    course_errors: list[float] = []
    for a, b in zip(np.append(0, gaps), np.append(gaps, len(flight.step_time)), strict=True):
        if b - a < min_steps:
            continue
        steps = flight.step_time[a:b]
        start = float(steps[0])
        x0, y0 = (float(np.interp(start, tt, flight.truth_xy[:, k])) for k in range(2))
        state = vehicle.reset((x0, y0, _ALTITUDE), float(yaw[a]))
        response = AutopilotResponse(params.without_estimate_error())
        response.reset(state.yaw)
        sent = -1
        for t in np.arange(start, min(float(steps[-1]) + 0.1, float(tt[-1])), 0.1):
            j = a + int(np.searchsorted(steps, t + 1e-9)) - 1
            if j != sent:
                response.command_world(float(setpoints[j, 0]), float(setpoints[j, 1]), 0.0)
                sent = j
            for _ in range(4):
                state = vehicle.step(response.setpoint(state, altitude=_ALTITUDE), CHUNK_S)
            sim = np.asarray(state.velocity[:2], dtype=float)
            real = np.array([np.interp(t + 0.1, tt, tv[:, k]) for k in range(2)])
            speed_errors.append(float(np.hypot(*sim) - np.hypot(*real)))
            if np.hypot(*sim) > SLIP_MIN_SPEED and np.hypot(*real) > SLIP_MIN_SPEED:
                course = math.atan2(sim[1], sim[0]) - math.atan2(real[1], real[0])
                course_errors.append(math.remainder(course, 2.0 * math.pi))
    if not speed_errors:
        raise ValueError(f"no commanded segment of {min_steps} steps or more")
    e = np.array(speed_errors)
    course = float(np.degrees(np.sqrt(np.mean(np.square(course_errors))))) if course_errors else math.nan
    return FlightErrors(
        speed=float(np.sqrt(np.mean(e**2))), bias=float(np.mean(e)), course_deg=course, samples=len(e)
    )
