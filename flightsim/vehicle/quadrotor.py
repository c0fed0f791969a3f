"""A JSBSim quadrotor flown by the cascaded controller of :mod:`flightsim.vehicle.control`.

JSBSim does the physics: 6-DOF rigid-body integration, gravity, ground contact and drag, for
the project's own model ``flightsim/vehicle/models/aircraft/lidar_quad``. Python runs the controller
and a first-order motor lag each physics step and writes the four rotor thrusts (and the rotor
drag yaw moment) into the model's ``external_reactions`` through cached property nodes.

Frames: world ENU in metres (x East, y North, z Up; z = 0 is the floor), body FLU. JSBSim works
on a WGS84 Earth in NED and feet; the vehicle is placed near latitude 0, longitude 0 and a flat
local tangent frame is used there (curvature over a 30 m room is below 0.1 mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import jsbsim
import numpy as np

from flightsim.vehicle.control import (
    CascadedController,
    ControllerConfig,
    Setpoint,
    control_step,
    setpoint_values,
    wrap_angle,
)

MODEL_ROOT = Path(__file__).resolve().parent / "models"
MODEL_NAME = "lidar_quad"
FRAME_MASS_KG = 0.6
"""Airframe mass without battery/payload (the model's empty weight); the rest is a point mass at the CG."""
MAX_MASS_KG = 2.5
"""Heaviest take-off mass: 4 x 8 N of thrust still leaves 1.3 g for climbing and attitude control."""
GEAR_HEIGHT_M = 0.08
"""Height of the CG above the feet: on the floor the vehicle's z is this less a few mm of spring sag."""
MAX_ROTOR_THRUST_N = 8.0
"""Per-rotor thrust limit of the model's motors, whatever the controller assumes."""
YAW_MOMENT_PER_THRUST_M = 0.016
"""Rotor drag torque per newton of thrust (N m / N)."""

_FT = 0.3048
_LBF_PER_N = 0.22480894387096
_LBFFT_PER_NM = _LBF_PER_N / _FT
_WGS84_A = 6378137.0
_WGS84_E2 = 6.69437999014e-3
_METRES_PER_RAD_NORTH = _WGS84_A * (1.0 - _WGS84_E2)  # meridian radius of curvature at the equator
_METRES_PER_RAD_EAST = _WGS84_A  # prime-vertical radius at the equator (cos(lat) = 1)
_SETTLE_S = 0.25


@dataclass(frozen=True)
class VehicleConfig:
    """Rates, mass and controller of a simulated vehicle.

    :param mass_kg: take-off mass (kg), unless a reset overrides it.
    :param physics_hz: JSBSim integration rate; an exact multiple of ``control_hz``.
    :param control_hz: the rate setpoints arrive at; ``step()`` advances 1/control_hz by default.
    :param motor_time_constant_s: first-order lag of each rotor's thrust.
    :param controller: gains, limits and airframe model of the cascaded controller.
    """

    mass_kg: float = field(default=1.5, metadata={"min": FRAME_MASS_KG + 0.1, "max": MAX_MASS_KG})
    physics_hz: int = field(default=120, metadata={"min": 1})
    control_hz: int = field(default=10, metadata={"min": 1})
    motor_time_constant_s: float = field(default=0.03, metadata={"min": 0.0})
    controller: ControllerConfig = ControllerConfig()

    def __post_init__(self) -> None:
        if self.physics_hz <= 0 or self.control_hz <= 0:
            raise ValueError(
                f"physics_hz ({self.physics_hz}) and control_hz ({self.control_hz}) must be positive"
            )
        if self.physics_hz % self.control_hz:
            raise ValueError(
                f"physics_hz ({self.physics_hz}) must be an exact multiple of control_hz ({self.control_hz})"
            )
        _check_mass(self.mass_kg)


def _check_mass(mass_kg: float) -> None:
    if not FRAME_MASS_KG + 0.1 <= mass_kg <= MAX_MASS_KG:
        raise ValueError(f"mass_kg ({mass_kg}) must be within [{FRAME_MASS_KG + 0.1}, {MAX_MASS_KG}] kg")


@dataclass
class VehicleState:
    """Where the vehicle is and how it moves.

    :param time: s since reset.
    :param position: (3,) CG position, world ENU, m.
    :param velocity: (3,) world ENU, m/s.
    :param roll: rad, > 0 right side down (about body FLU x).
    :param pitch: rad, > 0 nose down (about body FLU y).
    :param yaw: rad, counter-clockwise from +x (East).
    :param angular_rate: (3,) body FLU rates, rad/s (r > 0 turning left).
    :param on_ground: a foot touches the floor.
    :param armed: motors enabled.
    """

    time: float
    position: np.ndarray
    velocity: np.ndarray
    roll: float
    pitch: float
    yaw: float
    angular_rate: np.ndarray
    on_ground: bool
    armed: bool

    def rotation(self) -> np.ndarray:
        """3x3 rotation matrix body FLU -> world ENU (Z-Y-X: yaw, pitch, roll)."""
        cr, sr = math.cos(self.roll), math.sin(self.roll)
        cp, sp = math.cos(self.pitch), math.sin(self.pitch)
        cy, sy = math.cos(self.yaw), math.sin(self.yaw)
        return np.array(  # from a flat list: numpy builds that several times faster than nested ones
            [
                cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr,
                sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr,
                -sp, cp * sr, cp * cr,
            ]
        ).reshape(3, 3)  # fmt: skip

    @property
    def forward_speed(self) -> float:
        """Velocity along the body x axis (the nose), m/s."""
        cp = math.cos(self.pitch)
        heading = (math.cos(self.yaw) * cp, math.sin(self.yaw) * cp, -math.sin(self.pitch))
        v = self.velocity
        return float(heading[0] * v[0] + heading[1] * v[1] + heading[2] * v[2])


class Vehicle:
    """A JSBSim quadrotor with its autopilot-like controller, stepped at the control rate."""

    def __init__(self, config: VehicleConfig = VehicleConfig()) -> None:
        """Load the JSBSim model (once; resets reuse it).

        :param config: rates, mass, controller.
        """
        self.config = config
        self._dt = 1.0 / config.physics_hz
        self._steps_per_control = config.physics_hz // config.control_hz
        tau = config.motor_time_constant_s
        self._lag = 1.0 - math.exp(-self._dt / tau) if tau > 0.0 else 1.0
        self.controller = CascadedController(config.controller)

        jsbsim.FGJSBBase().debug_lvl = 0  # JSBSim's banner and load messages; a process-wide static
        fdm = jsbsim.FGFDMExec(root_dir=str(MODEL_ROOT))
        fdm.set_debug_level(0)
        fdm.disable_output()
        if not fdm.load_model(MODEL_NAME):
            raise RuntimeError(f"JSBSim could not load model {MODEL_NAME!r} from {MODEL_ROOT}")
        fdm.set_dt(self._dt)
        fdm["ic/terrain-elevation-ft"] = 0.0
        self._frame_mass_kg = fdm["inertia/empty-weight-lbs"] * 0.45359237
        if abs(self._frame_mass_kg - FRAME_MASS_KG) > 1e-6:
            raise RuntimeError(
                f"model {MODEL_NAME!r} weighs {self._frame_mass_kg} kg empty, not {FRAME_MASS_KG}"
            )
        self._fdm = fdm

        node = fdm.get_property_manager().get_node
        read = [
            "position/h-sl-ft", "velocities/v-east-fps", "velocities/v-north-fps", "velocities/v-down-fps",
            "attitude/phi-rad", "attitude/theta-rad", "attitude/psi-rad",
            "velocities/p-rad_sec", "velocities/q-rad_sec", "velocities/r-rad_sec", "forces/fbz-gear-lbs",
            "position/lat-geod-rad", "position/long-gc-rad",
        ]  # fmt: skip
        self._get = [node(name).get_double_value for name in read]
        self._get_flight = tuple(self._get[:11])  # what the controller needs every physics step
        self._set_rotor = [node(f"external_reactions/rotor{i}/magnitude").set_double_value for i in range(4)]
        self._set_yaw_moment = node("external_reactions/rotor_drag/magnitude-lbsft").set_double_value
        self._set_payload = node("inertia/pointmass-weight-lbs[0]").set_double_value
        self._set_wind = [
            node(f"atmosphere/wind-{axis}-fps").set_double_value for axis in ("east", "north", "down")
        ]
        self._run = fdm.run

        self._thrust = [0.0, 0.0, 0.0, 0.0]
        self._armed = False
        self._time = 0.0
        self._mass_kg = config.mass_kg
        self._state: VehicleState
        self.reset((0.0, 0.0, 1.0), 0.0)

    # ------------------------------------------------------------------ public API
    def reset(
        self, position: np.ndarray | tuple[float, float, float], yaw: float, *,
        mass_kg: float | None = None, on_ground: bool = False,
    ) -> VehicleState:  # fmt: skip
        """Start a new flight (the wind is cleared; set it again after a reset).

        :param position: (x, y, z) world ENU, m. Airborne: the CG is put at z. On the ground:
            z is ignored and the vehicle rests on the floor (CG at about ``GEAR_HEIGHT_M``).
        :param yaw: heading, rad CCW from +x.
        :param mass_kg: take-off mass for this flight (default: the configured mass).
        :param on_ground: rest on the floor, disarmed, instead of hovering armed with the motors
            at hover thrust and zero velocity.
        """
        mass = self.config.mass_kg if mass_kg is None else float(mass_kg)
        _check_mass(mass)
        x, y, z = (float(v) for v in position)
        if on_ground:
            z = GEAR_HEIGHT_M  # feet just touching; the settling run below lets the springs sag
        elif z < GEAR_HEIGHT_M:
            raise ValueError(f"airborne reset needs z >= {GEAR_HEIGHT_M} m (feet above the floor), got {z}")
        self._mass_kg = mass
        fdm = self._fdm
        self._set_payload((mass - self._frame_mass_kg) / 0.45359237)
        for setter in self._set_wind:
            setter(0.0)
        # Twice: each of these setters converts through the geodetic position the initial
        # conditions already hold (the previous flight's), so one pass lands an ulp or two off
        # depending on where that was; the second pass starts from (nearly) here and lands on the
        # same bits whatever came before, which keeps a seeded episode's replay bit-exact.
        for _ in range(2):
            fdm["ic/lat-geod-rad"] = y / _METRES_PER_RAD_NORTH
            fdm["ic/long-gc-rad"] = x / _METRES_PER_RAD_EAST
            fdm["ic/h-sl-ft"] = z / _FT
        fdm["ic/psi-true-rad"] = (math.pi / 2.0 - yaw) % (2.0 * math.pi)
        for name in ("ic/phi-rad", "ic/theta-rad", "ic/u-fps", "ic/v-fps", "ic/w-fps",
                     "ic/p-rad_sec", "ic/q-rad_sec", "ic/r-rad_sec"):  # fmt: skip
            fdm[name] = 0.0
        hover = 0.0 if on_ground else mass * 9.8 / 4.0
        self._thrust = [hover] * 4
        self._apply_thrust()
        if not fdm.run_ic():
            raise RuntimeError("JSBSim rejected the initial conditions")
        self._armed = not on_ground
        if on_ground:
            for _ in range(round(_SETTLE_S / self._dt)):  # let the feet springs take the weight
                self._run()
        self.controller.reset(altitude=z, yaw=yaw, hover_mass_kg=None if on_ground else mass)
        self._time = 0.0
        self._state = self._read_state()
        return self._state

    def set_armed(self, armed: bool) -> None:
        """Arm (the controller takes over from the current altitude and heading) or disarm (motors off).

        :param armed: the new arming state.
        """
        if armed and not self._armed:
            s = self._read_state()
            self.controller.reset(altitude=float(s.position[2]), yaw=s.yaw)
        self._armed = bool(armed)
        self._state = self._read_state()

    def set_wind(self, wind_enu: np.ndarray) -> None:
        """Set the steady wind (gusts are the caller's: call this as often as needed).

        :param wind_enu: (3,) air velocity in the world frame, m/s (the direction it blows to).
        """
        east, north, up = (float(v) for v in wind_enu)
        set_east, set_north, set_down = self._set_wind
        set_east(east / _FT)
        set_north(north / _FT)
        set_down(-up / _FT)

    def step(self, setpoint: Setpoint, duration: float | None = None) -> VehicleState:
        """Fly ``setpoint`` for ``duration`` seconds and return the state at the end.

        :param setpoint: what the autopilot asks for (held for the whole duration).
        :param duration: s; default 1/control_hz; must be a whole number of physics steps.
        """
        if duration is None:
            n = self._steps_per_control
        else:
            n = round(duration * self.config.physics_hz)
            if n < 1 or abs(n - duration * self.config.physics_hz) > 1e-6:
                raise ValueError(
                    f"duration ({duration} s) must be a positive whole number of physics steps "
                    f"(1/{self.config.physics_hz} s)"
                )
        self._advance(setpoint, n)
        self._time += n * self._dt
        self._state = self._read_state()
        return self._state

    @property
    def state(self) -> VehicleState:
        """The state after the last reset, arm change or step."""
        return self._state

    @property
    def mass_kg(self) -> float:
        """Mass of the current flight, kg."""
        return self._mass_kg

    def close(self) -> None:
        """Release the JSBSim instance."""
        self._fdm = None  # type: ignore[assignment]
        self._run = None  # type: ignore[assignment]

    # ------------------------------------------------------------------ internals
    def _advance(self, setpoint: Setpoint, n: int) -> None:
        """The hot loop: read state, control, motor lag, write forces, integrate; n times."""
        get_h, get_ve, get_vn, get_vd, get_phi, get_theta, get_psi, get_p, get_q, get_r, get_gear = (
            self._get_flight
        )
        set0, set1, set2, set3 = self._set_rotor
        set_yaw = self._set_yaw_moment
        run = self._run
        memory, gains = self.controller.memory, self.controller.gains
        vx_sp, vy_sp, vz_sp, altitude_sp, yaw_rate_sp, yaw_sp, ax_ff, ay_ff = setpoint_values(setpoint)
        dt = self._dt
        lag = self._lag
        km = YAW_MOMENT_PER_THRUST_M * _LBFFT_PER_NM
        t0, t1, t2, t3 = self._thrust
        armed = self._armed
        half_pi = 0.5 * math.pi
        t_max = MAX_ROTOR_THRUST_N
        limit = self.controller.config.max_rotor_thrust_n > t_max  # the controller assumes more
        c0 = c1 = c2 = c3 = 0.0
        for _ in range(n):
            if armed:
                c0, c1, c2, c3 = control_step(
                    memory, gains, vx_sp, vy_sp, vz_sp, altitude_sp, yaw_rate_sp, yaw_sp, ax_ff, ay_ff, dt,
                    get_h() * _FT, get_ve() * _FT, get_vn() * _FT, -get_vd() * _FT,
                    get_phi(), -get_theta(), half_pi - get_psi(),
                    get_p(), -get_q(), -get_r(),
                    get_gear() != 0.0,
                )  # fmt: skip
                if limit:
                    c0, c1, c2, c3 = min(c0, t_max), min(c1, t_max), min(c2, t_max), min(c3, t_max)
            t0 += lag * (c0 - t0)
            t1 += lag * (c1 - t1)
            t2 += lag * (c2 - t2)
            t3 += lag * (c3 - t3)
            set0(t0 * _LBF_PER_N)
            set1(t1 * _LBF_PER_N)
            set2(t2 * _LBF_PER_N)
            set3(t3 * _LBF_PER_N)
            set_yaw(km * (t2 + t3 - t0 - t1))
            run()
        self._thrust = [t0, t1, t2, t3]

    def _apply_thrust(self) -> None:
        t0, t1, t2, t3 = self._thrust
        for setter, t in zip(self._set_rotor, self._thrust, strict=True):
            setter(t * _LBF_PER_N)
        self._set_yaw_moment(YAW_MOMENT_PER_THRUST_M * _LBFFT_PER_NM * (t2 + t3 - t0 - t1))

    def _read_state(self) -> VehicleState:
        h, ve, vn, vd, phi, theta, psi, p, q, r, gear_force, lat, lon = [g() for g in self._get]
        return VehicleState(
            time=self._time,
            position=np.array([lon * _METRES_PER_RAD_EAST, lat * _METRES_PER_RAD_NORTH, h * _FT]),
            velocity=np.array([ve * _FT, vn * _FT, -vd * _FT]),
            roll=phi,
            pitch=-theta,
            yaw=wrap_angle(math.pi / 2.0 - psi),
            angular_rate=np.array([p, -q, -r]),
            on_ground=gear_force != 0.0,
            armed=self._armed,
        )
