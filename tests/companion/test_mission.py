"""Mission download state machine, frames and goal tracking (pure logic, real MAVLink encoding)."""

from __future__ import annotations

import dataclasses
import math
import struct

import numpy as np
import pytest

from companion.autopilot.mavlink_adapter import mavlink
from companion.guidance.goal import GoalTracker, NavInputs, Waypoint
from companion.guidance.goal_frames import GlobalOrigin, global_to_local_ne, ned_to_body_flu, offset_global
from companion.guidance.mission import (
    MISSION_CURRENT_MISSION_ID_OFFSET,
    Mission,
    MissionDownloader,
    MissionItem,
    Phase,
    Request,
    extension_u32,
    mission_waypoints,
)

OWN = (1, 191)
AP = (1, 1)
ORIGIN = GlobalOrigin(473977420, 85455940, 488.0)


def wire(msg, src=AP, extension: bytes = b""):
    """Encode ``msg`` as the autopilot would (optionally with extension bytes) and parse it back."""
    sender = mavlink.MAVLink(None, *src)
    frame = msg.pack(sender)
    if extension:
        payload = bytes(msg.unpacker.pack(*(getattr(msg, f) for f in msg.ordered_fieldnames))) + extension
        frame = msg._pack(sender, msg.crc_extra, payload)
    parser = mavlink.MAVLink(None)
    return parser.parse_buffer(frame)[0]


def item(seq, frame=mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, command=mavlink.MAV_CMD_NAV_WAYPOINT,
         x=473977420, y=85455940, z=2.0, radius=0.0, target=OWN):
    return wire(mavlink.MAVLink_mission_item_int_message(*target, seq, frame, command, 0, 1, 0, radius, 0, 0,
                                                         x, y, z, 0))


def count(n, target=OWN, opaque_id=0):
    msg = mavlink.MAVLink_mission_count_message(*target, n, 0)
    return wire(msg, extension=struct.pack("<I", opaque_id) if opaque_id else b"")


def current(seq, total, mission_id):
    msg = mavlink.MAVLink_mission_current_message(seq, total, 0, 0)
    return wire(msg, extension=struct.pack("<III", mission_id, 0, 0))


def download(d: MissionDownloader, items: list, now: float = 0.0, opaque_id: int = 0) -> list[Request]:
    """Answer the downloader's requests like an autopilot holding ``items``; return every request."""
    sent = d.start(now)
    log = list(sent)
    while sent:
        reply = []
        for r in sent:
            if r.kind == "MISSION_REQUEST_LIST":
                reply += d.on_message(count(len(items), opaque_id=opaque_id), now)
            elif r.kind == "MISSION_REQUEST_INT":
                reply += d.on_message(items[r.seq], now)
        log += reply
        sent = reply
    return log


def test_extension_field_read_from_the_payload():
    assert extension_u32(current(2, 5, 0xDEADBEEF), MISSION_CURRENT_MISSION_ID_OFFSET) == 0xDEADBEEF
    assert extension_u32(current(2, 5, 0), MISSION_CURRENT_MISSION_ID_OFFSET) == 0  # trimmed trailing zeros


def test_download_skips_ardupilot_home_and_acks():
    d = MissionDownloader(OWN, skip_home=True)
    items = [item(0, frame=mavlink.MAV_FRAME_GLOBAL, z=488.0), item(1), item(2, z=3.0)]
    log = download(d, items, opaque_id=77)
    assert [r.kind for r in log] == ["MISSION_REQUEST_LIST", "MISSION_REQUEST_INT", "MISSION_REQUEST_INT",
                                     "MISSION_ACK"]
    assert [r.seq for r in log if r.kind == "MISSION_REQUEST_INT"] == [1, 2]  # item 0 (home) never asked
    assert d.phase is Phase.DONE and d.mission is not None
    assert [i.seq for i in d.mission.items] == [1, 2] and d.mission.mission_id == 77
    assert d.drain_events() == ["mission downloaded: 2 items"]


def test_download_px4_keeps_item_zero():
    d = MissionDownloader(OWN, skip_home=False)
    download(d, [item(0), item(1)])
    assert [i.seq for i in d.mission.items] == [0, 1]


