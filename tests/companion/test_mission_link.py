"""Mission download through the real links over loopback: both simulated firmwares, a pymavlink peer."""

from __future__ import annotations

import dataclasses
import time

import pytest

from companion.app import open_goal
from companion.autopilot.ardupilot import ArduPilotLink
from companion.autopilot.mavlink_adapter import mavlink
from companion.config import AutopilotConfig, CompanionConfig, GoalConfig
from companion.guidance.goal_frames import offset_global
from companion.guidance.mission import Phase
from flightsim.sitl.ground_station import GroundStation, MissionItemSpec
from flightsim.sitl.sim_autopilot.frames import HOME_LAT_DEG, HOME_LON_DEG
from flightsim.sitl.sim_autopilot.server import SimAutopilotServer
from tests.companion.mavlink_peer import AutopilotPeer, free_udp_port

HOME = (round(HOME_LAT_DEG * 1e7), round(HOME_LON_DEG * 1e7))
REL = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT


def spec(north: float, east: float, alt: float, **kw) -> MissionItemSpec:
    lat, lon = offset_global(*HOME, north, east)
    return MissionItemSpec(kw.pop("frame", REL), round(lat), round(lon), alt, **kw)


def config(personality: str, **goal) -> CompanionConfig:
    return dataclasses.replace(CompanionConfig(), autopilot=AutopilotConfig(type=personality),
                               goal=GoalConfig(source="mission", **goal))


def open_link(personality: str, port: int):
    if personality == "px4":
        from companion.autopilot.px4 import Px4Link

        return Px4Link(f"udpin://127.0.0.1:{port}")
    return ArduPilotLink(f"udpin:127.0.0.1:{port}")


