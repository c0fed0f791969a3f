"""Autopilot-like cascaded multirotor controller: velocity -> attitude -> body rates -> motor mix.

Pure logic (no JSBSim, no I/O): the vehicle feeds it the measured state each physics step and
applies the per-rotor thrusts it returns. Frames are the project's: world ENU (x East, y North,
z Up), body FLU (x forward, y left, z up). Euler angles are Z-Y-X about those axes, so yaw is
counter-clockwise from +x, roll > 0 lowers the right side and pitch > 0 lowers the nose.

Rotor order and spin (seen from above), shared with the JSBSim model ``lidar_quad``:
0 front-right CCW, 1 back-left CCW, 2 front-left CW, 3 back-right CW. A rotor spinning CCW
pushes the body clockwise, so yawing left (CCW) means speeding up the CW pair 2 and 3.

The hot path (:meth:`CascadedController.update`) takes plain floats: it runs 120+ times per
simulated second in every training environment, and small numpy arrays would cost more than
the arithmetic itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

GRAVITY = 9.80665
"""Standard gravity (m/s^2); the controller's integrators absorb the simulator's local value."""


def wrap_angle(angle: float) -> float:
    """Wrap an angle to [-pi, pi).

    :param angle: radians.
    """
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


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
    """

    vx: float = 0.0
    vy: float = 0.0
    vz: float | None = None
    altitude: float | None = None
    yaw_rate: float | None = 0.0
    yaw: float | None = None

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

    Airframe defaults match the JSBSim model ``flightsim/models/aircraft/lidar_quad``.
    Gains are bandwidths (1/s): each loop is about 3x slower than the one inside it.
    """

    mass_kg: float = field(default=1.5, metadata={"min": 0.1})
    arm_length_m: float = field(default=0.225, metadata={"min": 0.01})
    yaw_moment_per_thrust_m: float = field(default=0.016, metadata={"min": 1e-4})
    max_rotor_thrust_n: float = field(default=8.0, metadata={"min": 0.1})
    idle_rotor_thrust_n: float = field(default=0.15, metadata={"min": 0.0})
    inertia_kg_m2: tuple[float, float, float] = (0.015, 0.015, 0.027)

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
    t_max = config.max_rotor_thrust_n
    arm = 4.0 * config.arm_length_m * math.sqrt(0.5)
    rx = torque_x / arm
    ry = torque_y / arm
    yaw = torque_z / (4.0 * config.yaw_moment_per_thrust_m)
    # Roll/pitch parts of rotors 0..3 (front-right, back-left, front-left, back-right).
    a0, a1, a2, a3 = -rx - ry, rx + ry, rx - ry, -rx + ry
    span = max(a0, a1, a2, a3) - min(a0, a1, a2, a3)
    if span > t_max:
        k = t_max / span
        a0, a1, a2, a3 = a0 * k, a1 * k, a2 * k, a3 * k
    base = _clip(collective, 0.0, 4.0 * t_max) * 0.25
    hi = base + max(a0, a1, a2, a3)
    lo = base + min(a0, a1, a2, a3)
    if hi > t_max:
        base -= hi - t_max
    elif lo < 0.0:
        base -= lo
    u0, u1, u2, u3 = base + a0, base + a1, base + a2, base + a3
    # Yaw: rotors 2, 3 (CW) get +yaw, rotors 0, 1 (CCW) get -yaw; use what headroom allows
    # (every u is inside [0, t_max] here, so the headroom is never negative).
    if yaw > 0.0:
        yaw = min(yaw, u0, u1, t_max - u2, t_max - u3)
    elif yaw < 0.0:
        yaw = max(yaw, -u2, -u3, u0 - t_max, u1 - t_max)
    return (
        _clip(u0 - yaw, 0.0, t_max),
        _clip(u1 - yaw, 0.0, t_max),
        _clip(u2 + yaw, 0.0, t_max),
        _clip(u3 + yaw, 0.0, t_max),
    )


class CascadedController:
    """Velocity -> attitude -> body-rate -> mixer cascade, with the integrators a real one has.

    Call :meth:`reset` at the start of a flight, then :meth:`update` every physics step with the
    measured state. The only memory is the integrators and the altitude/heading latched for
    "hold" setpoints; everything else is a function of (state, setpoint, dt).
    """

    def __init__(self, config: ControllerConfig = ControllerConfig()) -> None:
        """:param config: gains, limits and airframe model."""
        self.config = config
        self._tan_tilt = math.tan(math.radians(config.max_tilt_deg))
        self._ixx, self._iyy, self._izz = config.inertia_kg_m2
        self.reset(altitude=0.0, yaw=0.0)

    def reset(self, *, altitude: float, yaw: float, hover_mass_kg: float | None = None) -> None:
        """Clear the integrators and latch the holds.

        :param altitude: current z (m, up): the altitude a hold setpoint keeps.
        :param yaw: current heading (rad): the heading a hold setpoint keeps.
        :param hover_mass_kg: the true mass when resetting a vehicle that is already hovering:
            pre-loads the climb-rate integrator as a converged hover-thrust estimate would be.
            None: start from the configured mass (e.g. on the ground before take-off).
        """
        self._alt_hold = altitude
        self._yaw_hold = yaw
        self._vel_i_x = 0.0
        self._vel_i_y = 0.0
        # The climb-rate integrator is an acceleration bias: g * (true mass / assumed mass - 1) at hover.
        mass_ratio = 1.0 if hover_mass_kg is None else hover_mass_kg / self.config.mass_kg
        self._climb_i = GRAVITY * (mass_ratio - 1.0)
        self._rate_i_x = 0.0
        self._rate_i_y = 0.0
        self._rate_i_z = 0.0

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
        c = self.config
        # --- vertical: altitude -> climb rate -> vertical acceleration
        if setpoint.vz is not None:
            vz_sp = _clip(setpoint.vz, -c.max_descent_rate, c.max_climb_rate)
            self._alt_hold = z
        else:
            if setpoint.altitude is not None:
                target = setpoint.altitude
                self._alt_hold = z
            else:
                target = self._alt_hold
            vz_sp = _clip(c.altitude_p * (target - z), -c.max_descent_rate, c.max_climb_rate)

        # --- heading: yaw-rate demand (Euler rate)
        if setpoint.yaw_rate is not None:
            yaw_rate_sp = setpoint.yaw_rate
            self._yaw_hold = yaw
        else:
            if setpoint.yaw is not None:
                target_yaw = setpoint.yaw
                self._yaw_hold = yaw
            else:
                target_yaw = self._yaw_hold
            yaw_rate_sp = c.yaw_p * wrap_angle(target_yaw - yaw)
        yaw_rate_sp = _clip(yaw_rate_sp, -c.max_yaw_rate, c.max_yaw_rate)

        if on_ground and vz_sp <= 0.1:
            self.reset(altitude=self._alt_hold, yaw=self._yaw_hold)
            idle = c.idle_rotor_thrust_n
            return idle, idle, idle, idle

        err_vz = vz_sp - vz
        az = c.climb_rate_p * err_vz + self._climb_i
        az = _clip(az, -0.7 * GRAVITY, GRAVITY)
        if not on_ground:
            self._climb_i = _clip(self._climb_i + c.climb_rate_i * err_vz * dt, -4.0, 4.0)
        fz = GRAVITY + az

        # --- horizontal: velocity -> acceleration (tilt-limited, anti-windup)
        ex = setpoint.vx - vx
        ey = setpoint.vy - vy
        ax = c.velocity_p * ex + self._vel_i_x
        ay = c.velocity_p * ey + self._vel_i_y
        a_max = fz * self._tan_tilt
        a_norm = math.hypot(ax, ay)
        if a_norm > a_max:
            k = a_max / a_norm
            ax *= k
            ay *= k
        elif not on_ground:
            lim = c.velocity_i_limit
            self._vel_i_x = _clip(self._vel_i_x + c.velocity_i * ex * dt, -lim, lim)
            self._vel_i_y = _clip(self._vel_i_y + c.velocity_i * ey * dt, -lim, lim)

        # --- attitude from the thrust direction in the heading frame
        cy, sy = math.cos(yaw), math.sin(yaw)
        f_fwd = cy * ax + sy * ay
        f_left = -sy * ax + cy * ay
        pitch_sp = math.atan2(f_fwd, fz)
        roll_sp = math.atan2(-f_left, math.hypot(f_fwd, fz))

        # --- attitude -> Euler rates -> body rates (Z-Y-X kinematics)
        roll_dot = c.attitude_p * (roll_sp - roll)
        pitch_dot = c.attitude_p * (pitch_sp - pitch)
        sr, cr = math.sin(roll), math.cos(roll)
        sp_, cp = math.sin(pitch), math.cos(pitch)
        lim = c.max_roll_pitch_rate
        p_sp = _clip(roll_dot - yaw_rate_sp * sp_, -lim, lim)
        q_sp = _clip(pitch_dot * cr + yaw_rate_sp * sr * cp, -lim, lim)
        r_sp = -pitch_dot * sr + yaw_rate_sp * cr * cp

        # --- body rates -> torques (P + I on angular acceleration, scaled by inertia)
        ep, eq, er = p_sp - p, q_sp - q, r_sp - r
        if not on_ground:
            self._rate_i_x = _clip(self._rate_i_x + c.rate_i * ep * dt, -5.0, 5.0)
            self._rate_i_y = _clip(self._rate_i_y + c.rate_i * eq * dt, -5.0, 5.0)
            self._rate_i_z = _clip(self._rate_i_z + c.yaw_rate_i * er * dt, -3.0, 3.0)
        tx = self._ixx * (c.rate_p * ep + self._rate_i_x)
        ty = self._iyy * (c.rate_p * eq + self._rate_i_y)
        tz = self._izz * (c.yaw_rate_p * er + self._rate_i_z)

        tilt = max(cr * cp, 0.5)
        collective = c.mass_kg * fz / tilt
        return mix(collective, tx, ty, tz, c)
