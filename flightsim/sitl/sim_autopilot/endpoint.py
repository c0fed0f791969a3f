"""The simulated autopilot's MAVLink sockets: framing, parsing, counting; no flight logic.

Each link is one socket, described like a pymavlink/MAVProxy connection string:

- ``udpin:HOST:PORT``: bind HOST:PORT, answer every peer that has sent something (a GCS or a
  companion that connects with ``udpout:``), as ArduPilot SITL's UDP ports do;
- ``udpout:HOST:PORT``: send to HOST:PORT from an ephemeral port, as PX4 SITL does towards
  MAVSDK's ``udpin://`` (14540);
- ``tcpin:HOST:PORT``: listen; every accepted client shares the link (ArduPilot SITL's 5760).

Malformed input (garbage, bad CRC, truncated frames, unknown message ids) is counted per link and
dropped; it never raises.

MAVLink 2 signing, as the firmware does it: with a key (given at start, or installed by a
SETUP_SIGNING message, which an all-zero key and timestamp turns off again) every frame sent is
signed, and a frame that arrives unsigned or badly signed is counted (``signature_rejected``) and
dropped unless its message id is in ``accept_unsigned`` (ArduPilot and PX4 both still take
RADIO_STATUS from a telemetry radio).
"""

from __future__ import annotations

import logging
import select
import socket
import time
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.autopilot.signing import disable_signing, enable_signing
from companion.common.errors import UserError

log = logging.getLogger(__name__)

#: peers of a ``udpin`` link that stay silent this long are forgotten, seconds
PEER_TIMEOUT = 10.0


@dataclass
class LinkSpec:
    kind: str  # udpin | udpout | tcpin
    host: str
    port: int

    @classmethod
    def parse(cls, text: str) -> LinkSpec:
        """Parse ``udpin:HOST:PORT`` / ``udpout:HOST:PORT`` / ``tcpin:HOST:PORT`` (UserError if bad)."""
        parts = text.split(":")
        if len(parts) != 3 or parts[0] not in ("udpin", "udpout", "tcpin"):
            raise UserError(
                f"autopilot link {text!r}: expected udpin:HOST:PORT, udpout:HOST:PORT or tcpin:HOST:PORT"
            )
        try:
            port = int(parts[2])
        except ValueError:
            raise UserError(f"autopilot link {text!r}: port {parts[2]!r} is not a number") from None
        if not 0 <= port <= 65535:
            raise UserError(f"autopilot link {text!r}: port {port} out of range")
        return cls(parts[0], parts[1] or "127.0.0.1", port)


@dataclass
class _Link:
    spec: LinkSpec
    sock: socket.socket
    parser: Any
    encoder: Any
    peers: dict[Any, float] = field(default_factory=dict)  # udpin: addr -> last heard; tcpin: sock -> 0
    parsers: dict[Any, Any] = field(default_factory=dict)  # tcpin: one stream parser per client