def run_until(link, goal, predicate, timeout: float = 15.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        status = link.poll()
        out = goal.step(status.heartbeat_time is not None)
        if predicate(out):
            return out
        time.sleep(0.02)
    raise AssertionError(f"timed out; goal {goal.output}, download {goal.downloader.phase}, "
                         f"said {goal.announcements}")


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_download_track_and_change_against_the_simulated_autopilot(personality):
    port = free_udp_port()
    with SimAutopilotServer(personality, [f"udpout:127.0.0.1:{port}", "udpin:127.0.0.1:0"]) as server:
        gcs = GroundStation("udpout:{}:{}".format(*server.endpoint.address(1)))
        link = open_link(personality, port)
        try:
            gcs.wait_heartbeat()
            gcs.upload_mission([spec(10.0, 0.0, 2.0), spec(10.0, 8.0, 3.0, acceptance_radius=2.0)])
            goal = open_goal(config(personality), link, time.monotonic)
            out = run_until(link, goal, lambda o: o.hold_reason is None)
            # the vehicle rests at home facing east (ENU yaw 0): 10 m north is 10 m to its left
            assert out.goal_body == pytest.approx((0.0, 10.0, 2.0), abs=0.15)
            # PX4 takes an item's own radius; ArduPilot Copter leaves it unused (its WPNAV_RADIUS)
            radii = [None, 2.0] if personality == "px4" else [None, None]
            assert [w.acceptance_radius for w in goal.tracker.waypoints] == radii
            said = goal.drain_announcements()
            assert "mission downloaded: 2 items" in said
            # the pilot uploads another mission: MISSION_CURRENT's plan id changes, the companion follows
            gcs.upload_mission([spec(0.0, -6.0, 2.5)])
            out = run_until(link, goal, lambda o: goal.downloader.counters["downloads"] == 2
                            and o.hold_reason is None)
            assert out.goal_body == pytest.approx((-6.0, 0.0, 2.5), abs=0.15)  # 6 m west: straight behind
        finally:
            link.close()
            gcs.close()


def _set_current(gcs: GroundStation, seq: int) -> None:
    gcs.mav.mav.mission_set_current_send(gcs.target_system, 1, seq)


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_mission_follows_the_autopilots_current_item_and_ignores_an_unchanged_redownload(personality):
    """The autopilot's current item (a ground station sets it) is where the goal goes; a new plan id
    with the same items (PX4 announced one right after the first download) is downloaded again and
    is no change: the goal stays; a real change resumes at the autopilot's current item, not at the
    nearest waypoint; the companion's own progress is sent back as MISSION_SET_CURRENT."""
    port = free_udp_port()
    with SimAutopilotServer(personality, [f"udpout:127.0.0.1:{port}", "udpin:127.0.0.1:0"]) as server:
        gcs = GroundStation("udpout:{}:{}".format(*server.endpoint.address(1)))
        link = open_link(personality, port)
        first = 1 if personality == "ardupilot" else 0  # ArduPilot's item 0 is home
        try:
            gcs.wait_heartbeat()
            gcs.upload_mission([spec(10.0, 0.0, 2.0), spec(10.0, 8.0, 3.0), spec(0.0, 8.0, 2.0)])
            goal = open_goal(config(personality), link, time.monotonic)
            run_until(link, goal, lambda o: o.hold_reason is None)
            assert goal.tracker.current_seq == first
            _set_current(gcs, first + 1)  # the pilot skips an item from the ground station
            run_until(link, goal, lambda o: goal.tracker.current_seq == first + 1)
            # the MISSION_CURRENT the link heard before the upload may bring one download more: let it
            settle = time.monotonic() + 2.0
            run_until(link, goal, lambda o: time.monotonic() > settle, timeout=5.0)
            goal.drain_announcements()
            downloads = goal.downloader.counters["downloads"]
            server.call(lambda ap: setattr(ap.mission, "mission_id", ap.mission.mission_id + 1))
            run_until(link, goal, lambda o: goal.downloader.counters["downloads"] == downloads + 1
                      and o.hold_reason is None)
            said = goal.drain_announcements()
            assert goal.tracker.current_seq == first + 1, said  # where it was
            assert f"mission unchanged, carrying on to item {first + 1}" in said
            assert not any("waypoints, next" in s for s in said), said
            # a real change: the vehicle (at home, on the ground) is nearest the new third item, but
            # the autopilot's current item after the upload is its first: the goal goes there
            _set_current(gcs, first + 2)
            run_until(link, goal, lambda o: goal.tracker.current_seq == first + 2)
            gcs.upload_mission([spec(-8.0, 0.0, 2.0), spec(0.0, -8.0, 2.0), spec(1.5, 0.0, 2.0)])
            run_until(link, goal, lambda o: o.hold_reason is None and goal.tracker.waypoints[0].north < -7)
            assert goal.tracker.current_seq == server.autopilot.mission.current == first
            # an item the vehicle is at is reached: the autopilot's current item follows the companion
            gcs.upload_mission([spec(0.0, 0.0, 0.0), spec(0.0, -8.0, 2.0)])
            run_until(link, goal, lambda o: len(goal.tracker.waypoints) == 2
                      and goal.tracker.current_seq == first + 1)
            end = time.monotonic() + 5.0
            while server.autopilot.mission.current != first + 1 and time.monotonic() < end:
                time.sleep(0.05)
            assert server.autopilot.mission.current == first + 1
            run_until(link, goal, lambda o: True, timeout=1.0)
            assert goal.tracker.current_seq == first + 1  # its own MISSION_SET_CURRENT's echo: no jump
        finally:
            link.close()
            gcs.close()


def test_unsupported_items_hold_and_are_named():
    port = free_udp_port()
    with SimAutopilotServer("ardupilot", [f"udpout:127.0.0.1:{port}", "udpin:127.0.0.1:0"]) as server:
        gcs = GroundStation("udpout:{}:{}".format(*server.endpoint.address(1)))
        link = ArduPilotLink(f"udpin:127.0.0.1:{port}")
        try:
            gcs.wait_heartbeat()
            loiter = spec(5.0, 0.0, 2.0, command=mavlink.MAV_CMD_NAV_LOITER_TIME)
            gcs.upload_mission([spec(5.0, 0.0, 2.0), loiter])
            goal = open_goal(config("ardupilot"), link, time.monotonic)
            out = run_until(link, goal, lambda o: o.hold_reason == "mission has unsupported items")
            assert out.goal_body is None
            assert "mission item 2: NAV_LOITER_TIME not supported" in goal.drain_announcements()
        finally:
            link.close()
            gcs.close()


def test_against_a_pymavlink_peer_with_a_lost_request():
    """The exact bytes: requests addressed to the autopilot, an unanswered request repeated, the ACK."""
    port = free_udp_port()
    link = ArduPilotLink(f"udpin:127.0.0.1:{port}")
    peer = AutopilotPeer(f"udpout:127.0.0.1:{port}")
    goal = open_goal(config("ardupilot", download_timeout=0.3), link, time.monotonic)
    try:
        items = [(0, HOME[0], HOME[1], 488.0, mavlink.MAV_FRAME_GLOBAL),
                 (1, HOME[0] + 900, HOME[1], 2.0, REL)]
        answered_once = set()
        end = time.monotonic() + 10.0
        while goal.downloader.phase is not Phase.DONE and time.monotonic() < end:
            peer.heartbeat()
            for msg in peer.drain(0.02):
                kind = msg.get_type()
                if kind == "MISSION_REQUEST_LIST":
                    assert (msg.target_system, msg.target_component) == (1, 1)
                    peer.mav.mission_count_send(1, 191, len(items), 0)
                elif kind == "MISSION_REQUEST_INT":
                    assert msg.seq == 1  # ArduPilot: item 0, home, is never asked for
                    if msg.seq not in answered_once:
                        answered_once.add(msg.seq)  # lose the first answer
                        continue
                    seq, x, y, z, frame = items[msg.seq]
                    peer.mav.mission_item_int_send(1, 191, seq, frame, 16, 0, 1, 0, 0, 0, 0, x, y, z, 0)
            link.poll()
            goal.step(True)
        assert goal.downloader.phase is Phase.DONE
        assert goal.downloader.counters["timeouts"] >= 1
        acks = [m for m in peer.drain(0.3) if m.get_type() == "MISSION_ACK"]
        assert acks and acks[0].type == mavlink.MAV_MISSION_ACCEPTED and acks[0].target_system == 1
        assert goal.downloader.mission.items[0].x == HOME[0] + 900
    finally:
        link.close()
        peer.close()


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_mission_uploaded_after_the_companion_started(personality):
    """The usual order on a field: the companion finds an empty mission, then the pilot uploads one."""
    port = free_udp_port()
    with SimAutopilotServer(personality, [f"udpout:127.0.0.1:{port}", "udpin:127.0.0.1:0"]) as server:
        gcs = GroundStation("udpout:{}:{}".format(*server.endpoint.address(1)))
        link = open_link(personality, port)
        try:
            goal = open_goal(config(personality), link, time.monotonic)
            run_until(link, goal, lambda o: o.hold_reason == "mission empty")
            gcs.wait_heartbeat()
            gcs.upload_mission([spec(4.0, 0.0, 2.0)])
            out = run_until(link, goal, lambda o: o.hold_reason is None)
            assert out.goal_body == pytest.approx((0.0, 4.0, 2.0), abs=0.15)
        finally:
            link.close()
            gcs.close()
