"""The simulated autopilots' mission protocol: upload as a GCS does, download as the companion does."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from companion.guidance.mission import (
    MISSION_CURRENT_MISSION_ID_OFFSET,
    MissionDownloader,
    Phase,
    extension_u32,
)
from flightsim.sitl.sim_autopilot.frames import HOME_ALT_AMSL_M
from flightsim.sitl.sim_autopilot.mission import UPLOAD_RETRIES
from flightsim.sitl.sim_autopilot.server import make_autopilot
from flightsim.sitl.sim_autopilot.snapshot import VehicleSnapshot

GCS = (255, 190)
COMPANION = (1, 191)
LAT, LON = 473977420, 85455940


def encode(msg, src):
    """Put ``msg`` on the wire from ``src`` and parse it back (real bytes, extensions included)."""
    frame = msg.pack(mavlink.MAVLink(None, *src))
    return mavlink.MAVLink(None).parse_buffer(frame)[0]


def autopilot(personality):
    ap = make_autopilot(personality, 0.0)
    ap.observe(VehicleSnapshot())
    return ap


def replies(ap, msg, src, now=0.0):
    return [encode(o.message, (ap.system_id, ap.component_id)) for o in ap.handle(encode(msg, src), 0, now)]


def wp(seq, frame=mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=mavlink.MAV_CMD_NAV_WAYPOINT, dlat=0):
    return mavlink.MAVLink_mission_item_int_message(1, 1, seq, frame, command, 0, 1, 0, 0, 0, 0,
                                                    LAT + dlat, LON, 2.0, 0)


def upload(ap, items, now=0.0):
    """A GCS upload; returns the final MISSION_ACK."""
    out = replies(ap, mavlink.MAVLink_mission_count_message(1, 1, len(items), 0), GCS, now)
    while out and out[0].get_type() == "MISSION_REQUEST_INT":
        assert (out[0].target_system, out[0].target_component) == GCS
        out = replies(ap, items[out[0].seq], GCS, now)
    assert out[0].get_type() == "MISSION_ACK"
    return out[0]


def companion_download(ap, skip_home, now=0.0):
    d = MissionDownloader(COMPANION, skip_home)
    pending = d.start(now)
    while pending:
        r = pending.pop(0)
        if r.kind == "MISSION_REQUEST_LIST":
            msg = mavlink.MAVLink_mission_request_list_message(1, 1, 0)
        elif r.kind == "MISSION_REQUEST_INT":
            msg = mavlink.MAVLink_mission_request_int_message(1, 1, r.seq, 0)
        else:
            msg = mavlink.MAVLink_mission_ack_message(1, 1, r.result, 0)
        for reply in replies(ap, msg, COMPANION, now):
            pending += d.on_message(reply, now)
    return d


def test_ardupilot_item_zero_is_home():
    ap = autopilot("ardupilot")
    ack = upload(ap, [wp(0, dlat=999), wp(1, dlat=100), wp(2, dlat=200)])
    assert ack.type == mavlink.MAV_MISSION_ACCEPTED and ap.mission.mission_id != 0
    assert len(ap.mission.items) == 2  # the uploaded item 0 was not kept: home is there
    out = replies(ap, mavlink.MAVLink_mission_request_list_message(1, 1, 0), COMPANION)
    assert out[0].count == 3
    home = replies(ap, mavlink.MAVLink_mission_request_int_message(1, 1, 0, 0), COMPANION)[0]
    assert (home.x, home.y, home.z) == (LAT, LON, HOME_ALT_AMSL_M)
    d = companion_download(ap, skip_home=True)
    assert d.phase is Phase.DONE and [i.x - LAT for i in d.mission.items] == [100, 200]
    assert d.mission.mission_id == ap.mission.mission_id  # MISSION_COUNT's opaque_id


def test_px4_items_start_at_zero():
    ap = autopilot("px4")
    upload(ap, [wp(0, dlat=100), wp(1, dlat=200)])
    d = companion_download(ap, skip_home=False)
    assert [i.x - LAT for i in d.mission.items] == [100, 200]


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_mission_current_streams_the_plan_id(personality):
    ap = autopilot(personality)
    ap.add_link(0)
    first = ap.tick(0.0)
    assert any(o.message.get_type() == "MISSION_CURRENT" for o in first)
    upload(ap, [wp(0), wp(1, dlat=100)])
    msg = encode(ap.build("MISSION_CURRENT"), (1, 1))
    assert extension_u32(msg, MISSION_CURRENT_MISSION_ID_OFFSET) == ap.mission.mission_id != 0
    old = ap.mission.mission_id
    upload(ap, [wp(0), wp(1, dlat=300)])
    assert ap.mission.mission_id != old


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_local_frames_refused(personality):
    ap = autopilot(personality)
    ack = upload(ap, [wp(0), wp(1, frame=mavlink.MAV_FRAME_LOCAL_NED)])
    assert ack.type == mavlink.MAV_MISSION_UNSUPPORTED_FRAME and ap.mission.items == []


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_stalled_upload_reasked_then_cancelled(personality):
    ap = autopilot(personality)
    replies(ap, mavlink.MAVLink_mission_count_message(1, 1, 2, 0), GCS, 0.0)
    asked = []
    for k in range(1, UPLOAD_RETRIES + 2):
        asked += [o.message for o in ap.tick(k * 1.0) if o.message.get_type() in ("MISSION_REQUEST_INT",
                                                                                   "MISSION_ACK")]
    assert [m.get_type() for m in asked] == ["MISSION_REQUEST_INT"] * UPLOAD_RETRIES + ["MISSION_ACK"]
    assert asked[-1].type == mavlink.MAV_MISSION_OPERATION_CANCELLED


def test_unsupported_command_kept_for_the_companion_to_report():
    ap = autopilot("px4")
    upload(ap, [wp(0), wp(1, command=mavlink.MAV_CMD_NAV_LOITER_TIME)])
    d = companion_download(ap, skip_home=False)
    assert "mission item 1: NAV_LOITER_TIME not supported" in d.drain_events()


def test_world_waypoints_as_mission_items_and_reached_in_order():
    import numpy as np

    from companion.guidance.goal_frames import GlobalOrigin, global_to_local_ne
    from flightsim.sitl.flight_report import waypoints_reached
    from flightsim.sitl.ground_station import mission_items
    from flightsim.worlds.world import load_world

    world = load_world("flightsim/worlds/slalom.json")  # start (-8.5, 0); waypoints (8.5, 0), (-8.5, -2)
    items = mission_items(world, (LAT, LON))
    assert [i.frame for i in items] == [mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT] * 2
    home = GlobalOrigin(LAT, LON, 0.0)
    assert global_to_local_ne(items[0].x, items[0].y, home) == (pytest.approx(0.0, abs=0.01),
                                                                 pytest.approx(17.0, abs=0.01))
    assert global_to_local_ne(items[1].x, items[1].y, home) == (pytest.approx(-2.0, abs=0.01),
                                                                 pytest.approx(0.0, abs=0.01))
    assert items[0].z == 1.5
    # (t, x, y, z, yaw, speed): the second waypoint first (not counted: out of order), the first, the second
    traj = np.array([[10.0, -8.5, -2.0, 1.5, 0, 0], [14.0, 8.0, 0.2, 1.5, 0, 0],
                     [20.0, -8.2, -2.3, 1.5, 0, 0]])
    assert waypoints_reached(world, traj, engaged_at=9.0) == [(0, 5.0), (1, 11.0)]
    assert waypoints_reached(world, traj[:2], engaged_at=9.0) == [(0, 5.0)]
