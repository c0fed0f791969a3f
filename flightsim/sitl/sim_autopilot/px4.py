"""PX4 personality: main/sub custom modes, OFFBOARD proof-of-life, offboard-loss failsafe, bytewise params.

Modelled on PX4's commander and mavlink modules: custom_mode = main << 16 | sub << 24; OFFBOARD
is entered only while setpoints have been streaming at > 2 Hz for > 1 s; losing them for
COM_OF_LOSS_T triggers the COM_OBL_RC_ACT action (without RC, the RC-based choices 0-2 fall back to
Return); NAV_TAKEOFF goes to AUTO.TAKEOFF and ends in AUTO.LOITER (Hold); STATUSTEXT goes only to
links that have sent a GCS heartbeat; AUTOPILOT_VERSION advertises bytewise parameter encoding.
"""

from __future__ import annotations

import logging
import math
from enum import IntEnum
from typing import Any, ClassVar

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from flightsim.sitl.sim_autopilot.common import Command, Guidance, Outgoing, SimAutopilot
from flightsim.sitl.sim_autopilot.frames import HOME_ALT_AMSL_M
from flightsim.sitl.sim_autopilot.position_target import decode_position_target

log = logging.getLogger(__name__)


class MainMode(IntEnum):
    """PX4_CUSTOM_MAIN_MODE."""

    MANUAL = 1
    ALTCTL = 2
    POSCTL = 3
    AUTO = 4
    ACRO = 5
    OFFBOARD = 6
    STABILIZED = 7


class AutoSubMode(IntEnum):
    """PX4_CUSTOM_SUB_MODE_AUTO."""

    READY = 1
    TAKEOFF = 2
    LOITER = 3
    MISSION = 4
    RTL = 5
    LAND = 6


#: setpoints must arrive at least this often to count as a stream (> 2 Hz), seconds
STREAM_MAX_GAP = 0.5
#: ... and the stream must have lasted this long before OFFBOARD is accepted, seconds
STREAM_MIN_DURATION = 1.0


def px4_custom_mode(main: int, sub: int = 0) -> int:
    """The HEARTBEAT custom_mode of a PX4 main/sub mode."""
    return (main << 16) | (sub << 24)


MODE_NAMES = {
    (MainMode.MANUAL, 0): "MANUAL",
    (MainMode.ALTCTL, 0): "ALTCTL",
    (MainMode.POSCTL, 0): "POSCTL",
    (MainMode.OFFBOARD, 0): "OFFBOARD",
    (MainMode.STABILIZED, 0): "STABILIZED",
    (MainMode.AUTO, AutoSubMode.TAKEOFF): "AUTO.TAKEOFF",
    (MainMode.AUTO, AutoSubMode.LOITER): "AUTO.LOITER",
    (MainMode.AUTO, AutoSubMode.RTL): "AUTO.RTL",
    (MainMode.AUTO, AutoSubMode.LAND): "AUTO.LAND",
}
ARMABLE = {
    (MainMode.POSCTL, 0),
    (MainMode.ALTCTL, 0),
    (MainMode.OFFBOARD, 0),
    (MainMode.AUTO, AutoSubMode.LOITER),
    (MainMode.AUTO, AutoSubMode.TAKEOFF),
}
#: COM_OBL_RC_ACT value → (main, sub) of the failsafe mode; None: disarm
OFFBOARD_LOSS_ACTIONS: dict[int, tuple[int, int] | None] = {
    0: (MainMode.AUTO, AutoSubMode.RTL),  # Position mode needs RC: without RC, Return
    1: (MainMode.AUTO, AutoSubMode.RTL),  # Altitude mode needs RC
    2: (MainMode.AUTO, AutoSubMode.RTL),  # Stabilized needs RC
    3: (MainMode.AUTO, AutoSubMode.RTL),
    4: (MainMode.AUTO, AutoSubMode.LAND),
    5: (MainMode.AUTO, AutoSubMode.LOITER),
    6: None,  # Terminate
    7: None,  # Disarm
}


