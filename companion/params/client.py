"""The wire side of the parameter check: one parameter at a time over a pymavlink connection.

:class:`MavlinkParamClient` reads and writes single parameters (PARAM_REQUEST_READ / PARAM_SET /
PARAM_VALUE) with bounded timeouts and retries, and takes the value encoding from the autopilot's
AUTOPILOT_VERSION capabilities (:mod:`companion.params.codec`); :func:`open_connection` and
:func:`wait_for_autopilot` give it a link and a peer. What to read and how to judge it is
:mod:`companion.params.check`.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from typing import Any

from companion.common.errors import UserError
from companion.params.codec import decode_param_value, encode_param_value

REFUSED = object()  # the autopilot said it does not know the parameter
# MAVLink component id of an onboard computer; the companion's identity on the link.
COMPANION_SYSTEM_ID = 1
COMPANION_COMPONENT_ID = 191


@dataclass
class LinkStats:
    """What the parameter exchange cost, for the report: requests sent, retries, timeouts."""

    requests: int = 0
    retries: int = 0
    timeouts: int = 0


@dataclass
class AutopilotInfo:
    """The autopilot found on the link (from its HEARTBEAT)."""

    system_id: int
    component_id: int
    autopilot: int


class MavlinkParamClient:
    """One-parameter-at-a-time access to an autopilot's parameters over a pymavlink connection.

    :param conn: a ``mavutil`` connection (``mavlink_connection(...)``)
    :param target_system: the autopilot's system id
    :param target_component: the autopilot's component id
    :param timeout: seconds to wait for each reply
    :param retries: extra attempts after the first before a parameter counts as not answered
    :param bytewise: value encoding (see :meth:`detect_bytewise`, which sets it)
    """

    def __init__(
        self,
        conn: Any,
        target_system: int,
        target_component: int,
        timeout: float = 1.0,
        retries: int = 2,
        bytewise: bool = False,
    ) -> None:
        self.conn = conn
        self.target_system = target_system
        self.target_component = target_component
        self.timeout = timeout
        self.retries = retries
        self.bytewise = bytewise
        self.stats = LinkStats()
        self.encoding_source = "not detected"

    def detect_bytewise(self, heartbeat_autopilot: int | None = None) -> bool:
        """Ask for AUTOPILOT_VERSION and take the encoding from its capability bits.

        Sends MAV_CMD_REQUEST_MESSAGE (falls back to the older MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES
        when the autopilot rejects it). With no answer at all, the HEARTBEAT's autopilot field decides
        (PX4 → bytewise), and :attr:`encoding_source` says so.

        :param heartbeat_autopilot: MAV_AUTOPILOT from the autopilot's HEARTBEAT, for the fallback
        """
        mav = self.conn.mav
        mavlink = mavlink_common()
        use_legacy = False
        for attempt in range(self.retries + 1):
            self._count_attempt(attempt)
            if use_legacy:
                mav.command_long_send(
                    self.target_system,
                    self.target_component,
                    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
                    0,
                    1,
                    0,
                    0,
                    0,
                    0,
                    0,
                    0,
                )
            else:
                mav.command_long_send(
                    self.target_system,
                    self.target_component,
                    mavlink.MAV_CMD_REQUEST_MESSAGE,
                    0,
                    mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                    0,
                    0,
                    0,
                    0,
                    0,
                    0,
                )
            deadline = time.monotonic() + self.timeout
            while (msg := self._recv(["AUTOPILOT_VERSION", "COMMAND_ACK"], deadline)) is not None:
                if msg.get_type() == "AUTOPILOT_VERSION":
                    self.bytewise = bool(
                        msg.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
                    )
                    self.encoding_source = "AUTOPILOT_VERSION capabilities"
                    return self.bytewise
                if (
                    msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE
                    and msg.result != mavlink.MAV_RESULT_ACCEPTED
                ):
                    use_legacy = True  # an older firmware: ask the deprecated way on the next attempt
                    break
            else:
                self.stats.timeouts += 1
        self.bytewise = heartbeat_autopilot == mavlink.MAV_AUTOPILOT_PX4
        self.encoding_source = "HEARTBEAT autopilot type (no AUTOPILOT_VERSION reply)"
        return self.bytewise

    def read(self, name: str) -> tuple[float, int] | None:
        """The parameter's decoded value and MAV_PARAM_TYPE, None when the autopilot never answers.

        Both firmwares stay silent for a name they do not know, so "no answer after all retries"
        is how an unknown parameter shows up.
        """
        for attempt in range(self.retries + 1):
            self._count_attempt(attempt)
            self.conn.mav.param_request_read_send(
                self.target_system, self.target_component, name.encode("ascii"), -1
            )
            reply = self._wait_param_value(name)
            if reply is not None:
                return reply
            self.stats.timeouts += 1
        return None

    def link_alive(self) -> bool:
        """Does the autopilot answer at all? Asks for its first parameter by index.

        Both firmwares stay silent for a name they do not know, exactly as a dead link does; an
        answer to this request tells the two apart.
        """
        for attempt in range(self.retries + 1):
            self._count_attempt(attempt)
            self.conn.mav.param_request_read_send(self.target_system, self.target_component, b"", 0)
            if self._recv(["PARAM_VALUE"], time.monotonic() + self.timeout) is not None:
                return True
            self.stats.timeouts += 1
        return False

    def write(self, name: str, value: float, param_type: int) -> tuple[float, int] | None:
        """Send PARAM_SET and wait for the PARAM_VALUE echo; None when none comes (or PX4 says unknown).

        :param value: the value in the parameter's own type
        :param param_type: the parameter's MAV_PARAM_TYPE (as the autopilot reports it)
        """
        field_value = encode_param_value(value, param_type, self.bytewise)
        for attempt in range(self.retries + 1):
            self._count_attempt(attempt)
            self.conn.mav.param_set_send(
                self.target_system, self.target_component, name.encode("ascii"), field_value, param_type
            )
            # PX4 answers a set of a name it does not know with this STATUSTEXT and nothing else
            reply = self._wait_param_value(name, refused_text=f"unknown param: {name}")
            if reply is REFUSED:
                return None
            if reply is not None:
                return reply
            self.stats.timeouts += 1
        return None

    def _count_attempt(self, attempt: int) -> None:
        self.stats.requests += 1
        if attempt:
            self.stats.retries += 1

    def _recv(self, types: list[str], deadline: float) -> Any:
        """Next message of ``types`` from the target system before ``deadline``, else None."""
        while (remaining := deadline - time.monotonic()) > 0:
            msg = self.conn.recv_match(type=types, blocking=True, timeout=remaining)
            if msg is not None and msg.get_srcSystem() == self.target_system:
                return msg
        return None

    def _wait_param_value(self, name: str, refused_text: str | None = None) -> Any:
        """The (value, type) of the next PARAM_VALUE for ``name``; :data:`REFUSED` or None on timeout."""
        deadline = time.monotonic() + self.timeout
        while (msg := self._recv(["PARAM_VALUE", "STATUSTEXT"], deadline)) is not None:
            if msg.get_type() == "STATUSTEXT":
                if refused_text is not None and msg.text.endswith(refused_text):
                    return REFUSED
                continue
            if msg.param_id == name:
                return decode_param_value(msg.param_value, msg.param_type, self.bytewise), msg.param_type
        return None


def mavlink_common() -> Any:
    from pymavlink.dialects.v20 import common

    return common


def open_connection(url: str, baud: int) -> Any:
    """A MAVLink 2 pymavlink connection as the companion (system 1, component 191).

    :param url: mavutil connection string: ``udpin:0.0.0.0:14550``, ``udpout:HOST:PORT``,
        ``tcp:HOST:PORT``, a serial device such as ``/dev/ttyTHS1``
    :param baud: serial baud rate (ignored for network links)
    """
    os.environ["MAVLINK20"] = "1"  # pymavlink picks the wire protocol from the environment
    from pymavlink import mavutil

    try:
        return mavutil.mavlink_connection(
            url,
            baud=baud,
            source_system=COMPANION_SYSTEM_ID,
            source_component=COMPANION_COMPONENT_ID,
            dialect="common",
            autoreconnect=False,
        )
    except Exception as exc:  # pymavlink raises whatever the transport raises (OSError, SerialException…)
        raise UserError(f"cannot open MAVLink connection {url!r}: {exc}") from exc


def wait_for_autopilot(conn: Any, timeout: float) -> AutopilotInfo:
    """Wait for an autopilot HEARTBEAT, sending the companion's own heartbeat meanwhile.

    Sending first matters on ``udpout:`` links, where the autopilot learns our address from it.

    :raises UserError: no autopilot heartbeat within ``timeout`` seconds
    """
    mavlink = mavlink_common()
    deadline = time.monotonic() + timeout
    next_beat = 0.0
    while (now := time.monotonic()) < deadline:
        if now >= next_beat:
            conn.mav.heartbeat_send(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
            )
            next_beat = now + 0.5
        msg = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=min(0.5, deadline - now))
        if msg is not None and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID:
            return AutopilotInfo(msg.get_srcSystem(), msg.get_srcComponent(), msg.autopilot)
    raise UserError(f"no autopilot HEARTBEAT within {timeout:g} s; check --connect and the wiring")
