"""Hostile MAVLink against ArduPilotLink over real loopback sockets: impostors, strangers, forgeries.

Each test here failed on the link that locked onto the first heartbeat, answered every address
that ever sent a datagram and had no signing.
"""

from __future__ import annotations

import contextlib
import socket
import time

import pytest

from companion.autopilot.ardupilot import ArduPilotLink
from companion.autopilot.mavlink_adapter import mavlink
from companion.autopilot.signing import enable_signing, signing_timestamp
from tests.companion.mavlink_peer import COPTER_LOITER, AutopilotPeer, free_udp_port

KEY = bytes(range(1, 33))
OTHER_KEY = bytes(range(101, 133))


def _poll_until(link, condition, timeout=3.0):
    deadline = time.monotonic() + timeout
    status = link.poll()
    while not condition(status):
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not reached; last status {status}, counters {link.counters}")
        time.sleep(0.005)
        status = link.poll()
    return status


def _datagrams(sock: socket.socket, duration: float = 0.2) -> list[bytes]:
    """Every datagram ``sock`` receives within ``duration`` seconds."""
    out = []
    sock.settimeout(0.01)
    deadline = time.monotonic() + duration
    while time.monotonic() < deadline:
        with contextlib.suppress(TimeoutError):
            out.append(sock.recv(65535))
    return out


@pytest.fixture
def port():
    return free_udp_port()


def test_an_impostor_system_that_speaks_first_never_takes_the_companion(port):
    """System 42 claiming GUIDED and armed before the autopilot: counted, ignored, never answered."""
    link = ArduPilotLink(f"udpin:127.0.0.1:{port}")
    impostor = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=42, compid=1)
    autopilot = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=1, compid=1)
    try:
        for _ in range(3):
            impostor.heartbeat(armed=True)
            impostor.flying(altitude=5.0)
        _poll_until(link, lambda s: link.counters["foreign_heartbeats"] == 3)
        status = link.poll()
        assert status.heartbeat_time is None and not status.armed and not status.guided
        assert status.altitude is None  # its status streams are not believed either
        assert link.target is None
        link.send_velocity(1.0, 0.0)
        assert link.counters["setpoints_without_target"] == 1

        autopilot.heartbeat(armed=True, custom_mode=COPTER_LOITER)
        status = _poll_until(link, lambda s: s.heartbeat_time is not None)
        assert link.target == (1, 1) and status.mode == "LOITER"
        impostor.heartbeat(armed=True)  # still claiming GUIDED: changes nothing
        _poll_until(link, lambda s: link.counters["foreign_heartbeats"] == 4)
        assert link.poll().mode == "LOITER"
        link.send_velocity(0.5, 0.0)
        got = autopilot.wait_for("SET_POSITION_TARGET_LOCAL_NED")
        assert (got.target_system, got.target_component) == (1, 1)
        assert [m for m in impostor.drain(0.2) if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"] == []
    finally:
        link.close()
        impostor.close()
        autopilot.close()


def test_the_configured_autopilot_ids_are_the_ones_listened_to(port):
    link = ArduPilotLink(f"udpin:127.0.0.1:{port}", autopilot=(3, 1))
    default_ids = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=1, compid=1)
    other_component = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=3, compid=2)
    autopilot = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=3, compid=1)
    try:
        default_ids.heartbeat()
        other_component.heartbeat()
        _poll_until(link, lambda s: link.counters["foreign_heartbeats"] == 2)
        assert link.target is None
        autopilot.heartbeat()
        _poll_until(link, lambda s: s.guided)
        assert link.target == (3, 1)
    finally:
        for end in (link, default_ids, other_component, autopilot):
            end.close()


