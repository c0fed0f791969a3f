"""ArduCopter personality: modes, arming, guided take-off and velocity control, GUID_TIMEOUT, streams,
parameters and proximity stop (pure logic with a fake clock; the take-off flies the real JSBSim vehicle)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from flightsim.sitl.sim_autopilot.ardupilot import ArduCopterAutopilot, CopterMode
from flightsim.sitl.sim_autopilot.common import Guidance
from flightsim.sitl.sim_autopilot.params import default_table
from flightsim.vehicle.quadrotor import Vehicle, VehicleConfig
from tests.sitl.helpers import (
    COMPANION,
    acks,
    airborne,
    body_velocity,
    command,
    fly,
    on_ground,
    wire,
)

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
FAILED = mavlink.MAV_RESULT_FAILED


def make(state=None, response: bool = False) -> ArduCopterAutopilot:
    """Without the firmware response by default: these tests check the target the firmware's
    position controller is given (the response to it is tested in test_autopilot_response.py)."""
    ap = ArduCopterAutopilot(default_table("ardupilot"), response=response)
    ap.observe(state or on_ground())
    return ap


def flying_guided(yaw: float = 0.0) -> ArduCopterAutopilot:
    ap = make(airborne(yaw=yaw))
    ap.armed = True
    ap.set_mode(CopterMode.GUIDED)
    return ap


def test_heartbeat_is_ardupilot_copter_with_custom_mode():
    ap = make()
    ap.handle(wire(mavlink.MAVLink_set_mode_message(1, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4)), 0, 0.0)
    hb = ap.build("HEARTBEAT")
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert hb.type == mavlink.MAV_TYPE_QUADROTOR
    assert hb.custom_mode == CopterMode.GUIDED
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED


@pytest.mark.parametrize("mode", [0, 2, 4, 5, 6, 9, 17])
def test_do_set_mode_accepts_every_copter_mode(mode):
    ap = make()
    out = ap.handle(command(mavlink.MAV_CMD_DO_SET_MODE, 1, mode), 0, 0.0)
    assert acks(out) == [(mavlink.MAV_CMD_DO_SET_MODE, ACCEPTED)]
    assert ap.build("HEARTBEAT").custom_mode == mode


def test_unknown_mode_and_auto_without_mission_are_refused():
    ap = make()
    assert acks(ap.handle(command(mavlink.MAV_CMD_DO_SET_MODE, 1, 42), 0, 0.0))[0][1] == FAILED
    assert acks(ap.handle(command(mavlink.MAV_CMD_DO_SET_MODE, 1, 3), 0, 0.0))[0][1] == FAILED
    assert ap.mode == CopterMode.STABILIZE


def test_arming_only_in_armable_modes_and_disarm_refused_in_flight():
    ap = make()
    ap.set_mode(CopterMode.LAND)
    assert acks(ap.handle(command(400, 1), 0, 0.0)) == [(400, FAILED)]
    assert not ap.armed
    ap.set_mode(CopterMode.GUIDED)
    assert acks(ap.handle(command(400, 1), 0, 0.0)) == [(400, ACCEPTED)]
    assert ap.build("HEARTBEAT").base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    ap.observe(airborne())
    assert acks(ap.handle(command(400, 0), 0, 1.0)) == [(400, FAILED)]
    assert ap.armed
    assert acks(ap.handle(command(400, 0, 21196), 0, 1.0)) == [(400, ACCEPTED)]  # forced
    assert not ap.armed


def test_takeoff_needs_guided_armed_and_landed():
    ap = make()
    ap.set_mode(CopterMode.GUIDED)
    assert acks(ap.handle(command(22, 0, 0, 0, 0, 0, 0, 1.5), 0, 0.0)) == [(22, FAILED)]  # disarmed
    ap.handle(command(400, 1), 0, 0.0)
    ap.set_mode(CopterMode.LOITER)
    assert acks(ap.handle(command(22, 0, 0, 0, 0, 0, 0, 1.5), 0, 0.0)) == [(22, FAILED)]  # not GUIDED
    ap.set_mode(CopterMode.GUIDED)
    assert acks(ap.handle(command(22, 0, 0, 0, 0, 0, 0, 1.5), 0, 0.0)) == [(22, ACCEPTED)]
    assert ap.landed_state() == mavlink.MAV_LANDED_STATE_TAKEOFF


@pytest.fixture(scope="module")
def vehicle():
    return Vehicle(VehicleConfig())


def test_guided_takeoff_flies_the_vehicle_to_the_altitude(vehicle):
    ap = make(vehicle.reset((0.0, 0.0, 0.0), 0.0, on_ground=True))
    ap.set_mode(CopterMode.GUIDED)
    ap.handle(command(400, 1), 0, 0.0)
    ap.handle(command(22, 0, 0, 0, 0, 0, 0, 1.5), 0, 0.0)
    t = fly(ap, vehicle, 0.0, 6.0)
    assert ap.guidance == Guidance.HOLD
    assert ap.landed_state() == mavlink.MAV_LANDED_STATE_IN_AIR
    assert ap.build("GLOBAL_POSITION_INT").relative_alt == pytest.approx(1500, abs=120)
    assert abs(ap.build("LOCAL_POSITION_NED").z + 1.5) < 0.12
    # LAND brings it down and disarms on touch-down
    ap.set_mode(CopterMode.LAND)
    fly(ap, vehicle, t, 6.0)
    assert not ap.armed
    assert ap.landed_state() == mavlink.MAV_LANDED_STATE_ON_GROUND


def test_velocity_during_takeoff_ends_the_climb(vehicle):
    """ArduCopter: a velocity target switches GUIDED out of its take-off sub-mode (the climb freezes)."""
    ap = make(vehicle.reset((0.0, 0.0, 0.0), 0.0, on_ground=True))
    ap.set_mode(CopterMode.GUIDED)
    ap.handle(command(400, 1), 0, 0.0)
    ap.handle(command(22, 0, 0, 0, 0, 0, 0, 3.0), 0, 0.0)
    t = fly(ap, vehicle, 0.0, 0.8)
    ap.handle(body_velocity(0.0), 1, t)
    height = ap.snap.position[2]
    fly(ap, vehicle, t, 2.0, each=lambda now: ap.handle(body_velocity(0.0), 1, now))
    assert ap.guidance == Guidance.VELOCITY
    assert ap.snap.position[2] < height + 0.5 < 3.0


def test_body_offset_velocity_is_rotated_by_heading_and_yaw_rate_is_frd():
    yaw_enu = math.radians(90.0)  # facing North
    ap = flying_guided(yaw=yaw_enu)
    ap.handle(body_velocity(1.0, yaw_rate_frd=0.5), 1, 0.0)
    armed, sp = ap.flight_command(0.0)
    assert armed
    assert (sp.vx, sp.vy) == pytest.approx((0.0, 1.0), abs=1e-9)  # forward = North in ENU
    assert sp.yaw_rate == pytest.approx(-0.5)  # FRD clockwise → ENU counter-clockwise negative
    assert sp.altitude == pytest.approx(1.5)  # vz = 0 given: hold the altitude


def test_local_ned_velocity_and_position_targets_honour_the_type_mask():
    ap = flying_guided(yaw=0.3)
    vel = wire(
        mavlink.MAVLink_set_position_target_local_ned_message(
            0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, 0x0DC7, 0, 0, 0, 1.0, 2.0, 0, 0, 0, 0, 0, 0
        ),
        COMPANION,
    )
    ap.handle(vel, 1, 0.0)
    _, sp = ap.flight_command(0.0)
    assert (sp.vx, sp.vy) == pytest.approx((2.0, 1.0))  # NED (1 N, 2 E) → ENU (2 E, 1 N)
    assert sp.yaw_rate is None and sp.yaw == pytest.approx(0.3)  # yaw and rate ignored: hold heading
    pos = wire(
        mavlink.MAVLink_set_position_target_local_ned_message(
            0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, 0x0DF8, 3.0, 0.0, -2.0, 9, 9, 9, 0, 0, 0, 0, 0
        ),
        COMPANION,
    )
    ap.handle(pos, 1, 0.1)
    assert ap.guidance == Guidance.POSITION
    np.testing.assert_allclose(ap.target.position, [0.0, 3.0, 2.0])
    _, sp = ap.flight_command(0.1)
    assert sp.vy > 0.5 and abs(sp.vx) < 1e-9 and sp.altitude == pytest.approx(2.0)


def test_invalid_frame_or_all_ignored_stops_the_vehicle():
    ap = flying_guided()
    ap.handle(body_velocity(1.0), 1, 0.0)
    ap.handle(body_velocity(1.0, frame=mavlink.MAV_FRAME_GLOBAL), 1, 0.1)
    assert ap.guidance == Guidance.HOLD
    ap.handle(body_velocity(1.0), 1, 0.2)
    ap.handle(body_velocity(1.0, mask=0x0FFF), 1, 0.3)
    assert ap.guidance == Guidance.HOLD


def test_setpoints_outside_guided_are_ignored():
    ap = make(airborne())
    ap.armed = True
    ap.set_mode(CopterMode.LOITER)
    ap.handle(body_velocity(2.0), 1, 0.0)
    _, sp = ap.flight_command(0.0)
    assert ap.guidance == Guidance.HOLD and (sp.vx, sp.vy) == (0.0, 0.0)
    assert ap.counters["setpoint_ignored_not_guided"] == 1


def test_guid_timeout_stops_a_stale_velocity_target():
    ap = flying_guided()
    ap.handle(body_velocity(1.5, yaw_rate_frd=0.4), 1, 10.0)
    ap.tick(12.9)
    assert ap.flight_command(12.9)[1].vx == pytest.approx(1.5)
    ap.tick(13.1)  # 3.1 s after the last target
    _, sp = ap.flight_command(13.1)
    assert (sp.vx, sp.vy, sp.yaw_rate) == (0.0, 0.0, 0.0)
    assert ap.counters["guided_timeout"] == 1
    ap.params.set("GUID_TIMEOUT", 1.0)
    ap.handle(body_velocity(1.0), 1, 20.0)
    ap.tick(21.2)
    assert ap.flight_command(21.2)[1].vx == 0.0


def test_set_message_interval_changes_the_stream_rate_per_link():
    ap = make()
    ap.add_link(0)
    ap.add_link(1)
    out = ap.handle(
        command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_ATTITUDE, 50_000), 1, 0.0
    )
    assert acks(out) == [(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, ACCEPTED)]
    ap.handle(command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_SYS_STATUS, -1), 1, 0.0)
    sent = [o for k in range(200) for o in ap.tick(k * 0.005)]  # 1 s at 200 Hz
    count = {(link, name): 0 for link in (0, 1) for name in ("ATTITUDE", "SYS_STATUS", "HEARTBEAT")}
    for o in sent:
        key = (o.link, o.message.get_type())
        if key in count:
            count[key] += 1
    assert count[(1, "ATTITUDE")] == 20
    assert count[(0, "ATTITUDE")] == 10  # the other link keeps the default
    assert count[(1, "SYS_STATUS")] == 0 and count[(0, "SYS_STATUS")] == 2
    assert count[(0, "HEARTBEAT")] == count[(1, "HEARTBEAT")] == 1


def test_request_message_and_parameters():
    ap = make()
    out = ap.handle(
        command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION), 0, 0.0
    )
    assert acks(out) == [(mavlink.MAV_CMD_REQUEST_MESSAGE, ACCEPTED)]
    version = next(o.message for o in out if o.message.get_type() == "AUTOPILOT_VERSION")
    assert version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    assert not version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    out = ap.handle(
        wire(mavlink.MAVLink_param_set_message(1, 1, b"PRX1_TYPE", 2.0, mavlink.MAV_PARAM_TYPE_INT8)), 0, 0.0
    )
    assert out[0].message.get_type() == "PARAM_VALUE" and out[0].message.param_value == 2.0
    assert ap.param("PRX1_TYPE", 0) == 2
    assert acks(ap.handle(command(31999), 0, 0.0)) == [(31999, mavlink.MAV_RESULT_UNSUPPORTED)]


def obstacle_ahead(distance_cm: int) -> object:
    distances = [distance_cm] + [1001] * 71  # sector 0 = straight ahead (BODY_FRD), the rest clear
    return wire(
        mavlink.MAVLink_obstacle_distance_message(
            0, mavlink.MAV_DISTANCE_SENSOR_LASER, distances, 5, 10, 1000, 5.0, 0.0, mavlink.MAV_FRAME_BODY_FRD
        ),
        COMPANION,
    )


def test_proximity_stop_only_when_prx1_type_is_mavlink_and_avoid_enabled():
    ap = flying_guided(yaw=math.radians(90.0))  # nose North
    ap.handle(obstacle_ahead(100), 1, 0.0)
    ap.handle(body_velocity(1.0), 1, 0.0)
    assert ap.flight_command(0.0)[1].vy == pytest.approx(1.0)  # PRX1_TYPE = 0: not read
    ap.params.set("PRX1_TYPE", 2)
    ap.handle(obstacle_ahead(100), 1, 0.1)
    _, sp = ap.flight_command(0.1)
    assert abs(sp.vy) < 1e-9  # 1 m < AVOID_MARGIN 2 m straight ahead: no forward motion
    ap.handle(obstacle_ahead(300), 1, 0.2)
    assert ap.flight_command(0.2)[1].vy == pytest.approx(1.0)  # beyond the margin
    ap.handle(obstacle_ahead(100), 1, 0.3)
    ap.params.set("AVOID_ENABLE", 1)  # fence only
    assert ap.flight_command(0.3)[1].vy == pytest.approx(1.0)
    ap.params.set("AVOID_ENABLE", 3)
    assert ap.flight_command(1.0)[1].vy == pytest.approx(1.0)  # the reading is stale after 0.5 s


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_no_position_and_no_arming_until_the_estimator_has_its_origin(personality):
    """``position_delay``: a fresh ArduPilot SITL reports no position for 40-47 s (GPS fix, EKF
    origin) and refuses to arm meanwhile; attitude and heartbeats flow from boot."""
    from flightsim.sitl.sim_autopilot.server import make_autopilot

    ap = make_autopilot(personality, boot_time=0.0, response=False, position_delay=2.0)
    ap.observe(on_ground())
    ap.add_link(0)
    gcs = mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3)
    ap.handle(wire(gcs), 0, 0.0)  # PX4 sends its STATUSTEXTs to ground stations
    if personality == "ardupilot":
        ap.set_mode(CopterMode.GUIDED)
    else:
        from flightsim.sitl.sim_autopilot.px4 import AutoSubMode, MainMode

        ap.main, ap.sub = MainMode.AUTO, AutoSubMode.LOITER

    def names(t0: float, t1: float) -> set[str]:
        return {o.message.get_type() for k in range(int((t1 - t0) / 0.01)) for o in ap.tick(t0 + k * 0.01)}

    early = names(0.0, 1.9)
    assert "ATTITUDE" in early and "HEARTBEAT" in early
    assert not early & {"LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "HOME_POSITION"}
    refused = ap.handle(command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1), 0, 1.9)
    assert acks(refused) == [(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, FAILED)] and not ap.armed
    texts = [o.message.text for o in refused if o.message.get_type() == "STATUSTEXT"]
    assert any(ap.NO_POSITION_REFUSAL in text for text in texts), texts
    late = names(2.0, 3.0)
    assert {"LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"} <= late
    accepted = ap.handle(command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1), 0, 3.0)
    assert acks(accepted) == [(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, ACCEPTED)] and ap.armed
