"""ArduPilot Copter over raw MAVLink 2 (pymavlink): GUIDED velocity setpoints and the vehicle's status.

What goes out: SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_BODY_OFFSET_NED with only velocity and
yaw rate enabled (type mask 0x05C7), OBSTACLE_DISTANCE for ArduPilot's own proximity avoidance,
the companion's HEARTBEAT and STATUSTEXT. What comes in: HEARTBEAT (armed, mode),
EXTENDED_SYS_STATE (landed state), GLOBAL_POSITION_INT / LOCAL_POSITION_NED (altitude above home),
LOCAL_POSITION_NED + ATTITUDE (the measured velocity, turned into the body frame by the heading)
and VFR_HUD (climb rate); the link asks for those streams with MAV_CMD_SET_MESSAGE_INTERVAL because
ArduPilot's default SRx_ rates may be zero on a companion port.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from companion.autopilot.link import LandedState, VehicleStatus, body_velocity
from companion.autopilot.mavlink_adapter import MavlinkEndpoint, mavlink, mode_name
from companion.autopilot.obstacle_distance import sector_distances

log = logging.getLogger(__name__)

#: SET_POSITION_TARGET type mask: ignore position (bits 0-2), acceleration (6-8) and yaw (10);
#: use velocity and yaw rate.
VELOCITY_YAW_RATE_TYPE_MASK = 0x05C7
#: ArduCopter custom_mode number of GUIDED.
COPTER_GUIDED = 4
#: OBSTACLE_DISTANCE sector width, degrees (72 sectors cover the circle).
SECTOR_INCREMENT_DEG = 5
#: Messages the supervisor needs, requested at ``stream_rate_hz``.
STATUS_STREAMS = ("EXTENDED_SYS_STATE", "GLOBAL_POSITION_INT", "LOCAL_POSITION_NED", "VFR_HUD", "ATTITUDE")
#: A position source older than this no longer counts as current, seconds.
POSITION_FRESH_S = 2.0
#: A heading older than this does not turn a velocity into the body frame, seconds.
ATTITUDE_FRESH_S = 0.5
#: STATUSTEXT carries 50 bytes per message; longer texts are chunked, up to this many chunks.
STATUSTEXT_CHUNK = 50
STATUSTEXT_MAX_CHUNKS = 4


def statustext_chunks(text: str) -> list[tuple[bytes, int, int]]:
    """Split ``text`` into STATUSTEXT ``(text, id_needed, chunk_seq)`` pieces (MAVLink 2 chunking).

    ``id_needed`` is 0 for a text that fits one message (no chunk id), else 1. A last chunk of
    exactly 50 bytes is followed by an empty one, because receivers only stop at a NUL.
    """
    data = text.encode("utf-8")[: STATUSTEXT_CHUNK * STATUSTEXT_MAX_CHUNKS]
    if len(data) <= STATUSTEXT_CHUNK:
        return [(data, 0, 0)]
    pieces = [data[i : i + STATUSTEXT_CHUNK] for i in range(0, len(data), STATUSTEXT_CHUNK)]
    if len(pieces[-1]) == STATUSTEXT_CHUNK:
        pieces.append(b"")
    return [(p, 1, seq) for seq, p in enumerate(pieces)]


class ArduPilotLink:
    """The :class:`~companion.autopilot.link.AutopilotLink` for ArduPilot Copter in GUIDED.

    The link listens to one autopilot only, the configured ``autopilot`` (system, component): its
    HEARTBEATs set the status, every command is addressed to it and (on ``udpin``) every reply goes
    to its address. Heartbeats from anyone else, whoever came first, are counted in
    ``foreign_heartbeats`` and ignored; so are their other messages. COMMAND_ACKs addressed to
    another system or component (a ground station's) are not the companion's and are not counted.

    :param connect: pymavlink connection string (``udpin:0.0.0.0:14550``, ``tcp:127.0.0.1:5760``,
        ``/dev/ttyTHS1``)
    :param baud: serial baud rate
    :param clock: monotonic clock, seconds (injected so tests and the supervisor share one)
    :param source_system: system id the companion sends as (normally the vehicle's own)
    :param source_component: component id (191 = MAV_COMP_ID_ONBOARD_COMPUTER)
    :param autopilot: (system id, component id) of the autopilot to talk to
    :param signing_key: MAVLink 2 signing secret (32 bytes): sign everything sent, drop every
        unsigned or badly signed frame received; None = no signing
    :param stream_rate_hz: rate asked for each status stream
    :param min_distance_cm: OBSTACLE_DISTANCE ``min_distance``
    :param max_distance_cm: OBSTACLE_DISTANCE ``max_distance`` (a sector with no return holds this + 1)
    """

    def __init__(
        self,
        connect: str,
        baud: int = 921600,
        clock: Callable[[], float] = time.monotonic,
        source_system: int = 1,
        source_component: int = 191,
        autopilot: tuple[int, int] = (1, 1),
        signing_key: bytes | None = None,
        stream_rate_hz: float = 10.0,
        min_distance_cm: int = 10,
        max_distance_cm: int = 1000,
    ) -> None:
        self._endpoint = MavlinkEndpoint(connect, baud, source_system, source_component, autopilot,
                                         signing_key)
        self._autopilot = autopilot
        self._own_ids = (source_system, source_component)
        self._clock = clock
        self._start = clock()
        self._stream_interval_us = round(1e6 / stream_rate_hz)
        self._min_cm = min_distance_cm
        self._max_cm = max_distance_cm
        self._target: tuple[int, int] | None = None
        self._status = VehicleStatus()
        self._last_seen: dict[str, float] = {}
        self._yaw_ned = math.nan
        self._last_stream_request = -math.inf
        self._statustext_id = 0
        self._streams: tuple[str, ...] = STATUS_STREAMS
        self._listeners: list[Callable[[Any], None]] = []
        self.counters: dict[str, int] = {
            "received": 0,
            "bad_data": 0,
            "unknown_messages": 0,
            "read_errors": 0,
            "foreign_heartbeats": 0,
            "signature_rejected": 0,
            "acks_for_others": 0,
            "setpoints_sent": 0,
            "setpoints_without_target": 0,
            "obstacle_distance_sent": 0,
            "heartbeats_sent": 0,
            "statustext_sent": 0,
            "stream_requests": 0,
            "command_nacks": 0,
            "send_errors": 0,
            "mission_messages_sent": 0,
        }

    # ---- receiving -------------------------------------------------------------------------

    def fileno(self) -> int | None:
        """File descriptor of the connection, for ``select()``."""
        return self._endpoint.fileno()

    @property
    def target(self) -> tuple[int, int] | None:
        """(system id, component id) of the autopilot, once its heartbeat has been heard."""
        return self._target

    def poll(self) -> VehicleStatus:
        """Read whatever is waiting (never blocks), keep the status streams asked for, return the status."""
        for msg in self._endpoint.receive():
            self.counters["received"] += 1
            self._handle(msg)
        self.counters["bad_data"] = self._endpoint.bad_data
        self.counters["unknown_messages"] = self._endpoint.unknown
        self.counters["read_errors"] = self._endpoint.read_errors
        self.counters["signature_rejected"] = self._endpoint.signature_rejected
        self._request_missing_streams()
        return dataclasses.replace(self._status)

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if kind == "HEARTBEAT":
            self._on_heartbeat(msg, src)
            return
        if src != self._target:
            return
        now = self._clock()
        self._last_seen[kind] = now
        for listener in self._listeners:
            listener(msg)
        if kind == "EXTENDED_SYS_STATE":
            try:
                self._status.landed_state = LandedState(msg.landed_state)
            except ValueError:
                self._status.landed_state = None
        elif kind == "GLOBAL_POSITION_INT":
            self._status.altitude = msg.relative_alt / 1000.0
            if not self._fresh("VFR_HUD", now):
                self._status.climb_rate = -msg.vz / 100.0
        elif kind == "LOCAL_POSITION_NED":
            # Without GPS (indoors) GLOBAL_POSITION_INT may be absent; the EKF origin is then home.
            if not self._fresh("GLOBAL_POSITION_INT", now):
                self._status.altitude = -float(msg.z)
            if not self._fresh("VFR_HUD", now):
                self._status.climb_rate = -float(msg.vz)
            self._on_velocity(float(msg.vx), float(msg.vy), now)
        elif kind == "ATTITUDE":
            self._yaw_ned = float(msg.yaw)
        elif kind == "VFR_HUD":
            # VFR_HUD.alt may be above sea level depending on firmware; only its climb rate is used.
            self._status.climb_rate = float(msg.climb)
        elif kind == "COMMAND_ACK":
            self._on_command_ack(msg)

    def _on_command_ack(self, msg: Any) -> None:
        """Count the autopilot's refusals of the companion's own commands (not a ground station's)."""
        if (msg.target_system, msg.target_component) != self._own_ids:
            self.counters["acks_for_others"] += 1
            return
        if msg.result != mavlink.MAV_RESULT_ACCEPTED:
            self.counters["command_nacks"] += 1
            log.debug("command %d refused by the autopilot: result %d", msg.command, msg.result)

    def _on_velocity(self, v_north: float, v_east: float, now: float) -> None:
        """LOCAL_POSITION_NED's velocity into the body frame, if the heading is current."""
        if now - self._last_seen.get("ATTITUDE", -math.inf) > ATTITUDE_FRESH_S:
            return
        body = body_velocity(v_north, v_east, self._yaw_ned)
        if body is not None:
            self._status.velocity_body = body
            self._status.velocity_time = now

    def _fresh(self, kind: str, now: float) -> bool:
        return now - self._last_seen.get(kind, -math.inf) < POSITION_FRESH_S

    def _on_heartbeat(self, msg: Any, src: tuple[int, int]) -> None:
        if src != self._autopilot or msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID or msg.type in (
            mavlink.MAV_TYPE_GCS,
            mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
            mavlink.MAV_TYPE_GIMBAL,
            mavlink.MAV_TYPE_ADSB,
        ):
            # ground stations, other companions, peripherals, other vehicles, impostors
            self.counters["foreign_heartbeats"] += 1
            return
        if self._target is None:
            self._target = src
            log.info("autopilot found: system %d component %d (%s)", src[0], src[1], mode_name(msg))
            self._last_stream_request = -math.inf
        status = self._status
        status.heartbeat_time = self._clock()
        status.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        status.mode = mode_name(msg)
        status.guided = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED) and (
            msg.custom_mode == COPTER_GUIDED and status.mode == "GUIDED"
        )

    def _request_missing_streams(self) -> None:
        """Ask for each status stream not seen lately (at start, and again after an autopilot reboot)."""
        if self._target is None:
            return
        now = self._clock()
        if now - self._last_stream_request < 5.0:
            return
        self._last_stream_request = now
        for name in self._streams:
            if now - self._last_seen.get(name, -math.inf) < 5.0:
                continue
            msg_id = getattr(mavlink, f"MAVLINK_MSG_ID_{name}")
            self._send(
                "stream_requests",
                self._endpoint.mav.command_long_send,
                *self._target,
                mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                0,
                msg_id,
                self._stream_interval_us,
                0, 0, 0, 0, 0,
            )

    def add_message_listener(self, listener: Callable[[Any], None], streams: tuple[str, ...] = ()) -> None:
        """Call ``listener`` with every message from the autopilot; also keep ``streams`` requested."""
        self._listeners.append(listener)
        self._streams = tuple(dict.fromkeys(self._streams + streams))

    # ---- sending ---------------------------------------------------------------------------

    def send_message(self, msg: Any) -> None:
        """Send a pymavlink message built by the caller (the mission protocol's requests)."""
        if self._target is None:
            return
        self._send("mission_messages_sent", self._endpoint.mav.send, msg)

    def _send(self, counter: str, send: Callable[..., None], *args: Any) -> bool:
        try:
            send(*args)
        except (OSError, ValueError) as exc:  # a vanished serial port, an unencodable value
            self.counters["send_errors"] += 1
            log.debug("MAVLink send failed: %s", exc)
            return False
        self.counters[counter] += 1
        return True

    def send_velocity(self, forward: float, yaw_rate: float, lateral: float = 0.0,
                      vertical: float = 0.0) -> None:
        """Send one body-frame velocity + yaw-rate setpoint to the autopilot.

        :param forward: body x velocity, m/s
        :param yaw_rate: rad/s, FLU (counter-clockwise positive); sent negated, as FRD
        :param lateral: body y velocity, m/s, left positive; sent negated, as FRD
        :param vertical: climb rate, m/s, up positive; sent negated as vz (BODY_OFFSET_NED is
            down-positive)
        """
        if self._target is None:
            self.counters["setpoints_without_target"] += 1
            return
        if not all(math.isfinite(v) for v in (forward, yaw_rate, lateral, vertical)):
            forward, yaw_rate, lateral, vertical = 0.0, 0.0, 0.0, 0.0  # the shield never lets this through
        time_boot_ms = int((self._clock() - self._start) * 1000) & 0xFFFFFFFF
        self._send(
            "setpoints_sent",
            self._endpoint.mav.set_position_target_local_ned_send,
            time_boot_ms,
            *self._target,
            mavlink.MAV_FRAME_BODY_OFFSET_NED,
            VELOCITY_YAW_RATE_TYPE_MASK,
            0.0, 0.0, 0.0,
            float(forward), -float(lateral), -float(vertical),
            0.0, 0.0, 0.0,
            0.0,
            -float(yaw_rate),
        )

    def send_obstacle_distance(self, sectors_cm: np.ndarray) -> None:
        """Send OBSTACLE_DISTANCE: 72 sectors of 5°, sector j at j × 5° clockwise from forward (FRD).

        :param sectors_cm: ``(72,)`` uint16 centimetres (no return = ``max_distance_cm + 1``)
        """
        distances = sector_distances(sectors_cm)
        self._send(
            "obstacle_distance_sent",
            self._endpoint.mav.obstacle_distance_send,
            int(self._clock() * 1e6),
            mavlink.MAV_DISTANCE_SENSOR_LASER,
            distances,
            SECTOR_INCREMENT_DEG,
            self._min_cm,
            self._max_cm,
            0.0,
            0.0,
            mavlink.MAV_FRAME_BODY_FRD,
        )

    def send_heartbeat(self) -> None:
        """Send the companion's HEARTBEAT (MAV_TYPE_ONBOARD_CONTROLLER, no autopilot)."""
        self._send(
            "heartbeats_sent",
            self._endpoint.mav.heartbeat_send,
            mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
            mavlink.MAV_AUTOPILOT_INVALID,
            0,
            0,
            mavlink.MAV_STATE_ACTIVE,
        )

    def send_statustext(self, text: str, severity: int) -> None:
        """Send ``text`` as STATUSTEXT (chunked past 50 bytes) so the pilot's GCS shows it.

        :param severity: MAV_SEVERITY (0 emergency … 7 debug)
        """
        chunks = statustext_chunks(text)
        chunk_id = 0
        if len(chunks) > 1:
            self._statustext_id = self._statustext_id % 0xFFFF + 1
            chunk_id = self._statustext_id
        for data, needs_id, seq in chunks:
            self._send(
                "statustext_sent",
                self._endpoint.mav.statustext_send,
                severity,
                data,
                chunk_id if needs_id else 0,
                seq,
            )

    def close(self) -> None:
        """Close the connection."""
        self._endpoint.close()
