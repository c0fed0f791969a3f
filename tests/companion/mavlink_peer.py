"""A real pymavlink socket on loopback posing as an autopilot, for the link and process tests.

It speaks MAVLink 2 (the companion's adapter selects it before pymavlink is used) and decodes
exactly what the companion put on the wire.
"""

from __future__ import annotations

import math
import os
import select
import socket
import struct
import subprocess
import threading
import time
from typing import Any

from pymavlink import mavutil

from companion.autopilot.mavlink_adapter import mavlink
from flightsim.sitl.companion_setup import free_tcp_port as free_tcp_port  # the tests' ports, re-exported
from flightsim.sitl.companion_setup import free_udp_port as free_udp_port

COPTER_GUIDED = 4
COPTER_LOITER = 5
#: the message the companion's velocity setpoints travel in (both firmwares' GUIDED/OFFBOARD)
SETPOINT = "SET_POSITION_TARGET_LOCAL_NED"


class AutopilotPeer:
    """One end of a MAVLink link that behaves like an autopilot's telemetry port.

    :param connect: pymavlink connection string of the peer's end (``udpout:127.0.0.1:PORT``, ...)
    :param autopilot: MAV_AUTOPILOT of its heartbeats (ArduPilot by default)
    """

    def __init__(
        self,
        connect: str,
        sysid: int = 1,
        compid: int = 1,
        autopilot: int = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
    ) -> None:
        self.conn = mavutil.mavlink_connection(connect, source_system=sysid, source_component=compid)
        self.autopilot = autopilot
        self.received: list[Any] = []  # every message drained so far
        self._unclaimed: list[Any] = []  # drained but not yet returned by wait_for

    @property
    def mav(self) -> Any:
        return self.conn.mav

    def heartbeat(
        self, armed: bool = True, custom_mode: int = COPTER_GUIDED, base_mode: int | None = None
    ) -> None:
        if base_mode is None:
            base_mode = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
            if armed:
                base_mode |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        self.mav.heartbeat_send(
            mavlink.MAV_TYPE_QUADROTOR, self.autopilot, base_mode, custom_mode, mavlink.MAV_STATE_ACTIVE
        )

    def flying(
        self,
        altitude: float = 1.5,
        climb: float = 0.0,
        landed: int = mavlink.MAV_LANDED_STATE_IN_AIR,
        velocity_ned: tuple[float, float] | None = (0.0, 0.0),
        yaw_ned: float = 0.0,
        position_ned: tuple[float, float, float] | None = None,
    ) -> None:
        """One round of the status streams of a vehicle hovering at ``altitude`` (at ``position_ned``,
        default over the origin; moving at ``velocity_ned``, north and east m/s; None: no
        LOCAL_POSITION_NED and ATTITUDE, so neither position nor velocity is measured)."""
        self.mav.extended_sys_state_send(0, landed)
        if velocity_ned is not None:
            position = position_ned if position_ned is not None else (0.0, 0.0, -altitude)
            self.mav.attitude_send(0, 0.0, 0.0, yaw_ned, 0.0, 0.0, 0.0)
            self.mav.local_position_ned_send(0, *position, *velocity_ned, -climb)
        hdg = round(math.degrees(yaw_ned) * 100) % 36000  # the same heading as ATTITUDE's, centidegrees
        self.mav.global_position_int_send(0, 0, 0, int(altitude * 1000) + 100_000, int(altitude * 1000),
                                          0, 0, int(-climb * 100), hdg)
        self.mav.vfr_hud_send(0.0, 0.0, 0, 0, 100.0 + altitude, climb)

    def drain(self, duration: float = 0.0) -> list[Any]:
        """Collect every message arriving within ``duration`` seconds (at least one read pass)."""
        out: list[Any] = []
        deadline = time.monotonic() + duration
        while True:
            while True:
                msg = self.conn.recv_msg()
                if msg is None:
                    break
                if msg.get_type() != "BAD_DATA":
                    out.append(msg)
            if time.monotonic() >= deadline:
                break
            time.sleep(0.002)
        self.received.extend(out)
        self._unclaimed.extend(out)
        return out

    def wait_for(self, kind: str, timeout: float = 3.0, condition=None) -> Any:
        """The first ``kind`` message (matching ``condition``) within ``timeout`` seconds, else None."""
        deadline = time.monotonic() + timeout
        while True:
            for i, msg in enumerate(self._unclaimed):
                if msg.get_type() == kind and (condition is None or condition(msg)):
                    del self._unclaimed[: i + 1]
                    return msg
            self._unclaimed.clear()
            if time.monotonic() >= deadline:
                return None
            self.drain(0.01)

    def close(self) -> None:
        self.conn.close()


