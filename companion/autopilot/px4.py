"""PX4 through MAVSDK (the native ``mavsdk`` ≥ 4 binding): OFFBOARD velocity setpoints and telemetry.

MAVSDK runs its own I/O thread. The link configures it as a companion computer with component id
191, so MAVSDK's own 1 Hz HEARTBEAT is already MAV_TYPE_ONBOARD_CONTROLLER (``send_heartbeat`` has
nothing to add). Setpoints go through the Offboard plugin as VelocityBodyYawspeed (MAVSDK sends
SET_POSITION_TARGET_LOCAL_NED, MAV_FRAME_BODY_NED, type mask 0x05C7). Armed state, flight mode,
landed state, altitude, climb rate and the measured velocity (NED velocity turned into the body
frame by the attitude's yaw) come from the Telemetry plugin; the autopilot's HEARTBEAT
time, OBSTACLE_DISTANCE and STATUSTEXT go through the MavlinkDirect plugin.

The companion never starts OFFBOARD itself: the pilot switches to it, which PX4 only accepts while
setpoints are already streaming. MAVSDK's Offboard plugin repeats the last setpoint at 20 Hz on
its own thread for as long as the vehicle stays in OFFBOARD; that would hide a stalled companion
from PX4's offboard-loss failsafe (COM_OF_LOSS_T), so this link stops the repetition whenever no
fresh setpoint arrived within ``setpoint_timeout``.

MAVSDK's bytes travel through :class:`~companion.autopilot.px4_transport.RawMavlinkTransport`
(the companion's own endpoint): MAVSDK's ``udpin://`` would answer every address it has heard,
and MAVSDK cannot sign. The transport replies to the autopilot's address only, passes MAVSDK only
the autopilot system's frames, and signs and checks signatures when a key is given.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from mavsdk import (
    ComponentType,
    Configuration,
    ConnectionResult,
    LogLevel,
    Mavsdk,
    MavsdkError,
    log_subscribe,
)
from mavsdk.plugins.mavlink_direct.mavlink_direct import MavlinkDirect, MavlinkMessage
from mavsdk.plugins.offboard.offboard import Offboard, VelocityBodyYawspeed
from mavsdk.plugins.telemetry.telemetry import FlightMode, Telemetry

from companion.autopilot.ardupilot import SECTOR_INCREMENT_DEG, statustext_chunks
from companion.autopilot.link import LandedState, VehicleStatus, body_velocity
from companion.autopilot.mavlink_adapter import mavlink
from companion.autopilot.obstacle_distance import sector_distances
from companion.autopilot.px4_transport import RawMavlinkTransport
from companion.common.errors import UserError

log = logging.getLogger(__name__)

_MAV_TYPE_ONBOARD_CONTROLLER = 18
_MAV_DISTANCE_SENSOR_LASER = 0
_MAV_FRAME_BODY_FRD = 12
#: A position source older than this no longer counts as current, seconds.
_POSITION_FRESH_S = 2.0
#: A heading older than this does not turn a velocity into the body frame, seconds.
_ATTITUDE_FRESH_S = 0.5

_MAVSDK_LOG_LEVELS = {
    LogLevel.DEBUG: logging.DEBUG,
    LogLevel.INFO: logging.DEBUG,  # MAVSDK's INFO is chatty (every component discovered)
    LogLevel.WARN: logging.WARNING,
    LogLevel.ERROR: logging.ERROR,
}
_mavsdk_log = logging.getLogger("mavsdk")


#: MAVSDK's warning when the raw connection's reader subscribes before the connection exists,
#: which :class:`Px4Link` does on purpose (see :class:`RawMavlinkTransport`): not worth a warning
_EXPECTED_AT_START = "No raw connection available"


def _forward_mavsdk_log(level: LogLevel, message: str, file: str | None, line: int) -> bool:
    python_level = _MAVSDK_LOG_LEVELS.get(level, logging.INFO)
    if message.startswith(_EXPECTED_AT_START):
        python_level = logging.DEBUG
    _mavsdk_log.log(python_level, "%s", message)
    return True  # handled: MAVSDK prints nothing itself


class Px4Link:
    """The :class:`~companion.autopilot.link.AutopilotLink` for PX4 in OFFBOARD, over MAVSDK.

    The constructor only opens the connection; the autopilot is picked up by :meth:`poll` once
    MAVSDK has heard its heartbeat, so start-up never waits for the vehicle.

    :param connect: MAVSDK connection URL (``udpin://0.0.0.0:14540``, ``serial:///dev/ttyTHS1:921600``)
    :param clock: monotonic clock, seconds (heartbeat times are on it)
    :param source_system: MAVLink system id the companion sends as
    :param source_component: component id (191 = MAV_COMP_ID_ONBOARD_COMPUTER)
    :param autopilot: (system id, component id) of the autopilot: other systems' frames are
        counted (``foreign_messages``) and never reach MAVSDK, whichever was heard first
    :param signing_key: MAVLink 2 signing secret (32 bytes): MAVSDK's frames are signed on their
        way out and unsigned or badly signed frames never reach MAVSDK; None = no signing
    :param stream_rate_hz: rate asked for position, velocity and landed-state telemetry
    :param min_distance_cm: OBSTACLE_DISTANCE ``min_distance``
    :param max_distance_cm: OBSTACLE_DISTANCE ``max_distance``
    :param setpoint_timeout: MAVSDK may repeat a setpoint for at most this long after the last
        :meth:`send_velocity`, seconds
    """

    #: PX4 accepts a switch to OFFBOARD only while setpoints stream: the application streams zero
    #: setpoints while the vehicle is armed and the supervisor is ready, so the pilot can switch.
    setpoints_before_offboard = True

    def __init__(
        self,
        connect: str,
        clock: Callable[[], float] = time.monotonic,
        source_system: int = 1,
        source_component: int = 191,
        autopilot: tuple[int, int] = (1, 1),
        signing_key: bytes | None = None,
        stream_rate_hz: float = 10.0,
        min_distance_cm: int = 10,
        max_distance_cm: int = 1000,
        setpoint_timeout: float = 0.3,
    ) -> None:
        log_subscribe(_forward_mavsdk_log)
        self._clock = clock
        self._autopilot = autopilot
        self._next_discovery = -math.inf
        self._stream_rate_hz = stream_rate_hz
        self._min_cm = min_distance_cm
        self._max_cm = max_distance_cm
        self._setpoint_timeout = setpoint_timeout
        self.counters: dict[str, int] = {
            "heartbeats_received": 0,
            "setpoints_sent": 0,
            "setpoints_without_autopilot": 0,
            "setpoint_repeat_stopped": 0,
            "obstacle_distance_sent": 0,
            "statustext_sent": 0,
            "messages_without_autopilot": 0,
            "send_errors": 0,
            "stream_rate_refused": 0,
            "foreign_heartbeats": 0,
        }
        configuration = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
        configuration.system_id = source_system
        configuration.component_id = source_component
        self._configuration = configuration  # kept alive as long as MAVSDK runs
        self._mavsdk = Mavsdk(configuration)
        # MAVSDK gets its bytes through the companion's own endpoint (one autopilot, one address,
        # signing), not through a socket of its own: see companion.autopilot.px4_transport. The
        # transport listens before the raw connection exists: MAVSDK sends a heartbeat at once.
        try:
            self._transport = RawMavlinkTransport(self._mavsdk, connect, autopilot, source_system,
                                                  source_component, signing_key)
        except BaseException:
            self._mavsdk.destroy()
            raise
        result = self._mavsdk.add_any_connection("raw://")
        if result != ConnectionResult.SUCCESS:
            self._mavsdk.destroy()
            self._transport.close()
            raise UserError(f"autopilot.connect: MAVSDK refused its raw connection: {result.name}")
        self._transport.start_reading()
        self.connect = connect

        # Two locks, so MAVSDK's callback thread (status) never waits on a plugin teardown (offboard).
        self._status_lock = threading.Lock()
        self._offboard_lock = threading.Lock()
        self._system: Any = None
        self._telemetry: Telemetry | None = None
        self._direct: MavlinkDirect | None = None
        self._offboard: Offboard | None = None
        self._last_setpoint = -math.inf
        self._status = VehicleStatus()
        self._seen: dict[str, float] = {}
        self._yaw_ned = math.nan
        self._statustext_id = 0
        self._extra_streams: tuple[str, ...] = ()

        self._stop = threading.Event()
        self._guard = threading.Thread(target=self._guard_setpoint_repeat, name="px4-setpoint-guard",
                                       daemon=True)
        self._guard.start()

    # ---- discovery and telemetry (callbacks run on MAVSDK's thread) -------------------------

    def _discover(self) -> None:
        """Set up the configured autopilot once MAVSDK knows it (main thread, checked at 2 Hz).

        Not ``first_autopilot``: that takes whichever autopilot spoke first. (The transport passes
        MAVSDK only the autopilot system's frames, so no other system should appear at all.)
        """
        now = self._clock()
        if now < self._next_discovery:
            return
        self._next_discovery = now + 0.5
        for system in self._mavsdk.get_systems():
            wanted = system.get_system_id() == self._autopilot[0] and system.has_autopilot()
            if self._system is None and wanted:
                self._set_up(system)
            else:
                system.destroy()  # only this wrapper; MAVSDK keeps its own record of the system

    def _set_up(self, system: Any) -> None:
        """Create the plugins and subscriptions for the autopilot MAVSDK found (main thread)."""
        self._system = system
        log.info("PX4 autopilot found: system %d", system.get_system_id())
        telemetry = Telemetry(system)
        telemetry.subscribe_armed(self._on_armed)
        telemetry.subscribe_flight_mode(self._on_flight_mode)
        telemetry.subscribe_landed_state(self._on_landed_state)
        telemetry.subscribe_position(self._on_position)
        telemetry.subscribe_velocity_ned(self._on_velocity)
        telemetry.subscribe_position_velocity_ned(self._on_local_position)
        telemetry.subscribe_attitude_euler(self._on_attitude)
        for name in ("position", "velocity_ned", "landed_state", "position_velocity_ned", "attitude_euler"):
            getattr(telemetry, f"set_rate_{name}_async")(self._stream_rate_hz, self._on_rate_result)
        direct = MavlinkDirect(system)
        direct.subscribe_message("HEARTBEAT", self._on_heartbeat)
        self._telemetry, self._direct = telemetry, direct
        self._request_extra_streams()

    def _on_rate_result(self, result: Any, _user_data: Any) -> None:
        if result.name != "SUCCESS":
            with self._status_lock:
                self.counters["stream_rate_refused"] += 1
            log.debug("PX4 refused a telemetry rate: %s", result.name)

    def _on_heartbeat(self, message: MavlinkMessage, _user_data: Any) -> None:
        if (message.system_id, message.component_id) != self._autopilot:
            with self._status_lock:
                self.counters["foreign_heartbeats"] += 1
            return
        now = self._clock()
        with self._status_lock:
            self._status.heartbeat_time = now
            self.counters["heartbeats_received"] += 1

    def _on_armed(self, armed: bool, _user_data: Any) -> None:
        with self._status_lock:
            self._status.armed = bool(armed)

    def _on_flight_mode(self, mode: FlightMode, _user_data: Any) -> None:
        with self._status_lock:
            self._status.mode = mode.name
            self._status.guided = mode == FlightMode.OFFBOARD

    def _on_landed_state(self, state: Any, _user_data: Any) -> None:
        with self._status_lock:
            # MAVSDK says UNKNOWN until EXTENDED_SYS_STATE arrives: "not reported", not a state.
            self._status.landed_state = LandedState(int(state)) if int(state) else None

    def _on_position(self, position: Any, _user_data: Any) -> None:
        if not math.isfinite(position.relative_altitude_m):
            return
        with self._status_lock:
            self._seen["position"] = self._clock()
            self._status.altitude = float(position.relative_altitude_m)

    def _on_velocity(self, velocity: Any, _user_data: Any) -> None:
        if not math.isfinite(velocity.down_m_s):
            return
        with self._status_lock:
            self._seen["velocity"] = self._clock()
            self._status.climb_rate = -float(velocity.down_m_s)

    def _on_attitude(self, euler: Any, _user_data: Any) -> None:
        if not math.isfinite(euler.yaw_deg):
            return
        with self._status_lock:
            self._seen["attitude"] = self._clock()
            self._yaw_ned = math.radians(float(euler.yaw_deg))

    def _on_local_position(self, pv: Any, _user_data: Any) -> None:
        """LOCAL_POSITION_NED: the measured velocity, and the altitude source when there is no
        global position (indoors)."""
        now = self._clock()
        with self._status_lock:
            if now - self._seen.get("attitude", -math.inf) <= _ATTITUDE_FRESH_S:
                body = body_velocity(pv.velocity.north_m_s, pv.velocity.east_m_s, self._yaw_ned)
                if body is not None:
                    self._status.velocity_body = body
                    self._status.velocity_time = now
            if now - self._seen.get("position", -math.inf) >= _POSITION_FRESH_S and math.isfinite(
                pv.position.down_m
            ):
                self._status.altitude = -float(pv.position.down_m)
            if now - self._seen.get("velocity", -math.inf) >= _POSITION_FRESH_S and math.isfinite(
                pv.velocity.down_m_s
            ):
                self._status.climb_rate = -float(pv.velocity.down_m_s)

    # ---- AutopilotLink ---------------------------------------------------------------------

    def fileno(self) -> int | None:
        """None: MAVSDK owns its sockets; the application polls this link on a timer."""
        return None

    @property
    def connected(self) -> bool:
        """True once MAVSDK has found the autopilot and the plugins are set up."""
        return self._system is not None

    def poll(self) -> VehicleStatus:
        """Set the plugins up once the autopilot has been found; return the latest status."""
        if self._system is None:
            self._discover()
        self.counters.update(self._transport.endpoint_counters)
        self.counters["foreign_messages"] = self._transport.counters["foreign_messages"]
        self.counters["unsignable_frames"] = self._transport.counters["unsignable_frames"]
        with self._status_lock:
            return dataclasses.replace(self._status)

    def send_velocity(self, forward: float, yaw_rate: float, lateral: float = 0.0,
                      vertical: float = 0.0) -> None:
        """Send one OFFBOARD body-frame setpoint.

        :param forward: body x velocity, m/s
        :param yaw_rate: rad/s, FLU (counter-clockwise positive); sent as FRD yaw speed in deg/s
        :param lateral: body y velocity, m/s, left positive; sent as right_m_s
        :param vertical: climb rate, m/s, up positive; sent as down_m_s (negated)
        """
        if self._system is None:
            self.counters["setpoints_without_autopilot"] += 1
            return
        if not all(math.isfinite(v) for v in (forward, yaw_rate, lateral, vertical)):
            forward, yaw_rate, lateral, vertical = 0.0, 0.0, 0.0, 0.0
        setpoint = VelocityBodyYawspeed(float(forward), -float(lateral), -float(vertical),
                                        -math.degrees(yaw_rate))
        with self._offboard_lock:
            if self._offboard is None:
                self._offboard = Offboard(self._system)
            try:
                self._offboard.set_velocity_body(setpoint)
            except MavsdkError as exc:
                self.counters["send_errors"] += 1
                log.debug("offboard setpoint failed: %s", exc)
                return
            self._last_setpoint = self._clock()
            self.counters["setpoints_sent"] += 1

    def _guard_setpoint_repeat(self) -> None:
        """Stop MAVSDK repeating a setpoint the companion no longer sends (guard thread)."""
        while not self._stop.wait(0.02):
            with self._offboard_lock:
                if self._offboard is None or self._clock() - self._last_setpoint <= self._setpoint_timeout:
                    continue
                # Destroying the plugin is the one way to end MAVSDK's repetition without a mode
                # change (Offboard.stop() would switch the vehicle to HOLD: the pilot's call).
                self._offboard.destroy()
                self._offboard = None
                self.counters["setpoint_repeat_stopped"] += 1
            log.debug("no setpoint for %.2f s: MAVSDK's setpoint repetition stopped", self._setpoint_timeout)

    def _send_direct(self, counter: str, name: str, fields: dict[str, Any]) -> None:
        if self._direct is None:
            self.counters["messages_without_autopilot"] += 1
            return
        try:
            self._direct.send_message(MavlinkMessage(name, 0, 0, 0, 0, json.dumps(fields)))
        except MavsdkError as exc:
            self.counters["send_errors"] += 1
            log.debug("%s not sent: %s", name, exc)
            return
        self.counters[counter] += 1

    def send_obstacle_distance(self, sectors_cm: np.ndarray) -> None:
        """Send OBSTACLE_DISTANCE: 72 sectors of 5°, sector j at j × 5° clockwise (MAV_FRAME_BODY_FRD).

        :param sectors_cm: ``(72,)`` uint16 centimetres (no return = ``max_distance_cm + 1``)
        """
        distances = sector_distances(sectors_cm)
        self._send_direct(
            "obstacle_distance_sent",
            "OBSTACLE_DISTANCE",
            {
                "time_usec": int(self._clock() * 1e6),
                "sensor_type": _MAV_DISTANCE_SENSOR_LASER,
                "distances": distances,
                "increment": SECTOR_INCREMENT_DEG,
                "min_distance": self._min_cm,
                "max_distance": self._max_cm,
                "increment_f": 0.0,
                "angle_offset": 0.0,
                "frame": _MAV_FRAME_BODY_FRD,
            },
        )

    def add_message_listener(self, listener: Callable[[Any], None], streams: tuple[str, ...] = ()) -> None:
        """Call ``listener`` (from the reader thread) with every message from the autopilot.

        ``streams`` are asked for with MAV_CMD_SET_MESSAGE_INTERVAL once the autopilot is found.
        The mission protocol goes this way rather than through MAVSDK's MissionRaw: one download
        state machine for both firmwares, with MISSION_CURRENT's plan id seen on the same stream.
        """
        autopilot = self._autopilot

        def from_autopilot(msg: Any) -> None:
            if (msg.get_srcSystem(), msg.get_srcComponent()) == autopilot:
                listener(msg)

        self._transport.listeners.append(from_autopilot)
        self._extra_streams = tuple(dict.fromkeys(self._extra_streams + streams))

    def send_message(self, msg: Any) -> None:
        """Send a pymavlink message of the companion's own (the mission protocol's requests)."""
        if self._system is None:
            self.counters["messages_without_autopilot"] += 1
            return
        self._transport.send_message(msg)
        self.counters["mission_messages_sent"] = self.counters.get("mission_messages_sent", 0) + 1

    def _request_extra_streams(self) -> None:
        interval_us = round(1e6 / self._stream_rate_hz)
        for name in self._extra_streams:
            msg_id = getattr(mavlink, f"MAVLINK_MSG_ID_{name}")
            self._transport.send_message(mavlink.MAVLink_command_long_message(
                *self._autopilot, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, interval_us,
                0, 0, 0, 0, 0))

    def send_heartbeat(self) -> None:
        """Nothing to do: MAVSDK sends the companion's HEARTBEAT (ONBOARD_CONTROLLER, 1 Hz) itself."""

    def send_statustext(self, text: str, severity: int) -> None:
        """Send ``text`` as STATUSTEXT (chunked past 50 bytes) so the pilot's GCS shows it."""
        chunks = statustext_chunks(text)
        chunk_id = 0
        if len(chunks) > 1:
            self._statustext_id = self._statustext_id % 0xFFFF + 1
            chunk_id = self._statustext_id
        for data, needs_id, seq in chunks:
            self._send_direct(
                "statustext_sent",
                "STATUSTEXT",
                {
                    "severity": int(severity),
                    "text": data.decode("utf-8", errors="ignore"),
                    "id": chunk_id if needs_id else 0,
                    "chunk_seq": seq,
                },
            )

    def close(self) -> None:
        """Stop the guard thread and MAVSDK (its plugins, subscriptions and connections)."""
        self._stop.set()
        self._guard.join(timeout=1.0)
        with self._offboard_lock:
            self._offboard = None
        self._transport.stop_reading()
        self._mavsdk.destroy()
        self._transport.close()
