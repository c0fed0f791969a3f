"""How a real autopilot answers the companion's setpoints: a response model between command and vehicle.

The companion sends, 10 times a second, a body-frame forward speed and a yaw rate. A real flight
controller does not fly that command as given. Recordings of ArduCopter SITL and PX4 SIH SITL
(``tests/fixtures/autopilot-response/``) show it: PX4 reaches only 64-75 % of a 1 m/s step in 4 s
and slows to 1.3-1.5 m/s in a 2 m/s, 1 rad/s turn; ArduPilot delays 0.4 s, overshoots 8 % and caps
the yaw rate at 60 deg/s; both slide 24-35 deg sideways in that turn. This module reproduces that
with each firmware's controller structure, so the simulated vehicle is as hard to fly as the real
one (never easier), and training can see it.

Spec (the whole API; pure numpy/math, no I/O, no JSBSim):

* :class:`ResponseParams`: one firmware personality's limits and gains. Presets :data:`PX4` and
  :data:`ARDUPILOT` (calibrated against the recordings), :func:`random_params` (drawn per episode
  over ranges that cover both firmwares plus a margin) and :func:`response_params` (by name:
  ``"px4"``, ``"ardupilot"``; ``"ideal"`` gives None, meaning no response model at all).
* :class:`AutopilotResponse`: the stateful model. ``reset(yaw, velocity_xy)`` at the start of a
  flight (or when velocity control begins); ``command(forward, lateral, yaw_rate, yaw)`` each time
  a setpoint message arrives (body FLU m/s and rad/s CCW; rotated into the world by the heading at
  that moment, as MAV_FRAME_BODY_NED/BODY_OFFSET_NED do); and every physics chunk
  (:data:`CHUNK_S`, 3/120 s) ``setpoint(state, dt, altitude=..)`` returns the
  :class:`flightsim.control.Setpoint` the vehicle's cascaded controller should fly now: the
  firmware's shaped world-frame velocity reference with its acceleration as feedforward, and a
  yaw-rate demand that steers the vehicle onto the firmware's yaw reference.
* :func:`fly`: one command for one control period on a vehicle, through a response or (None) the
  ideal autopilot the env always had. The env, the replay and the nav env use it.
* ``measured_body_velocity(state)``: what the autopilot would report as its velocity, (forward,
  left) m/s in the body FLU frame: the truth plus the estimator's error (a slowly wandering bias,
  PX4: median 0.2-0.4 m/s; ArduPilot: 0.02-0.04 m/s). The same error is what the firmware's
  velocity loop closes on, so the true velocity wanders by it too, as PX4's did.

Structure per firmware (parameters named after the firmware's own):

* velocity: the command is delayed (``command_delay_s``: link, estimator and scheduling), then
  optionally shaped ArduPilot-style (``AC_PosControl::input_vel_accel_NE``: a square-root
  controller with gain PSC_JERK_NE / accel limit and a jerk-limited acceleration); then the
  firmware's velocity PID (PSC_NE_VEL_P/I/D, MPC_XY_VEL_P/I/D_ACC) flies a point-mass model of the
  airframe with its tilt lag (``tilt_lag_s``), acceleration limit and the linear drag its
  integrator has to work off (``drag_per_s``; this is PX4's slow, short-of-command approach).
  The point mass's velocity and acceleration are the reference the JSBSim vehicle tracks.
* yaw: the commanded rate is scaled by ``yaw_rate_gain`` (PX4's steady 94 %), capped at
  ``yaw_rate_max`` (ArduPilot: ATC_RATE_WPY_MAX), shaped by a first-order input filter
  (ATC_INPUT_TC) and an angular-acceleration limit (ATC_ACC_Y_MAX), integrated into a heading
  target; the attitude loop asks target rate + ``yaw_angle_p`` (ATC_ANG_YAW_P) x the vehicle's
  heading error, which is where ArduPilot's 20 % rate overshoot comes from. That demand, lagged
  by ``yaw_lag_s`` (what the firmware's rate loop adds to the JSBSim vehicle's own), is the yaw
  rate the vehicle flies.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from flightsim.control import Setpoint, wrap_angle

CHUNK_S = 3 / 120
"""The step the model is called at: 3 physics steps of the 120 Hz vehicle (the sim autopilot's chunk)."""
_INNER_DT = 0.005
"""Internal integration step of the model, s: several per chunk keeps the lags and the jerk limit stable."""
NAMES = ("ideal", "px4", "ardupilot", "random")
"""The values of ``EnvConfig.autopilot_response`` and of the sim autopilots' response option."""


@dataclass(frozen=True)
class ResponseParams:
    """One firmware personality's response (SI units, rad).

    :param name: what it imitates
    :param command_delay_s: from the setpoint's arrival to the velocity loop acting on it
    :param shape_accel_max: ArduPilot input shaping acceleration limit (WP_ACC), m/s^2; 0 = no shaping
    :param shape_jerk_max: ArduPilot input shaping jerk limit (PSC_JERK_NE), m/s^3
    :param vel_p: velocity loop P, (m/s^2)/(m/s)
    :param vel_i: velocity loop I, (m/s^2)/m
    :param vel_d: velocity loop D, (m/s^2)/(m/s^2)
    :param accel_max: horizontal acceleration the loop may ask (tilt limit), m/s^2
    :param tilt_lag_s: attitude/thrust lag between asked and achieved acceleration
    :param drag_per_s: linear drag of the airframe the loop flies, 1/s
    :param yaw_rate_gain: steady yaw rate / commanded
    :param yaw_rate_max: yaw-rate cap, rad/s
    :param yaw_accel_max: yaw angular-acceleration limit of the shaped target, rad/s^2
    :param yaw_input_tc: first-order time constant of the yaw-rate input shaping, s
    :param yaw_angle_p: heading-error gain of the attitude loop, 1/s (0: rate feedforward only)
    :param yaw_lag_s: yaw-rate lag behind the attitude loop's demand, beyond the JSBSim vehicle's own
    :param est_vel_sigma: velocity-estimate error per horizontal axis (stationary std), m/s
    :param est_vel_tau_s: correlation time of that error, s
    """

    name: str
    command_delay_s: float
    shape_accel_max: float
    shape_jerk_max: float
    vel_p: float
    vel_i: float
    vel_d: float
    accel_max: float
    tilt_lag_s: float
    drag_per_s: float
    yaw_rate_gain: float
    yaw_rate_max: float
    yaw_accel_max: float
    yaw_input_tc: float
    yaw_angle_p: float
    yaw_lag_s: float
    est_vel_sigma: float
    est_vel_tau_s: float

    def without_estimate_error(self) -> ResponseParams:
        """The same response with a perfect velocity estimate (for replaying recorded commands)."""
        return replace(self, est_vel_sigma=0.0)


PX4 = ResponseParams(
    name="px4",
    command_delay_s=0.05,
    shape_accel_max=0.0,  # offboard velocity setpoints reach the PID unshaped (no flight task)
    shape_jerk_max=0.0,
    vel_p=1.8,  # MPC_XY_VEL_P_ACC
    vel_i=0.4,  # MPC_XY_VEL_I_ACC
    vel_d=0.2,  # MPC_XY_VEL_D_ACC
    accel_max=5.0,  # MPC_ACC_HOR_MAX
    tilt_lag_s=0.20,
    drag_per_s=0.9,
    yaw_rate_gain=0.91,  # the recordings hold 94 %; the JSBSim vehicle adds 3 %
    yaw_rate_max=math.radians(200.0),  # MC_YAWRATE_MAX; MPC_YAWRAUTO_MAX is not applied in offboard
    yaw_accel_max=10.0,
    yaw_input_tc=0.0,
    yaw_angle_p=0.0,  # offboard yaw rate only: the yaw setpoint follows the heading
    yaw_lag_s=0.25,
    est_vel_sigma=0.25,
    est_vel_tau_s=3.0,
)
ARDUPILOT = ResponseParams(
    name="ardupilot",
    command_delay_s=0.075,
    shape_accel_max=2.5,  # WP_ACC (GUIDED velocity control uses the WP navigation limits)
    shape_jerk_max=5.0,  # PSC_JERK_NE
    vel_p=2.0,  # PSC_NE_VEL_P
    vel_i=1.0,  # PSC_NE_VEL_I
    vel_d=0.25,  # PSC_NE_VEL_D
    accel_max=5.66,  # ATC_ANGLE_MAX 30 deg: g tan 30
    tilt_lag_s=0.20,
    drag_per_s=0.05,
    yaw_rate_gain=1.0,
    yaw_rate_max=math.radians(60.0),  # ATC_RATE_WPY_MAX
    yaw_accel_max=math.radians(270.0),  # ATC_ACC_Y_MAX
    yaw_input_tc=0.15,  # ATC_INPUT_TC
    yaw_angle_p=3.0,  # ATC_ANG_YAW_P is 4.5; 3.0 on this vehicle gives the recorded 20 % overshoot
    yaw_lag_s=0.02,
    est_vel_sigma=0.03,
    est_vel_tau_s=3.0,
)
PRESETS = {"px4": PX4, "ardupilot": ARDUPILOT}


def response_params(name: str, rng: np.random.Generator | None = None) -> ResponseParams | None:
    """The response a name stands for: None for ``"ideal"`` (fly the command as given).

    :param name: one of :data:`NAMES`
    :param rng: required for ``"random"`` (a fresh draw per call)
    """
    if name == "ideal":
        return None
    if name == "random":
        if rng is None:
            raise ValueError("autopilot response 'random' needs a random generator")
        return random_params(rng)
    if name not in PRESETS:
        raise ValueError(f"unknown autopilot response {name!r}; known: {', '.join(NAMES)}")
    return PRESETS[name]


def random_ranges(margin: float = 0.25) -> dict[str, tuple[float, float]]:
    """Per numeric field, the range :func:`random_params` draws from: the two presets' span,
    widened by ``margin`` of each end toward the harder side only (slower, laggier, tighter caps,
    more estimate error), so a policy trained on it meets nothing easier than either firmware.

    :param margin: fraction to widen by
    """
    harder_up = {"command_delay_s", "tilt_lag_s", "drag_per_s", "yaw_input_tc", "yaw_lag_s",
                 "est_vel_sigma"}  # fmt: skip
    harder_down = {"yaw_rate_gain", "yaw_rate_max", "yaw_accel_max", "accel_max"}
    out: dict[str, tuple[float, float]] = {}
    for f in fields(ResponseParams):
        if f.name == "name":
            continue
        a, b = sorted((getattr(PX4, f.name), getattr(ARDUPILOT, f.name)))
        if f.name in harder_up:
            b *= 1.0 + margin
        elif f.name in harder_down:
            a *= 1.0 - margin
        out[f.name] = (a, b)
    return out


def random_params(rng: np.random.Generator, margin: float = 0.25) -> ResponseParams:
    """A response drawn per episode: each firmware's structure half of the time, its numbers drawn
    from :func:`random_ranges` (so shaping on/off follows the structure, the rest is mixed).

    :param rng: the episode's generator
    :param margin: see :func:`random_ranges`
    """
    base = PX4 if rng.uniform() < 0.5 else ARDUPILOT
    values: dict[str, Any] = {"name": f"random-{base.name}"}
    for name, (low, high) in random_ranges(margin).items():
        values[name] = float(rng.uniform(low, high))
    for structural in ("shape_accel_max", "shape_jerk_max", "yaw_angle_p", "yaw_input_tc"):
        values[structural] = getattr(base, structural)  # a firmware shapes, or it does not
    return ResponseParams(**values)


def _sqrt_controller(error: float, p: float, second_order_limit: float, dt: float) -> float:
    """ArduPilot's ``sqrt_controller``: linear near zero, square root beyond, never overshooting in dt."""
    if second_order_limit <= 0.0:
        correction = error * p
    else:
        linear = second_order_limit / (p * p)
        if error > linear:
            correction = math.sqrt(2.0 * second_order_limit * (error - 0.5 * linear))
        elif error < -linear:
            correction = -math.sqrt(2.0 * second_order_limit * (-error - 0.5 * linear))
        else:
            correction = error * p
    if dt > 0.0:  # never ask more than closes the error in one step
        limit = abs(error) / dt
        correction = max(-limit, min(limit, correction))
    return correction


class AutopilotResponse:
    """A firmware's response to body-frame velocity + yaw-rate setpoints (see the module docstring)."""

    def __init__(self, params: ResponseParams, rng: np.random.Generator | None = None) -> None:
        """:param params: the personality
        :param rng: drives the velocity-estimate error (None: no estimate error whatever params say)
        """
        self.params = params
        self._rng = rng
        self.reset(0.0)

    def reset(self, yaw: float, velocity_xy: tuple[float, float] | np.ndarray = (0.0, 0.0)) -> None:
        """Start from a vehicle flying ``velocity_xy`` (world ENU, m/s) at heading ``yaw`` (rad), no command.

        :param yaw: the vehicle's heading, rad CCW from East
        :param velocity_xy: its horizontal velocity
        """
        vx, vy = (float(v) for v in velocity_xy)
        self._pending: deque[tuple[float, float, float, float]] = deque()  # (due, vx, vy, rate)
        self._time = 0.0
        self._cmd = (vx, vy, 0.0)  # the command the loops act on (world velocity, yaw rate)
        self._shaped_v = [vx, vy]
        self._shaped_a = [0.0, 0.0]
        self._v = [vx, vy]  # the modelled airframe's velocity and achieved acceleration
        self._a = [0.0, 0.0]
        self._integral = [0.0, 0.0]
        self._previous_error: list[float] | None = None
        self._bias = [0.0, 0.0]
        if self._rng is not None and self.params.est_vel_sigma > 0.0:
            self._bias = [float(b) for b in self._rng.normal(0.0, self.params.est_vel_sigma, 2)]
        self._rate_target = 0.0
        self._yaw_target = yaw
        self._rate = 0.0  # the yaw rate demand after the firmware's rate-loop lag

    # ----------------------------------------------------------------- public API
    def command(self, forward: float, lateral: float, yaw_rate: float, yaw: float) -> None:
        """A setpoint message arrives: rotate it into the world by the heading now, as the firmware
        does with MAV_FRAME_BODY_NED / BODY_OFFSET_NED; it takes effect after ``command_delay_s``.

        :param forward: commanded body velocity along the nose, m/s
        :param lateral: commanded body velocity to the left, m/s
        :param yaw_rate: commanded yaw rate, rad/s CCW
        :param yaw: the vehicle's heading as the autopilot knows it, rad CCW from East
        """
        c, s = math.cos(yaw), math.sin(yaw)
        self._pending.append(
            (self._time + self.params.command_delay_s, forward * c - lateral * s, forward * s + lateral * c,
             float(yaw_rate))
        )  # fmt: skip

    def setpoint(self, state: Any, dt: float = CHUNK_S, *, altitude: float | None = None,
                 vz: float | None = None) -> Setpoint:  # fmt: skip
        """Advance ``dt`` and return what the vehicle's cascaded controller should fly now.

        :param state: the vehicle now (``yaw``, rad CCW from East, is read)
        :param dt: s; a multiple of the internal 5 ms step (:data:`CHUNK_S` is)
        :param altitude: altitude to hold (see :class:`Setpoint`)
        :param vz: climb rate instead of an altitude
        """
        n = max(1, round(dt / _INNER_DT))
        h = dt / n
        for _ in range(n):
            self._time += h
            while self._pending and self._pending[0][0] <= self._time + 1e-9:
                self._cmd = self._pending.popleft()[1:]
            self._step_velocity(h)
            self._step_yaw(h, state.yaw)
        return Setpoint(
            vx=self._v[0], vy=self._v[1], ax=self._a[0] - self.params.drag_per_s * self._v[0],
            ay=self._a[1] - self.params.drag_per_s * self._v[1], yaw_rate=self._rate,
            altitude=altitude, vz=vz,
        )  # fmt: skip

    def measured_body_velocity(self, state: Any) -> np.ndarray:
        """(forward, left) m/s in the body FLU frame as the autopilot's estimator would report it.

        :param state: the vehicle now (``velocity`` world ENU and ``yaw`` are read)
        """
        vx = float(state.velocity[0]) + self._bias[0]
        vy = float(state.velocity[1]) + self._bias[1]
        c, s = math.cos(state.yaw), math.sin(state.yaw)
        return np.array([c * vx + s * vy, -s * vx + c * vy])

    @property
    def reference_velocity(self) -> tuple[float, float]:
        """The modelled airframe's true velocity (world ENU, m/s): what the vehicle is steered to fly."""
        return self._v[0], self._v[1]

    # ----------------------------------------------------------------- the model
    def _step_velocity(self, h: float) -> None:
        p = self.params
        target = self._cmd[:2]
        if p.shape_accel_max > 0.0 and p.shape_jerk_max > 0.0:
            target = self._shape(target, h)
        rng = self._rng
        if rng is not None and p.est_vel_sigma > 0.0:  # Ornstein-Uhlenbeck estimate error
            k = h / p.est_vel_tau_s
            noise = p.est_vel_sigma * math.sqrt(2.0 * k)
            self._bias = [b - k * b + noise * float(rng.standard_normal()) for b in self._bias]
        error = [target[i] - (self._v[i] + self._bias[i]) for i in range(2)]
        previous = self._previous_error or error
        self._previous_error = error
        ff = self._shaped_a if p.shape_accel_max > 0.0 else [0.0, 0.0]
        demand = [
            ff[i] + p.vel_p * error[i] + self._integral[i] + p.vel_d * (error[i] - previous[i]) / h
            for i in range(2)
        ]
        norm = math.hypot(*demand)
        if norm > p.accel_max:
            demand = [d * p.accel_max / norm for d in demand]
        else:  # integrate only while unsaturated, as both firmwares do
            self._integral = [self._integral[i] + p.vel_i * error[i] * h for i in range(2)]
        lag = 1.0 - math.exp(-h / p.tilt_lag_s) if p.tilt_lag_s > 0.0 else 1.0
        for i in range(2):
            self._a[i] += lag * (demand[i] - self._a[i])
            self._v[i] += (self._a[i] - p.drag_per_s * self._v[i]) * h

    def _shape(self, target: tuple[float, float], h: float) -> list[float]:
        """ArduPilot's shape_vel_accel_xy: a jerk-limited acceleration toward the commanded velocity."""
        p = self.params
        kpa = p.shape_jerk_max / p.shape_accel_max
        ex = target[0] - self._shaped_v[0]
        ey = target[1] - self._shaped_v[1]
        e = math.hypot(ex, ey)
        want = [0.0, 0.0]
        if e > 0.0:
            size = min(_sqrt_controller(e, kpa, p.shape_jerk_max, h), p.shape_accel_max)
            want = [ex / e * size, ey / e * size]
        dx, dy = want[0] - self._shaped_a[0], want[1] - self._shaped_a[1]
        step = math.hypot(dx, dy)
        if step > p.shape_jerk_max * h:
            dx, dy = dx * p.shape_jerk_max * h / step, dy * p.shape_jerk_max * h / step
        self._shaped_a = [self._shaped_a[0] + dx, self._shaped_a[1] + dy]
        self._shaped_v = [self._shaped_v[i] + self._shaped_a[i] * h for i in range(2)]
        return self._shaped_v

    def _step_yaw(self, h: float, yaw: float) -> None:
        """Shape the commanded rate into a heading target; the attitude loop closes on the vehicle's
        heading ``yaw``; its demand, lagged, is the yaw rate the vehicle's own rate loop flies."""
        p = self.params
        desired = max(-p.yaw_rate_max, min(p.yaw_rate_max, p.yaw_rate_gain * self._cmd[2]))
        target = self._rate_target
        if p.yaw_input_tc > 0.0:
            desired = target + _sqrt_controller(desired - target, 1.0 / p.yaw_input_tc, 0.0, h) * h
        step = p.yaw_accel_max * h
        self._rate_target = max(target - step, min(target + step, desired))
        if p.yaw_angle_p > 0.0:
            self._yaw_target = wrap_angle(self._yaw_target + self._rate_target * h)
        else:
            self._yaw_target = yaw  # rate-only control: the heading target follows the vehicle
        demand = self._rate_target + p.yaw_angle_p * wrap_angle(self._yaw_target - yaw)
        lag = 1.0 - math.exp(-h / p.yaw_lag_s) if p.yaw_lag_s > 0.0 else 1.0
        self._rate += lag * (demand - self._rate)


def fly(
    vehicle: Any, response: AutopilotResponse | None, forward: float, yaw_rate: float, *,
    altitude: float, duration: float = 0.1, lateral: float = 0.0,
) -> Any:  # fmt: skip
    """Fly one command for ``duration`` s on a :class:`flightsim.vehicle.Vehicle` and return its state.

    ``response`` None is the ideal autopilot the env always had: the body command rotated by the
    heading now and held for the whole duration. Otherwise the response model is stepped every
    :data:`CHUNK_S` and the vehicle flies its setpoint.

    :param vehicle: the vehicle (``state`` and ``step(setpoint, duration)`` are used)
    :param response: the firmware response, or None
    :param forward: commanded body velocity along the nose, m/s
    :param yaw_rate: commanded yaw rate, rad/s CCW
    :param altitude: altitude to hold, m
    :param duration: s, a whole number of chunks when ``response`` is given
    :param lateral: commanded body velocity to the left, m/s
    """
    state = vehicle.state
    if response is None:
        return vehicle.step(
            Setpoint.from_body(forward, lateral, state.yaw, yaw_rate=yaw_rate, altitude=altitude), duration
        )
    n = round(duration / CHUNK_S)
    if n < 1 or abs(n * CHUNK_S - duration) > 1e-9:
        raise ValueError(f"duration ({duration} s) must be a whole number of {CHUNK_S} s chunks")
    response.command(forward, lateral, yaw_rate, state.yaw)
    for _ in range(n):
        state = vehicle.step(response.setpoint(state, altitude=altitude), CHUNK_S)
    return state