class MavlinkEndpoint:
    """Open sockets for ``links`` and move MAVLink frames through them.

    :param links: connection strings (see module doc); the index in this list is the link number
    :param system_id: source system id of everything sent
    :param component_id: source component id of everything sent
    :param signing_key: MAVLink 2 signing secret (32 bytes) to start with; None = unsigned
    :param accept_unsigned: message ids accepted unsigned while signing is on
    """

    def __init__(
        self,
        links: list[str],
        system_id: int = 1,
        component_id: int = 1,
        signing_key: bytes | None = None,
        accept_unsigned: frozenset[int] = frozenset(),
    ) -> None:
        self.system_id = system_id
        self.component_id = component_id
        self.counters: dict[str, int] = {}
        self.signing_key = signing_key
        self.accept_unsigned = accept_unsigned
        self._links: list[_Link] = []
        try:
            for text in links:
                self._links.append(self._open(LinkSpec.parse(text)))
        except OSError as exc:
            self.close()
            raise UserError(f"autopilot link: cannot open {text!r}: {exc.strerror or exc}") from None

    def _new_parser(self, link_id: int = 0) -> Any:
        parser = mavlink.MAVLink(None, self.system_id, self.component_id)
        parser.robust_parsing = True
        if self.signing_key is not None:
            enable_signing(parser, self.signing_key, link_id, self.accept_unsigned)
        return parser

    def set_signing_key(self, key: bytes | None, initial_timestamp: int | None = None) -> None:
        """Sign with ``key`` from now on, on every link (None: stop signing, accept unsigned)."""
        self.signing_key = key
        for index, link in enumerate(self._links):
            for mav in (link.parser, link.encoder, *link.parsers.values()):
                if key is None:
                    disable_signing(mav)
                else:
                    enable_signing(mav, key, index, self.accept_unsigned, initial_timestamp)

    def _on_setup_signing(self, msg: Any) -> None:
        """SETUP_SIGNING: take the key (as both firmwares do, on whichever link it arrived)."""
        key = bytes(msg.secret_key)
        if key == bytes(len(key)) and msg.initial_timestamp == 0:
            self.set_signing_key(None)
            self.count("signing_disabled")
            log.info("signing disabled by SETUP_SIGNING")
        else:
            self.set_signing_key(key, msg.initial_timestamp or None)
            self.count("signing_key_set")
            log.info("signing key installed by SETUP_SIGNING")

    def _open(self, spec: LinkSpec) -> _Link:
        if spec.kind == "tcpin":
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((spec.host, spec.port))
            sock.listen(4)
        else:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            if spec.kind == "udpin":
                sock.bind((spec.host, spec.port))
            else:
                sock.bind(("127.0.0.1" if spec.host in ("127.0.0.1", "localhost") else "", 0))
        sock.setblocking(False)
        index = len(self._links)
        link = _Link(spec, sock, self._new_parser(index), self._new_parser(index))
        if spec.kind == "udpout":
            link.peers[(spec.host, spec.port)] = float("inf")
        log.info("autopilot link %d: %s:%s:%d", len(self._links), spec.kind, spec.host, spec.port)
        return link

    @property
    def link_count(self) -> int:
        return len(self._links)

    def address(self, link: int) -> tuple[str, int]:
        """The local (host, port) of ``link`` (useful with port 0)."""
        return self._links[link].sock.getsockname()[:2]

    def count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n

    # ----------------------------------------------------------------- receive
    def poll(self, timeout: float) -> list[tuple[int, Any, float]]:
        """Wait up to ``timeout`` s for input; return (link, message, receive time) of every good frame."""
        fds: list[Any] = []
        for link in self._links:
            fds.append(link.sock)
            if link.spec.kind == "tcpin":
                fds.extend(link.peers)
        try:
            readable, _, _ = select.select(fds, [], [], max(0.0, timeout))
        except (OSError, ValueError):
            return []
        out: list[tuple[int, Any, float]] = []
        for sock in readable:
            for index, link in enumerate(self._links):
                if sock is link.sock:
                    out.extend(self._read_link(index, link))
                elif sock in link.peers:
                    out.extend(self._read_tcp_client(index, link, sock))
        return out

    def _read_link(self, index: int, link: _Link) -> list[tuple[int, Any, float]]:
        if link.spec.kind == "tcpin":
            try:
                client, addr = link.sock.accept()
            except OSError:
                return []
            client.setblocking(False)
            link.peers[client] = 0.0
            link.parsers[client] = self._new_parser(index)
            log.info("autopilot link %d: TCP client %s:%d", index, *addr[:2])
            return []
        out = []
        while True:
            try:
                data, addr = link.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # e.g. ICMP port unreachable reported on a udpout socket
                self.count("socket_errors")
                break
            now = time.monotonic()
            if link.spec.kind == "udpin":
                link.peers[addr] = now
            out.extend((index, msg, now) for msg in self._parse(link.parser, data, index))
            if link.parser.buf_len() > 0:
                # a datagram carries whole frames: a leftover is a truncated frame, not the start of
                # the next datagram's (resynchronising across datagrams would eat a good frame)
                self.count("malformed")
                _drop_partial_frame(link.parser)
        return out

    def _read_tcp_client(
        self, index: int, link: _Link, client: socket.socket
    ) -> list[tuple[int, Any, float]]:
        try:
            data = client.recv(65535)
        except OSError:
            data = b""
        if not data:
            link.peers.pop(client, None)
            link.parsers.pop(client, None)
            client.close()
            return []
        now = time.monotonic()
        return [(index, msg, now) for msg in self._parse(link.parsers[client], data, index)]

    def _parse(self, parser: Any, data: bytes, index: int) -> list[Any]:
        self.count("bytes_in", len(data))
        try:
            msgs = parser.parse_buffer(data) or []
        except Exception as exc:  # pymavlink raises a variety of errors on hostile input
            self.count("malformed")
            log.debug("link %d: unparseable input dropped: %s", index, exc)
            return []
        good = []
        for msg in msgs:
            kind = msg.get_type()
            if kind == "BAD_DATA" and msg.reason == "Invalid signature":
                self.count("signature_rejected")
            elif kind == "BAD_DATA":
                self.count("malformed")
            elif kind.startswith("UNKNOWN"):
                self.count("unknown_message")
            else:
                self.count("frames_in")
                good.append(msg)
                if kind == "SETUP_SIGNING":
                    self._on_setup_signing(msg)
        return good

    # ----------------------------------------------------------------- send
    def send(self, link: int | None, message: Any) -> None:
        """Send ``message`` on ``link`` (None: every link) to every known peer of that link."""
        targets = range(len(self._links)) if link is None else (link,)
        now = time.monotonic()
        for index in targets:
            lk = self._links[index]
            enc = lk.encoder
            buf = message.pack(enc)
            enc.seq = (enc.seq + 1) % 256
            for peer, heard in list(lk.peers.items()):
                try:
                    if lk.spec.kind == "tcpin":
                        peer.sendall(buf)
                    elif now - heard > PEER_TIMEOUT:
                        del lk.peers[peer]
                    else:
                        lk.sock.sendto(buf, peer)
                    self.count("frames_out")
                except OSError:
                    self.count("socket_errors")

    def send_raw(self, link: int, data: bytes) -> None:
        """Send raw bytes on ``link`` to its peers (fault injection: line noise, corrupt frames)."""
        lk = self._links[link]
        for peer in list(lk.peers):
            try:
                if lk.spec.kind == "tcpin":
                    peer.sendall(data)
                else:
                    lk.sock.sendto(data, peer)
            except OSError:
                self.count("socket_errors")

    def close(self) -> None:
        for link in self._links:
            if link.spec.kind == "tcpin":
                for client in link.peers:
                    client.close()
            link.sock.close()
        self._links = []


def _drop_partial_frame(parser: Any) -> None:
    """Forget a truncated frame left in ``parser`` (keeps its signing state: replay protection)."""
    parser.buf = bytearray()
    parser.buf_index = 0
    parser.expected_length = mavlink.HEADER_LEN_V1 + 2
