"""The telemetry a simulated autopilot streams: each message built from the personality's state.

Split from :mod:`flightsim.sitl.sim_autopilot.common`, which decides what the autopilot does; this only
says it, in MAVLink's frames and units (NED, yaw from North; millimetres, cm/s, centidegrees and
degE7 where the message wants them). The velocity in LOCAL_POSITION_NED and GLOBAL_POSITION_INT is
the one the firmware's estimator reports
(:meth:`~flightsim.sitl.sim_autopilot.common.SimAutopilot.reported_velocity`), not the truth, as a real
estimator's is.
"""

from __future__ import annotations

import math
from typing import Any, Protocol

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from flightsim.sitl.sim_autopilot.frames import HOME_ALT_AMSL_M, enu_to_ned, lat_lon, yaw_enu_to_ned
from flightsim.sitl.sim_autopilot.mission import MissionStore
from flightsim.sitl.sim_autopilot.snapshot import VehicleSnapshot


class TelemetrySource(Protocol):
    """What telemetry reads of a simulated autopilot
    (:class:`~flightsim.sitl.sim_autopilot.common.SimAutopilot` is one), so that this module does not
    import the autopilot that calls it."""

    AUTOPILOT: int
    CAPABILITIES: int
    params: Any
    system_id: int
    boot_time: float
    now: float
    snap: VehicleSnapshot
    home: np.ndarray
    armed: bool
    mission: MissionStore

    def time_boot_ms(self) -> int: ...

    def heartbeat_mode(self) -> tuple[int, int]: ...

    def landed_state(self) -> int: ...

    def vtol_state(self) -> int: ...

    def flight_sw_version(self) -> int: ...

    def reported_velocity(self) -> np.ndarray: ...


def telemetry_message(ap: TelemetrySource, name: str) -> Any:
    """The message ``name`` (one of the personality's ``STREAMABLE`` or those sent on request) now.

    :param ap: the simulated autopilot whose state it reports
    :param name: MAVLink message name, e.g. ``"LOCAL_POSITION_NED"``
    :raises KeyError: for a message no personality builds
    """
    s = ap.snap
    t = ap.time_boot_ms()
    if name == "HEARTBEAT":
        base, custom = ap.heartbeat_mode()
        if ap.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        status = mavlink.MAV_STATE_ACTIVE if ap.armed else mavlink.MAV_STATE_STANDBY
        return mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_QUADROTOR, ap.AUTOPILOT, base, custom, status, 3
        )
    if name == "SYS_STATUS":
        sensors = (
            mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
            | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
            | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG
            | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            | mavlink.MAV_SYS_STATUS_SENSOR_GPS
            | mavlink.MAV_SYS_STATUS_AHRS
        )
        return mavlink.MAVLink_sys_status_message(
            sensors, sensors, sensors, 100, 12600, 500, 90, 0, 0, 0, 0, 0, 0
        )
    if name == "ATTITUDE":
        p, q, r = s.angular_rate
        return mavlink.MAVLink_attitude_message(
            t, s.roll, -s.pitch, yaw_enu_to_ned(s.yaw), float(p), float(-q), float(-r)
        )
    if name == "LOCAL_POSITION_NED":
        pos = enu_to_ned(s.position - ap.home)
        vel = enu_to_ned(ap.reported_velocity())
        return mavlink.MAVLink_local_position_ned_message(t, *map(float, pos), *map(float, vel))
    if name == "GLOBAL_POSITION_INT":
        rel = s.position - ap.home
        lat, lon = lat_lon(rel)
        vel = enu_to_ned(ap.reported_velocity())
        hdg = round(math.degrees(yaw_enu_to_ned(s.yaw)) % 360.0 * 100) % 36000
        return mavlink.MAVLink_global_position_int_message(
            t,
            lat,
            lon,
            round((HOME_ALT_AMSL_M + rel[2]) * 1000),
            round(rel[2] * 1000),
            *(round(v * 100) for v in vel),
            hdg,
        )
    if name == "EXTENDED_SYS_STATE":
        return mavlink.MAVLink_extended_sys_state_message(ap.vtol_state(), ap.landed_state())
    if name == "HOME_POSITION":
        lat, lon = lat_lon(np.zeros(3))
        return mavlink.MAVLink_home_position_message(
            lat,
            lon,
            int(HOME_ALT_AMSL_M * 1000),
            0.0,
            0.0,
            0.0,
            [1.0, 0.0, 0.0, 0.0],
            0.0,
            0.0,
            0.0,
            int((ap.now - ap.boot_time) * 1e6),
        )
    if name == "AUTOPILOT_VERSION":
        return mavlink.MAVLink_autopilot_version_message(
            ap.CAPABILITIES | getattr(ap.params, "protocol_capabilities", 0),
            ap.flight_sw_version(),
            0,
            0,
            0,
            [0] * 8,
            [0] * 8,
            [0] * 8,
            0,
            0,
            0x5349_4D00 + ap.system_id,
        )
    if name == "MISSION_CURRENT":
        return ap.mission.current_message()
    if name == "VFR_HUD":
        speed = float(np.linalg.norm(s.velocity[:2]))
        hdg = int(math.degrees(yaw_enu_to_ned(s.yaw)) % 360.0)
        return mavlink.MAVLink_vfr_hud_message(
            speed,
            speed,
            hdg,
            50 if ap.armed else 0,
            HOME_ALT_AMSL_M + float(s.position[2] - ap.home[2]),
            float(s.velocity[2]),
        )
    raise KeyError(name)