def test_timeouts_are_retried_then_fail_then_start_over():
    d = MissionDownloader(OWN, skip_home=False, timeout=1.0, retries=2, retry_after=5.0)
    assert d.start(0.0) == [Request("MISSION_REQUEST_LIST")]
    assert d.tick(0.5) == []
    assert d.tick(1.0) == [Request("MISSION_REQUEST_LIST")]
    assert d.tick(2.0) == [Request("MISSION_REQUEST_LIST")]
    assert d.tick(3.0) == [] and d.phase is Phase.FAILED
    assert "no MISSION_COUNT after 2 retries" in d.drain_events()[-1]
    assert d.tick(7.9) == []
    assert d.tick(8.0) == [Request("MISSION_REQUEST_LIST")] and d.phase is Phase.LISTING


def test_lost_item_is_asked_again_and_duplicates_ignored():
    d = MissionDownloader(OWN, skip_home=False, timeout=1.0)
    d.start(0.0)
    assert d.on_message(count(2), 0.1) == [Request("MISSION_REQUEST_INT", 0)]
    assert d.tick(1.2) == [Request("MISSION_REQUEST_INT", 0)]  # item 0 lost: asked again
    assert d.on_message(item(0), 1.3) == [Request("MISSION_REQUEST_INT", 1)]
    assert d.on_message(item(0), 1.4) == []  # the late duplicate
    assert d.on_message(item(1), 1.5)[0].kind == "MISSION_ACK"


def test_replies_for_someone_else_are_not_ours():
    d = MissionDownloader(OWN, skip_home=False)
    d.start(0.0)
    assert d.on_message(count(3, target=(255, 190)), 0.1) == []  # a GCS's transfer
    assert d.phase is Phase.LISTING


def test_autopilot_refusal_fails_the_download():
    d = MissionDownloader(OWN, skip_home=False)
    d.start(0.0)
    d.on_message(wire(mavlink.MAVLink_mission_ack_message(*OWN, mavlink.MAV_MISSION_DENIED, 0)), 0.1)
    assert d.phase is Phase.FAILED


@pytest.mark.parametrize("sign", ["mission_id", "total", "upload_ack", "foreign_count"])
def test_mission_change_starts_a_new_download(sign):
    d = MissionDownloader(OWN, skip_home=False, change_settle=0.5)
    d.on_message(current(0, 2, 5), 0.0)
    download(d, [item(0), item(1)], opaque_id=5)
    d.on_message(current(0, 2, 5), 1.0)  # the same mission: nothing
    assert d.tick(2.0) == []
    msg = {
        "mission_id": current(0, 2, 6),
        "total": current(0, 3, 0),
        "upload_ack": wire(mavlink.MAVLink_mission_ack_message(255, 190, 0, 0)),
        "foreign_count": count(3, target=AP),
    }[sign]
    if sign == "total":
        d2 = MissionDownloader(OWN, skip_home=False, change_settle=0.5)
        download(d2, [item(0), item(1)])  # no plan ids: the total tells
        d2.on_message(current(0, 2, 0), 1.0)
        d = d2
    d.on_message(msg, 2.0)
    assert d.tick(2.2) == []  # settling
    assert d.tick(2.5) == [Request("MISSION_REQUEST_LIST")]
    assert d.counters["changes"] == 1


def test_upload_between_download_and_first_mission_current():
    """The companion started before the pilot uploaded; the first MISSION_CURRENT after the download
    already shows the new mission (the race `avoid-sim fly --mission` met): still noticed."""
    d = MissionDownloader(OWN, skip_home=True, change_settle=0.0)
    d.on_message(current(0, 0, 0), 0.0)
    download(d, [item(0, frame=mavlink.MAV_FRAME_GLOBAL)], now=0.1)  # ArduPilot: only home
    assert d.mission.items == ()
    d.on_message(current(1, 2, 1234), 1.0)
    assert d.tick(1.0) == [Request("MISSION_REQUEST_LIST")]
    download(d, [item(0, frame=mavlink.MAV_FRAME_GLOBAL), item(1), item(2)], now=1.1)
    d.on_message(current(1, 2, 1234), 2.0)  # the same mission from now on: no more downloads
    assert d.tick(3.0) == [] and d.counters["downloads"] == 2


def test_first_download_checked_against_the_first_mission_current():
    d = MissionDownloader(OWN, skip_home=False, change_settle=0.0)
    download(d, [item(0)])
    d.on_message(current(0, 3, 0), 1.0)  # three items, one downloaded: changed meanwhile
    assert d.tick(1.0) == [Request("MISSION_REQUEST_LIST")]


