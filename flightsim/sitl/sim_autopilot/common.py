"""The core both simulated-autopilot personalities share: pure logic, no sockets.

A personality is fed decoded MAVLink messages (:meth:`SimAutopilot.handle`), the vehicle's state
(:meth:`SimAutopilot.observe`) and the time (``now``, an injected clock in seconds); it answers with
messages to send (:class:`Outgoing`) and, through :meth:`SimAutopilot.flight_command`, what the
vehicle's own controller should do (armed or not, and a :class:`~flightsim.vehicle.control.Setpoint`).
Sockets, framing and real time live in :mod:`flightsim.sitl.sim_autopilot.endpoint` and
:mod:`flightsim.sitl.sim_autopilot.server`, so everything here can be unit-tested with a fake clock.

Frames and the vehicle's place on Earth are in :mod:`flightsim.sitl.sim_autopilot.frames`; the decoding of
a position target in :mod:`flightsim.sitl.sim_autopilot.position_target`; the telemetry each message
carries in :mod:`flightsim.sitl.sim_autopilot.telemetry`.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from enum import Enum
from typing import Any, ClassVar

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from flightsim.sitl.sim_autopilot.frames import HOME_ALT_AMSL_M, lat_lon
from flightsim.sitl.sim_autopilot.mission import MissionStore, StoredItem
from flightsim.sitl.sim_autopilot.position_target import ExternalTarget
from flightsim.sitl.sim_autopilot.snapshot import VehicleSnapshot
from flightsim.sitl.sim_autopilot.telemetry import telemetry_message
from flightsim.vehicle.autopilot_response import CHUNK_S, PRESETS, AutopilotResponse
from flightsim.vehicle.control import Setpoint

log = logging.getLogger(__name__)

#: Horizontal speed limit of the position-hold loop and of return-to-launch, m/s.
HOLD_SPEED_MAX = 1.0
RTL_SPEED = 2.0
#: Proportional gain of the position-hold loop, 1/s.
HOLD_GAIN = 1.0
TAKEOFF_DONE_MARGIN = 0.1


@dataclass
class Outgoing:
    """A message to send: to one link (its index) or, with ``link=None``, to every link."""

    message: Any
    link: int | None = None


@dataclass
class LinkInfo:
    """What the autopilot knows about the peer on one link (from its HEARTBEATs)."""

    system_id: int | None = None
    component_id: int | None = None
    mav_type: int | None = None
    is_gcs: bool = False
    last_heartbeat: float | None = None


@dataclass
class Command:
    """COMMAND_LONG and COMMAND_INT in one shape (params 5..7 are x, y, z of COMMAND_INT)."""

    command: int
    params: tuple[float, float, float, float, float, float, float]
    source_system: int
    source_component: int


class Guidance(Enum):
    """What the flight controller is doing right now (independent of the personality's mode names)."""

    IDLE = "idle"  # disarmed, or armed on the ground
    TAKEOFF = "takeoff"  # climbing to the take-off altitude
    HOLD = "hold"  # holding a position (loiter, brake, guided without a target)
    VELOCITY = "velocity"  # following an external velocity target
    POSITION = "position"  # flying to an external position target
    LAND = "land"  # descending to the ground, then disarming
    RTL = "rtl"  # flying home at the current altitude, then landing


#: the altitude estimate's drift grows to :attr:`SimAutopilot.altitude_drift` over this from arming, s
ALTITUDE_DRIFT_S = 20.0


def _setpoint(**kw: Any) -> Setpoint:
    """A Setpoint where a given ``yaw`` is held (Setpoint's yaw_rate defaults to 0, which wins)."""
    if "yaw" in kw:
        kw.setdefault("yaw_rate", None)
    return Setpoint(**kw)


class SimAutopilot:
    """Shared behaviour of a simulated flight controller; subclasses add the firmware's personality.

    :param params: the parameter table (:class:`flightsim.sitl.sim_autopilot.params.ParameterTable`)
    :param system_id: this autopilot's MAVLink system id
    :param boot_time: clock time of "boot" (time_boot_ms counts from here)
    :param response: fly velocity control through the firmware's calibrated response
        (:mod:`flightsim.vehicle.autopilot_response`, preset :attr:`RESPONSE`) and report its velocity
        estimate; False flies setpoints as given with a perfect estimate (the ideal autopilot)
    :param seed: seeds the velocity-estimate error (None: fresh entropy)
    :param altitude_drift: how far the altitude estimate ends up above the truth, m (negative:
        below), reached :data:`ALTITUDE_DRIFT_S` after arming; the autopilot flies its estimate, so
        the vehicle flies that much lower (the real PX4 SIH flights: -1.08 to +0.82 m)
    :param position_delay: seconds from boot until the estimator has an origin; until then no
        :attr:`POSITION_MESSAGES` and no arming, as a fresh ArduPilot SITL waits 40-47 s for its
        GPS fix and EKF origin (0: a position at once, as PX4 SIH)
    """

    AUTOPILOT: int = mavlink.MAV_AUTOPILOT_GENERIC
    #: message ids the firmware accepts unsigned while MAVLink 2 signing is on
    UNSIGNED_ACCEPTED: ClassVar[frozenset[int]] = frozenset()
    #: the :data:`flightsim.vehicle.autopilot_response.PRESETS` entry this firmware flies
    RESPONSE: str = ""
    #: message name -> default stream interval (s) on every link
    DEFAULT_INTERVALS: ClassVar[dict[str, float]] = {}
    #: message names this autopilot can stream or send on request
    STREAMABLE = (
        "HEARTBEAT",
        "SYS_STATUS",
        "ATTITUDE",
        "LOCAL_POSITION_NED",
        "GLOBAL_POSITION_INT",
        "EXTENDED_SYS_STATE",
        "HOME_POSITION",
        "AUTOPILOT_VERSION",
        "VFR_HUD",
        "MISSION_CURRENT",
    )
    #: messages that need the estimator's origin (a GPS fix): none of them until it has one
    POSITION_MESSAGES = frozenset(("LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "HOME_POSITION"))
    #: why arming is refused while the estimator has no origin (the firmware's pre-arm text)
    NO_POSITION_REFUSAL = "no position estimate yet"
    #: mission-protocol messages, handled by :class:`~flightsim.sitl.sim_autopilot.mission.MissionStore`
    MISSION_MESSAGES = frozenset((
        "MISSION_REQUEST_LIST", "MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_COUNT",
        "MISSION_ITEM_INT", "MISSION_ITEM", "MISSION_ACK", "MISSION_CLEAR_ALL", "MISSION_SET_CURRENT",
    ))
    #: the firmware keeps home as mission item 0 (ArduPilot)
    MISSION_HOME_ITEM = False
    #: COMMAND_ACK result of a refused DO_SET_MODE
    MODE_REFUSED: int = mavlink.MAV_RESULT_FAILED
    #: MAV_PROTOCOL_CAPABILITY bits of AUTOPILOT_VERSION (plus the parameter table's encoding bit)
    CAPABILITIES = (
        mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
        | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
        | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
        | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
        | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    )

    def __init__(
        self, params: Any, *, system_id: int = 1, boot_time: float = 0.0, response: bool = True,
        seed: int | None = None, position_delay: float = 0.0, altitude_drift: float = 0.0,
    ) -> None:  # fmt: skip
        self.params = params
        self.position_delay = position_delay
        self.altitude_drift = altitude_drift
        self.armed_at: float | None = None
        self.response = (
            AutopilotResponse(PRESETS[self.RESPONSE], np.random.default_rng(seed))
            if response and self.RESPONSE
            else None
        )
        self._response_input: tuple[float, ...] | None = None
        self.system_id = system_id
        self.component_id = mavlink.MAV_COMP_ID_AUTOPILOT1
        self.boot_time = boot_time
        self.now = boot_time
        self.snap = VehicleSnapshot()
        self.home = np.zeros(3)
        self.home_set = False
        self.armed = False
        self.guidance = Guidance.IDLE
        self.hold_position = np.zeros(3)
        self.hold_yaw = 0.0
        self.takeoff_altitude = 0.0
        self.target: ExternalTarget | None = None
        self.target_altitude: float | None = None  # altitude latched when a target has vz = 0
        self.links: dict[int, LinkInfo] = {}
        self.intervals: dict[tuple[int, str], float] = {}
        self.next_due: dict[tuple[int, str], float] = {}
        self.counters: dict[str, int] = {}
        #: set by a test harness to stop this autopilot's HEARTBEATs (a "dead" autopilot)
        self.heartbeat_enabled = True
        self.ground_since: float | None = None
        self.pending: list[Outgoing] = []
        self.mission = MissionStore(self._mission_home if self.MISSION_HOME_ITEM else None)

    def _mission_home(self) -> StoredItem:
        """Home as ArduPilot reports it in mission item 0 (absolute altitude)."""
        lat, lon = lat_lon(np.zeros(3))
        return StoredItem(mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_CMD_NAV_WAYPOINT, (0.0, 0.0, 0.0, 0.0),
                          lat, lon, HOME_ALT_AMSL_M)

    # ----------------------------------------------------------------- helpers for subclasses
    def count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n

    def param(self, name: str, default: float) -> float:
        """A parameter's value, or ``default`` when the table lacks it."""
        try:
            value = self.params.get(name)
        except KeyError:
            return default
        return default if value is None else float(value)

    def altitude_bias(self) -> float:
        """The altitude estimate's error now (estimate minus truth), m: :attr:`altitude_drift`,
        grown linearly over :data:`ALTITUDE_DRIFT_S` from arming; none on the ground before it."""
        if not self.altitude_drift or self.armed_at is None:
            return 0.0
        return self.altitude_drift * min(1.0, max(0.0, self.now - self.armed_at) / ALTITUDE_DRIFT_S)

    @property
    def has_position(self) -> bool:
        """The estimator has its origin (:attr:`position_delay` has passed since boot)."""
        return self.now - self.boot_time >= self.position_delay

    def time_boot_ms(self) -> int:
        return max(0, int((self.now - self.boot_time) * 1000.0)) & 0xFFFFFFFF

    def ack(self, link: int, cmd: Command, result: int) -> Outgoing:
        return Outgoing(
            mavlink.MAVLink_command_ack_message(
                cmd.command, result, 0, 0, cmd.source_system, cmd.source_component
            ),
            link,
        )

    def statustext(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO) -> list[Outgoing]:
        """A STATUSTEXT to the links this firmware sends them to (every link by default)."""
        log.info("autopilot: %s", text)
        msg = mavlink.MAVLink_statustext_message(severity, text.encode()[:50])
        return [Outgoing(msg, None)]

    # ----------------------------------------------------------------- personality hooks
    def mode_name(self) -> str:
        raise NotImplementedError

    def heartbeat_mode(self) -> tuple[int, int]:
        """(base_mode without the armed flag, custom_mode)."""
        raise NotImplementedError

    def landed_state(self) -> int:
        if self.snap.on_ground and self.guidance in (Guidance.IDLE, Guidance.LAND):
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if self.guidance == Guidance.TAKEOFF:
            return mavlink.MAV_LANDED_STATE_TAKEOFF
        if self.guidance == Guidance.LAND or (self.guidance == Guidance.RTL and self._rtl_landing()):
            return mavlink.MAV_LANDED_STATE_LANDING
        if self.snap.on_ground and not self.armed:
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        return mavlink.MAV_LANDED_STATE_IN_AIR

    def handle_command(self, cmd: Command, link: int) -> list[Outgoing]:
        """Personality-specific commands; the base handles the common ones first."""
        return [self.ack(link, cmd, mavlink.MAV_RESULT_UNSUPPORTED)]

    def handle_set_mode(self, base_mode: int, custom_mode: int, custom_sub_mode: int) -> bool:
        """DO_SET_MODE (param1..3); True when the mode was changed (or already set)."""
        raise NotImplementedError

    def handle_set_mode_message(self, base_mode: int, custom_mode: int) -> bool:
        """The SET_MODE message (custom_mode as in HEARTBEAT)."""
        return self.handle_set_mode(base_mode, custom_mode, 0)

    def handle_position_target(self, msg: Any, link: int) -> list[Outgoing]:
        raise NotImplementedError

    def personality_tick(self) -> list[Outgoing]:
        """Mode-specific timeouts and failsafes, called from :meth:`tick`."""
        return []

    def on_landed(self) -> list[Outgoing]:
        """Touch-down in LAND/RTL: disarm (both firmwares do, after a short delay)."""
        return self.disarm("landed")

    # ----------------------------------------------------------------- inputs
    def observe(self, state: Any) -> None:
        """Take the vehicle's latest state (a VehicleState or a :class:`VehicleSnapshot`): what the
        estimator says, the truth with :meth:`altitude_bias` on its altitude."""
        self.snap = state if isinstance(state, VehicleSnapshot) else VehicleSnapshot.of(state)
        bias = self.altitude_bias()
        if bias:
            estimate = self.snap.position + np.array([0.0, 0.0, bias])
            self.snap = dataclasses.replace(self.snap, position=estimate)
        if not self.home_set:
            self.home = self.snap.position.copy()
            self.hold_position = self.snap.position.copy()
            self.hold_yaw = self.snap.yaw
            self.home_set = True

    def take_pending(self) -> list[Outgoing]:
        """Messages queued by a state change (mode refusals, failsafes) since the last call."""
        out, self.pending = self.pending, []
        return out

    def handle(self, msg: Any, link: int, now: float) -> list[Outgoing]:
        """One decoded message that arrived on ``link``; returns the replies."""
        return self._handle(msg, link, now) + self.take_pending()

    def _handle(self, msg: Any, link: int, now: float) -> list[Outgoing]:
        self.now = now
        kind = msg.get_type()
        self.count(f"rx_{kind}")
        target = getattr(msg, "target_system", 0)
        if kind not in ("HEARTBEAT",) and target not in (0, self.system_id):
            return []
        if kind == "HEARTBEAT":
            self._handle_heartbeat(msg, link)
            return []
        if kind in ("PARAM_REQUEST_READ", "PARAM_REQUEST_LIST", "PARAM_SET"):
            return [Outgoing(reply, link) for reply in self.params.handle(msg)]
        if kind == "COMMAND_LONG":
            cmd = Command(
                msg.command,
                (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7),
                msg.get_srcSystem(),
                msg.get_srcComponent(),
            )
            return self._dispatch_command(cmd, link)
        if kind == "COMMAND_INT":
            cmd = Command(
                msg.command,
                (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z),
                msg.get_srcSystem(),
                msg.get_srcComponent(),
            )
            return self._dispatch_command(cmd, link)
        if kind == "SET_MODE":
            self.handle_set_mode_message(msg.base_mode, msg.custom_mode)
            return self.take_pending()
        if kind == "SET_POSITION_TARGET_LOCAL_NED":
            return self.handle_position_target(msg, link)
        if kind == "TIMESYNC":
            if msg.tc1 == 0:
                tc1 = int((self.now - self.boot_time) * 1e9)
                return [Outgoing(mavlink.MAVLink_timesync_message(tc1, msg.ts1), link)]
            return []
        if kind == "REQUEST_DATA_STREAM":
            return self.handle_request_data_stream(msg, link)
        if kind == "PING" and msg.target_system == 0:
            # a ping request (MAVSDK sends them): answer to its sender with the same sequence
            reply = mavlink.MAVLink_ping_message(
                int((self.now - self.boot_time) * 1e6), msg.seq, msg.get_srcSystem(), msg.get_srcComponent()
            )
            return [Outgoing(reply, link)]
        if kind in self.MISSION_MESSAGES:
            return [Outgoing(reply, to) for reply, to in self.mission.handle(msg, link, now)]
        return self.handle_other(msg, link)

    def handle_other(self, msg: Any, link: int) -> list[Outgoing]:
        """Messages only a personality understands (OBSTACLE_DISTANCE, ...)."""
        return []

    def handle_request_data_stream(self, msg: Any, link: int) -> list[Outgoing]:
        return []

    def _handle_heartbeat(self, msg: Any, link: int) -> None:
        info = self.links.setdefault(link, LinkInfo())
        info.system_id = msg.get_srcSystem()
        info.component_id = msg.get_srcComponent()
        info.mav_type = msg.type
        info.last_heartbeat = self.now
        if msg.type == mavlink.MAV_TYPE_GCS:
            info.is_gcs = True

    def _dispatch_command(self, cmd: Command, link: int) -> list[Outgoing]:
        self.count(f"cmd_{cmd.command}")
        p = cmd.params
        if cmd.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return [self.ack(link, cmd, self.set_message_interval(link, int(p[0]), p[1]))]
        if cmd.command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            name = self._message_name(int(p[0]))
            if name is None:
                return [self.ack(link, cmd, mavlink.MAV_RESULT_UNSUPPORTED)]
            if name in self.POSITION_MESSAGES and not self.has_position:
                return [self.ack(link, cmd, mavlink.MAV_RESULT_TEMPORARILY_REJECTED)]
            return [self.ack(link, cmd, mavlink.MAV_RESULT_ACCEPTED), Outgoing(self.build(name), link)]
        if cmd.command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return [
                self.ack(link, cmd, mavlink.MAV_RESULT_ACCEPTED),
                Outgoing(self.build("AUTOPILOT_VERSION"), link),
            ]
        if cmd.command == mavlink.MAV_CMD_GET_HOME_POSITION:
            if not self.has_position:
                return [self.ack(link, cmd, mavlink.MAV_RESULT_TEMPORARILY_REJECTED)]
            return [
                self.ack(link, cmd, mavlink.MAV_RESULT_ACCEPTED),
                Outgoing(self.build("HOME_POSITION"), link),
            ]
        if cmd.command == mavlink.MAV_CMD_DO_SET_MODE:
            ok = self.handle_set_mode(int(p[0]), int(p[1]), int(p[2]))
            return [self.ack(link, cmd, mavlink.MAV_RESULT_ACCEPTED if ok else self.MODE_REFUSED)]
        if cmd.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            return self.handle_arm(cmd, link)
        return self.handle_command(cmd, link)

    def _message_name(self, msg_id: int) -> str | None:
        cls = mavlink.mavlink_map.get(msg_id)
        if cls is None:
            return None
        name = cls.msgname
        return name if name in self.STREAMABLE else None

    def set_message_interval(self, link: int, msg_id: int, interval_us: float) -> int:
        """MAV_CMD_SET_MESSAGE_INTERVAL on ``link``: -1 stops, 0 restores the default."""
        name = self._message_name(msg_id)
        if name is None:
            return mavlink.MAV_RESULT_UNSUPPORTED
        key = (link, name)
        if interval_us < 0:
            self.intervals[key] = 0.0
        elif interval_us == 0:
            self.intervals.pop(key, None)
        else:
            self.intervals[key] = interval_us / 1e6
        self.next_due.pop(key, None)
        return mavlink.MAV_RESULT_ACCEPTED

    def interval(self, link: int, name: str) -> float:
        """Current stream interval of ``name`` on ``link`` (0: not streamed)."""
        return self.intervals.get((link, name), self.DEFAULT_INTERVALS.get(name, 0.0))

    # ----------------------------------------------------------------- arming
    def arm_allowed(self) -> str | None:
        """Why arming is refused now (None: allowed)."""
        return None

    def handle_arm(self, cmd: Command, link: int) -> list[Outgoing]:
        force = abs(cmd.params[1] - 21196.0) < 0.5
        if cmd.params[0] > 0.5:
            if self.armed:
                return [self.ack(link, cmd, mavlink.MAV_RESULT_ACCEPTED)]
            reason = None
            if not force:
                reason = self.NO_POSITION_REFUSAL if not self.has_position else self.arm_allowed()
            if reason is not None:
                return [
                    self.ack(link, cmd, mavlink.MAV_RESULT_FAILED),
                    *self.statustext(f"Arm: {reason}", mavlink.MAV_SEVERITY_CRITICAL),
                ]
            return [self.ack(link, cmd, mavlink.MAV_RESULT_ACCEPTED), *self.arm()]
        if not self.armed:
            return [self.ack(link, cmd, mavlink.MAV_RESULT_ACCEPTED)]
        if not self.snap.on_ground and not force:
            return [
                self.ack(link, cmd, mavlink.MAV_RESULT_FAILED),
                *self.statustext("Disarm: vehicle is flying", mavlink.MAV_SEVERITY_CRITICAL),
            ]
        return [self.ack(link, cmd, mavlink.MAV_RESULT_ACCEPTED), *self.disarm("command")]

    def arm(self) -> list[Outgoing]:
        self.armed = True
        self.armed_at = self.now
        self.ground_since = self.now
        self.guidance = Guidance.IDLE
        self.hold_position = self.snap.position.copy()
        self.hold_yaw = self.snap.yaw
        self.count("armed")
        return self.statustext("Arming motors")

    def disarm(self, why: str) -> list[Outgoing]:
        if not self.armed:
            return []
        self.armed = False
        self.guidance = Guidance.IDLE
        self.target = None
        self.count("disarmed")
        return self.statustext(f"Disarming motors ({why})")

    # ----------------------------------------------------------------- guidance changes
    def start_hold(self) -> None:
        """Hold the current position (brake to a stop first: the hold point is where we are)."""
        self.target = None
        if not self.armed or (self.snap.on_ground and self.guidance in (Guidance.IDLE, Guidance.LAND)):
            self.guidance = Guidance.IDLE
            return
        self.guidance = Guidance.HOLD
        self.hold_position = self.snap.position.copy()
        self.hold_yaw = self.snap.yaw

    def start_takeoff(self, altitude_above_home: float) -> None:
        self.target = None
        self.guidance = Guidance.TAKEOFF
        self.takeoff_altitude = self.home[2] + altitude_above_home
        self.hold_position = self.snap.position.copy()
        self.hold_yaw = self.snap.yaw

    def start_land(self) -> None:
        self.target = None
        self.guidance = Guidance.LAND if self.armed else Guidance.IDLE
        self.hold_position = self.snap.position.copy()
        self.hold_yaw = self.snap.yaw

    def start_rtl(self) -> None:
        self.target = None
        self.guidance = Guidance.RTL if self.armed else Guidance.IDLE
        self.hold_position = self.snap.position.copy()
        self.hold_yaw = self.snap.yaw

    def set_target(self, target: ExternalTarget) -> None:
        """Follow an external target (ends a take-off, like ArduCopter's guided sub-modes)."""
        if target.velocity is not None and target.vz_used and abs(target.velocity[2]) < 1e-3:
            if self.target_altitude is None or self.guidance != Guidance.VELOCITY:
                self.target_altitude = float(self.snap.position[2])
        else:
            self.target_altitude = None
        if (
            target.yaw_rate is None
            and target.yaw is None
            and self.guidance not in (Guidance.VELOCITY, Guidance.POSITION)
        ):
            self.hold_yaw = self.snap.yaw
        if self.response is not None and target.velocity is not None and self.guidance != Guidance.VELOCITY:
            self.response.reset(self.snap.yaw, self.snap.velocity[:2])  # velocity control starts here
            self._response_input = None
        self.target = target
        self.guidance = Guidance.VELOCITY if target.velocity is not None else Guidance.POSITION
        if target.position is None:
            self.hold_position = self.snap.position.copy()

    def _rtl_landing(self) -> bool:
        return bool(np.linalg.norm(self.snap.position[:2] - self.home[:2]) < 0.3)

    # ----------------------------------------------------------------- periodic work
    def tick(self, now: float) -> list[Outgoing]:
        """Advance the clock: takeoff/landing progress, timeouts, failsafes, streams."""
        self.now = now
        out: list[Outgoing] = []
        if self.guidance == Guidance.TAKEOFF and self.snap.position[2] >= (
            self.takeoff_altitude - TAKEOFF_DONE_MARGIN
        ):
            out += self.takeoff_complete()
        if (
            self.armed
            and self.guidance in (Guidance.LAND, Guidance.RTL)
            and self.snap.on_ground
            and (self.guidance == Guidance.LAND or self._rtl_landing())
        ):
            out += self.on_landed()
        if self.armed and self.guidance == Guidance.IDLE and self.snap.on_ground:
            delay = self.param("DISARM_DELAY", 10.0)
            if delay > 0 and self.ground_since is not None and now - self.ground_since > delay:
                out += self.disarm("auto-disarm on the ground")
        elif not self.snap.on_ground:
            self.ground_since = now
        out += self.personality_tick()
        out += [Outgoing(reply, to) for reply, to in self.mission.tick(now)]
        out += self.take_pending()
        out += self._streams()
        return out

    def takeoff_complete(self) -> list[Outgoing]:
        self.start_hold()
        self.hold_position[2] = self.takeoff_altitude
        return []

    def _streams(self) -> list[Outgoing]:
        out: list[Outgoing] = []
        links = set(self.links) | {link for link, _ in self.intervals}
        for link in sorted(links):
            for name in self.STREAMABLE:
                if name == "HEARTBEAT" and not self.heartbeat_enabled:
                    continue
                if name in self.POSITION_MESSAGES and not self.has_position:
                    continue
                period = self.interval(link, name)
                if period <= 0:
                    continue
                key = (link, name)
                due = self.next_due.get(key, self.now)
                if self.now >= due:
                    out.append(Outgoing(self.build(name), link))
                    # keep the phase, but never queue a burst after a stall
                    self.next_due[key] = max(due + period, self.now + 0.5 * period)
        return out

    def add_link(self, link: int) -> None:
        """Make ``link`` known so its default streams start before the peer says anything."""
        self.links.setdefault(link, LinkInfo())

    # ----------------------------------------------------------------- flight control
    def flight_command(self, now: float) -> tuple[bool, Setpoint]:
        """What the vehicle's controller should do now: (motors armed, setpoint); an altitude to hold
        is the estimate's, so the vehicle truly holds it less :meth:`altitude_bias`."""
        armed, setpoint = self._flight_command(now)
        bias = self.altitude_bias()
        if bias and setpoint.altitude is not None:
            setpoint = dataclasses.replace(setpoint, altitude=setpoint.altitude - bias)
        return armed, setpoint

    def _flight_command(self, now: float) -> tuple[bool, Setpoint]:
        self.now = now
        s = self.snap
        if not self.armed or self.guidance == Guidance.IDLE:
            return self.armed, Setpoint(vx=0.0, vy=0.0, vz=0.0, yaw_rate=0.0)
        if self.guidance == Guidance.TAKEOFF:
            vx, vy = self._toward(self.hold_position)
            return True, _setpoint(vx=vx, vy=vy, altitude=self.takeoff_altitude, yaw=self.hold_yaw)
        if self.guidance == Guidance.HOLD:
            vx, vy = self._toward(self.hold_position)
            return True, _setpoint(vx=vx, vy=vy, altitude=float(self.hold_position[2]), yaw=self.hold_yaw)
        if self.guidance == Guidance.LAND:
            vx, vy = self._toward(self.hold_position)
            speed = self.param("LAND_SPEED", 50.0) / 100.0
            return True, _setpoint(vx=vx, vy=vy, vz=-abs(speed), yaw=self.hold_yaw)
        if self.guidance == Guidance.RTL:
            if self._rtl_landing():
                vx, vy = self._toward(self.home)
                return True, _setpoint(vx=vx, vy=vy, vz=-0.5, yaw=self.hold_yaw)
            vx, vy = self._toward(self.home, gain=HOLD_GAIN, vmax=RTL_SPEED)
            return True, _setpoint(vx=vx, vy=vy, altitude=float(self.hold_position[2]), yaw=self.hold_yaw)
        target = self.target
        assert target is not None
        yaw_kw: dict[str, float]
        if target.yaw_rate is not None:
            yaw_kw = {"yaw_rate": target.yaw_rate}
            self.hold_yaw = s.yaw
        elif target.yaw is not None:
            yaw_kw = {"yaw": target.yaw}
        else:
            yaw_kw = {"yaw": self.hold_yaw}
        if self.guidance == Guidance.POSITION:
            assert target.position is not None
            vx, vy = self._toward(target.position, vmax=2.0)
            if target.velocity is not None:
                vx, vy = vx + target.velocity[0], vy + target.velocity[1]
            return True, _setpoint(vx=vx, vy=vy, altitude=float(target.position[2]), **yaw_kw)
        assert target.velocity is not None
        vx, vy = self.limit_velocity(float(target.velocity[0]), float(target.velocity[1]))
        vertical: dict[str, float]
        if self.target_altitude is not None:
            vertical = {"altitude": self.target_altitude}
        elif target.vz_used:
            vertical = {"vz": float(target.velocity[2])}
        else:
            vertical = {"altitude": float(self.hold_position[2])}
        if self.response is not None:
            return True, self._respond(vx, vy, target, yaw_kw, vertical)
        return True, _setpoint(vx=vx, vy=vy, **vertical, **yaw_kw)

    def _respond(
        self, vx: float, vy: float, target: ExternalTarget, yaw_kw: dict[str, float],
        vertical: dict[str, float],
    ) -> Setpoint:  # fmt: skip
        """Velocity control through the firmware's response; called once per physics chunk.

        Each new target (a setpoint message, or a change the avoidance hook makes to it) reaches the
        response once, as a message reaches the firmware's position controller.
        """
        assert self.response is not None
        rate = target.yaw_rate if target.yaw_rate is not None else 0.0
        received = (target.time, vx, vy, rate)
        if received != self._response_input:
            self._response_input = received
            self.response.command_world(vx, vy, rate)
        setpoint = self.response.setpoint(self.snap, CHUNK_S, **vertical)
        if target.yaw_rate is None:  # an absolute or held heading: the ideal heading hold flies it
            setpoint = dataclasses.replace(setpoint, yaw_rate=None, **yaw_kw)
        return setpoint

    def reported_velocity(self) -> np.ndarray:
        """(3,) world ENU velocity as this autopilot's estimator reports it (truth + the estimate error)."""
        v = self.snap.velocity.copy()
        if self.response is not None:
            v[:2] += self.response.estimate_error
        return v

    def limit_velocity(self, vx: float, vy: float) -> tuple[float, float]:
        """Hook for the firmware's own obstacle avoidance (ENU horizontal velocity in and out)."""
        return vx, vy

    def _toward(
        self, point: np.ndarray, gain: float = HOLD_GAIN, vmax: float = HOLD_SPEED_MAX
    ) -> tuple[float, float]:
        err = (point[:2] - self.snap.position[:2]) * gain
        norm = float(np.linalg.norm(err))
        if norm > vmax:
            err = err * (vmax / norm)
        return float(err[0]), float(err[1])

    # ----------------------------------------------------------------- telemetry
    def build(self, name: str) -> Any:
        """Build one telemetry message from the current state
        (:mod:`flightsim.sitl.sim_autopilot.telemetry`)."""
        return telemetry_message(self, name)

    def vtol_state(self) -> int:
        return mavlink.MAV_VTOL_STATE_UNDEFINED

    def flight_sw_version(self) -> int:
        return 0
