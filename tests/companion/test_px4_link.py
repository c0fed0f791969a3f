"""Px4Link (native MAVSDK) against a real pymavlink peer posing as PX4 on loopback."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from companion.autopilot.link import LandedState
from companion.autopilot.mavlink_adapter import mavlink
from companion.autopilot.px4 import Px4Link
from companion.common.errors import UserError
from tests.companion.mavlink_peer import (
    PX4_MAIN_OFFBOARD,
    PX4_MAIN_POSCTL,
    SimulatedAutopilot,
    free_udp_port,
    px4_custom_mode,
)


def _wait(condition, timeout=5.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.01)
    raise AssertionError("condition not reached")


@pytest.fixture(scope="module")
def px4():
    """One link and one simulated PX4 for the module (MAVSDK discovery takes a moment)."""
    port = free_udp_port()
    link = Px4Link(f"udpin://127.0.0.1:{port}", source_system=1, setpoint_timeout=0.3)
    vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{port}", autopilot=mavlink.MAV_AUTOPILOT_PX4)
    _wait(lambda: link.poll().heartbeat_time is not None and link.poll().altitude is not None)
    yield link, vehicle
    link.close()
    vehicle.close()


def test_status_from_telemetry(px4):
    link, vehicle = px4
    vehicle.altitude, vehicle.climb = 1.5, 0.25
    status = _wait(lambda: (s := link.poll()).climb_rate is not None and abs(s.climb_rate - 0.25) < 1e-3
                   and s)
    assert status.armed and status.guided and status.mode == "OFFBOARD"
    assert status.landed_state is LandedState.IN_AIR
    assert status.altitude == pytest.approx(1.5)
    assert time.monotonic() - status.heartbeat_time < 1.0
    vehicle.custom_mode = px4_custom_mode(PX4_MAIN_POSCTL)
    status = _wait(lambda: (s := link.poll()).mode == "POSCTL" and s)
    assert not status.guided
    vehicle.custom_mode = px4_custom_mode(PX4_MAIN_OFFBOARD)
    _wait(lambda: link.poll().guided)


def test_measured_velocity_turned_into_the_body_frame(px4):
    link, vehicle = px4
    vehicle.yaw_ned, vehicle.velocity_ned = math.radians(90.0), (1.0, 2.0)  # nose east
    try:
        status = _wait(lambda: (s := link.poll()).velocity_body is not None
                       and abs(s.velocity_body[0] - 2.0) < 1e-3 and s)
        assert status.velocity_body == pytest.approx((2.0, 1.0), abs=1e-3)  # forward east, left north
        assert time.monotonic() - status.velocity_time < 0.5
    finally:
        vehicle.yaw_ned, vehicle.velocity_ned = 0.0, (0.0, 0.0)


def test_companion_heartbeat_is_an_onboard_controller(px4):
    link, vehicle = px4
    link.send_heartbeat()  # MAVSDK sends it on its own; the call must not add a second stream
    msg = vehicle.wait_for("HEARTBEAT")
    assert msg.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    assert msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID
    assert (msg.get_srcSystem(), msg.get_srcComponent()) == (1, 191)
    t0 = time.monotonic()
    time.sleep(2.2)
    assert 2 <= len(vehicle.times("HEARTBEAT", since=t0)) <= 3  # 1 Hz


def test_velocity_setpoint_on_the_wire(px4):
    link, vehicle = px4
    t0 = time.monotonic()
    link.send_velocity(1.5, 0.4)  # FLU: turning left
    msg = vehicle.wait_for("SET_POSITION_TARGET_LOCAL_NED", since=t0)
    assert msg is not None
    assert msg.type_mask == 0x05C7
    assert msg.coordinate_frame == mavlink.MAV_FRAME_BODY_NED  # MAVSDK's body frame for PX4
    assert (msg.target_system, msg.target_component) == (1, 1)
    assert msg.vx == pytest.approx(1.5) and msg.vy == 0.0 and msg.vz == 0.0
    assert msg.yaw_rate == pytest.approx(-0.4, abs=1e-5)  # FRD, clockwise positive
    t1 = time.monotonic()
    link.send_velocity(-0.3, 0.0, lateral=0.2)  # the shield's brake: back and to the left
    msg = vehicle.wait_for("SET_POSITION_TARGET_LOCAL_NED", since=t1, condition=lambda m: m.vx < 0)
    assert msg.vx == pytest.approx(-0.3) and msg.vy == pytest.approx(-0.2)  # FRD: right positive
    t2 = time.monotonic()
    link.send_velocity(1.0, 0.0, vertical=-0.3)  # descending toward a waypoint's height
    msg = vehicle.wait_for("SET_POSITION_TARGET_LOCAL_NED", since=t2, condition=lambda m: m.vz != 0)
    assert msg.vx == pytest.approx(1.0) and msg.vz == pytest.approx(0.3)  # down_m_s: down positive


def test_setpoint_repetition_stops_when_the_companion_stops(px4):
    """MAVSDK repeats setpoints at 20 Hz; the link ends that within setpoint_timeout of the last one."""
    link, vehicle = px4
    for _ in range(5):
        link.send_velocity(0.5, 0.0)
        time.sleep(0.1)
    last_call = time.monotonic()
    time.sleep(1.0)
    times = vehicle.times("SET_POSITION_TARGET_LOCAL_NED", since=last_call)
    assert times, "MAVSDK sent nothing after the last call"
    assert max(times) - last_call < 0.3 + 0.15
    assert link.counters["setpoint_repeat_stopped"] >= 1
    # Sending again restarts the stream.
    t0 = time.monotonic()
    link.send_velocity(0.0, 0.0)
    assert vehicle.wait_for("SET_POSITION_TARGET_LOCAL_NED", since=t0, timeout=2.0) is not None


def test_setpoints_stream_before_offboard(px4):
    """The pilot can only switch to OFFBOARD while setpoints already flow: they must flow in POSCTL."""
    link, vehicle = px4
    vehicle.custom_mode = px4_custom_mode(PX4_MAIN_POSCTL)
    _wait(lambda: link.poll().mode == "POSCTL")
    t0 = time.monotonic()
    for _ in range(10):
        link.send_velocity(0.0, 0.0)
        time.sleep(0.1)
    assert len(vehicle.times("SET_POSITION_TARGET_LOCAL_NED", since=t0)) >= 10
    vehicle.custom_mode = px4_custom_mode(PX4_MAIN_OFFBOARD)
    _wait(lambda: link.poll().guided)


def test_obstacle_distance_and_statustext(px4):
    link, vehicle = px4
    t0 = time.monotonic()
    sectors = np.arange(72, dtype=np.uint16) * 7 + 15
    link.send_obstacle_distance(sectors)
    msg = vehicle.wait_for("OBSTACLE_DISTANCE", since=t0)
    assert list(msg.distances) == [int(v) for v in sectors]
    assert msg.increment == 5 and msg.min_distance == 10 and msg.max_distance == 1000
    assert msg.frame == mavlink.MAV_FRAME_BODY_FRD
    assert msg.sensor_type == mavlink.MAV_DISTANCE_SENSOR_LASER
    assert msg.get_srcComponent() == 191
    link.send_statustext("HOLD: lidar stale", mavlink.MAV_SEVERITY_WARNING)
    text = vehicle.wait_for("STATUSTEXT", since=t0)
    assert text.text == "HOLD: lidar stale" and text.severity == mavlink.MAV_SEVERITY_WARNING
    long_text = "y" * 70
    link.send_statustext(long_text, mavlink.MAV_SEVERITY_INFO)
    _wait(lambda: len(vehicle.messages("STATUSTEXT", since=t0)) >= 3)
    chunks = vehicle.messages("STATUSTEXT", since=t0)[1:3]
    assert [c.chunk_seq for c in chunks] == [0, 1] and chunks[0].id == chunks[1].id != 0
    assert "".join(c.text for c in chunks) == long_text


def test_before_the_autopilot_is_found_nothing_is_sent():
    link = Px4Link(f"udpin://127.0.0.1:{free_udp_port()}")
    try:
        status = link.poll()
        assert status.heartbeat_time is None and not link.connected
        link.send_velocity(1.0, 0.0)
        link.send_obstacle_distance(np.full(72, 1001, np.uint16))
        assert link.counters["setpoints_without_autopilot"] == 1
        assert link.counters["messages_without_autopilot"] == 1
    finally:
        link.close()


def test_bad_connection_url_is_a_user_error():
    with pytest.raises(UserError, match=r"autopilot\.connect: cannot open 'serial:///dev/nonexistent-tty:57600'"):
        Px4Link("serial:///dev/nonexistent-tty:57600")
    with pytest.raises(UserError, match=r"MAVLink connection 'bogus://what': unknown scheme 'bogus'"):
        Px4Link("bogus://what")


def test_an_impostor_px4_that_speaks_first_is_never_used():
    """first_autopilot() took whichever autopilot MAVSDK heard first (system 42, OFFBOARD, armed), and
    MAVSDK's own udpin:// wrote everything to every address it had heard."""
    port = free_udp_port()
    link = Px4Link(f"udpin://127.0.0.1:{port}", autopilot=(1, 1))
    impostor = SimulatedAutopilot(f"udpout:127.0.0.1:{port}", autopilot=mavlink.MAV_AUTOPILOT_PX4, sysid=42)
    vehicle = None
    try:
        _wait(lambda: link.poll() and link.counters["foreign_messages"] >= 10)  # never reach MAVSDK
        time.sleep(1.0)
        status = link.poll()
        assert not link.connected and status.heartbeat_time is None and not status.armed
        link.send_velocity(1.0, 0.0)
        assert link.counters["setpoints_without_autopilot"] == 1
        vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{port}", autopilot=mavlink.MAV_AUTOPILOT_PX4, sysid=1)
        _wait(lambda: link.poll().heartbeat_time is not None and link.connected)
        assert link._system.get_system_id() == 1
        t0 = time.monotonic()
        link.send_velocity(0.5, 0.0)
        msg = vehicle.wait_for("SET_POSITION_TARGET_LOCAL_NED", since=t0)
        assert (msg.target_system, msg.target_component) == (1, 1)
        time.sleep(0.3)
        assert impostor.messages() == [], "MAVSDK's udpin:// wrote to every address it had heard"
    finally:
        link.close()
        impostor.close()
        if vehicle is not None:
            vehicle.close()


def test_a_normal_start_logs_no_warning_or_error(caplog):
    """MAVSDK sends its first heartbeat as soon as its raw connection exists: before, the transport
    subscribed after, and that heartbeat failed with "ERROR mavsdk: Sending message failed" at
    every start. The link then finds the autopilot and its first heartbeat goes out."""
    port = free_udp_port()
    with caplog.at_level("DEBUG"):
        link = Px4Link(f"udpin://127.0.0.1:{port}", source_system=1)
        vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{port}", autopilot=mavlink.MAV_AUTOPILOT_PX4)
        try:
            _wait(lambda: link.poll().heartbeat_time is not None)
            assert vehicle.wait_for("HEARTBEAT").type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
        finally:
            link.close()
            vehicle.close()
    loud = [f"{r.levelname} {r.name}: {r.getMessage()}" for r in caplog.records if r.levelno >= 30]
    assert loud == []