def test_unsupported_items_named():
    d = MissionDownloader(OWN, skip_home=False)
    download(d, [item(0), item(1, command=mavlink.MAV_CMD_NAV_LOITER_TIME),
                 item(2, frame=mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT)])
    events = d.drain_events()
    assert "mission item 1: NAV_LOITER_TIME not supported" in events
    assert "mission item 2: frame GLOBAL_TERRAIN_ALT_INT not supported" in events
    with pytest.raises(ValueError, match="NAV_LOITER_TIME"):
        mission_waypoints(d.mission, ORIGIN, 488.0)


@pytest.mark.parametrize(("bad", "why"), [
    ({"z": math.nan}, "not a number"),
    ({"radius": math.inf}, "not a number"),
    ({"x": 950_000_000}, "latitude/longitude out of range"),
    ({"y": -1_900_000_000}, "latitude/longitude out of range"),
])
def test_malformed_items_are_not_flown(bad, why):
    m = _mission(item(1, **bad))
    assert m.problems() == [f"item 1: {why}"]
    with pytest.raises(ValueError, match=why):
        mission_waypoints(m, ORIGIN, 488.0)


def _mission(*items):
    return Mission(tuple(MissionItem.of(i) for i in items))


def test_global_frames_to_local_ned():
    lat, lon = offset_global(ORIGIN.lat_e7, ORIGIN.lon_e7, 10.0, -4.0)
    m = _mission(item(1, x=round(lat), y=round(lon), z=2.0),
                 item(2, frame=mavlink.MAV_FRAME_GLOBAL_INT, x=round(lat), y=round(lon), z=493.0, radius=2.5),
                 item(3, frame=mavlink.MAV_FRAME_LOCAL_NED, x=31000, y=-20000, z=-1.5))
    # home 1 m above the EKF origin: a relative altitude of 2 m is 3 m above the origin
    wps = mission_waypoints(m, ORIGIN, home_amsl=489.0)
    assert wps[0].north == pytest.approx(10.0, abs=0.01) and wps[0].east == pytest.approx(-4.0, abs=0.01)
    assert wps[0].down == pytest.approx(-3.0) and wps[0].acceptance_radius is None
    assert wps[1].down == pytest.approx(-5.0) and wps[1].acceptance_radius == 2.5
    assert (wps[2].north, wps[2].east, wps[2].down) == (3.1, -2.0, -1.5)
    with pytest.raises(ValueError, match="no origin"):
        mission_waypoints(m, None, 489.0)
    with pytest.raises(ValueError, match="no home altitude"):
        mission_waypoints(m, ORIGIN, None)


def test_latlon_round_trip_and_scale():
    lat, lon = offset_global(ORIGIN.lat_e7, ORIGIN.lon_e7, 250.0, 120.0)
    n, e = global_to_local_ne(lat, lon, ORIGIN)
    assert (n, e) == (pytest.approx(250.0, abs=1e-6), pytest.approx(120.0, abs=1e-6))
    # one degree of longitude at 47.4° is cos(47.4°) of one of latitude
    n, e = global_to_local_ne(ORIGIN.lat_e7, ORIGIN.lon_e7 + 10_000_000, ORIGIN)
    assert e == pytest.approx(111_318.8 * math.cos(math.radians(47.3977)), rel=1e-4)


@pytest.mark.parametrize(("heading_deg", "expected"), [
    (0.0, (3.0, -4.0, 1.0)),  # facing north: north ahead, east to the right
    (90.0, (4.0, 3.0, 1.0)),  # facing east: east ahead, north to the left
    (180.0, (-3.0, 4.0, 1.0)),
])
def test_body_frame(heading_deg, expected):
    got = ned_to_body_flu((3.0, 4.0, -1.0), math.radians(heading_deg))
    assert got == pytest.approx(expected)


def _nav(pos, t, heading=0.0):
    nav = NavInputs()
    nav.on_message(wire(mavlink.MAVLink_local_position_ned_message(0, *pos, 0, 0, 0)), t)
    nav.on_message(wire(mavlink.MAVLink_attitude_message(0, 0, 0, heading, 0, 0, 0)), t)
    return nav


