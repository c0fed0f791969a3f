"""MAVLink connection strings, written either way, for either autopilot: parsed and checked in one place.

pymavlink (ArduPilot link, parameter check) and MAVSDK (PX4 link) spell the same links
differently, and users copy one into the other's place. Every form below is accepted wherever a
connection is asked for (``autopilot.connect``, ``params --connect``) and turned into whichever
form the library at hand needs:

==========================  ==========================  ==========================================
pymavlink                   MAVSDK                      link
==========================  ==========================  ==========================================
``udpin:0.0.0.0:14540``     ``udpin://0.0.0.0:14540``   listen for UDP (``udp:`` / ``udp://`` too)
``udpout:10.0.0.2:14550``   ``udpout://10.0.0.2:14550`` send UDP to an address
``tcp:127.0.0.1:5760``      ``tcpout://127.0.0.1:5760`` connect over TCP (``tcp://`` too)
``tcpin:0.0.0.0:5760``      ``tcpin://0.0.0.0:5760``    accept a TCP connection
``/dev/ttyTHS1[:921600]``   ``serial:///dev/ttyTHS1:921600``  serial port (``serial_flowcontrol://``)
==========================  ==========================  ==========================================

A port outside 1-65535, a missing host or baud, or an unknown scheme is a :class:`UserError`
naming the string; :func:`ensure_port_free` refuses a listening port another process holds
(pymavlink binds UDP with SO_REUSEADDR, so without it a second companion would share the port).
"""

from __future__ import annotations

import errno
import socket
from dataclasses import dataclass
from typing import Literal

from companion.common.errors import UserError

Kind = Literal["udpin", "udpout", "tcpout", "tcpin", "serial"]

#: scheme as written (pymavlink ``scheme:`` or MAVSDK ``scheme://``) -> link kind
_SCHEMES: dict[str, Kind] = {
    "udpin": "udpin",
    "udp": "udpin",
    "udpout": "udpout",
    "tcp": "tcpout",
    "tcpout": "tcpout",
    "tcpin": "tcpin",
}
_PYMAVLINK: dict[Kind, str] = {"udpin": "udpin", "udpout": "udpout", "tcpout": "tcp", "tcpin": "tcpin"}
FORMS = "udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, tcpin:HOST:PORT, /dev/DEVICE[:BAUD] or MAVSDK URLs"


@dataclass(frozen=True)
class Connection:
    """One MAVLink link, whichever way it was written.

    :param kind: the link's direction and transport
    :param address: host for network links, device path for serial ones
    :param port: network port (0 for serial)
    :param baud: serial baud rate (0 for network links)
    :param flow_control: serial RTS/CTS (MAVSDK's ``serial_flowcontrol://``)
    """

    kind: Kind
    address: str
    port: int = 0
    baud: int = 0
    flow_control: bool = False

    @property
    def pymavlink(self) -> str:
        """The pymavlink device string (for serial links the baud goes separately: :attr:`baud`)."""
        if self.kind == "serial":
            return self.address
        return f"{_PYMAVLINK[self.kind]}:{self.address}:{self.port}"

    @property
    def mavsdk(self) -> str:
        """The MAVSDK connection URL."""
        if self.kind == "serial":
            scheme = "serial_flowcontrol" if self.flow_control else "serial"
            return f"{scheme}://{self.address}:{self.baud}"
        return f"{self.kind}://{self.address}:{self.port}"


def parse_connection(text: str, default_baud: int = 921600) -> Connection:
    """Parse a pymavlink string or a MAVSDK URL.

    :param default_baud: the baud of a serial device written without one (``/dev/ttyTHS1``)
    :raises UserError: the string names no link this project can open
    """
    text = text.strip()
    if not text:
        raise UserError(f"empty MAVLink connection (expected {FORMS})")
    scheme, sep, rest = text.partition("://")
    if not sep:
        scheme, sep, rest = text.partition(":")
        if text.startswith("/"):
            scheme, rest = "serial", text
        elif not sep:
            raise UserError(f"MAVLink connection {text!r}: expected {FORMS}")
    if scheme in ("serial", "serial_flowcontrol"):
        return _parse_serial(text, rest, default_baud, flow_control=scheme == "serial_flowcontrol")
    if scheme not in _SCHEMES:
        raise UserError(f"MAVLink connection {text!r}: unknown scheme {scheme!r} (expected {FORMS})")
    host, _, port_text = rest.rpartition(":")
    if not host:
        raise UserError(f"MAVLink connection {text!r}: expected HOST:PORT after {scheme!r}")
    return Connection(_SCHEMES[scheme], host, port=_port(text, port_text))


def _port(text: str, port_text: str) -> int:
    if not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
        raise UserError(f"MAVLink connection {text!r}: port {port_text!r} is not a port number 1-65535")
    return int(port_text)


def _parse_serial(text: str, rest: str, default_baud: int, flow_control: bool) -> Connection:
    device, _, baud_text = rest.rpartition(":")
    if not device:  # no ":BAUD"
        device, baud_text = rest, ""
    if baud_text and not baud_text.isdigit():
        raise UserError(f"MAVLink connection {text!r}: baud {baud_text!r} is not a number")
    baud = int(baud_text) if baud_text else default_baud
    if not device.startswith("/") or baud <= 0:
        raise UserError(f"MAVLink connection {text!r}: expected /dev/DEVICE[:BAUD]")
    return Connection("serial", device, baud=baud, flow_control=flow_control)


def ensure_port_free(conn: Connection) -> None:
    """Refuse a listening link (``udpin``/``tcpin``) whose port another process already holds.

    The probe binds without SO_REUSEADDR, which fails against any socket already bound there,
    even one that set it (pymavlink's UDP listener does, so a second companion would otherwise
    start and share the autopilot's datagrams with the first).

    :raises UserError: the port is in use, or the address is not one of this machine's
    """
    if conn.kind not in ("udpin", "tcpin"):
        return
    kind = socket.SOCK_DGRAM if conn.kind == "udpin" else socket.SOCK_STREAM
    try:
        infos = socket.getaddrinfo(conn.address, conn.port, type=kind)
    except OSError as exc:
        raise UserError(
            f"MAVLink connection {conn.pymavlink}: cannot resolve {conn.address!r}: {exc}"
        ) from None
    family, _, _, _, sockaddr = infos[0]
    with socket.socket(family, kind) as probe:
        if kind == socket.SOCK_STREAM:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # TIME_WAIT is no conflict
        try:
            probe.bind(sockaddr)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise UserError(
                    f"MAVLink connection {conn.pymavlink}: port {conn.port} is already in use "
                    "(another companion, or a ground station on this machine?)"
                ) from None
            raise UserError(f"MAVLink connection {conn.pymavlink}: cannot listen there: {exc}") from None
