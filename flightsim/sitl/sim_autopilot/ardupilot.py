"""ArduPilot Copter personality: Copter flight modes, GUIDED take-off and velocity control, proximity stop.

Modelled on ArduCopter's GCS_MAVLink_Copter.cpp / mode_guided.cpp / AC_Avoid: SET_POSITION_TARGET_*
is obeyed only in GUIDED; a velocity target that is not refreshed within GUID_TIMEOUT makes the
vehicle stop; a velocity target during the guided take-off ends the take-off sub-mode (so a zero
vertical speed freezes the climb, as on the real firmware). OBSTACLE_DISTANCE is read when
PRX1_TYPE = 2 (MAVLink) and, when AVOID_ENABLE has the proximity bit, the velocity towards any
obstacle closer than AVOID_MARGIN is removed ("simple avoidance", stop behaviour).
"""

from __future__ import annotations

import math
from enum import IntEnum
from typing import Any, ClassVar

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from flightsim.sitl.sim_autopilot.common import Command, Guidance, Outgoing, SimAutopilot
from flightsim.sitl.sim_autopilot.frames import yaw_enu_to_ned
from flightsim.sitl.sim_autopilot.position_target import ExternalTarget, decode_position_target

AVOID_USE_PROXIMITY = 1 << 1
PRX_TYPE_MAVLINK = 2
#: ArduPilot drops proximity readings older than this (AP_Proximity_MAV timeout), seconds.
PROXIMITY_TIMEOUT = 0.5


class CopterMode(IntEnum):
    """ArduCopter custom_mode numbers (Mode::Number)."""

    STABILIZE = 0
    ALT_HOLD = 2
    AUTO = 3
    GUIDED = 4
    LOITER = 5
    RTL = 6
    LAND = 9
    BRAKE = 17


ARMABLE = {CopterMode.STABILIZE, CopterMode.ALT_HOLD, CopterMode.GUIDED, CopterMode.LOITER}
GUIDED_FLAG_MODES = {CopterMode.AUTO, CopterMode.RTL, CopterMode.LOITER, CopterMode.GUIDED, CopterMode.BRAKE}

# REQUEST_DATA_STREAM groups (GCS_MAVLink ap_message lists, the subset this simulator sends)
STREAM_GROUPS = {
    mavlink.MAV_DATA_STREAM_EXTENDED_STATUS: ("SYS_STATUS",),
    mavlink.MAV_DATA_STREAM_POSITION: ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"),
    mavlink.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
    mavlink.MAV_DATA_STREAM_EXTRA2: ("VFR_HUD",),
    mavlink.MAV_DATA_STREAM_EXTRA3: ("EXTENDED_SYS_STATE",),
}