def test_tracker_reaches_in_order_and_completes():
    tr = GoalTracker(acceptance_radius=1.0, max_vertical_speed=0.5)
    tr.set_waypoints([Waypoint(5, 0, -2, label="a"), Waypoint(5, 5, -2, 2.0, label="b")], None)
    out = tr.update(_nav((0, 0, -2), 0.0), 0.0)
    assert out.hold_reason is None and out.goal_body == pytest.approx((5, 0, 0)) and out.index == 0
    out = tr.update(_nav((4.5, 0, -2), 1.0), 1.0)
    assert out.index == 1 and out.goal_body == pytest.approx((0.5, -5, 0))
    out = tr.update(_nav((5, 3.2, -2), 2.0), 2.0)  # within b's own 2 m radius
    assert out.complete and out.hold_reason == "goal complete"
    assert tr.drain_events() == ["goal: 2 waypoints, next a", "goal: reached a (1/2)",
                                 "goal: reached b (2/2)", "goal: complete, holding"]
    assert tr.drain_reached_items() == []  # not a mission's: no MISSION_ITEM_REACHED


def test_tracker_names_the_mission_items_reached():
    tr = GoalTracker(acceptance_radius=1.0, max_vertical_speed=0.5)
    tr.set_waypoints([Waypoint(5, 0, -2, seq=1), Waypoint(5, 5, -2, seq=2)], None)
    tr.update(_nav((5, 0, -2), 0.0), 0.0)
    assert tr.drain_reached_items() == [1]
    tr.update(_nav((5, 0, -2), 0.1), 0.1)
    assert tr.drain_reached_items() == []  # once per item
    tr.update(_nav((5, 5, -2), 0.2), 0.2)
    assert tr.drain_reached_items() == [2]


def test_vertical_speed_bounded():
    tr = GoalTracker(acceptance_radius=1.0, max_vertical_speed=0.5)
    tr.set_waypoints([Waypoint(10, 0, -12)], None)
    assert tr.update(_nav((0, 0, -2), 0.0), 0.0).vertical_speed == 0.5
    assert tr.update(_nav((0, 0, -12.2), 0.1), 0.1).vertical_speed == pytest.approx(-0.2)


def test_position_loss_holds():
    tr = GoalTracker(1.0, 0.5)
    tr.set_waypoints([Waypoint(10, 0, -2)], None)
    nav = _nav((0, 0, -2), 0.0)
    assert tr.update(nav, 1.0).hold_reason is None
    assert tr.update(nav, 1.01).hold_reason == "no position"  # LOCAL_POSITION_NED older than 1 s
    assert tr.update(NavInputs(), 0.0).hold_reason == "no position"


def test_first_mission_starts_at_its_first_waypoint():
    tr = GoalTracker(1.0, 0.5)
    tr.set_waypoints([Waypoint(17, 0, -2), Waypoint(0, -2, -2)], (0, 0, -2))  # the second is nearer
    assert tr.index == 0


def test_changed_mission_resumes_at_the_autopilots_current_item_not_the_nearest():
    tr = GoalTracker(1.0, 0.5)
    a, b, c, d = (Waypoint(5, 0, -2, seq=1), Waypoint(10, 0, -2, seq=2), Waypoint(15, 0, -2, seq=3),
                  Waypoint(20, 0, -2, seq=2))
    tr.set_waypoints([a, b, c], 1)
    tr.update(_nav((5, 0, -2), 0.0), 0.0)  # a reached
    assert tr.index == 1
    tr.set_waypoints([a, d, c], 1)  # the vehicle is near c; the autopilot's current item is 1
    assert tr.index == 0
    tr.set_waypoints([a, b], 2)
    assert tr.index == 1 and tr.current_seq == 2
    tr.set_waypoints([a, d], 7)  # past the end: the firmware starts over
    assert tr.index == 0


def test_tracker_follows_the_autopilots_current_item_and_its_reached_items():
    tr = GoalTracker(1.0, 0.5)
    tr.set_waypoints([Waypoint(5, 0, -2, seq=1), Waypoint(10, 0, -2, seq=2), Waypoint(15, 0, -2, seq=3)], 1)
    tr.follow_current(3)
    assert tr.current_seq == 3
    tr.follow_current(1)
    assert tr.current_seq == 1
    tr.follow_current(9)  # no such item: stays
    assert tr.current_seq == 1
    tr.autopilot_reached(2)  # MISSION_ITEM_REACHED 2: 1 and 2 are behind
    assert tr.current_seq == 3 and tr.drain_reached_items() == []  # not echoed back
    tr.autopilot_reached(3)
    assert tr.update(_nav((0, 0, -2), 0.0), 0.0).complete


