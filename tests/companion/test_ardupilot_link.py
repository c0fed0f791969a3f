"""ArduPilotLink against a real pymavlink peer on loopback: what goes on the wire, what comes back."""

from __future__ import annotations

import math
import os
import socket
import time

import numpy as np
import pytest

from companion.autopilot.ardupilot import VELOCITY_YAW_RATE_TYPE_MASK, ArduPilotLink, statustext_chunks
from companion.autopilot.link import LandedState
from companion.autopilot.mavlink_adapter import mavlink
from companion.common.errors import UserError
from tests.companion.mavlink_peer import COPTER_LOITER, AutopilotPeer, free_tcp_port, free_udp_port


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def linked():
    """A link listening on UDP and a peer (system 7) that has sent it one heartbeat."""
    port = free_udp_port()
    clock = Clock()
    link = ArduPilotLink(f"udpin:127.0.0.1:{port}", clock=clock, source_system=7, autopilot=(7, 1))
    peer = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=7, compid=1)
    peer.heartbeat(armed=True)
    _poll_until(link, lambda s: s.heartbeat_time is not None)
    yield link, peer, clock
    link.close()
    peer.close()


def _poll_until(link, condition, timeout=3.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status = link.poll()
        if condition(status):
            return status
        time.sleep(0.005)
    raise AssertionError(f"condition not reached; last status {status}")


def test_heartbeat_sets_target_armed_and_guided(linked):
    link, peer, clock = linked
    assert link.target == (7, 1)
    status = link.poll()
    assert status.armed and status.guided and status.mode == "GUIDED"
    assert status.heartbeat_time == clock.t
    peer.heartbeat(armed=False, custom_mode=COPTER_LOITER)
    status = _poll_until(link, lambda s: not s.armed)
    assert not status.guided and status.mode == "LOITER"


def test_status_streams_decode_landed_state_altitude_and_climb(linked):
    link, peer, _ = linked
    peer.flying(altitude=1.5, climb=0.25)
    status = _poll_until(link, lambda s: s.climb_rate is not None and s.altitude is not None
                         and s.landed_state is not None)
    assert status.landed_state is LandedState.IN_AIR
    assert status.altitude == pytest.approx(1.5)
    assert status.climb_rate == pytest.approx(0.25)


def test_local_position_used_without_gps(linked):
    link, peer, _ = linked
    peer.mav.local_position_ned_send(0, 1.0, 2.0, -2.5, 0.0, 0.0, -0.4)
    status = _poll_until(link, lambda s: s.altitude is not None)
    assert status.altitude == pytest.approx(2.5)
    assert status.climb_rate == pytest.approx(0.4)


def test_measured_velocity_turned_into_the_body_frame(linked):
    link, peer, clock = linked
    peer.mav.attitude_send(0, 0.0, 0.0, math.radians(90.0), 0.0, 0.0, 0.0)  # nose east
    peer.mav.local_position_ned_send(0, 0.0, 0.0, -1.5, 1.0, 2.0, 0.0)  # 1 m/s north, 2 m/s east
    status = _poll_until(link, lambda s: s.velocity_body is not None)
    assert status.velocity_body == pytest.approx((2.0, 1.0))  # forward = east, left = north
    assert status.velocity_time == clock.t
    assert "ATTITUDE" in {mavlink.mavlink_map[int(m.param1)].msgname
                          for m in peer.drain(0.2) if m.get_type() == "COMMAND_LONG"}


def test_velocity_without_a_current_heading_is_not_measured(linked):
    link, peer, clock = linked
    peer.mav.local_position_ned_send(0, 0.0, 0.0, -1.5, 1.0, 0.0, 0.0)
    status = _poll_until(link, lambda s: s.altitude is not None)
    assert status.velocity_body is None and status.velocity_time is None  # no ATTITUDE yet
    peer.mav.attitude_send(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    peer.mav.local_position_ned_send(0, 0.0, 0.0, -1.5, 1.0, 0.0, 0.0)
    status = _poll_until(link, lambda s: s.velocity_body is not None)
    measured_at = status.velocity_time
    clock.t += 0.6  # the heading is now too old to turn the next velocity
    peer.mav.local_position_ned_send(0, 0.0, 0.0, -1.5, 0.0, 1.0, 0.0)
    time.sleep(0.1)
    status = link.poll()
    assert status.velocity_body == pytest.approx((1.0, 0.0)) and status.velocity_time == measured_at


def test_velocity_setpoint_on_the_wire(linked):
    link, peer, _ = linked
    link.send_velocity(1.5, 0.4)  # FLU: turning left
    msg = peer.wait_for("SET_POSITION_TARGET_LOCAL_NED")
    assert msg is not None
    assert msg.get_msgbuf()[0] == 0xFD  # MAVLink 2
    assert msg.type_mask == VELOCITY_YAW_RATE_TYPE_MASK == 0x05C7
    assert msg.coordinate_frame == mavlink.MAV_FRAME_BODY_OFFSET_NED
    assert (msg.target_system, msg.target_component) == (7, 1)
    assert (msg.get_srcSystem(), msg.get_srcComponent()) == (7, 191)
    assert msg.vx == pytest.approx(1.5)
    assert msg.vy == 0.0 and msg.vz == 0.0
    assert msg.yaw_rate == pytest.approx(-0.4)  # FRD: clockwise positive
    assert link.counters["setpoints_sent"] == 1
    link.send_velocity(-0.3, 0.0, lateral=0.2)  # the shield's brake: back and to the left
    msg = peer.wait_for("SET_POSITION_TARGET_LOCAL_NED")
    assert msg.vx == pytest.approx(-0.3) and msg.vy == pytest.approx(-0.2)  # FRD: right positive
    link.send_velocity(1.0, 0.0, vertical=0.4)  # climbing toward a waypoint's height
    msg = peer.wait_for("SET_POSITION_TARGET_LOCAL_NED")
    assert msg.type_mask == 0x05C7 and msg.vz == pytest.approx(-0.4)  # NED: down positive


def test_non_finite_setpoint_goes_out_as_zero(linked):
    link, peer, _ = linked
    link.send_velocity(float("nan"), float("inf"))
    msg = peer.wait_for("SET_POSITION_TARGET_LOCAL_NED")
    assert msg.vx == 0.0 and msg.yaw_rate == 0.0


def test_no_setpoint_before_an_autopilot_is_heard():
    port = free_udp_port()
    link = ArduPilotLink(f"udpin:127.0.0.1:{port}")
    link.send_velocity(1.0, 0.0)
    assert link.counters["setpoints_without_target"] == 1
    assert link.counters["setpoints_sent"] == 0
    link.close()


def test_obstacle_distance_fields(linked):
    link, peer, clock = linked
    sectors = np.arange(72, dtype=np.uint16) * 10 + 20
    sectors[5] = 1001
    link.send_obstacle_distance(sectors)
    msg = peer.wait_for("OBSTACLE_DISTANCE")
    assert msg is not None
    assert list(msg.distances) == [int(v) for v in sectors]
    assert msg.increment == 5
    assert msg.min_distance == 10 and msg.max_distance == 1000
    assert msg.frame == mavlink.MAV_FRAME_BODY_FRD
    assert msg.sensor_type == mavlink.MAV_DISTANCE_SENSOR_LASER
    assert msg.angle_offset == 0.0 and msg.increment_f == 0.0
    assert msg.time_usec == int(clock.t * 1e6)
    with pytest.raises(ValueError, match="72"):
        link.send_obstacle_distance(np.zeros(36, np.uint16))


def test_companion_heartbeat(linked):
    link, peer, _ = linked
    link.send_heartbeat()
    msg = peer.wait_for("HEARTBEAT")
    assert msg.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    assert msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID
    assert msg.get_srcComponent() == 191 == mavlink.MAV_COMP_ID_ONBOARD_COMPUTER


def test_statustext_short_and_chunked(linked):
    link, peer, _ = linked
    link.send_statustext("HOLD: lidar stale", mavlink.MAV_SEVERITY_WARNING)
    msg = peer.wait_for("STATUSTEXT")
    assert msg.text == "HOLD: lidar stale" and msg.severity == mavlink.MAV_SEVERITY_WARNING
    assert msg.id == 0
    long_text = "x" * 60 + "END"
    link.send_statustext(long_text, mavlink.MAV_SEVERITY_INFO)
    chunks = [peer.wait_for("STATUSTEXT"), peer.wait_for("STATUSTEXT")]
    assert [c.chunk_seq for c in chunks] == [0, 1]
    assert chunks[0].id == chunks[1].id != 0
    assert "".join(c.text for c in chunks) == long_text


def test_statustext_chunk_boundaries():
    assert statustext_chunks("a" * 50) == [(b"a" * 50, 0, 0)]
    assert statustext_chunks("a" * 100) == [(b"a" * 50, 1, 0), (b"a" * 50, 1, 1), (b"", 1, 2)]
    assert len(statustext_chunks("a" * 1000)) == 5  # capped at 200 bytes + terminator


def test_requests_status_streams_until_they_arrive(linked):
    link, peer, clock = linked
    requests = []
    deadline = time.monotonic() + 2.0
    while len(requests) < 5 and time.monotonic() < deadline:
        requests += [m for m in peer.drain(0.01) if m.get_type() == "COMMAND_LONG"]
    assert all(m.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL for m in requests)
    assert all((m.target_system, m.target_component) == (7, 1) for m in requests)
    assert sorted(int(m.param1) for m in requests) == sorted(
        [mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
         mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_VFR_HUD,
         mavlink.MAVLINK_MSG_ID_ATTITUDE])
    assert all(m.param2 == 100_000 for m in requests)  # 10 Hz
    # Streams that are arriving are not asked for again; the missing one is, 5 s later.
    clock.t += 5.5
    peer.flying(velocity_ned=None)
    time.sleep(0.05)  # loopback delivery
    status = link.poll()  # reads the streams first, then asks for what is still missing
    assert status.landed_state is not None
    again = [m for m in peer.drain(0.2) if m.get_type() == "COMMAND_LONG"]
    assert [int(m.param1) for m in again] == [mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
                                               mavlink.MAVLINK_MSG_ID_ATTITUDE]


def test_refused_command_is_counted(linked):
    link, peer, _ = linked
    peer.mav.command_ack_send(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_RESULT_DENIED, 0, 0, 7, 191)
    _poll_until(link, lambda s: link.counters["command_nacks"] == 1)


def test_acks_addressed_to_others_are_not_the_companions(linked):
    """ArduPilot sends every COMMAND_ACK on every link: 20 NACKs meant for the GCS are not ours."""
    link, peer, _ = linked
    for _ in range(20):
        peer.mav.command_ack_send(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_RESULT_DENIED, 0, 0, 255, 190)
    peer.mav.command_ack_send(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_RESULT_DENIED, 0, 0, 7, 0)
    peer.mav.command_ack_send(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_RESULT_DENIED)  # no target
    _poll_until(link, lambda s: link.counters["acks_for_others"] == 22)
    assert link.counters["command_nacks"] == 0


def test_other_systems_and_ground_stations_are_ignored(linked):
    link, _, _ = linked
    port = int(link._endpoint.connect.rsplit(":", 1)[1])
    other = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=9, compid=1)
    gcs = AutopilotPeer(f"udpout:127.0.0.1:{port}", sysid=255, compid=190)
    other.heartbeat(armed=False)
    gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    _poll_until(link, lambda s: link.counters["foreign_heartbeats"] == 2)
    assert link.target == (7, 1)
    assert link.poll().armed  # still the locked autopilot's state
    other.close()
    gcs.close()


def test_garbage_and_corrupt_frames_are_counted_not_fatal(linked):
    link, peer, _ = linked
    port = int(link._endpoint.connect.rsplit(":", 1)[1])
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rng = np.random.default_rng(1)
    raw.sendto(rng.integers(0, 256, 300, dtype=np.uint8).tobytes(), ("127.0.0.1", port))
    good = peer.mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                     mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, COPTER_LOITER, 4)
    frame = bytearray(good.pack(peer.mav))
    frame[-1] ^= 0xFF  # broken CRC
    raw.sendto(bytes(frame), ("127.0.0.1", port))
    raw.sendto(b"\xfd\x09", ("127.0.0.1", port))  # truncated header
    raw.close()
    time.sleep(0.05)
    status = link.poll()
    assert link.counters["bad_data"] >= 2
    assert status.mode == "GUIDED"  # the corrupt LOITER heartbeat was not believed
    peer.heartbeat(armed=True, custom_mode=COPTER_LOITER)
    _poll_until(link, lambda s: s.mode == "LOITER")


