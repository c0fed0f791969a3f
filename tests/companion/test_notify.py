"""sd_notify against a real AF_UNIX datagram socket standing in for systemd."""

from __future__ import annotations

import socket

import pytest

from companion.notify import SystemdNotifier


@pytest.fixture
def systemd_socket(tmp_path):
    path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(2.0)
    yield path, sock
    sock.close()


def test_ready_watchdog_status_reach_the_socket(systemd_socket):
    path, sock = systemd_socket
    notifier = SystemdNotifier({"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "3000000"})
    assert notifier.enabled
    assert notifier.watchdog_period == pytest.approx(1.5)
    notifier.ready()
    notifier.watchdog()
    notifier.status("ACTIVE")
    assert sock.recv(256) == b"READY=1"
    assert sock.recv(256) == b"WATCHDOG=1"
    assert sock.recv(256) == b"STATUS=ACTIVE"
    assert notifier.counters["ready"] == notifier.counters["watchdog"] == 1
    notifier.close()


def test_ready_with_status_is_one_datagram(systemd_socket):
    path, sock = systemd_socket
    notifier = SystemdNotifier({"NOTIFY_SOCKET": str(path)})
    notifier.ready("model loaded")
    assert sock.recv(256) == b"READY=1\nSTATUS=model loaded"
    assert notifier.watchdog_period is None


def test_outside_systemd_does_nothing():
    notifier = SystemdNotifier({})
    assert not notifier.enabled
    notifier.ready()
    notifier.watchdog()
    assert notifier.counters == {"ready": 0, "watchdog": 0, "status": 0, "failed": 0}


def test_vanished_socket_is_counted_not_raised(tmp_path):
    notifier = SystemdNotifier({"NOTIFY_SOCKET": str(tmp_path / "gone.sock")})
    notifier.watchdog()
    notifier.watchdog()
    assert notifier.counters["failed"] == 2
    assert notifier.counters["watchdog"] == 0


def test_abstract_namespace_address():
    name = f"lidar-avoid-test-{id(object())}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2.0)
    try:
        SystemdNotifier({"NOTIFY_SOCKET": "@" + name}).watchdog()
        assert sock.recv(64) == b"WATCHDOG=1"
    finally:
        sock.close()


def test_full_queue_never_blocks(systemd_socket):
    """Nobody reads the socket: notifications are dropped and counted, the caller does not wait."""
    path, _sock = systemd_socket
    notifier = SystemdNotifier({"NOTIFY_SOCKET": str(path)})
    for _ in range(2000):  # far beyond net.unix.max_dgram_qlen
        notifier.watchdog()
    assert notifier.counters["failed"] > 0
    assert notifier.counters["watchdog"] + notifier.counters["failed"] == 2000
