"""A minimal ground station over pymavlink: what the pilot does in a SITL flight (mode, arm, take-off,
a world's waypoints planned as a mission and uploaded).

Used by the SITL harness and the SITL tests against the simulated autopilots and, with
``--autopilot external``, against a real ArduPilot/PX4 SITL. It speaks only MAVLink (no simulator
internals), so it exercises the autopilot the way a GCS would.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pymavlink import mavutil

from companion.autopilot.connection import parse_connection
from companion.common.errors import UserError
from companion.guidance.goal_frames import offset_global

if TYPE_CHECKING:
    from flightsim.worlds.world import World

log = logging.getLogger(__name__)

#: Acceptance radius of the waypoints :func:`mission_items` plans (``avoid-sim fly --mission``), m.
MISSION_ACCEPTANCE_RADIUS = 1.0

ARDUCOPTER_MODES = {
    "STABILIZE": 0,
    "ALT_HOLD": 2,
    "AUTO": 3,
    "GUIDED": 4,
    "LOITER": 5,
    "RTL": 6,
    "LAND": 9,
    "BRAKE": 17,
}
#: PX4 mode name -> (main, sub)
PX4_MODES = {
    "POSCTL": (3, 0),
    "OFFBOARD": (6, 0),
    "TAKEOFF": (4, 2),
    "LOITER": (4, 3),
    "HOLD": (4, 3),
    "RTL": (4, 5),
    "LAND": (4, 6),
}


class GroundStation:
    """One GCS connection to an autopilot.

    :param connect: a MAVLink connection, either spelling (``udpout:127.0.0.1:14550``,
        ``udpin://0.0.0.0:14550``, ``/dev/ttyUSB0:57600``), checked by :mod:`companion.autopilot.connection`
    :param system_id: the GCS's own system id (255 as Mission Planner/QGC use)
    """

    def __init__(self, connect: str, system_id: int = 255) -> None:
        link = parse_connection(connect, default_baud=57600)
        try:
            self.mav = mavutil.mavlink_connection(
                link.pymavlink,
                baud=link.baud or 115200,
                source_system=system_id,
                source_component=mavutil.mavlink.MAV_COMP_ID_MISSIONPLANNER,
                dialect="ardupilotmega",
                autoreconnect=True,
            )
        except Exception as exc:
            raise UserError(f"ground station: cannot open {connect!r}: {exc}") from None
        self.target_system = 1
        self.autopilot: int | None = None
        self.heartbeat: Any = None
        self.last: dict[str, Any] = {}
        self.statustexts: list[str] = []
        self._next_hb = 0.0
        #: called with every message received (the SITL harness relays an external SITL with it)
        self.on_message: Any = None

    # ----------------------------------------------------------------- plumbing
    def pump(self, duration: float = 0.0) -> None:
        """Send our heartbeat when due and read everything for ``duration`` seconds."""
        end = time.monotonic() + duration
        while True:
            now = time.monotonic()
            if now >= self._next_hb:
                self.mav.mav.heartbeat_send(
                    mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
                )
                self._next_hb = now + 1.0
            msg = self.mav.recv_match(blocking=True, timeout=max(0.0, min(0.05, end - now)))
            if msg is not None:
                self._note(msg)
            if time.monotonic() >= end and msg is None:
                return

    def _note(self, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return
        if self.on_message is not None:
            self.on_message(msg)
        self.last[kind] = msg
        if kind == "HEARTBEAT" and msg.get_srcComponent() == mavutil.mavlink.MAV_COMP_ID_AUTOPILOT1:
            self.heartbeat = msg
            self.autopilot = msg.autopilot
            self.target_system = msg.get_srcSystem()
        elif kind == "STATUSTEXT":
            self.statustexts.append(msg.text)

    def _drain(self, timeout: float = 0.05) -> list[Any]:
        """Pump once (heartbeat when due) and return every message read, each already noted."""
        now = time.monotonic()
        if now >= self._next_hb:
            self.mav.mav.heartbeat_send(
                mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
            )
            self._next_hb = now + 1.0
        out = []
        msg = self.mav.recv_match(blocking=True, timeout=timeout)
        while msg is not None:
            if msg.get_type() != "BAD_DATA":
                self._note(msg)
                out.append(msg)
            msg = self.mav.recv_match(blocking=False)
        return out

    def wait(self, predicate: Any, timeout: float, what: str) -> None:
        """Pump until ``predicate()`` holds; RuntimeError naming ``what`` on timeout."""
        end = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > end:
                raise RuntimeError(f"ground station: timed out after {timeout:.0f} s waiting for {what}")
            self.pump(0.05)

    def wait_heartbeat(self, timeout: float = 10.0) -> None:
        self.wait(lambda: self.heartbeat is not None, timeout, "the autopilot's HEARTBEAT")

    @property
    def is_px4(self) -> bool:
        return self.autopilot == mavutil.mavlink.MAV_AUTOPILOT_PX4

    def command(self, command: int, *params: float, timeout: float = 3.0) -> int:
        """COMMAND_LONG, sent up to three times (confirmation counting up) until a COMMAND_ACK answers
        it; returns MAV_RESULT.

        The first answer is the one that counts. Under load the ACK to one attempt can arrive with
        the ACK to the next, and a command that is already running (NAV_TAKEOFF climbing) refuses the
        repeat, so the latest ACK would turn an accepted command into a refused one.
        """
        p = [*params, *([0.0] * (7 - len(params)))]
        for attempt in range(3):
            self.mav.mav.command_long_send(self.target_system, 1, command, attempt, *p)
            end = time.monotonic() + timeout / 3
            while time.monotonic() < end:
                for msg in self._drain(0.02):
                    if msg.get_type() == "COMMAND_ACK" and msg.command == command:
                        return int(msg.result)
        raise RuntimeError(f"ground station: no COMMAND_ACK for command {command}")

    # ----------------------------------------------------------------- state
    @property
    def armed(self) -> bool:
        return bool(self.heartbeat and self.heartbeat.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    @property
    def mode(self) -> str:
        """The autopilot's mode name (ArduCopter number names, or PX4 names from :data:`PX4_MODES`)."""
        if self.heartbeat is None:
            return "UNKNOWN"
        custom = self.heartbeat.custom_mode
        if self.is_px4:
            main, sub = (custom >> 16) & 0xFF, (custom >> 24) & 0xFF
            for name, ms in PX4_MODES.items():
                if ms == (main, sub if main == 4 else 0):
                    return name
            return f"PX4({main},{sub})"
        for name, number in ARDUCOPTER_MODES.items():
            if number == custom:
                return name
        return str(custom)

    @property
    def altitude(self) -> float:
        """Relative altitude (m, up) from GLOBAL_POSITION_INT, NaN before the first one."""
        msg = self.last.get("GLOBAL_POSITION_INT")
        return msg.relative_alt / 1000.0 if msg is not None else math.nan

    @property
    def speed(self) -> float:
        """Horizontal speed (m/s) from LOCAL_POSITION_NED, NaN before the first one."""
        msg = self.last.get("LOCAL_POSITION_NED")
        return math.hypot(msg.vx, msg.vy) if msg is not None else math.nan

    # ----------------------------------------------------------------- pilot actions
    def set_mode(self, name: str, timeout: float = 5.0) -> None:
        """Change mode with DO_SET_MODE and wait until the heartbeat shows it."""
        flag = mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.is_px4:
            main, sub = PX4_MODES[name]
            result = self.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, flag, main, sub)
        else:
            result = self.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, flag, ARDUCOPTER_MODES[name])
        if result != mavutil.mavlink.MAV_RESULT_ACCEPTED:
            raise RuntimeError(f"ground station: mode {name} refused (MAV_RESULT {result})")
        want = "LOITER" if name == "HOLD" else name
        self.wait(lambda: self.mode == want, timeout, f"mode {name}")

    def arm(self, timeout: float = 5.0) -> None:
        result = self.command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        if result != mavutil.mavlink.MAV_RESULT_ACCEPTED:
            raise RuntimeError(f"ground station: arming refused {result} {self.statustexts[-1:]}")
        self.wait(lambda: self.armed, timeout, "armed")

    def takeoff(self, altitude: float, timeout: float = 20.0) -> None:
        """NAV_TAKEOFF to ``altitude`` m above home and wait until reached (within 0.15 m)."""
        if self.is_px4:
            home = self.last.get("HOME_POSITION")
            if home is not None:
                home_amsl = home.altitude / 1000.0
            else:
                home_amsl = self.last["GLOBAL_POSITION_INT"].alt / 1000.0 - self.altitude
            nan, amsl = math.nan, home_amsl + altitude
            result = self.command(mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, nan, nan, nan, amsl)
        else:
            result = self.command(mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, altitude)
        if result != mavutil.mavlink.MAV_RESULT_ACCEPTED:
            raise RuntimeError(f"ground station: take-off refused (MAV_RESULT {result})")
        self.wait(lambda: self.altitude >= altitude - 0.15, timeout, f"altitude {altitude} m")

    def home_position(self, timeout: float = 5.0) -> tuple[int, int]:
        """Home's (latitude, longitude) × 1e7, asked for with MAV_CMD_GET_HOME_POSITION."""
        self.last.pop("HOME_POSITION", None)
        self.command(mavutil.mavlink.MAV_CMD_GET_HOME_POSITION)
        self.wait(lambda: "HOME_POSITION" in self.last, timeout, "HOME_POSITION")
        home = self.last["HOME_POSITION"]
        return int(home.latitude), int(home.longitude)

    def upload_mission(self, items: list[MissionItemSpec], timeout: float = 10.0) -> None:
        """Upload ``items`` as the mission, as a ground station does; RuntimeError unless accepted.

        MISSION_COUNT, then each item the autopilot asks for (MISSION_REQUEST_INT, or the legacy
        MISSION_REQUEST) as MISSION_ITEM_INT, until its MISSION_ACK. On ArduPilot a placeholder
        home is sent as item 0 first (the firmware keeps its own home there).
        """
        items = list(items)
        if not self.is_px4:
            items = [MissionItemSpec(mavutil.mavlink.MAV_FRAME_GLOBAL, 0, 0, 0.0), *items]
        target = (self.target_system, mavutil.mavlink.MAV_COMP_ID_AUTOPILOT1)
        self.last.pop("MISSION_ACK", None)
        self.mav.mav.mission_count_send(*target, len(items), mavutil.mavlink.MAV_MISSION_TYPE_MISSION)
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for msg in self._drain():  # every message is noted (and relayed, with an external SITL)
                kind = msg.get_type()
                if getattr(msg, "target_system", None) != self.mav.source_system:
                    continue  # not the ground station's transfer (the companion's, relayed)
                if kind == "MISSION_ACK":
                    if msg.type != mavutil.mavlink.MAV_MISSION_ACCEPTED:
                        raise RuntimeError(f"ground station: mission refused (MAV_MISSION_RESULT {msg.type})")
                    log.info("mission of %d items uploaded", len(items))
                    return
                if kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST") and 0 <= msg.seq < len(items):
                    it = items[msg.seq]
                    self.mav.mav.mission_item_int_send(
                        *target, msg.seq, it.frame, it.command, int(msg.seq == 0), 1,
                        0.0, it.acceptance_radius, 0.0, math.nan, it.x, it.y, it.z,
                        mavutil.mavlink.MAV_MISSION_TYPE_MISSION)
        raise RuntimeError("ground station: no MISSION_ACK for the mission upload")

    def close(self) -> None:
        self.mav.close()