def test_a_strangers_datagram_does_not_make_it_a_receiver(port):
    """One 6-byte datagram used to be enough to receive every setpoint afterwards."""
    link = ArduPilotLink(f"udpin:127.0.0.1:{port}")
    autopilot = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=1, compid=1)
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        stranger.bind(("127.0.0.1", 0))
        stranger.sendto(b"\xfd\x00\x00\x00\x00\x00", ("127.0.0.1", port))
        autopilot.heartbeat()
        _poll_until(link, lambda s: s.guided)
        link.send_heartbeat()
        link.send_velocity(1.0, 0.0)
        link.send_statustext("hello", mavlink.MAV_SEVERITY_INFO)
        assert autopilot.wait_for("SET_POSITION_TARGET_LOCAL_NED") is not None
        assert _datagrams(stranger) == []
        assert link.counters["bad_data"] >= 1
    finally:
        link.close()
        autopilot.close()
        stranger.close()


def test_replies_follow_the_autopilot_not_the_latest_sender(port):
    """A stranger sending after the autopilot gets nothing; the autopilot moving address is followed."""
    link = ArduPilotLink(f"udpin:127.0.0.1:{port}")
    first = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=1, compid=1)
    stranger = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=255, compid=190)
    moved = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=1, compid=1)  # the autopilot after a restart
    try:
        first.heartbeat()
        _poll_until(link, lambda s: s.guided)
        stranger.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        _poll_until(link, lambda s: link.counters["foreign_heartbeats"] == 1)
        link.send_velocity(1.0, 0.0)
        assert first.wait_for("SET_POSITION_TARGET_LOCAL_NED") is not None
        assert stranger.drain(0.2) == []
        moved.heartbeat()
        moved_port = moved.conn.port.getsockname()[1]
        _poll_until(link, lambda s: (link._endpoint.reply_address or ("", 0))[1] == moved_port)
        link.send_velocity(2.0, 0.0)
        assert moved.wait_for("SET_POSITION_TARGET_LOCAL_NED").vx == pytest.approx(2.0)
        assert [m for m in first.drain(0.2) if m.get_type() == "SET_POSITION_TARGET_LOCAL_NED"] == []
    finally:
        for end in (link, first, stranger, moved):
            end.close()


def test_many_spoofed_source_addresses_cost_nothing_per_setpoint(port):
    """200 source addresses: each setpoint is still one datagram, to the autopilot only.

    pymavlink's udpin wrote every frame to every address ever heard (20,000 spoofed addresses cut
    the companion's setpoint rate to 7.1 Hz); the work per setpoint must not grow with them.
    """
    link = ArduPilotLink(f"udpin:127.0.0.1:{port}")
    peer = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=1, compid=1)
    spoofers = []
    try:
        for i in range(200):  # more would overflow the socket's receive buffer before one poll
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind((f"127.0.{1 + i // 250}.{1 + i % 250}", 0))  # all of 127/8 is loopback on Linux
            s.sendto(b"\x00" * 6, ("127.0.0.1", port))
            spoofers.append(s)
        _poll_until(link, lambda s: link.counters["bad_data"] == 200)
        peer.heartbeat()
        _poll_until(link, lambda s: s.guided)
        sent = []
        real_sendto = link._endpoint._conn.port.sendto

        def counting_sendto(data, address):
            sent.append(address)
            return real_sendto(data, address)

        link._endpoint._conn.port = _SendCounter(link._endpoint._conn.port, counting_sendto)
        for _ in range(10):
            link.send_velocity(0.5, 0.0)
        assert len(sent) == 10
        assert {port for _, port in sent} == {peer.conn.port.getsockname()[1]}
        assert all(_datagrams(s, 0.01) == [] for s in spoofers[:20])
    finally:
        link.close()
        peer.close()
        for s in spoofers:
            s.close()


class _SendCounter:
    """Wraps a socket: ``sendto`` goes through ``hook``, everything else to the socket."""

    def __init__(self, sock: socket.socket, hook) -> None:
        self._sock, self.sendto = sock, hook

    def __getattr__(self, name):
        return getattr(self._sock, name)


# ---- signing ------------------------------------------------------------------------------------


def _signed_peer(port: int, key: bytes, sysid: int = 1) -> AutopilotPeer:
    peer = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=sysid, compid=1)
    enable_signing(peer.mav, key, link_id=0)
    return peer


