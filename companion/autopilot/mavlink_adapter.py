"""Thin adapter over pymavlink: open a connection string, read without blocking, send encoded messages.

pymavlink chooses its wire protocol from the ``MAVLINK20`` environment variable when ``mavutil``
is first imported and keeps the choice in module globals, so this module sets it before importing
and re-selects the dialect if someone imported ``mavutil`` earlier. Nothing else in the companion
imports pymavlink: the links speak through :class:`MavlinkEndpoint`.
"""

from __future__ import annotations

import logging
import os
from typing import Any

os.environ["MAVLINK20"] = "1"

from pymavlink import mavutil

if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
    mavutil.set_dialect("ardupilotmega")

from companion.autopilot.signing import enable_signing
from companion.common.errors import UserError

#: The MAVLink 2 ``ardupilotmega`` dialect module: message ids, enums and message classes.
mavlink: Any = mavutil.mavlink

log = logging.getLogger(__name__)

#: Most messages one :meth:`MavlinkEndpoint.receive` call parses, so a flood cannot stall the loop.
MAX_MESSAGES_PER_RECEIVE = 512


class MavlinkEndpoint:
    """One MAVLink connection opened from a ``mavutil`` connection string.

    ``udpin:0.0.0.0:14550`` listens, ``tcp:127.0.0.1:5760`` connects, a device path such as
    ``/dev/ttyTHS1`` opens a serial port at ``baud``.

    On ``udpin`` pymavlink would write to every address that ever sent a datagram, and never forget
    one: a stranger's single datagram would receive every setpoint, and thousands of spoofed source
    addresses would multiply the cost of each send. Here replies go only to the address of the
    newest datagram holding a HEARTBEAT from ``peer`` (signed, when signing is on); until one
    arrives nothing is sent.

    :param connect: the connection string
    :param baud: serial baud rate (ignored for network links)
    :param source_system: MAVLink system id this end sends as
    :param source_component: MAVLink component id this end sends as
    :param peer: (system, component) of the autopilot, whose address replies go to
    :param signing_key: MAVLink 2 signing secret (32 bytes); None = no signing. With a key every
        frame sent is signed and every frame received unsigned or badly signed is dropped.
    :param label: how error messages name the connection (default: ``repr(connect)``)
    """

    def __init__(
        self,
        connect: str,
        baud: int,
        source_system: int,
        source_component: int,
        peer: tuple[int, int] = (1, 1),
        signing_key: bytes | None = None,
        label: str | None = None,
    ) -> None:
        try:
            self._conn = mavutil.mavlink_connection(
                connect,
                baud=baud,
                source_system=source_system,
                source_component=source_component,
                autoreconnect=True,
                retries=1,
                reconnect_delay=0.5,
                dialect="ardupilotmega",  # pymavlink's dialect is global: others may have switched it
            )
        except (OSError, ValueError) as exc:  # refused TCP, busy port, missing device, bad syntax
            raise UserError(f"autopilot.connect: cannot open {label or repr(connect)}: {exc}") from None
        self.connect = connect
        self.peer = peer
        if signing_key is not None:
            enable_signing(self._conn.mav, signing_key)
        self._udp_server = isinstance(self._conn, mavutil.mavudp) and self._conn.udp_server
        if self._udp_server:
            self._conn.clients = set()  # pymavlink's reply list: kept to the autopilot's address
        #: address replies go to (udpin only): where the autopilot's heartbeats come from
        self.reply_address: tuple[str, int] | None = None
        #: garbage bytes and frames that failed length/CRC checks (pymavlink BAD_DATA)
        self.bad_data = 0
        #: well-formed frames of message ids this dialect does not know
        self.unknown = 0
        #: socket or device errors while reading (the link stays open)
        self.read_errors = 0
        #: frames dropped because signing is on and they were unsigned or badly signed
        self.signature_rejected = 0

    @property
    def mav(self) -> Any:
        """pymavlink's encoder: ``mav.<message>_send(...)`` writes one frame to the link."""
        return self._conn.mav

    def fileno(self) -> int | None:
        """File descriptor to ``select()`` on, when the link has one."""
        fd = getattr(self._conn, "fd", None)
        return fd if isinstance(fd, int) and fd >= 0 else None

    def receive(self) -> list[Any]:
        """Parse whatever is waiting, without blocking; malformed input is counted and dropped."""
        out: list[Any] = []
        try:
            if isinstance(self._conn, mavutil.mavudp):
                self._receive_datagrams(out)
            else:
                self._receive_stream(out)
        except OSError as exc:
            self.read_errors += 1
            log.debug("MAVLink read error on %s: %s", self.connect, exc)
        return out

    def _keep(self, msg: Any, out: list[Any]) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA":
            if msg.reason == "Invalid signature":
                self.signature_rejected += 1
            else:
                self.bad_data += 1
        elif kind.startswith("UNKNOWN_"):
            self.unknown += 1
        else:
            out.append(msg)

    def _receive_stream(self, out: list[Any]) -> None:
        for _ in range(MAX_MESSAGES_PER_RECEIVE):
            msg = self._conn.recv_msg()
            if msg is None:
                return
            self._keep(msg, out)

    def _receive_datagrams(self, out: list[Any]) -> None:
        """UDP: a datagram holds whole frames, so a partial frame left at its end is garbage.

        pymavlink parses UDP as one byte stream; dropping the remainder per datagram stops a
        truncated frame from swallowing the start of the next, valid, datagram.
        """
        parser = self._conn.mav
        for _ in range(MAX_MESSAGES_PER_RECEIVE):
            try:
                data, address = self._conn.port.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionRefusedError:  # an ICMP "port unreachable" left by an earlier send
                continue
            for msg in parser.parse_buffer(data) or ():
                self._keep(msg, out)
                if self._udp_server and self._from_peer_heartbeat(msg) and address != self.reply_address:
                    self.reply_address = address
                    self._conn.clients = {address}
                    log.info("autopilot at %s:%d on %s", address[0], address[1], self.connect)
            if parser.buf_len() > 0:
                self.bad_data += 1
                parser.buf = bytearray()
                parser.buf_index = 0
                parser.expected_length = mavlink.HEADER_LEN_V1 + 2

    def write(self, frame: bytes) -> None:
        """Send an already encoded frame (on ``udpin``: to the autopilot's address only)."""
        self._conn.write(frame)

    def _from_peer_heartbeat(self, msg: Any) -> bool:
        """A HEARTBEAT from the autopilot's ids (parsing already dropped any that failed signing)."""
        return msg.get_type() == "HEARTBEAT" and (msg.get_srcSystem(), msg.get_srcComponent()) == self.peer

    def close(self) -> None:
        """Close the socket or serial port."""
        try:
            self._conn.close()
        except OSError as exc:
            log.debug("closing %s: %s", self.connect, exc)


def mode_name(heartbeat: Any) -> str:
    """The flight mode name pymavlink derives from a HEARTBEAT (vehicle type and autopilot aware)."""
    return str(mavutil.mode_string_v10(heartbeat))
