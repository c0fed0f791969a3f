"""MAVSDK's bytes carried by the companion's own MAVLink endpoint: one autopilot, one address, signing.

MAVSDK's own ``udpin://`` connection writes to every address it has heard from, and MAVSDK cannot
sign MAVLink 2 frames. So the PX4 link gives MAVSDK a ``raw://`` connection and moves its bytes
itself, through the same :class:`~companion.autopilot.mavlink_adapter.MavlinkEndpoint` the
ArduPilot link uses:

- in (a reader thread): frames parsed and, with a key, signature-checked by the endpoint; only
  those from the autopilot's system reach MAVSDK (the rest are counted), so MAVSDK never even
  discovers an impostor;
- out (MAVSDK's thread): each frame MAVSDK writes is re-signed when signing is on, and sent by
  the endpoint, which on ``udpin`` replies only to the address the autopilot's heartbeats come from.
"""

from __future__ import annotations

import logging
import select
import threading
from typing import Any

from companion.autopilot.connection import parse_connection
from companion.autopilot.mavlink_adapter import MavlinkEndpoint, mavlink
from companion.autopilot.signing import FrameSigner

log = logging.getLogger(__name__)

class RawMavlinkTransport:
    """Pump MAVLink between a MAVSDK ``raw://`` connection and a :class:`MavlinkEndpoint`.

    :param mavsdk: the ``Mavsdk`` instance; its ``raw://`` connection is added after this subscribed
        to what MAVSDK sends (MAVSDK sends its first heartbeat as soon as the connection exists, and
        a raw connection nobody reads fails it: "Sending message failed"), then
        :meth:`start_reading` feeds it
    :param url: MAVSDK URL of the autopilot link (``udpin://0.0.0.0:14540``, ``serial:///dev/X:B``)
    :param autopilot: (system id, component id) of the autopilot
    :param signing_key: MAVLink 2 signing secret (32 bytes); None = no signing
    """

    def __init__(self, mavsdk: Any, url: str, autopilot: tuple[int, int], source_system: int,
                 source_component: int, signing_key: bytes | None = None, baud: int = 921600) -> None:
        link = parse_connection(url, baud)  # the MAVSDK URL, as pymavlink opens it
        connect, baud = link.pymavlink, link.baud or baud
        self._endpoint = MavlinkEndpoint(connect, baud, source_system, source_component, autopilot,
                                         signing_key, label=repr(url))
        self._mavsdk = mavsdk
        self._system_id = autopilot[0]
        self._signer = FrameSigner(signing_key) if signing_key is not None else None
        self._out_parser = mavlink.MAVLink(None)
        self._out_parser.robust_parsing = True
        self._out_encoder = mavlink.MAVLink(None, source_system, source_component)
        #: called (reader thread) with every message from the autopilot's system
        self.listeners: list[Any] = []
        self._lock = threading.Lock()
        self.counters: dict[str, int] = {"foreign_messages": 0, "frames_out": 0, "unsignable_frames": 0,
                                          "send_errors": 0}
        self._stop = threading.Event()
        self._send_handle = mavsdk.subscribe_raw_bytes_to_be_sent(self._on_outgoing)
        self._reader = threading.Thread(target=self._read, name="px4-mavlink-in", daemon=True)

    def start_reading(self) -> None:
        """Feed MAVSDK what the autopilot sends (once its ``raw://`` connection exists)."""
        self._reader.start()

    @property
    def endpoint_counters(self) -> dict[str, int]:
        """The endpoint's counts: malformed input, unknown ids, rejected signatures, read errors."""
        e = self._endpoint
        return {"bad_data": e.bad_data, "unknown_messages": e.unknown, "read_errors": e.read_errors,
                "signature_rejected": e.signature_rejected}

    def _read(self) -> None:
        fd = self._endpoint.fileno()
        while not self._stop.is_set():
            if fd is not None:
                try:
                    select.select([fd], [], [], 0.05)
                except (OSError, ValueError):  # closed under us on the way out
                    return
            else:
                self._stop.wait(0.005)
            for msg in self._endpoint.receive():
                if msg.get_srcSystem() != self._system_id:
                    with self._lock:
                        self.counters["foreign_messages"] += 1
                    continue
                self._mavsdk.pass_received_raw_bytes(bytes(msg.get_msgbuf()))
                for listener in self.listeners:
                    listener(msg)

    def send_message(self, msg: Any) -> None:
        """Send a pymavlink message of the companion's own beside MAVSDK's (same ids, same signer)."""
        with self._lock:
            frame = bytes(msg.pack(self._out_encoder))
            self._out_encoder.seq = (self._out_encoder.seq + 1) % 256
        self._on_outgoing(frame)

    def _on_outgoing(self, data: bytes) -> None:
        """MAVSDK's thread: frames to send, re-signed when signing is on."""
        with self._lock:
            for msg in self._out_parser.parse_buffer(data) or ():
                if msg.get_type() == "BAD_DATA":
                    continue
                frame = bytes(msg.get_msgbuf())
                if self._signer is not None:
                    signed = self._signer.sign(frame, msg.crc_extra)
                    if signed is None:
                        self.counters["unsignable_frames"] += 1
                        continue
                    frame = signed
                try:
                    self._endpoint.write(frame)
                except OSError as exc:
                    self.counters["send_errors"] += 1
                    log.debug("MAVLink send failed: %s", exc)
                    continue
                self.counters["frames_out"] += 1

    def stop_reading(self) -> None:
        """Stop feeding MAVSDK (before it is destroyed: the reader thread calls into it)."""
        self._stop.set()
        if self._reader.is_alive():
            self._reader.join(timeout=1.0)

    def close(self) -> None:
        """Close the endpoint (after MAVSDK is destroyed, so nothing writes to it any more)."""
        self.stop_reading()
        self._endpoint.close()