class ArduCopterAutopilot(SimAutopilot):
    """A simulated ArduCopter (custom modes, GUIDED, GUID_TIMEOUT, simple proximity avoidance)."""

    RESPONSE = "ardupilot"
    NO_POSITION_REFUSAL = "AHRS: waiting for home"
    AUTOPILOT = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    #: accepted unsigned while signing is on (GCS_Signing.cpp's accept list; USB, which takes
    #: everything unsigned, is not simulated)
    UNSIGNED_ACCEPTED = frozenset((mavlink.MAVLINK_MSG_ID_RADIO_STATUS, mavlink.MAVLINK_MSG_ID_RADIO))
    DEFAULT_INTERVALS: ClassVar[dict[str, float]] = {
        "HEARTBEAT": 1.0,
        "SYS_STATUS": 0.5,
        "ATTITUDE": 0.1,
        "LOCAL_POSITION_NED": 0.1,
        "GLOBAL_POSITION_INT": 0.1,
        "EXTENDED_SYS_STATE": 0.25,
        "VFR_HUD": 0.25,
        "MISSION_CURRENT": 1.0,
    }
    CAPABILITIES = SimAutopilot.CAPABILITIES | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
    MISSION_HOME_ITEM = True  # AP_Mission: item 0 is home

    def __init__(self, params: Any, **kw: Any) -> None:
        """:param params: the parameter table; ``kw``: see :class:`SimAutopilot`."""
        super().__init__(params, **kw)
        self.mode = CopterMode.STABILIZE
        self.obstacles: np.ndarray | None = None  # (K, 3): unit direction (ENU x, y) and distance m
        self.obstacles_time = -math.inf
        self.guided_timed_out = False

    # ----------------------------------------------------------------- modes
    def mode_name(self) -> str:
        return self.mode.name

    def heartbeat_mode(self) -> tuple[int, int]:
        base = (
            mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
            | mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        )
        if self.mode in GUIDED_FLAG_MODES:
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
        return base, int(self.mode)

    def handle_set_mode(self, base_mode: int, custom_mode: int, custom_sub_mode: int) -> bool:
        if not base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return False
        try:
            mode = CopterMode(custom_mode)
        except ValueError:
            return False
        return self.set_mode(mode)

    def set_mode(self, mode: CopterMode) -> bool:
        """Enter ``mode`` (True) or refuse it, as ArduCopter's Mode::init would."""
        if mode == CopterMode.AUTO:
            return False  # no mission support: ArduCopter refuses AUTO without a usable mission
        if mode == self.mode:
            return True
        self.mode = mode
        self.count(f"mode_{mode.name}")
        self.guided_timed_out = False
        if mode == CopterMode.LAND:
            self.start_land()
        elif mode == CopterMode.RTL:
            self.start_rtl()
        else:  # GUIDED, LOITER, BRAKE, ALT_HOLD, STABILIZE (sticks centred): hold where we are
            self.start_hold()
        return True

    # ----------------------------------------------------------------- commands
    def arm_allowed(self) -> str | None:
        if self.mode not in ARMABLE:
            return "Mode not armable"
        return None

    def handle_command(self, cmd: Command, link: int) -> list[Outgoing]:
        p = cmd.params
        if cmd.command == mavlink.MAV_CMD_NAV_TAKEOFF:
            if self.mode != CopterMode.GUIDED or not self.armed or not self.snap.on_ground:
                return [self.ack(link, cmd, mavlink.MAV_RESULT_FAILED)]
            altitude = float(p[6])
            if not math.isfinite(altitude) or altitude <= 0:
                return [self.ack(link, cmd, mavlink.MAV_RESULT_FAILED)]
            self.start_takeoff(altitude)
            return [self.ack(link, cmd, mavlink.MAV_RESULT_ACCEPTED)]
        if cmd.command == mavlink.MAV_CMD_NAV_LAND:
            return [
                self.ack(
                    link,
                    cmd,
                    mavlink.MAV_RESULT_ACCEPTED
                    if self.set_mode(CopterMode.LAND)
                    else mavlink.MAV_RESULT_FAILED,
                )
            ]
        if cmd.command == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return [
                self.ack(
                    link,
                    cmd,
                    mavlink.MAV_RESULT_ACCEPTED
                    if self.set_mode(CopterMode.RTL)
                    else mavlink.MAV_RESULT_FAILED,
                )
            ]
        return super().handle_command(cmd, link)

    def handle_request_data_stream(self, msg: Any, link: int) -> list[Outgoing]:
        groups = (
            list(STREAM_GROUPS) if msg.req_stream_id == mavlink.MAV_DATA_STREAM_ALL else [msg.req_stream_id]
        )
        for group in groups:
            for name in STREAM_GROUPS.get(group, ()):
                rate = msg.req_message_rate if msg.start_stop else 0
                self.intervals[(link, name)] = 1.0 / rate if rate > 0 else 0.0
                self.next_due.pop((link, name), None)
        return []

    # ----------------------------------------------------------------- guided
    def handle_position_target(self, msg: Any, link: int) -> list[Outgoing]:
        if self.mode != CopterMode.GUIDED:
            self.count("setpoint_ignored_not_guided")
            return []
        if not self.armed or (self.snap.on_ground and self.guidance == Guidance.IDLE):
            self.count("setpoint_ignored_landed")
            return []
        target = decode_position_target(msg, self.snap, self.now)
        self.count("setpoint_accepted" if target is not None else "setpoint_invalid")
        self.guided_timed_out = False
        if target is None:
            self.start_hold()  # ModeGuided::init(true): stop
            return []
        self.set_target(target)
        return []

    def personality_tick(self) -> list[Outgoing]:
        timeout = self.param("GUID_TIMEOUT", 3.0)
        target = self.target
        if (
            self.guidance == Guidance.VELOCITY
            and target is not None
            and not self.guided_timed_out
            and self.now - target.time > timeout
        ):
            # mode_guided.cpp: velocity control with a stale target → zero velocity and yaw rate
            self.guided_timed_out = True
            self.count("guided_timeout")
            stop = ExternalTarget(
                velocity=np.zeros(3), position=None, vz_used=True, yaw=None, yaw_rate=0.0, time=target.time
            )
            self.target_altitude = float(self.snap.position[2])
            self.target = stop
        return []

    # ----------------------------------------------------------------- proximity
    def handle_other(self, msg: Any, link: int) -> list[Outgoing]:
        if msg.get_type() == "OBSTACLE_DISTANCE" and int(self.param("PRX1_TYPE", 0)) == PRX_TYPE_MAVLINK:
            self._store_obstacles(msg)
        return []

    def _store_obstacles(self, msg: Any) -> None:
        increment = float(msg.increment_f) if msg.increment_f > 0 else float(msg.increment)
        if increment <= 0:
            self.count("obstacle_distance_invalid")
            return
        dists = np.asarray(msg.distances, dtype=float)
        n = min(len(dists), math.ceil(360.0 / increment))
        angles_cw = float(msg.angle_offset) + increment * np.arange(n)
        # BODY_FRD: angles from the nose; MAV_FRAME_GLOBAL / LOCAL_NED: angles from North
        heading = yaw_enu_to_ned(self.snap.yaw) if msg.frame == mavlink.MAV_FRAME_BODY_FRD else 0.0
        d = dists[:n]
        valid = (d != 65535) & (d >= msg.min_distance) & (d <= msg.max_distance)
        bearing = heading + np.radians(angles_cw[valid])  # NED, clockwise from North
        self.obstacles = np.column_stack([np.sin(bearing), np.cos(bearing), d[valid] / 100.0])
        self.obstacles_time = self.now
        self.count("obstacle_distance_used")

    def limit_velocity(self, vx: float, vy: float) -> tuple[float, float]:
        if (
            self.obstacles is None
            or not int(self.param("AVOID_ENABLE", 3)) & AVOID_USE_PROXIMITY
            or int(self.param("PRX1_TYPE", 0)) != PRX_TYPE_MAVLINK
            or self.now - self.obstacles_time > PROXIMITY_TIMEOUT
        ):
            return vx, vy
        margin = self.param("AVOID_MARGIN", 2.0)
        v = np.array([vx, vy])
        limited = False
        for ux, uy, _distance in self.obstacles[self.obstacles[:, 2] < margin]:
            toward = v[0] * ux + v[1] * uy
            if toward > 0:
                v = v - toward * np.array([ux, uy])
                limited = True
        if limited:
            self.count("avoid_limited")
        return float(v[0]), float(v[1])

    def flight_sw_version(self) -> int:
        return (4 << 24) | (5 << 16) | (7 << 8) | mavlink.FIRMWARE_VERSION_TYPE_OFFICIAL