def test_signing_on_both_ends_works_and_everything_sent_is_signed(port):
    link = ArduPilotLink(f"udpin:127.0.0.1:{port}", signing_key=KEY)
    peer = _signed_peer(port, KEY)
    try:
        peer.heartbeat()
        peer.flying(altitude=2.0)
        status = _poll_until(link, lambda s: s.guided and s.altitude is not None)
        assert status.altitude == pytest.approx(2.0)
        link.send_velocity(1.0, 0.0)
        link.send_heartbeat()
        msg = peer.wait_for("SET_POSITION_TARGET_LOCAL_NED")
        assert msg is not None and msg._signed  # verified by the peer with the shared key
        assert peer.wait_for("HEARTBEAT")._signed
        assert peer.mav.signing.goodsig_count >= 2 and peer.mav.signing.badsig_count == 0
        assert link.counters["signature_rejected"] == 0
    finally:
        link.close()
        peer.close()


def test_unsigned_and_wrongly_signed_frames_are_dropped_and_counted(port):
    link = ArduPilotLink(f"udpin:127.0.0.1:{port}", signing_key=KEY)
    unsigned = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=1, compid=1)
    wrong_key = _signed_peer(port, OTHER_KEY)
    genuine = _signed_peer(port, KEY)
    try:
        unsigned.heartbeat(armed=True)  # the autopilot's own ids, GUIDED, armed: but unsigned
        unsigned.flying(altitude=3.0)
        wrong_key.heartbeat(armed=True)
        _poll_until(link, lambda s: link.counters["signature_rejected"] == 7)  # 1 + flying()'s 5 + 1
        status = link.poll()
        assert status.heartbeat_time is None and not status.armed and status.altitude is None
        assert link.target is None and link._endpoint.reply_address is None
        link.send_velocity(1.0, 0.0)
        assert unsigned.drain(0.1) == [] and wrong_key.drain(0.1) == []

        genuine.heartbeat(armed=False, custom_mode=COPTER_LOITER)
        status = _poll_until(link, lambda s: s.heartbeat_time is not None)
        assert status.mode == "LOITER" and not status.armed
        unsigned.heartbeat(armed=True)  # an unsigned GUIDED+armed heartbeat changes nothing now either
        _poll_until(link, lambda s: link.counters["signature_rejected"] == 8)
        assert link.poll().mode == "LOITER"
    finally:
        for end in (link, unsigned, wrong_key, genuine):
            end.close()


def test_a_forged_future_timestamp_does_not_lock_the_autopilot_out(port):
    """pymavlink advanced a stream's timestamp before checking the signature: one forged frame with
    the autopilot's ids and a far-future timestamp made every later genuine frame 'old'."""
    link = ArduPilotLink(f"udpin:127.0.0.1:{port}", signing_key=KEY)
    forger = _signed_peer(port, OTHER_KEY)
    forger.mav.signing.timestamp = signing_timestamp() + 10**12  # ~115 days ahead
    genuine = _signed_peer(port, KEY)
    try:
        forger.heartbeat()  # same link id, system and component as the genuine autopilot
        _poll_until(link, lambda s: link.counters["signature_rejected"] == 1)
        genuine.heartbeat(armed=True)
        status = _poll_until(link, lambda s: s.heartbeat_time is not None)
        assert status.armed
    finally:
        for end in (link, forger, genuine):
            end.close()


def test_a_replayed_frame_is_rejected(port):
    link = ArduPilotLink(f"udpin:127.0.0.1:{port}", signing_key=KEY)
    genuine = _signed_peer(port, KEY)
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        msg = genuine.mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                           mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, COPTER_LOITER, 4)
        frame = msg.pack(genuine.mav)
        raw.sendto(frame, ("127.0.0.1", port))
        _poll_until(link, lambda s: s.mode == "LOITER")
        genuine.heartbeat(armed=True)  # GUIDED
        _poll_until(link, lambda s: s.mode == "GUIDED")
        raw.sendto(frame, ("127.0.0.1", port))  # the old LOITER frame again
        _poll_until(link, lambda s: link.counters["signature_rejected"] == 1)
        assert link.poll().mode == "GUIDED"
    finally:
        link.close()
        genuine.close()
        raw.close()