PX4_MAIN_POSCTL = 3
PX4_MAIN_OFFBOARD = 6


def px4_custom_mode(main: int, sub: int = 0) -> int:
    """PX4 packs its mode as main_mode << 16 | sub_mode << 24 in HEARTBEAT.custom_mode."""
    return (main << 16) | (sub << 24)


class SimulatedAutopilot:
    """A threaded :class:`AutopilotPeer`: heartbeat and status streams at ``rate_hz``, commands ACKed.

    Tests change ``armed``, ``custom_mode``, ``altitude``, ``climb``, ``landed`` at any time and
    read what the companion sent from :meth:`messages`. Posing as ArduPilot Copter (default) or
    PX4 (``autopilot=MAV_AUTOPILOT_PX4``; answers AUTOPILOT_VERSION requests as PX4 does).
    """

    def __init__(self, connect: str, autopilot: int = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                 rate_hz: float = 10.0, sysid: int = 1) -> None:
        import threading

        self.peer = AutopilotPeer(connect, sysid=sysid, compid=1, autopilot=autopilot)
        self.armed = True
        px4 = autopilot == mavlink.MAV_AUTOPILOT_PX4
        self.custom_mode = px4_custom_mode(PX4_MAIN_OFFBOARD) if px4 else COPTER_GUIDED
        self.altitude = 1.5
        self.climb = 0.0
        self.landed = mavlink.MAV_LANDED_STATE_IN_AIR
        #: north and east m/s streamed in LOCAL_POSITION_NED beside ATTITUDE's yaw (None: neither is sent,
        #: as when the autopilot has no position estimate)
        self.velocity_ned: tuple[float, float] | None = (0.0, 0.0)
        self.yaw_ned = 0.0
        #: (north, east, down) m in that LOCAL_POSITION_NED (None: hovering over the origin)
        self.local_position: tuple[float, float, float] | None = None
        self.sending = True  # False: go silent (heartbeat loss)
        self.params: dict[str, float] = {}  # answered to PARAM_REQUEST_READ (REAL32, C-cast)
        self._period = 1.0 / rate_hz
        self._lock = threading.Lock()
        self._received: list[tuple[float, Any]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_send = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_send:
                next_send = now + self._period
                if self.sending:
                    self.peer.heartbeat(armed=self.armed, custom_mode=self.custom_mode)
                    self.peer.flying(self.altitude, self.climb, self.landed, self.velocity_ned,
                                     self.yaw_ned, self.local_position)
            got = False
            while True:
                msg = self.peer.conn.recv_msg()
                if msg is None:
                    break
                got = True
                if msg.get_type() == "BAD_DATA":
                    continue
                with self._lock:
                    self._received.append((time.monotonic(), msg))
                if msg.get_type() == "COMMAND_LONG":
                    self._answer(msg)
                elif msg.get_type() == "PARAM_REQUEST_READ":
                    names = sorted(self.params)
                    by_index = not msg.param_id and 0 <= msg.param_index < len(names)
                    name = names[msg.param_index] if by_index else msg.param_id
                    if name in self.params:  # an unknown name gets no answer, as on both firmwares
                        self.peer.mav.param_value_send(name.encode(), self.params[name],
                                                       mavlink.MAV_PARAM_TYPE_REAL32, len(names),
                                                       names.index(name))
            if not got:
                time.sleep(0.001)

    def _answer(self, msg: Any) -> None:
        mav = self.peer.mav
        wanted = int(msg.param1) if msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE else -1
        if wanted == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            capabilities = (mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                            | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED)
            mav.autopilot_version_send(
                capabilities,
                0x010E0000, 0, 0, 0, b"\0" * 8, b"\0" * 8, b"\0" * 8, 0, 0, 1)
        mav.command_ack_send(msg.command, mavlink.MAV_RESULT_ACCEPTED)

    def messages(self, kind: str | None = None, since: float = 0.0) -> list[Any]:
        """Messages received (of ``kind``) at or after monotonic time ``since``, oldest first."""
        with self._lock:
            return [m for t, m in self._received if t >= since and (kind is None or m.get_type() == kind)]

    def times(self, kind: str, since: float = 0.0) -> list[float]:
        with self._lock:
            return [t for t, m in self._received if t >= since and m.get_type() == kind]

    def wait_for(self, kind: str, timeout: float = 5.0, since: float = 0.0, condition=None) -> Any:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for msg in self.messages(kind, since):
                if condition is None or condition(msg):
                    return msg
            time.sleep(0.01)
        return None

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.peer.close()


SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux


def _favour_this_thread(niceness: int) -> int | None:
    """Give this thread ``niceness`` (negative: a larger share of the processor); return the previous
    one, or None if not permitted. Not real-time: that would starve the kernel's softirq threads,
    which deliver loopback datagrams under load."""
    thread = threading.get_native_id()
    previous = os.getpriority(os.PRIO_PROCESS, thread)
    try:
        os.setpriority(os.PRIO_PROCESS, thread, niceness)
    except PermissionError:
        return None
    return previous


class StampingAutopilot:
    """An :class:`AutopilotPeer` (armed, GUIDED, hovering) that stamps each message with the kernel's
    receive time (SO_TIMESTAMPNS), so that its own scheduling delays never show as the companion's.

    Single-threaded: :meth:`run` sends the status streams at 10 Hz and collects what arrives. Stamps
    are converted to this machine's monotonic clock (shared by every process on Linux).
    """

    def __init__(self, connect: str) -> None:
        self.peer = AutopilotPeer(connect)
        self.sock = self.peer.conn.port
        self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        self.received: list[tuple[float, Any]] = []  # (monotonic arrival, message)
        self._last_status = -1.0

    def run(self, seconds: float, until=None, favoured: bool = False) -> None:
        """Play the autopilot for ``seconds`` (or until ``until(message)`` is true for one), then take
        in whatever already arrived (its stamps say when).

        :param favoured: run this thread at nice -10 meanwhile where permitted: an autopilot is never
            starved of the processor, and on a loaded test machine this process would be
        """
        previous = _favour_this_thread(-10) if favoured else None
        try:
            deadline = time.monotonic() + seconds
            while (now := time.monotonic()) < deadline:
                if now - self._last_status >= 0.1:
                    self._last_status = now
                    self.peer.heartbeat()
                    self.peer.flying()
                if self._receive(min(0.02, deadline - now), until):
                    return
            while self._receive(0.0, until) is False:
                pass
        finally:
            if previous is not None:
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), previous)

    def run_while(self, process: subprocess.Popen[str], favoured: bool = False) -> None:
        """Play the autopilot until ``process`` has exited, and a little longer (what it caused has
        arrived): a flood process that started late must not end its window unobserved."""
        while process.poll() is None:
            self.run(0.1, favoured=favoured)
        self.run(0.3, favoured=favoured)

    def _receive(self, timeout: float, until) -> bool | None:
        """One datagram within ``timeout``: None if none came, else whether ``until`` matched."""
        if not select.select([self.sock], [], [], timeout)[0]:
            return None
        data, ancillary, _flags, _addr = self.sock.recvmsg(4096, 64)
        arrived = time.monotonic()
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                seconds, nanoseconds = struct.unpack("qq", payload[:16])
                arrived = seconds + nanoseconds * 1e-9 - (time.time() - time.monotonic())
        matched = False
        for msg in self.peer.mav.parse_buffer(data) or ():
            self.received.append((arrived, msg))
            matched = matched or (until is not None and until(msg))
        return matched

    def messages(self, kind: str, since: float = 0.0, until: float = float("inf")) -> list[tuple[float, Any]]:
        """(arrival, message) of ``kind`` that arrived within [since, until)."""
        return [(t, m) for t, m in self.received if since <= t < until and m.get_type() == kind]

    def close(self) -> None:
        self.peer.close()
