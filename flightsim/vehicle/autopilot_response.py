"""How a real autopilot answers the companion's setpoints: a response model between command and vehicle.

The companion sends, 10 times a second, a body-frame forward speed and a yaw rate. A real flight
controller does not fly that command as given. Recordings of ArduCopter SITL and PX4 SIH SITL
(``tests/fixtures/autopilot-response/``) show it: PX4 reaches only 64-75 % of a 1 m/s step in 4 s
and slows to 1.3-1.5 m/s in a 2 m/s, 1 rad/s turn; ArduPilot delays 0.4 s, overshoots 8 % and caps
the yaw rate at 60 deg/s; both slide 24-35 deg sideways in that turn. This module reproduces that
with each firmware's controller structure, so the simulated vehicle is as hard to fly as the real
one (never easier), and training can see it.

Spec (the whole API; pure logic: numpy, and a numba-compiled core as in control.py; no I/O, no JSBSim):

* :class:`ResponseParams`: one firmware personality's limits and gains. Presets :data:`PX4` and
  :data:`ARDUPILOT` (calibrated against the recordings), :func:`random_params` (drawn per episode
  over ranges that cover both firmwares plus a margin) and :func:`response_params` (by name:
  ``"px4"``, ``"ardupilot"``; ``"ideal"`` gives None, meaning no response model at all).
* :class:`AutopilotResponse`: the stateful model. ``reset(yaw, velocity_xy)`` at the start of a
  flight (or when velocity control begins); ``command(forward, lateral, yaw_rate, yaw)`` each time
  a setpoint message arrives (body FLU m/s and rad/s CCW; rotated into the world by the heading at
  that moment, as MAV_FRAME_BODY_NED/BODY_OFFSET_NED do; ``command_world(vx, vy, yaw_rate)`` if
  it is already rotated); and every physics chunk
  (:data:`CHUNK_S`, 3/120 s) ``setpoint(state, dt, altitude=..)`` returns the
  :class:`flightsim.vehicle.control.Setpoint` the vehicle's cascaded controller should fly now: the
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
  ArduPilot keeps position stabilisation under GUIDED velocity control (``ModeGuided::
  velaccel_control_run`` unless GUID_OPTIONS says not): the shaped velocity is integrated into a
  position target, and PSC_NE_POS_P (``pos_p``, through ``sqrt_controller`` limited by WP_ACC)
  adds a correction towards it, closing on the flown vehicle's own position (``_pos_estimate``),
  so a vehicle that lags catches up and overshoots (1.9 m/s for 1.6 asked in the real flights).
  Its limits are the firmware's: the position error is held within what asks :data:`WP_SPD` of the
  correction (``AC_P_2D``, GUIDED's correction limits), and while the velocity loop's acceleration is
  at its limit neither the position target nor the shaped velocity moves on along it
  (``update_pos_vel_accel_xy``), so a vehicle held back finds no target run far ahead.
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
from numba import njit

from flightsim.vehicle.control import Setpoint, wrap_angle

CHUNK_S = 3 / 120
"""The step the model is called at: 3 physics steps of the 120 Hz vehicle (the sim autopilot's chunk)."""
_INNER_DT = 0.005
"""Internal integration step of the model, s: several per chunk keeps the lags and the jerk limit stable."""
_CHUNK_STEPS = round(CHUNK_S / _INNER_DT)
WP_SPD = 10.0
"""ArduPilot's WP_SPD, m/s (the SITL's default): GUIDED limits its position correction to it
(``set_correction_speed_accel_NE``), so the position error is held within what asks that speed."""
NAMES = ("ideal", "px4", "ardupilot", "random")
"""The values of ``EnvConfig.autopilot_response`` and of the sim autopilots' response option."""


@dataclass(frozen=True)
class ResponseParams:
    """One firmware personality's response (SI units, rad).

    :param name: what it imitates
    :param command_delay_s: from the setpoint's arrival to the velocity loop acting on it
    :param shape_accel_max: ArduPilot input shaping acceleration limit (WP_ACC), m/s^2; 0 = no shaping
    :param shape_jerk_max: ArduPilot input shaping jerk limit (PSC_JERK_NE), m/s^3
    :param pos_p: ArduPilot's position loop behind the shaping (PSC_NE_POS_P), 1/s: GUIDED velocity
        control integrates the shaped velocity into a position target and corrects towards it, so a
        lagging vehicle catches up and overshoots (0: no position loop, PX4 offboard velocity)
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
    pos_p: float
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

    @property
    def shapes_input(self) -> bool:
        """ArduPilot's structure: a velocity setpoint is shaped (jerk- and acceleration-limited)
        before the loop flies it; PX4's offboard setpoints reach the loop as sent."""
        return self.shape_jerk_max > 0.0

    def without_estimate_error(self) -> ResponseParams:
        """The same response with a perfect velocity estimate (for replaying recorded commands)."""
        return replace(self, est_vel_sigma=0.0)


# Fitted to the recordings (tests/fixtures/autopilot-response, bench/bench_response.py): the delays,
# lags and drag. The rest are the defaults the SITLs reported (px4-sih-params.txt,
# ardupilot-sitl-params.txt in the shared fixture set), except where a comment says otherwise.
PX4 = ResponseParams(
    name="px4",
    command_delay_s=0.05,
    shape_accel_max=0.0,  # offboard velocity setpoints reach the PID unshaped (no flight task)
    shape_jerk_max=0.0,
    pos_p=0.0,  # a velocity-only offboard setpoint has no position target
    vel_p=1.8,  # MPC_XY_VEL_P_ACC
    vel_i=0.4,  # MPC_XY_VEL_I_ACC
    vel_d=0.2,  # MPC_XY_VEL_D_ACC
    accel_max=5.0,  # MPC_ACC_HOR_MAX (MPC_ACC_HOR 3 and MPC_JERK_AUTO 4 shape auto modes, not offboard)
    tilt_lag_s=0.20,
    drag_per_s=1.5,
    yaw_rate_gain=0.91,  # the recordings hold 94 %; the JSBSim vehicle adds 3 %
    # MC_YAWRATE_MAX. The auto-mode limits do not act on an offboard yaw rate: the recording holds
    # 1.40 rad/s (MPC_YAWRAUTO_MAX is 60 deg/s = 1.05) and is at 90 % of it in 1.1 s (MPC_YAWRAUTO_ACC
    # 20 deg/s^2 would take 4 s); MC_YAW_P acts on a heading error, and offboard rate-only control has none.
    yaw_rate_max=math.radians(200.0),
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
    pos_p=1.0,  # PSC_NE_POS_P: GUIDED stabilises position under velocity control unless GUID_OPTIONS says not
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


#: fields whose larger value makes a response harder to fly (slower, laggier, a worse estimate)
_HARDER_UP = ("command_delay_s", "tilt_lag_s", "drag_per_s", "yaw_input_tc", "yaw_lag_s", "est_vel_sigma")
#: fields whose smaller value makes it harder (tighter caps)
_HARDER_DOWN = ("yaw_rate_gain", "yaw_rate_max", "yaw_accel_max", "accel_max")
#: a firmware's structure: it shapes its input, or holds a heading, or it does not
_STRUCTURAL = ("shape_accel_max", "shape_jerk_max", "pos_p", "yaw_angle_p", "yaw_input_tc")
#: structural fields :func:`random_params` gives no draw: one would move every later number of the
#: episode's generator (every episode, PX4-like ones too) for a value the base firmware sets anyway
_UNDRAWN = ("pos_p",)


def random_ranges(margin: float = 0.25) -> dict[str, tuple[float, float]]:
    """Per numeric field, the range :func:`random_params` draws from: the two presets' span,
    widened by ``margin`` of each end toward the harder side only (slower, laggier, tighter caps,
    more estimate error), so a policy trained on it meets nothing easier than either firmware.

    :param margin: fraction to widen by
    """
    out: dict[str, tuple[float, float]] = {}
    for f in fields(ResponseParams):
        if f.name == "name":
            continue
        a, b = sorted((getattr(PX4, f.name), getattr(ARDUPILOT, f.name)))
        if f.name in _HARDER_UP:
            b *= 1.0 + margin
        elif f.name in _HARDER_DOWN:
            a *= 1.0 - margin
        out[f.name] = (a, b)
    return out


def hardest_params(params: ResponseParams, margin: float = 0.25) -> ResponseParams:
    """``params`` at the end of every range of :func:`random_ranges` that makes it stop latest:
    delays and lags longest, caps tightest, and the airframe's drag least (drag slows the
    speeding-up :func:`random_ranges` counts as harder, but it also brakes a coasting vehicle).
    The firmware's structure (shaping, yaw loop) and loop gains are kept. A teacher that must stop
    clear through it as well as through the drawn response brakes where a student, which cannot
    see the draw, must brake too.

    :param params: the response (its structural fields are kept)
    :param margin: see :func:`random_ranges`
    """
    ranges = random_ranges(margin)
    hard = {name: ranges[name][1] for name in _HARDER_UP} | {name: ranges[name][0] for name in _HARDER_DOWN}
    kept = {name: getattr(params, name) for name in _STRUCTURAL}
    coasting = {"drag_per_s": ranges["drag_per_s"][0]}
    return replace(params, name=f"{params.name}-hardest", **(hard | kept | coasting))


def random_params(rng: np.random.Generator, margin: float = 0.25) -> ResponseParams:
    """A response drawn per episode: each firmware's structure half of the time, its numbers drawn
    from :func:`random_ranges` (so shaping on/off follows the structure, the rest is mixed).

    :param rng: the episode's generator
    :param margin: see :func:`random_ranges`
    """
    base = PX4 if rng.uniform() < 0.5 else ARDUPILOT
    values: dict[str, Any] = {"name": f"random-{base.name}"}
    for name, (low, high) in random_ranges(margin).items():
        if name not in _UNDRAWN:
            values[name] = float(rng.uniform(low, high))
    for structural in _STRUCTURAL:
        values[structural] = getattr(base, structural)  # a firmware shapes, or it does not
    return ResponseParams(**values)


@njit(cache=True)
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


@njit(cache=True)
def _inv_sqrt_controller(output: float, p: float, second_order_limit: float) -> float:
    """ArduPilot's ``inv_sqrt_controller``: the error :func:`_sqrt_controller` answers with ``output``."""
    if second_order_limit <= 0.0:
        return output / p
    if output < second_order_limit / p:
        return output / p
    return 0.5 * second_order_limit / (p * p) + output * output / (2.0 * second_order_limit)


# Layout of the parameter vector _advance reads and of the model's state vector.
_P_NAMES = ("shape_accel_max", "shape_jerk_max", "pos_p", "vel_p", "vel_i", "vel_d", "accel_max",
            "tilt_lag_s", "drag_per_s", "yaw_rate_gain", "yaw_rate_max", "yaw_accel_max", "yaw_input_tc",
            "yaw_angle_p", "yaw_lag_s")  # fmt: skip
_SHAPE_A, _SHAPE_J, _PP, _VP, _VI, _VD, _AMAX, _TILT, _DRAG = range(9)
_YGAIN, _YMAX, _YACC, _YTC, _YANG, _YLAG = range(9, 15)
_S_SVX, _S_SVY, _S_SAX, _S_SAY, _S_VX, _S_VY, _S_AX, _S_AY, _S_IX, _S_IY = range(10)
_S_EX, _S_EY, _S_HAS_E, _S_BX, _S_BY, _S_RT, _S_YT, _S_R, _S_PX, _S_PY, _S_MX, _S_MY = range(10, 22)
_S_LX, _S_LY = 22, 23
_N_STATE = 24
# _S_PX/_S_PY: the position target minus the flown vehicle's position (ArduPilot's position error);
# _S_MX/_S_MY: the flown vehicle's true velocity, which that error integrates (set by the caller: the
# JSBSim vehicle's in setpoint and the batch vehicle, the point mass's own in predict);
# _S_LX/_S_LY: the velocity loop's acceleration demand when the limit cut it, else 0


@njit(cache=True)
def _advance(
    x: np.ndarray, p: np.ndarray, cmd_vx: float, cmd_vy: float, cmd_r: float, yaw: float, h: float, n: int
) -> None:
    """``n`` steps of ``h`` s of the model (state ``x`` in place) with one command in force.

    Velocity: optional ArduPilot shaping (shape_vel_accel_xy), then the firmware's velocity PID on
    a point mass with tilt lag and drag, closing on velocity + estimate error. Yaw: gain, cap,
    input shaping, acceleration limit, heading target, attitude loop on the vehicle's ``yaw``, lag.
    """
    shaping = p[_SHAPE_A] > 0.0 and p[_SHAPE_J] > 0.0
    tilt = 1.0 - math.exp(-h / p[_TILT]) if p[_TILT] > 0.0 else 1.0
    ylag = 1.0 - math.exp(-h / p[_YLAG]) if p[_YLAG] > 0.0 else 1.0
    for _ in range(n):
        # --- velocity: the target the PID sees (shaped or raw) and its feedforward
        tx, ty, fx, fy = cmd_vx, cmd_vy, 0.0, 0.0
        if shaping:
            kpa = p[_SHAPE_J] / p[_SHAPE_A]
            ex, ey = cmd_vx - x[_S_SVX], cmd_vy - x[_S_SVY]
            e = math.sqrt(ex * ex + ey * ey)
            wx = wy = 0.0
            if e > 0.0:
                size = min(_sqrt_controller(e, kpa, p[_SHAPE_J], h), p[_SHAPE_A])
                wx, wy = ex / e * size, ey / e * size
            dx, dy = wx - x[_S_SAX], wy - x[_S_SAY]
            step = math.sqrt(dx * dx + dy * dy)
            jerk = p[_SHAPE_J] * h
            if step > jerk:
                dx, dy = dx * jerk / step, dy * jerk / step
            x[_S_SAX] += dx
            x[_S_SAY] += dy
            # update_pos_vel_accel_xy: while the last step's acceleration was limited (_S_LX/_S_LY,
            # AC_PosControl's _limit_vector), neither the position target nor the shaped velocity
            # moves further along the limit where its error already points that way
            lx, ly = x[_S_LX], x[_S_LY]
            limited = lx != 0.0 or ly != 0.0
            move_x = (x[_S_SVX] + 0.5 * x[_S_SAX] * h) * h  # the position target's step
            move_y = (x[_S_SVY] + 0.5 * x[_S_SAY] * h) * h
            if limited and move_x * lx + move_y * ly > 0.0 and x[_S_PX] * lx + x[_S_PY] * ly > 0.0:
                move_x = move_y = 0.0
            gain_x, gain_y = x[_S_SAX] * h, x[_S_SAY] * h  # the shaped velocity's step
            along = x[_S_SVX] * lx + x[_S_SVY] * ly >= 0.0  # a slowing target is never held
            if limited and along and gain_x * lx + gain_y * ly > 0.0 and x[_S_EX] * lx + x[_S_EY] * ly > 0.0:
                gain_x = gain_y = 0.0
            x[_S_SVX] += gain_x
            x[_S_SVY] += gain_y
            tx, ty, fx, fy = x[_S_SVX], x[_S_SVY], x[_S_SAX], x[_S_SAY]
            if p[_PP] > 0.0:
                # the position target the shaped velocity drags along, against the flown vehicle's
                # position as the firmware estimates it (AC_PosControl closes on _pos_estimate, not on
                # a model of itself), and its P loop (AC_P_2D: sqrt_controller limited by WP_ACC; the
                # error, and so the target, held within what asks WP_SPD of it)
                x[_S_PX] += move_x - (x[_S_MX] + x[_S_BX]) * h
                x[_S_PY] += move_y - (x[_S_MY] + x[_S_BY]) * h
                e = math.sqrt(x[_S_PX] * x[_S_PX] + x[_S_PY] * x[_S_PY])
                e_max = _inv_sqrt_controller(WP_SPD, p[_PP], p[_SHAPE_A])
                if e > e_max:
                    x[_S_PX], x[_S_PY], e = x[_S_PX] * e_max / e, x[_S_PY] * e_max / e, e_max
                if e > 0.0:
                    size = _sqrt_controller(e, p[_PP], p[_SHAPE_A], h)
                    tx += x[_S_PX] / e * size
                    ty += x[_S_PY] / e * size
        ex = tx - (x[_S_VX] + x[_S_BX])
        ey = ty - (x[_S_VY] + x[_S_BY])
        if x[_S_HAS_E] == 0.0:
            x[_S_EX], x[_S_EY], x[_S_HAS_E] = ex, ey, 1.0
        dx = fx + p[_VP] * ex + x[_S_IX] + p[_VD] * (ex - x[_S_EX]) / h
        dy = fy + p[_VP] * ey + x[_S_IY] + p[_VD] * (ey - x[_S_EY]) / h
        x[_S_EX], x[_S_EY] = ex, ey
        norm = math.sqrt(dx * dx + dy * dy)
        if norm > p[_AMAX]:
            x[_S_LX], x[_S_LY] = dx, dy
            dx, dy = dx * p[_AMAX] / norm, dy * p[_AMAX] / norm
        else:  # integrate only while unsaturated, as both firmwares do
            x[_S_LX] = x[_S_LY] = 0.0
            x[_S_IX] += p[_VI] * ex * h
            x[_S_IY] += p[_VI] * ey * h
        x[_S_AX] += tilt * (dx - x[_S_AX])
        x[_S_AY] += tilt * (dy - x[_S_AY])
        x[_S_VX] += (x[_S_AX] - p[_DRAG] * x[_S_VX]) * h
        x[_S_VY] += (x[_S_AY] - p[_DRAG] * x[_S_VY]) * h
        # --- yaw
        desired = max(-p[_YMAX], min(p[_YMAX], p[_YGAIN] * cmd_r))
        target = x[_S_RT]
        if p[_YTC] > 0.0:
            desired = target + _sqrt_controller(desired - target, 1.0 / p[_YTC], 0.0, h) * h
        step = p[_YACC] * h
        x[_S_RT] = max(target - step, min(target + step, desired))
        if p[_YANG] > 0.0:
            x[_S_YT] = wrap_angle(x[_S_YT] + x[_S_RT] * h)
        else:
            x[_S_YT] = yaw  # rate-only control: the heading target follows the vehicle
        demand = x[_S_RT] + p[_YANG] * wrap_angle(x[_S_YT] - yaw)
        x[_S_R] += ylag * (demand - x[_S_R])


@njit(cache=True)
def _predict(
    x0: np.ndarray, p: np.ndarray, queue: np.ndarray, active: np.ndarray, delay: float, yaw0: float,
    commands: np.ndarray, command_steps: int, total_steps: int, per_period: int, h: float, decay: float,
) -> np.ndarray:  # pragma: no cover - compiled  # fmt: skip
    """The kernel of :meth:`AutopilotResponse.predict` (the same stepping as ``setpoint``; the
    estimate error times ``decay`` every inner step)."""
    k_count = commands.shape[0]
    out = np.zeros((k_count, total_steps, 3))
    n_queue = queue.shape[0]
    dues = np.zeros(n_queue + total_steps)
    values = np.zeros((n_queue + total_steps, 3))
    for c in range(k_count):
        x = x0.copy()
        cmd = active.copy()
        dues[:n_queue] = queue[:, 0]
        values[:n_queue] = queue[:, 1:]
        n = n_queue
        head = 0
        px = py = 0.0
        yaw = yaw0
        t = 0.0
        for k in range(total_steps):
            forward = commands[c, 0] if k < command_steps else 0.0
            rate = commands[c, 1] if k < command_steps else 0.0
            left = commands[c, 2] if k < command_steps else 0.0
            dues[n] = t + delay
            cos_yaw, sin_yaw = math.cos(yaw), math.sin(yaw)
            values[n, 0] = forward * cos_yaw - left * sin_yaw
            values[n, 1] = forward * sin_yaw + left * cos_yaw
            values[n, 2] = rate
            n += 1
            for i in range(per_period):
                t += h
                while head < n and dues[head] <= t + 1e-9:
                    cmd[:] = values[head]
                    head += 1
                # the airframe the position loop closes on: the point mass, read once a chunk as setpoint does
                if (k * per_period + i) % _CHUNK_STEPS == 0:
                    x[_S_MX], x[_S_MY] = x[_S_VX], x[_S_VY]
                _advance(x, p, cmd[0], cmd[1], cmd[2], yaw, h, 1)
                x[_S_BX] *= decay
                x[_S_BY] *= decay
                px += x[_S_VX] * h
                py += x[_S_VY] * h
                yaw += x[_S_R] * h
            out[c, k, 0], out[c, k, 1], out[c, k, 2] = px, py, yaw
    return out


def _body_commands(commands: np.ndarray) -> np.ndarray:
    """``(K, 2)`` or ``(K, 3)`` body commands as the ``(K, 3)`` the kernel reads (no sideways part: 0)."""
    array = np.asarray(commands, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] not in (2, 3):
        raise ValueError(f"commands must be (K, 2) or (K, 3), got {array.shape}")
    if array.shape[1] == 2:
        array = np.hstack([array, np.zeros((array.shape[0], 1))])
    return np.ascontiguousarray(array)


def _param_vector(params: ResponseParams) -> np.ndarray:
    """The numbers the compiled kernels read, in their order."""
    return np.array([getattr(params, name) for name in _P_NAMES], dtype=np.float64)


class AutopilotResponse:
    """A firmware's response to body-frame velocity + yaw-rate setpoints (see the module docstring)."""

    def __init__(self, params: ResponseParams, rng: np.random.Generator | None = None) -> None:
        """:param params: the personality
        :param rng: drives the velocity-estimate error (None: no estimate error whatever params say)
        """
        self.params = params
        self._p = _param_vector(params)
        self._rng = rng if params.est_vel_sigma > 0.0 else None
        self._x = np.zeros(_N_STATE)
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
        x = self._x
        x[:] = 0.0
        x[_S_SVX], x[_S_SVY], x[_S_VX], x[_S_VY], x[_S_YT] = vx, vy, vx, vy, yaw
        x[_S_MX], x[_S_MY] = vx, vy
        if self._rng is not None:
            x[_S_BX], x[_S_BY] = self._rng.normal(0.0, self.params.est_vel_sigma, 2)

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
        self.command_world(forward * c - lateral * s, forward * s + lateral * c, yaw_rate)

    def command_world(self, vx: float, vy: float, yaw_rate: float) -> None:
        """A setpoint already rotated into the world (ENU m/s, yaw rate rad/s CCW) arrives now.

        :param vx: velocity East, m/s
        :param vy: velocity North, m/s
        :param yaw_rate: rad/s CCW
        """
        due = self._time + self.params.command_delay_s
        self._pending.append((due, float(vx), float(vy), float(yaw_rate)))

    def setpoint(self, state: Any, dt: float = CHUNK_S, *, altitude: float | None = None,
                 vz: float | None = None) -> Setpoint:  # fmt: skip
        """Advance ``dt`` and return what the vehicle's cascaded controller should fly now.

        :param state: the vehicle now (``yaw``, rad CCW from East, and ``velocity``, world ENU m/s,
            are read: ArduPilot's position loop closes on where the vehicle really goes)
        :param dt: s; a multiple of the internal 5 ms step (:data:`CHUNK_S` is)
        :param altitude: altitude to hold (see :class:`Setpoint`)
        :param vz: climb rate instead of an altitude
        """
        n = max(1, round(dt / _INNER_DT))
        h = dt / n
        x, yaw = self._x, float(state.yaw)
        if self._rng is not None:  # Ornstein-Uhlenbeck estimate error, exact over the chunk
            decay = math.exp(-dt / self.params.est_vel_tau_s)
            kick = self.params.est_vel_sigma * math.sqrt(1.0 - decay * decay)
            noise = self._rng.standard_normal(2)
            x[_S_BX] = x[_S_BX] * decay + kick * noise[0]
            x[_S_BY] = x[_S_BY] * decay + kick * noise[1]
        x[_S_MX], x[_S_MY] = float(state.velocity[0]), float(state.velocity[1])  # for the position loop
        done = 0
        while done < n:
            # inner step i (1-based) acts on the last command due by time + i h
            todo = n - done
            if self._pending:
                until_due = math.ceil((self._pending[0][0] - self._time) / h - 1e-9)
                if until_due <= 1:
                    self._cmd = self._pending.popleft()[1:]
                    continue
                todo = min(todo, until_due - 1)
            _advance(x, self._p, *self._cmd, yaw, h, todo)
            self._time += todo * h
            done += todo
        drag = self.params.drag_per_s
        return Setpoint(
            vx=x[_S_VX], vy=x[_S_VY], ax=x[_S_AX] - drag * x[_S_VX], ay=x[_S_AY] - drag * x[_S_VY],
            yaw_rate=x[_S_R], altitude=altitude, vz=vz,
        )  # fmt: skip

    def predict(
        self, yaw: float, commands: np.ndarray, command_steps: int, total_steps: int, period: float = 0.1,
        params: ResponseParams | None = None, held: tuple[float, float] = (0.0, 0.0),
    ) -> np.ndarray:  # fmt: skip
        """Where each of several command sequences would take the vehicle, from the model's state now.

        Candidate ``i`` sends the body command ``commands[i]`` every ``period`` s for
        ``command_steps`` periods, then zero (a hold) up to ``total_steps``; the commands already in
        flight (the delay) act first. The airframe is the model's own (its velocity integrated), the
        estimate error decays from today's value as its expectation does (the Ornstein-Uhlenbeck
        process's mean, ``exp(-t / est_vel_tau_s)``): a planner's prediction, not a simulation.
        Held at today's value instead, an error of 0.6 m/s carried every predicted stop 2 m
        sideways: near a wall no candidate of the predictive teacher was safe.

        :param yaw: the vehicle's heading now, rad CCW from East
        :param commands: (K, 2) body forward (m/s) and yaw rate (rad/s CCW), or (K, 3) with a
            sideways velocity (m/s, left positive) after them
        :param command_steps: periods the command is sent for
        :param total_steps: periods predicted
        :param period: s between commands, a whole number of the internal 5 ms steps
        :param params: predict with these numbers instead of the model's own, from the model's state
            (they must keep its structure: :func:`hardest_params`); the new commands take their delay
        :param held: velocity every setpoint carries on top of its command, world East and North
            m/s (a drift hold: the setpoint plus the estimate error), predicted as that much less
            estimate error
        :return: (K, total_steps, 3) displacement East, North (m) and heading (rad) at each period's end
        """
        queue = np.array([[due - self._time, *cmd] for due, *cmd in self._pending]).reshape(-1, 4)
        p = self._p if params is None else _param_vector(params)
        delay = (params or self.params).command_delay_s
        tau = (params or self.params).est_vel_tau_s
        decay = math.exp(-_INNER_DT / tau) if tau > 0.0 else 1.0
        x = self._x
        if held != (0.0, 0.0):
            x = x.copy()
            x[_S_BX] -= held[0]
            x[_S_BY] -= held[1]
        return _predict(
            x, p, queue, np.asarray(self._cmd, dtype=np.float64), delay,
            float(yaw), _body_commands(commands), int(command_steps),
            int(total_steps), round(period / _INNER_DT), _INNER_DT, decay,
        )  # fmt: skip

    def measured_body_velocity(self, state: Any) -> np.ndarray:
        """(forward, left) m/s in the body FLU frame as the autopilot's estimator would report it.

        :param state: the vehicle now (``velocity`` world ENU and ``yaw`` are read)
        """
        vx = float(state.velocity[0]) + self._x[_S_BX]
        vy = float(state.velocity[1]) + self._x[_S_BY]
        c, s = math.cos(state.yaw), math.sin(state.yaw)
        return np.array([c * vx + s * vy, -s * vx + c * vy])

    @property
    def estimate_error(self) -> np.ndarray:
        """(2,) the velocity estimate's error now, world ENU m/s (reported = true + this)."""
        return self._x[[_S_BX, _S_BY]].copy()

    @property
    def reference_velocity(self) -> tuple[float, float]:
        """The modelled airframe's true velocity (world ENU, m/s): what the vehicle is steered to fly."""
        return float(self._x[_S_VX]), float(self._x[_S_VY])


def fly(
    vehicle: Any, response: AutopilotResponse | None, forward: float, yaw_rate: float, *,
    altitude: float, duration: float = 0.1, lateral: float = 0.0,
) -> Any:  # fmt: skip
    """Fly one command for ``duration`` s on a :class:`flightsim.vehicle.quadrotor.Vehicle` and
    return its state.

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