def test_tcp_connection_string():
    port = free_tcp_port()
    server = AutopilotPeer(f"tcpin:127.0.0.1:{port}")
    link = ArduPilotLink(f"tcp:127.0.0.1:{port}")
    try:
        deadline = time.monotonic() + 3
        while server.conn.port is None and time.monotonic() < deadline:
            server.drain(0.01)  # accepts the connection
        server.heartbeat()
        _poll_until(link, lambda s: s.guided)
        link.send_velocity(0.5, -0.2)
        msg = server.wait_for("SET_POSITION_TARGET_LOCAL_NED")
        assert msg.vx == pytest.approx(0.5) and msg.yaw_rate == pytest.approx(0.2)
    finally:
        link.close()
        server.close()


def test_serial_device_with_baud():
    """A pseudo-terminal stands in for /dev/ttyTHS1: the link opens it as a serial port."""
    master, slave = os.openpty()
    try:
        link = ArduPilotLink(os.ttyname(slave), baud=921600)
        link.send_heartbeat()
        deadline = time.monotonic() + 2
        data = b""
        while len(data) < 21 and time.monotonic() < deadline:
            data += os.read(master, 256)
        parser = mavlink.MAVLink(None)
        msg = parser.parse_char(data)
        assert msg.get_type() == "HEARTBEAT" and msg.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
        link.close()
    finally:
        os.close(master)
        os.close(slave)


