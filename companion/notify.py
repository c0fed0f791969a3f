"""systemd notification (``sd_notify``): READY, WATCHDOG and STATUS for the service manager.

systemd hands a service the address of its notification socket in ``NOTIFY_SOCKET`` and, when the
unit sets ``WatchdogSec=``, the deadline in ``WATCHDOG_USEC``. Outside systemd neither is set and
every call here does nothing, so the same program runs from a shell, in tests and as a service.
The protocol is one AF_UNIX datagram per state (``sd_notify(3)``); a leading ``@`` in the
address is Linux's abstract namespace.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger(__name__)


class SystemdNotifier:
    """Send ``sd_notify`` states to systemd when running under it, else nothing.

    A notification that cannot be delivered (socket gone, receive queue full) is logged once and
    counted, never raised and never waited for: systemd must not be able to stall the flight loop.

    :param environ: where to read ``NOTIFY_SOCKET`` / ``WATCHDOG_USEC`` (default ``os.environ``)
    """

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        address = env.get("NOTIFY_SOCKET", "")
        self._sock: socket.socket | None = None
        if address:
            if address.startswith("@"):
                address = "\0" + address[1:]
            # Non-blocking: a full receive queue (systemd busy, max_dgram_qlen reached) must cost a
            # dropped notification, never a stalled flight loop.
            self._sock = socket.socket(
                socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC | socket.SOCK_NONBLOCK
            )
            self._address = address
        usec = env.get("WATCHDOG_USEC", "")
        #: seconds between WATCHDOG=1 pings: half the systemd deadline (as sd_watchdog_enabled advises);
        #: None when systemd runs no watchdog for this service
        self.watchdog_period: float | None = int(usec) / 2e6 if usec.isdigit() and int(usec) > 0 else None
        self.counters: dict[str, int] = {"ready": 0, "watchdog": 0, "status": 0, "failed": 0}

    @property
    def enabled(self) -> bool:
        """True when running under systemd (``NOTIFY_SOCKET`` set)."""
        return self._sock is not None

    def _send(self, state: str, counter: str) -> None:
        if self._sock is None:
            return
        try:
            self._sock.sendto(state.encode(), self._address)
            self.counters[counter] += 1
        except OSError as exc:
            if self.counters["failed"] == 0:
                log.warning("cannot notify systemd at %r: %s", self._address, exc)
            self.counters["failed"] += 1

    def ready(self, status: str | None = None) -> None:
        """Tell systemd start-up is done (the model is loaded and the links are open)."""
        self._send("READY=1" if status is None else f"READY=1\nSTATUS={status}", "ready")

    def watchdog(self) -> None:
        """Ping the watchdog. Call only from the main loop, and only while it is healthy."""
        self._send("WATCHDOG=1", "watchdog")

    def status(self, text: str) -> None:
        """One-line status shown by ``systemctl status``."""
        self._send(f"STATUS={text}", "status")

    def stopping(self) -> None:
        """Tell systemd the service is shutting down on purpose."""
        self._send("STOPPING=1", "status")

    def close(self) -> None:
        """Release the socket."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None