class PX4Autopilot(SimAutopilot):
    """A simulated PX4 multicopter (custom modes, OFFBOARD, offboard-loss failsafe)."""

    RESPONSE = "px4"
    NO_POSITION_REFUSAL = "no valid position estimate"
    AUTOPILOT = mavlink.MAV_AUTOPILOT_PX4
    #: accepted unsigned while signing is on (mavlink_sign_control.cpp, MAV_SIGN_CFG = 2)
    UNSIGNED_ACCEPTED = frozenset((mavlink.MAVLINK_MSG_ID_RADIO_STATUS, mavlink.MAVLINK_MSG_ID_ADSB_VEHICLE,
                                   mavlink.MAVLINK_MSG_ID_COLLISION))
    MODE_REFUSED = mavlink.MAV_RESULT_TEMPORARILY_REJECTED  # commander: transition denied
    DEFAULT_INTERVALS: ClassVar[dict[str, float]] = {
        "HEARTBEAT": 1.0,
        "SYS_STATUS": 0.2,
        "ATTITUDE": 0.05,
        "LOCAL_POSITION_NED": 0.05,
        "GLOBAL_POSITION_INT": 0.05,
        "EXTENDED_SYS_STATE": 0.2,
        "HOME_POSITION": 2.0,
        "VFR_HUD": 0.25,
        "MISSION_CURRENT": 1.0,
    }
    CAPABILITIES = (
        SimAutopilot.CAPABILITIES
        | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
        | mavlink.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
    )

    def __init__(self, params: Any, **kw: Any) -> None:
        """:param params: the parameter table; ``kw``: see :class:`SimAutopilot`."""
        super().__init__(params, **kw)
        self.main = int(MainMode.AUTO)
        self.sub = int(AutoSubMode.LOITER)
        self.stream_start: float | None = None
        self.last_setpoint: float | None = None
        self.pending_target: Any = None

    # ----------------------------------------------------------------- modes
    def mode_name(self) -> str:
        return MODE_NAMES.get((self.main, self.sub), f"PX4({self.main},{self.sub})")

    def heartbeat_mode(self) -> tuple[int, int]:
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.main in (MainMode.AUTO, MainMode.OFFBOARD):
            base |= (
                mavlink.MAV_MODE_FLAG_AUTO_ENABLED
                | mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
                | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
            )
        elif self.main == MainMode.POSCTL:
            base |= mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
        else:
            base |= mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        return base, px4_custom_mode(self.main, self.sub)

    def offboard_stream_ok(self) -> bool:
        """Setpoints streamed at > 2 Hz for > 1 s (the condition to enter OFFBOARD)."""
        return (
            self.stream_start is not None
            and self.last_setpoint is not None
            and self.now - self.last_setpoint <= STREAM_MAX_GAP
            and self.last_setpoint - self.stream_start >= STREAM_MIN_DURATION
        )

    def handle_set_mode(self, base_mode: int, custom_mode: int, custom_sub_mode: int) -> bool:
        if not base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return False
        return self.set_mode(custom_mode, custom_sub_mode)

    def handle_set_mode_message(self, base_mode: int, custom_mode: int) -> bool:
        """SET_MODE packs main/sub the way HEARTBEAT does."""
        return self.handle_set_mode(base_mode, (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF)

    def set_mode(self, main: int, sub: int = 0) -> bool:
        """Enter PX4 mode main/sub (True) or refuse it as commander would."""
        if main != MainMode.AUTO:
            sub = 0
        if (main, sub) not in MODE_NAMES:
            return False
        if main == MainMode.OFFBOARD and not self.offboard_stream_ok():
            self.pending += self.statustext(
                "Switching to Offboard is currently not available", mavlink.MAV_SEVERITY_CRITICAL
            )
            return False
        if (main, sub) == (self.main, self.sub):
            return True
        if (main, sub) == (MainMode.AUTO, AutoSubMode.TAKEOFF) and not (self.armed and self.snap.on_ground):
            return False
        self.main, self.sub = int(main), int(sub)
        self.count(f"mode_{self.mode_name()}")
        if main == MainMode.AUTO and sub == AutoSubMode.LAND:
            self.start_land()
        elif main == MainMode.AUTO and sub == AutoSubMode.RTL:
            self.start_rtl()
        elif main == MainMode.AUTO and sub == AutoSubMode.TAKEOFF:
            self.start_takeoff(self.param("MIS_TAKEOFF_ALT", 2.5))
        elif main == MainMode.OFFBOARD and self.pending_target is not None:
            self.start_hold()
            self._apply(self.pending_target)
        else:
            self.start_hold()
        return True

    # ----------------------------------------------------------------- commands
    def arm_allowed(self) -> str | None:
        if (self.main, self.sub) not in ARMABLE:
            return "Arming denied: not in an armable mode"
        return None

    def handle_command(self, cmd: Command, link: int) -> list[Outgoing]:
        p = cmd.params
        if cmd.command == mavlink.MAV_CMD_NAV_TAKEOFF:
            if not self.armed or not self.snap.on_ground:
                return [self.ack(link, cmd, mavlink.MAV_RESULT_TEMPORARILY_REJECTED)]
            amsl = float(p[6])
            above_home = amsl - HOME_ALT_AMSL_M if math.isfinite(amsl) else self.param("MIS_TAKEOFF_ALT", 2.5)
            if above_home <= 0:
                return [self.ack(link, cmd, mavlink.MAV_RESULT_DENIED)]
            self.main, self.sub = int(MainMode.AUTO), int(AutoSubMode.TAKEOFF)
            self.count("mode_AUTO.TAKEOFF")
            self.start_takeoff(above_home)
            return [self.ack(link, cmd, mavlink.MAV_RESULT_ACCEPTED)]
        if cmd.command == mavlink.MAV_CMD_NAV_LAND:
            ok = self.set_mode(MainMode.AUTO, AutoSubMode.LAND)
            return [self.ack(link, cmd, mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_DENIED)]
        if cmd.command == mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            ok = self.set_mode(MainMode.AUTO, AutoSubMode.RTL)
            return [self.ack(link, cmd, mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_DENIED)]
        return super().handle_command(cmd, link)

    def takeoff_complete(self) -> list[Outgoing]:
        out = super().takeoff_complete()
        self.main, self.sub = int(MainMode.AUTO), int(AutoSubMode.LOITER)
        self.count("mode_AUTO.LOITER")
        return out + self.statustext("Takeoff detected")

    def statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> list[Outgoing]:
        """PX4 sends STATUSTEXT only to links on which a GCS has announced itself."""
        log.info("autopilot: %s", text)
        msg = mavlink.MAVLink_statustext_message(severity, text.encode()[:50])
        return [Outgoing(msg, link) for link, info in sorted(self.links.items()) if info.is_gcs]

    # ----------------------------------------------------------------- offboard
    def handle_position_target(self, msg: Any, link: int) -> list[Outgoing]:
        if msg.coordinate_frame not in (
            mavlink.MAV_FRAME_LOCAL_NED,
            mavlink.MAV_FRAME_BODY_NED,
            mavlink.MAV_FRAME_LOCAL_OFFSET_NED,
            mavlink.MAV_FRAME_BODY_OFFSET_NED,
        ):
            self.count("setpoint_invalid")
            return []
        # any setpoint is proof of life for the offboard link, whatever the mode
        if self.last_setpoint is None or self.now - self.last_setpoint > STREAM_MAX_GAP:
            self.stream_start = self.now
        self.last_setpoint = self.now
        self.pending_target = msg
        if self.main != MainMode.OFFBOARD:
            self.count("setpoint_ignored_not_offboard")
            return []
        self._apply(msg)
        return []

    def _apply(self, msg: Any) -> None:
        if not self.armed or (self.snap.on_ground and self.guidance == Guidance.IDLE):
            self.count("setpoint_ignored_landed")
            return
        target = decode_position_target(msg, self.snap, self.now)
        if target is None:
            self.count("setpoint_invalid")
            self.start_hold()
            return
        self.count("setpoint_accepted")
        self.set_target(target)

    def personality_tick(self) -> list[Outgoing]:
        if self.main != MainMode.OFFBOARD:
            return []
        loss_t = self.param("COM_OF_LOSS_T", 1.0)
        if self.last_setpoint is not None and self.now - self.last_setpoint <= loss_t:
            return []
        action = int(self.param("COM_OBL_RC_ACT", 0))
        self.count("offboard_lost")
        out = self.statustext("Failsafe activated: no offboard signal", mavlink.MAV_SEVERITY_CRITICAL)
        mode = OFFBOARD_LOSS_ACTIONS.get(action, (MainMode.AUTO, AutoSubMode.RTL))
        if mode is None:
            self.main, self.sub = int(MainMode.AUTO), int(AutoSubMode.LOITER)
            return out + self.disarm("offboard loss")
        self.main, self.sub = 0, 0  # force the change even if the mode equals the current one
        self.set_mode(*mode)
        return out

    def flight_sw_version(self) -> int:
        return (1 << 24) | (15 << 16) | (4 << 8) | mavlink.FIRMWARE_VERSION_TYPE_OFFICIAL

    def vtol_state(self) -> int:
        return mavlink.MAV_VTOL_STATE_MC
