"""The simulated autopilot's sockets: real UDP/TCP on loopback, hostile input counted and dropped."""

from __future__ import annotations

import argparse
import os
import signal
import socket
import threading
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.common.errors import UserError
from flightsim.sitl.companion_setup import free_tcp_port
from flightsim.sitl.sim_autopilot.endpoint import LinkSpec, MavlinkEndpoint
from flightsim.sitl.sim_autopilot.server import SimAutopilotServer, command, configure_parser


def recv_messages(sock: socket.socket, duration: float) -> list:
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    out = []
    end = time.monotonic() + duration
    while time.monotonic() < end:
        sock.settimeout(max(0.01, end - time.monotonic()))
        try:
            data = sock.recv(65535)
        except (TimeoutError, OSError):
            continue
        out.extend(m for m in parser.parse_buffer(data) or [] if m.get_type() != "BAD_DATA")
    return out


def test_link_spec_errors_name_the_problem():
    assert LinkSpec.parse("udpin:127.0.0.1:14550") == LinkSpec("udpin", "127.0.0.1", 14550)
    with pytest.raises(UserError, match="expected udpin"):
        LinkSpec.parse("serial:/dev/ttyUSB0")
    with pytest.raises(UserError, match="not a number"):
        LinkSpec.parse("udpin:127.0.0.1:abc")


def test_port_in_use_is_a_user_error():
    first = MavlinkEndpoint(["udpin:127.0.0.1:0"])
    try:
        port = first.address(0)[1]
        with pytest.raises(UserError, match="cannot open"):
            MavlinkEndpoint([f"udpin:127.0.0.1:{port}"])
    finally:
        first.close()


def test_udp_server_answers_and_counts_garbage_and_corrupt_frames():
    with SimAutopilotServer("ardupilot", ["udpin:127.0.0.1:0"]) as server:
        port = server.endpoint.address(0)[1]
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        gcs = mavlink.MAVLink(None, 255, 190)
        good = mavlink.MAVLink_param_request_read_message(1, 1, b"GUID_TIMEOUT", -1).pack(gcs)
        corrupt = bytearray(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(gcs))
        corrupt[-1] ^= 0xFF  # bad CRC
        for data in (b"\x00\x01garbage\xfe\xfd" * 20, bytes(corrupt), good[:7], good):
            sock.sendto(data, ("127.0.0.1", port))
        msgs = recv_messages(sock, 1.2)
        sock.close()
    kinds = [m.get_type() for m in msgs]
    assert "HEARTBEAT" in kinds and "ATTITUDE" in kinds  # default streams reach the peer
    values = [m for m in msgs if m.get_type() == "PARAM_VALUE"]
    assert values and values[0].param_id == "GUID_TIMEOUT" and values[0].param_value == pytest.approx(3.0)
    assert server.endpoint.counters["malformed"] >= 2
    assert server.error is None


def test_udpout_and_tcp_links_reach_their_peers():
    listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    listener.bind(("127.0.0.1", 0))
    udp_port = listener.getsockname()[1]
    with SimAutopilotServer("px4", [f"udpout:127.0.0.1:{udp_port}", "tcpin:127.0.0.1:0"]) as server:
        tcp = socket.create_connection(server.endpoint.address(1), timeout=2.0)
        udp_msgs = recv_messages(listener, 1.2)
        tcp_msgs = recv_messages(tcp, 0.5)
        tcp.close()
    listener.close()
    assert any(m.get_type() == "HEARTBEAT" and m.autopilot == mavlink.MAV_AUTOPILOT_PX4 for m in udp_msgs)
    assert any(m.get_type() == "HEARTBEAT" for m in tcp_msgs)


def test_the_server_command_gives_the_callers_signal_handlers_back():
    """``avoid-sim autopilot`` stops on SIGINT/SIGTERM; called in a process that goes on (a test, a
    script), it must not leave that process a Ctrl-C that only sets a dead server's stop event."""
    parser = argparse.ArgumentParser()
    configure_parser(parser)
    args = parser.parse_args(["--link", f"tcpin:127.0.0.1:{free_tcp_port()}"])
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    # os.kill from another thread: the handler still runs on the main thread
    timer = threading.Timer(1.0, os.kill, (os.getpid(), signal.SIGTERM))
    timer.start()
    try:
        assert command(args) == 0
    finally:
        timer.cancel()
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