def test_unopenable_connections_are_user_errors(tmp_path):
    with pytest.raises(UserError, match=r"autopilot\.connect: cannot open 'tcp:127\.0\.0\.1:"):
        ArduPilotLink(f"tcp:127.0.0.1:{free_tcp_port()}")
    with pytest.raises(UserError, match=r"autopilot\.connect"):
        ArduPilotLink(str(tmp_path / "ttyMISSING"))
    with pytest.raises(UserError, match=r"autopilot\.connect"):
        ArduPilotLink("udpin:127.0.0.1")


def test_obstacle_distance_sectors_clockwise_on_the_wire(linked):
    """ArduPilot reads sector j at j × 5° clockwise; scan bins run counter-clockwise."""
    from companion.autopilot.obstacle_distance import obstacle_distance_from_scan

    link, peer, _ = linked
    max_range = 10.0
    scan = np.ones(360, np.float32)
    for j in range(72):  # an obstacle straight at the centre of every sector, each at its own range
        scan[(-5 * j) % 360] = (1.0 + 0.05 * j) / max_range
    link.send_obstacle_distance(obstacle_distance_from_scan(scan, max_range))
    msg = peer.wait_for("OBSTACLE_DISTANCE")
    for j in range(72):
        assert abs(msg.distances[j] - (100 + 5 * j)) <= 1, f"sector {j}"
    # Named directions: right (FLU bin 270) is 90° clockwise = sector 18, left is sector 54.
    scan = np.ones(360, np.float32)
    scan[270], scan[90], scan[0], scan[180] = 0.2, 0.3, 0.4, 0.5
    link.send_obstacle_distance(obstacle_distance_from_scan(scan, max_range))
    d = peer.wait_for("OBSTACLE_DISTANCE").distances
    assert (d[18], d[54], d[0], d[36]) == (200, 300, 400, 500)
    assert sum(v == 1001 for v in d) == 72 - 4  # a bin at a sector centre feeds only that sector
