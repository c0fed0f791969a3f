"""A real pymavlink socket on loopback posing as an autopilot, for the link and process tests.

It speaks MAVLink 2 (the companion's adapter selects it before pymavlink is used) and decodes
exactly what the companion put on the wire.
"""

from __future__ import annotations

import socket
import time
from typing import Any

from pymavlink import mavutil

from companion.autopilot.mavlink_adapter import mavlink

COPTER_GUIDED = 4
COPTER_LOITER = 5


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


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
        self, altitude: float = 1.5, climb: float = 0.0, landed: int = mavlink.MAV_LANDED_STATE_IN_AIR
    ) -> None:
        """One round of the status streams of a vehicle hovering at ``altitude``."""
        self.mav.extended_sys_state_send(0, landed)
        self.mav.global_position_int_send(0, 0, 0, int(altitude * 1000) + 100_000, int(altitude * 1000),
                                          0, 0, int(-climb * 100), 0)
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