def test_reached_as_each_firmware_judges_it():
    """ArduPilot: within the radius in 3D; PX4: the radius horizontally and NAV_MC_ALT_RAD vertically
    (1.05 m below a waypoint right over it is reached on PX4 with 1.1 m, never in ArduPilot's 1 m sphere)."""
    ardupilot, px4 = Waypoint(5, 0, -1.5), Waypoint(5, 0, -1.5, altitude_radius=1.1)
    assert not ardupilot.reached((5, 0, -0.45), 1.0) and px4.reached((5, 0, -0.45), 1.0)
    assert ardupilot.reached((5.6, 0.6, -1.5), 1.0) and px4.reached((5.6, 0.6, -1.5), 1.0)
    assert not px4.reached((5, 0, -0.3), 1.0)  # 1.2 m below: outside NAV_MC_ALT_RAD
    assert not px4.reached((6.01, 0, -1.5), 1.0)


def test_a_redownload_within_the_encodings_precision_is_the_same_mission():
    item = MissionItem(1, 6, 16, 0.0, 1.0, 473977420, 85455940, 1.5)
    again = dataclasses.replace(item, z=float(np.float32(1.5 + 1e-7)), param2=float(np.float32(1.0)))
    assert Mission((item,), 7).same_items(Mission((again,), 8))  # a new plan id is not a new mission
    assert not Mission((item,), 7).same_items(Mission((dataclasses.replace(item, x=item.x + 1),), 7))
    assert not Mission((item,), 7).same_items(Mission((item, item), 7))
    assert not Mission((item,), 7).same_items(None)


def test_same_mission_again_keeps_the_current_waypoint():
    tr = GoalTracker(1.0, 0.5)
    wps = [Waypoint(5, 0, -2), Waypoint(10, 0, -2), Waypoint(15, 0, -2)]
    tr.set_waypoints(wps, None)
    tr.update(_nav((5, 0, -2), 0.0), 0.0)
    tr.set_waypoints(list(wps), 3)  # another current item, but the list is the same
    assert tr.index == 1


def test_origin_from_global_and_local_position():
    nav = NavInputs()
    lat, lon = offset_global(ORIGIN.lat_e7, ORIGIN.lon_e7, 3.0, 4.0)
    nav.on_message(wire(mavlink.MAVLink_local_position_ned_message(0, 3.0, 4.0, -2.0, 0, 0, 0)), 0.0)
    nav.on_message(wire(mavlink.MAVLink_global_position_int_message(0, round(lat), round(lon), 491_000, 2_500,
                                                                     0, 0, 0, 9000)), 0.05)
    assert nav.origin is not None
    assert global_to_local_ne(nav.origin.lat_e7, nav.origin.lon_e7, ORIGIN) == (
        pytest.approx(0.0, abs=0.02), pytest.approx(0.0, abs=0.02))
    assert nav.origin.alt_amsl == pytest.approx(489.0)  # 491 m AMSL at 2 m above the origin
    assert nav.home_amsl == pytest.approx(488.5)
    assert nav.heading == pytest.approx(math.pi / 2)
    nav.on_message(wire(mavlink.MAVLink_gps_global_origin_message(1, 2, 3_000, 0)), 0.1)
    assert nav.origin == GlobalOrigin(1, 2, 3.0)  # GPS_GLOBAL_ORIGIN wins


@pytest.mark.parametrize(("text", "message"), [
    ('[goal]\nsource = "fixed"\n', r"goal: source is 'fixed' but waypoints lists none"),
    ('[goal]\nsource = "gps"\n', r"goal\.source: must be one of 'none', 'fixed', 'mission'"),
    ('[goal]\non_complete = "loiter"\n', r"goal\.on_complete: must be one of"),
    ('[goal]\nacceptance_radius = 0.0\n', r"goal\.acceptance_radius: 0\.0 is below the minimum"),
    ('[[goal.waypoints]]\nnorth = "far"\n', r"goal\.waypoints\[0\]\.north"),
])
def test_goal_config_errors_name_the_key(tmp_path, text, message):
    from companion.common.errors import UserError
    from companion.config import load_config

    path = tmp_path / "c.toml"
    path.write_text(f'[policy]\nmodel = "m.onnx"\n{text}')
    with pytest.raises(UserError, match=message):
        load_config(path)


def test_fixed_goal_config(tmp_path):
    from companion.config import load_config

    path = tmp_path / "c.toml"
    path.write_text('[policy]\nmodel = "m.onnx"\n[goal]\nsource = "fixed"\n'
                    '[[goal.waypoints]]\nnorth = 4.0\ndown = -2.0\nacceptance_radius = 0.5\n')
    goal = load_config(path).goal
    assert goal.source == "fixed" and goal.waypoints[0].north == 4.0
    assert goal.waypoints[0].acceptance_radius == 0.5