@dataclass(frozen=True)
class MissionItemSpec:
    """One mission item a ground station uploads (MISSION_ITEM_INT fields).

    :param frame: MAV_FRAME (global frames: x, y are degrees × 1e7)
    :param x: latitude × 1e7 (global) or metres × 1e4 (local)
    :param y: longitude × 1e7 (global) or metres × 1e4 (local)
    :param z: altitude, metres (its reference is the frame's)
    :param command: MAV_CMD (NAV_WAYPOINT by default)
    :param acceptance_radius: NAV_WAYPOINT param2, metres (0: the vehicle's default)
    """

    frame: int
    x: int
    y: int
    z: float
    command: int = mavutil.mavlink.MAV_CMD_NAV_WAYPOINT
    acceptance_radius: float = 0.0


def mission_items(world: World, home: tuple[int, int], rotation: float = 0.0) -> list[MissionItemSpec]:
    """The world's waypoints as NAV_WAYPOINTs relative to ``home`` (lat, lon × 1e7) at the world's start.

    :param rotation: rad, counter-clockwise, from the autopilot's East-North frame to the world's
        (0 for the simulated autopilots, whose frame is the world's)
    """
    sx, sy, _ = world.start_position
    c, s = math.cos(rotation), math.sin(rotation)
    items = []
    for x, y, z in world.waypoints:
        dx, dy = x - sx, y - sy
        east, north = c * dx + s * dy, -s * dx + c * dy  # the world's offset turned back by -rotation
        lat, lon = offset_global(*home, north, east)
        frame = mavutil.mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
        items.append(MissionItemSpec(frame, round(lat), round(lon), float(z),
                                     acceptance_radius=MISSION_ACCEPTANCE_RADIUS))
    return items
