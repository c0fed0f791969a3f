"""PX4 personality: main/sub custom modes, OFFBOARD proof of life, offboard-loss failsafe, GCS-only
STATUSTEXT, bytewise parameters (pure logic with a fake clock; the take-off flies the real vehicle)."""

from __future__ import annotations

import struct

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from flightsim.sitl.sim_autopilot.common import Guidance
from flightsim.sitl.sim_autopilot.frames import HOME_ALT_AMSL_M
from flightsim.sitl.sim_autopilot.params import default_table
from flightsim.sitl.sim_autopilot.px4 import AutoSubMode, MainMode, PX4Autopilot, px4_custom_mode
from flightsim.vehicle.quadrotor import Vehicle, VehicleConfig
from tests.sitl.helpers import COMPANION, acks, airborne, body_velocity, command, fly, on_ground, wire

ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
REJECTED = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
FLAG = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED


def make(state=None, response: bool = False) -> PX4Autopilot:
    """Without the firmware response by default: these tests check the target the firmware's
    position controller is given (the response to it is tested in test_autopilot_response.py)."""
    ap = PX4Autopilot(default_table("px4"), response=response)
    ap.observe(state or on_ground())
    return ap


def flying() -> PX4Autopilot:
    ap = make(airborne())
    ap.armed = True
    ap.set_mode(MainMode.AUTO, AutoSubMode.LOITER)
    return ap


def stream(ap: PX4Autopilot, start: float, duration: float, rate: float) -> float:
    t = start
    while t < start + duration:
        ap.handle(body_velocity(0.5, frame=mavlink.MAV_FRAME_BODY_NED), 1, t)
        ap.tick(t)
        t += 1.0 / rate
    return t


def test_custom_mode_is_main_and_sub_packed():
    ap = make()
    hb = ap.build("HEARTBEAT")
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_PX4
    assert hb.custom_mode == (4 << 16) | (3 << 24) == px4_custom_mode(MainMode.AUTO, AutoSubMode.LOITER)
    out = ap.handle(command(mavlink.MAV_CMD_DO_SET_MODE, FLAG, MainMode.POSCTL, 0), 0, 0.0)
    assert acks(out) == [(mavlink.MAV_CMD_DO_SET_MODE, ACCEPTED)]
    assert ap.build("HEARTBEAT").custom_mode == 3 << 16
    ap.handle(wire(mavlink.MAVLink_set_mode_message(1, FLAG, px4_custom_mode(4, 6))), 0, 0.0)
    assert ap.mode_name() == "AUTO.LAND"


def test_offboard_needs_a_setpoint_stream_above_2hz_for_a_second():
    ap = flying()
    assert acks(ap.handle(command(176, FLAG, MainMode.OFFBOARD), 0, 0.0))[0][1] == REJECTED
    t = stream(ap, 0.0, 3.0, 1.5)  # too slow
    assert acks(ap.handle(command(176, FLAG, MainMode.OFFBOARD), 0, t))[0][1] == REJECTED
    t = stream(ap, t + 1.0, 0.6, 10.0)  # fast, but not for long enough
    assert acks(ap.handle(command(176, FLAG, MainMode.OFFBOARD), 0, t - 0.1))[0][1] == REJECTED
    t = stream(ap, t, 0.6, 10.0)
    assert acks(ap.handle(command(176, FLAG, MainMode.OFFBOARD), 0, t - 0.1))[0][1] == ACCEPTED
    assert ap.mode_name() == "OFFBOARD"
    assert ap.guidance == Guidance.VELOCITY  # the streamed setpoint applies at once
    assert ap.flight_command(t)[1].vx == pytest.approx(0.5)


