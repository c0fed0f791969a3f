"""Autopilot-like cascaded multirotor controller: velocity -> attitude -> body rates -> motor mix.

Pure logic (no JSBSim, no I/O): the vehicle feeds it the measured state each physics step and
applies the per-rotor thrusts it returns. Frames are the project's: world ENU (x East, y North,
z Up), body FLU (x forward, y left, z up). Euler angles are Z-Y-X about those axes, so yaw is
counter-clockwise from +x, roll > 0 lowers the right side and pitch > 0 lowers the nose.

Rotor order and spin (seen from above), shared with the JSBSim model ``lidar_quad``:
0 front-right CCW, 1 back-left CCW, 2 front-left CW, 3 back-right CW. A rotor spinning CCW
pushes the body clockwise, so yawing left (CCW) means speeding up the CW pair 2 and 3.

The cascade itself (:func:`control_step`) is one numba-compiled function of plain floats, the
gains and the integrator memory: it runs 120 times per simulated second in every training
environment, where interpreted arithmetic cost more than JSBSim's own integration step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

GRAVITY = 9.80665
"""Standard gravity (m/s^2); the controller's integrators absorb the simulator's local value."""


@njit(cache=True)
def wrap_angle(angle: float) -> float:
    """Wrap an angle to [-pi, pi).

    :param angle: radians.
    """
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True)
def _clip(value: float, low: float, high: float) -> float:
    return low if value < low else high if value > high else value


@dataclass(frozen=True)
class Setpoint:
    """What the autopilot asks of the vehicle. Horizontal velocity in the world ENU frame.

    :param vx: velocity East, m/s.
    :param vy: velocity North, m/s.
    :param vz: climb rate, m/s up; ``None`` holds ``altitude``.
    :param altitude: z target (m, up) used when ``vz`` is None; both None hold the altitude the
        vehicle had when it entered this hold.
    :param yaw_rate: rad/s counter-clockwise (FLU); ``None`` holds ``yaw``.
    :param yaw: heading target (rad, CCW from +x) used when ``yaw_rate`` is None; both None hold
        the heading the vehicle had when it entered this hold.
    :param ax: acceleration feedforward East, m/s^2: the slope of a shaped velocity reference
        (:mod:`flightsim.vehicle.autopilot_response`), added to the velocity loop's output so the vehicle
        follows the reference instead of lagging it by its own loop.
    :param ay: acceleration feedforward North, m/s^2.
    """

    vx: float = 0.0
    vy: float = 0.0
    vz: float | None = None
    altitude: float | None = None
    yaw_rate: float | None = 0.0
    yaw: float | None = None
    ax: float = 0.0
    ay: float = 0.0

    @staticmethod
    def from_body(forward: float, lateral: float, yaw: float, **kw: float | None) -> Setpoint:
        """Build a setpoint from a body-frame (FLU) horizontal velocity.

        The body velocity is rotated into the world by the vehicle's current heading, which is
        what an autopilot does with a body-frame velocity command (MAV_FRAME_BODY_OFFSET_NED).

        :param forward: m/s along the nose.
        :param lateral: m/s to the left.
        :param yaw: the vehicle's current heading, rad CCW from +x.
        :param kw: the other :class:`Setpoint` fields (vz, altitude, yaw_rate, yaw).
        """
        c, s = math.cos(yaw), math.sin(yaw)
        return Setpoint(vx=forward * c - lateral * s, vy=forward * s + lateral * c, **kw)


@dataclass(frozen=True)
class ControllerConfig:
    """Gains, limits and the airframe model the controller assumes.

    Airframe defaults match the JSBSim model ``flightsim/vehicle/models/aircraft/lidar_quad``.
    Gains are bandwidths (1/s): each loop is about 3x slower than the one inside it.
    """

    mass_kg: float = field(default=1.5, metadata={"min": 0.1})
    arm_length_m: float = field(default=0.225, metadata={"min": 0.01})
    yaw_moment_per_thrust_m: float = field(default=0.016, metadata={"min": 1e-4})
    max_rotor_thrust_n: float = field(default=8.0, metadata={"min": 0.1})
    idle_rotor_thrust_n: float = field(default=0.15, metadata={"min": 0.0})
    ixx_kg_m2: float = field(default=0.015, metadata={"min": 1e-5})
    iyy_kg_m2: float = field(default=0.015, metadata={"min": 1e-5})
    izz_kg_m2: float = field(default=0.027, metadata={"min": 1e-5})

    max_tilt_deg: float = field(default=30.0, metadata={"min": 1.0, "max": 60.0})
    max_climb_rate: float = field(default=2.5, metadata={"min": 0.1})
    max_descent_rate: float = field(default=1.5, metadata={"min": 0.1})
    max_yaw_rate: float = field(default=2.0, metadata={"min": 0.1})
    max_roll_pitch_rate: float = field(default=4.0, metadata={"min": 0.1})

    altitude_p: float = 2.0
    climb_rate_p: float = 5.0
    climb_rate_i: float = 4.0
    velocity_p: float = 3.0
    velocity_i: float = 0.8
    velocity_i_limit: float = 2.0
    attitude_p: float = 9.0
    yaw_p: float = 3.0
    rate_p: float = 24.0
    rate_i: float = 10.0
    yaw_rate_p: float = 8.0
    yaw_rate_i: float = 4.0


# Layout of the gain vector that control_step reads (built from a ControllerConfig by
# CascadedController) and of the controller's memory (integrators and latched holds).
_G_MASS, _G_IDLE, _G_TAN_TILT, _G_MAX_CLIMB, _G_MAX_DESCENT, _G_MAX_YAW_RATE, _G_MAX_RP_RATE = range(7)
_G_ALT_P, _G_CLIMB_P, _G_CLIMB_I, _G_VEL_P, _G_VEL_I, _G_VEL_I_LIMIT, _G_ATT_P, _G_YAW_P = range(7, 15)
_G_RATE_P, _G_RATE_I, _G_YAW_RATE_P, _G_YAW_RATE_I, _G_IXX, _G_IYY, _G_IZZ = range(15, 22)
_G_MIX_RP, _G_MIX_YAW, _G_T_MAX = range(22, 25)
_N_GAINS = 25
_M_ALT_HOLD, _M_YAW_HOLD, _M_VEL_I_X, _M_VEL_I_Y, _M_CLIMB_I, _M_RATE_I_X, _M_RATE_I_Y, _M_RATE_I_Z = range(8)
_N_MEMORY = 8


def gain_vector(config: ControllerConfig) -> np.ndarray:
    """The gains and limits of ``config`` as the float64 vector :func:`control_step` reads.

    :param config: controller configuration.
    """
    g = np.empty(_N_GAINS)
    g[_G_MASS] = config.mass_kg
    g[_G_IDLE] = config.idle_rotor_thrust_n
    g[_G_TAN_TILT] = math.tan(math.radians(config.max_tilt_deg))
    g[_G_MAX_CLIMB] = config.max_climb_rate
    g[_G_MAX_DESCENT] = config.max_descent_rate
    g[_G_MAX_YAW_RATE] = config.max_yaw_rate
    g[_G_MAX_RP_RATE] = config.max_roll_pitch_rate
    g[_G_ALT_P] = config.altitude_p
    g[_G_CLIMB_P] = config.climb_rate_p
    g[_G_CLIMB_I] = config.climb_rate_i
    g[_G_VEL_P] = config.velocity_p
    g[_G_VEL_I] = config.velocity_i
    g[_G_VEL_I_LIMIT] = config.velocity_i_limit
    g[_G_ATT_P] = config.attitude_p
    g[_G_YAW_P] = config.yaw_p
    g[_G_RATE_P] = config.rate_p
    g[_G_RATE_I] = config.rate_i
    g[_G_YAW_RATE_P] = config.yaw_rate_p
    g[_G_YAW_RATE_I] = config.yaw_rate_i
    g[_G_IXX] = config.ixx_kg_m2
    g[_G_IYY] = config.iyy_kg_m2
    g[_G_IZZ] = config.izz_kg_m2
    # Per-rotor thrust (N) per N m of roll/pitch torque on an X quad, and per N m of yaw torque.
    g[_G_MIX_RP] = 1.0 / (4.0 * config.arm_length_m * math.sqrt(0.5))
    g[_G_MIX_YAW] = 1.0 / (4.0 * config.yaw_moment_per_thrust_m)
    g[_G_T_MAX] = config.max_rotor_thrust_n
    return g


def mix(
    collective: float, torque_x: float, torque_y: float, torque_z: float, config: ControllerConfig
) -> tuple[float, float, float, float]:
    """Per-rotor thrusts (N) for a collective thrust and a body FLU torque, X quad.

    Saturation keeps attitude first: the roll/pitch spread is scaled into the rotor range, the
    collective is shifted to fit it, and yaw gets only the headroom that is left.

    :param collective: total thrust, N.
    :param torque_x: roll torque about body x (forward), N m; > 0 lowers the right side.
    :param torque_y: pitch torque about body y (left), N m; > 0 lowers the nose.
    :param torque_z: yaw torque about body z (up), N m; > 0 turns left (CCW).
    :param config: airframe geometry and rotor limits.
    """
    g = gain_vector(config)
    return _mix(collective, torque_x, torque_y, torque_z, g[_G_MIX_RP], g[_G_MIX_YAW], g[_G_T_MAX])


@njit(cache=True)
def _mix(
    collective: float, tx: float, ty: float, tz: float, k_rp: float, k_yaw: float, t_max: float
) -> tuple[float, float, float, float]:
    base = 0.25 * collective
    rx = tx * k_rp
    ry = ty * k_rp
    yaw = tz * k_yaw
    # Roll/pitch parts of rotors 0..3 (front-right, back-left, front-left, back-right) are
    # (a0, -a0, a2, -a2); yaw adds -yaw to the CCW pair 0, 1 and +yaw to the CW pair 2, 3.
    a0 = -rx - ry
    a2 = rx - ry
    u0 = base + a0 - yaw
    u1 = base - a0 - yaw
    u2 = base + a2 + yaw
    u3 = base - a2 + yaw
    if 0.0 <= u0 <= t_max and 0.0 <= u1 <= t_max and 0.0 <= u2 <= t_max and 0.0 <= u3 <= t_max:
        return u0, u1, u2, u3
    # Saturated: scale roll/pitch into the range, shift the collective to fit them, then give
    # yaw what headroom is left (never negative: every base +- a is inside [0, t_max] by then).
    half_span = max(abs(a0), abs(a2))
    if 2.0 * half_span > t_max:
        k = 0.5 * t_max / half_span
        a0 *= k
        a2 *= k
        half_span = 0.5 * t_max
    base = min(max(base, half_span), t_max - half_span)
    if yaw > 0.0:
        yaw = min(yaw, base - abs(a0), t_max - base - abs(a2))
    else:
        yaw = max(yaw, abs(a2) - base, base + abs(a0) - t_max)
    return (
        _clip(base + a0 - yaw, 0.0, t_max),  # the clips only remove rounding error
        _clip(base - a0 - yaw, 0.0, t_max),
        _clip(base + a2 + yaw, 0.0, t_max),
        _clip(base - a2 + yaw, 0.0, t_max),
    )


def setpoint_values(setpoint: Setpoint) -> tuple[float, float, float, float, float, float, float, float]:
    """(vx, vy, vz, altitude, yaw_rate, yaw, ax, ay) of a setpoint as floats, NaN for None.

    :param setpoint: the setpoint to flatten for :func:`control_step`.
    """
    nan = math.nan
    return (
        float(setpoint.vx),
        float(setpoint.vy),
        nan if setpoint.vz is None else float(setpoint.vz),
        nan if setpoint.altitude is None else float(setpoint.altitude),
        nan if setpoint.yaw_rate is None else float(setpoint.yaw_rate),
        nan if setpoint.yaw is None else float(setpoint.yaw),
        float(setpoint.ax),
        float(setpoint.ay),
    )


@njit(cache=True)
def control_step(
    memory: np.ndarray,
    gains: np.ndarray,
    vx_sp: float,
    vy_sp: float,
    vz_sp: float,
    altitude_sp: float,
    yaw_rate_sp: float,
    yaw_sp: float,
    ax_ff: float,
    ay_ff: float,
    dt: float,
    z: float,
    vx: float,
    vy: float,
    vz: float,
    roll: float,
    pitch: float,
    yaw: float,
    p: float,
    q: float,
    r: float,
    on_ground: bool,
) -> tuple[float, float, float, float]:
    """One step of the cascade: per-rotor thrust commands (N, rotor order of :func:`mix`).

    The setpoint comes flattened by :func:`setpoint_values` (NaN = None); the state in the
    frames of :meth:`CascadedController.update`. Updates ``memory`` (integrators, holds) in place.

    :param memory: the controller's integrators and latched holds (see :class:`CascadedController`).
    :param gains: :func:`gain_vector` of the configuration.
    """
    g = gains
    m = memory
    # --- vertical: altitude -> climb rate demand
    if not math.isnan(vz_sp):
        climb_sp = _clip(vz_sp, -g[_G_MAX_DESCENT], g[_G_MAX_CLIMB])
        m[_M_ALT_HOLD] = z
    else:
        if not math.isnan(altitude_sp):
            target = altitude_sp
            m[_M_ALT_HOLD] = z
        else:
            target = m[_M_ALT_HOLD]
        climb_sp = _clip(g[_G_ALT_P] * (target - z), -g[_G_MAX_DESCENT], g[_G_MAX_CLIMB])

    # --- heading: yaw (Euler) rate demand
    if not math.isnan(yaw_rate_sp):
        yaw_dot = yaw_rate_sp
        m[_M_YAW_HOLD] = yaw
    else:
        if not math.isnan(yaw_sp):
            target_yaw = yaw_sp
            m[_M_YAW_HOLD] = yaw
        else:
            target_yaw = m[_M_YAW_HOLD]
        yaw_dot = g[_G_YAW_P] * wrap_angle(target_yaw - yaw)
    yaw_dot = _clip(yaw_dot, -g[_G_MAX_YAW_RATE], g[_G_MAX_YAW_RATE])

    # --- landed: motors idle, integrators cleared, until something asks to climb
    if on_ground and climb_sp <= 0.1:
        m[_M_VEL_I_X] = m[_M_VEL_I_Y] = m[_M_CLIMB_I] = 0.0
        m[_M_RATE_I_X] = m[_M_RATE_I_Y] = m[_M_RATE_I_Z] = 0.0
        idle = g[_G_IDLE]
        return idle, idle, idle, idle
    integrate = not on_ground  # ground contact fights the controller: integrators would wind up

    # --- climb rate -> vertical acceleration (the integrator is the hover-thrust estimate)
    err_vz = climb_sp - vz
    az = _clip(g[_G_CLIMB_P] * err_vz + m[_M_CLIMB_I], -0.7 * GRAVITY, GRAVITY)
    if integrate:
        # +-0.7 g covers the masses a vehicle accepts (0.47 ... 1.67 x the assumed mass).
        m[_M_CLIMB_I] = _clip(m[_M_CLIMB_I] + g[_G_CLIMB_I] * err_vz * dt, -0.7 * GRAVITY, 0.7 * GRAVITY)
    fz = GRAVITY + az

    # --- horizontal velocity -> acceleration, tilt-limited, integrating only when unsaturated
    ex = vx_sp - vx
    ey = vy_sp - vy
    ax = g[_G_VEL_P] * ex + m[_M_VEL_I_X] + ax_ff
    ay = g[_G_VEL_P] * ey + m[_M_VEL_I_Y] + ay_ff
    a_max = fz * g[_G_TAN_TILT]
    a_norm = math.sqrt(ax * ax + ay * ay)
    if a_norm > a_max:
        ax *= a_max / a_norm
        ay *= a_max / a_norm
    elif integrate:
        lim = g[_G_VEL_I_LIMIT]
        m[_M_VEL_I_X] = _clip(m[_M_VEL_I_X] + g[_G_VEL_I] * ex * dt, -lim, lim)
        m[_M_VEL_I_Y] = _clip(m[_M_VEL_I_Y] + g[_G_VEL_I] * ey * dt, -lim, lim)

    # --- attitude from the thrust direction, in the heading frame
    cy = math.cos(yaw)
    sy = math.sin(yaw)
    f_fwd = cy * ax + sy * ay
    f_left = -sy * ax + cy * ay
    pitch_sp = math.atan2(f_fwd, fz)
    roll_sp = math.atan2(-f_left, math.sqrt(f_fwd * f_fwd + fz * fz))

    # --- attitude error -> Euler rates -> body rates (Z-Y-X kinematics)
    roll_dot = g[_G_ATT_P] * (roll_sp - roll)
    pitch_dot = g[_G_ATT_P] * (pitch_sp - pitch)
    sr = math.sin(roll)
    cr = math.cos(roll)
    sp = math.sin(pitch)
    cp = math.cos(pitch)
    lim = g[_G_MAX_RP_RATE]
    p_sp = _clip(roll_dot - yaw_dot * sp, -lim, lim)
    q_sp = _clip(pitch_dot * cr + yaw_dot * sr * cp, -lim, lim)
    r_sp = -pitch_dot * sr + yaw_dot * cr * cp

    # --- body rates -> torques: P + I on angular acceleration, times inertia
    ep = p_sp - p
    eq = q_sp - q
    er = r_sp - r
    if integrate:
        m[_M_RATE_I_X] = _clip(m[_M_RATE_I_X] + g[_G_RATE_I] * ep * dt, -5.0, 5.0)
        m[_M_RATE_I_Y] = _clip(m[_M_RATE_I_Y] + g[_G_RATE_I] * eq * dt, -5.0, 5.0)
        m[_M_RATE_I_Z] = _clip(m[_M_RATE_I_Z] + g[_G_YAW_RATE_I] * er * dt, -3.0, 3.0)
    tx = g[_G_IXX] * (g[_G_RATE_P] * ep + m[_M_RATE_I_X])
    ty = g[_G_IYY] * (g[_G_RATE_P] * eq + m[_M_RATE_I_Y])
    tz = g[_G_IZZ] * (g[_G_YAW_RATE_P] * er + m[_M_RATE_I_Z])

    # --- collective: the vertical demand, corrected for the current tilt
    collective = g[_G_MASS] * fz / max(cr * cp, 0.5)
    return _mix(collective, tx, ty, tz, g[_G_MIX_RP], g[_G_MIX_YAW], g[_G_T_MAX])


class CascadedController:
    """Velocity -> attitude -> body-rate -> mixer cascade, with the integrators a real one has.

    Call :meth:`reset` at the start of a flight, then :meth:`update` every physics step with the
    measured state. The only memory (``memory``) is the integrators and the altitude/heading
    latched for "hold" setpoints; everything else is a function of (state, setpoint, dt).
    Hot loops call :func:`control_step` with ``memory`` and ``gains`` directly.
    """

    def __init__(self, config: ControllerConfig = ControllerConfig()) -> None:
        """:param config: gains, limits and airframe model."""
        self.config = config
        self.gains = gain_vector(config)
        self.memory = np.zeros(_N_MEMORY)
        self.reset(altitude=0.0, yaw=0.0)

    def reset(self, *, altitude: float, yaw: float, hover_mass_kg: float | None = None) -> None:
        """Clear the integrators and latch the holds.

        :param altitude: current z (m, up): the altitude a hold setpoint keeps.
        :param yaw: current heading (rad): the heading a hold setpoint keeps.
        :param hover_mass_kg: the true mass when resetting a vehicle that is already hovering:
            pre-loads the climb-rate integrator as a converged hover-thrust estimate would be.
            None: start from the configured mass (e.g. on the ground before take-off).
        """
        m = self.memory
        m[:] = 0.0
        m[_M_ALT_HOLD] = altitude
        m[_M_YAW_HOLD] = yaw
        # The climb-rate integrator is an acceleration bias: g * (true / assumed mass - 1) at hover.
        if hover_mass_kg is not None:
            m[_M_CLIMB_I] = GRAVITY * (hover_mass_kg / self.config.mass_kg - 1.0)

    def update(
        self,
        setpoint: Setpoint,
        dt: float,
        z: float,
        vx: float,
        vy: float,
        vz: float,
        roll: float,
        pitch: float,
        yaw: float,
        p: float,
        q: float,
        r: float,
        on_ground: bool = False,
    ) -> tuple[float, float, float, float]:
        """One control step: per-rotor thrust commands (N, rotor order of :func:`mix`).

        :param setpoint: what to fly.
        :param dt: time since the previous update, s.
        :param z: altitude, m up.
        :param vx: velocity East, m/s.
        :param vy: velocity North, m/s.
        :param vz: velocity up, m/s.
        :param roll: rad, > 0 right side down.
        :param pitch: rad, > 0 nose down (rotation about body +y, left).
        :param yaw: rad, CCW from +x.
        :param p: body roll rate (FLU x), rad/s.
        :param q: body pitch rate (FLU y), rad/s.
        :param r: body yaw rate (FLU z), rad/s, > 0 turning left.
        :param on_ground: the feet touch the floor: without a climb demand the motors idle
            and the integrators stay cleared, as an autopilot's landed state does.
        """
        return control_step(
            self.memory, self.gains, *setpoint_values(setpoint),
            dt, z, vx, vy, vz, roll, pitch, yaw, p, q, r, on_ground,
        )  # fmt: skip