@pytest.mark.parametrize(("action", "mode"), [(5, "AUTO.LOITER"), (0, "AUTO.RTL"), (4, "AUTO.LAND")])
def test_offboard_loss_runs_com_obl_rc_act_after_com_of_loss_t(action, mode):
    ap = flying()
    ap.params.set("COM_OBL_RC_ACT", action)
    t = stream(ap, 0.0, 1.5, 10.0)
    ap.handle(command(176, FLAG, MainMode.OFFBOARD), 0, t)
    assert ap.mode_name() == "OFFBOARD"
    last = t - 0.1
    ap.tick(last + 0.9)
    assert ap.mode_name() == "OFFBOARD"  # COM_OF_LOSS_T default 1.0 s
    ap.tick(last + 1.1)
    assert ap.mode_name() == mode
    assert ap.counters["offboard_lost"] == 1
    if action == 5:
        _, sp = ap.flight_command(last + 1.1)
        assert (sp.vx, sp.vy) == pytest.approx((0.0, 0.0), abs=1e-9)  # hold where it is


def test_statustext_goes_only_to_links_with_a_gcs_heartbeat():
    ap = flying()
    ap.add_link(0)
    ap.add_link(1)
    ap.handle(
        wire(
            mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, 8, 0, 0, 0, 3), COMPANION
        ),
        1,
        0.0,
    )
    assert [o for o in ap.statustext("hello") if o.link is not None] == []
    ap.handle(wire(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, 8, 0, 0, 0, 3)), 0, 0.0)
    out = ap.statustext("hello")
    assert [o.link for o in out] == [0]
    assert out[0].message.text == "hello"


def test_autopilot_version_advertises_bytewise_and_params_are_bytewise():
    ap = make()
    out = ap.handle(
        command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION), 0, 0.0
    )
    version = next(o.message for o in out if o.message.get_type() == "AUTOPILOT_VERSION")
    assert version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    field = struct.unpack("<f", struct.pack("<i", 5))[0]
    out = ap.handle(
        wire(mavlink.MAVLink_param_set_message(1, 1, b"COM_OBL_RC_ACT", field, mavlink.MAV_PARAM_TYPE_INT32)),
        0,
        0.0,
    )
    assert out[0].message.get_type() == "PARAM_VALUE"
    assert struct.unpack("<i", struct.pack("<f", out[0].message.param_value))[0] == 5
    assert ap.param("COM_OBL_RC_ACT", 0) == 5


def test_takeoff_goes_through_auto_takeoff_to_hold():
    vehicle = Vehicle(VehicleConfig())
    ap = make(vehicle.reset((0.0, 0.0, 0.0), 0.0, on_ground=True))
    assert acks(ap.handle(command(22, 0, 0, 0, 0, 0, 0, HOME_ALT_AMSL_M + 1.5), 0, 0.0))[0][1] == REJECTED
    assert acks(ap.handle(command(400, 1), 0, 0.0)) == [(400, ACCEPTED)]
    assert acks(ap.handle(command(22, 0, 0, 0, 0, 0, 0, HOME_ALT_AMSL_M + 1.5), 0, 0.0)) == [(22, ACCEPTED)]
    assert ap.mode_name() == "AUTO.TAKEOFF"
    assert ap.landed_state() == mavlink.MAV_LANDED_STATE_TAKEOFF
    fly(ap, vehicle, 0.0, 6.0)
    assert ap.mode_name() == "AUTO.LOITER"
    assert ap.landed_state() == mavlink.MAV_LANDED_STATE_IN_AIR
    assert ap.build("GLOBAL_POSITION_INT").relative_alt == pytest.approx(1500, abs=120)
    assert ap.build("EXTENDED_SYS_STATE").vtol_state == mavlink.MAV_VTOL_STATE_MC


def test_ping_requests_are_answered_to_the_sender():
    ap = make()
    out = ap.handle(wire(mavlink.MAVLink_ping_message(123, 7, 0, 0), COMPANION), 1, 0.5)
    assert len(out) == 1 and out[0].link == 1
    reply = out[0].message
    assert (reply.seq, reply.target_system, reply.target_component) == (7, *COMPANION)
