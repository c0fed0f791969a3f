"""SITL harness pieces without a flight: the generated companion config, latency matching, and the
lidar co-simulation's packets read back by the companion's own UDP source (real loopback)."""

from __future__ import annotations

import dataclasses
import math
import socket
import time

import numpy as np
import pytest

from companion.common.errors import UserError
from companion.common.tomlconfig import to_dict, toml_dumps
from companion.config import CompanionConfig, load_config
from companion.guidance.goal_frames import LATLON_TO_M
from companion.lidar.velodyne import VelodyneUdpSource
from companion.perception.scan import ScanConfig, scan_from_points
from flightsim.envs.raycast import LidarConfig
from flightsim.sitl.companion_setup import companion_config, ephemeral_range, free_tcp_port, free_udp_port
from flightsim.sitl.cosim import LidarCosim
from flightsim.sitl.flight_report import latency_ms
from flightsim.sitl.fly_cli import load_flight_world
from flightsim.vehicle.quadrotor import VehicleState
from flightsim.worlds.world import load_world


def test_generated_companion_config_loads_strictly(tmp_path):
    policy = tmp_path / "p.onnx"
    cfg = companion_config(
        autopilot_type="px4",
        connect="udpin://127.0.0.1:14540",
        lidar_port=23680,
        policy=policy,
        overrides={"runtime": {"log_interval": 1.0}},
    )
    path = tmp_path / "companion.toml"
    path.write_text(toml_dumps(to_dict(cfg)))
    loaded = load_config(path)
    assert isinstance(loaded, CompanionConfig)
    assert loaded.autopilot.type == "px4" and loaded.autopilot.connect == "udpin://127.0.0.1:14540"
    assert loaded.lidar.velodyne.port == 23680 and loaded.lidar.velodyne.host == "127.0.0.1"
    assert loaded.policy.model == str(policy)
    assert loaded.runtime.log_interval == 1.0
    assert loaded == cfg


def test_toml_dumps_writes_tables_arrays_of_tables_and_scalars(tmp_path):
    from companion.common.tomlconfig import load_toml

    data = {"a": 1, "b": {"c": 'x"y', "d": [1.5, 2.0], "e": True, "f": [{"g": 1}, {"g": 2}]}}
    path = tmp_path / "t.toml"
    path.write_text(toml_dumps(data))
    assert load_toml(path) == data


def test_latency_matches_each_revolution_to_the_next_setpoint():
    ends = [1.0, 1.1, 1.2, 1.3]
    setpoints = [0.95, 1.004, 1.103, 1.104, 1.6]
    assert latency_ms(ends, setpoints) == pytest.approx([4.0, 3.0])  # 1.2 and 1.3 got no setpoint in time


def test_world_arguments_are_checked():
    with pytest.raises(UserError, match="difficulty"):
        load_flight_world(None, 1, 1.5)
    with pytest.raises(UserError, match="seed"):
        load_flight_world(None, -1, 0.5)
    assert load_flight_world(None, 3, 0.2).name.startswith("gen-3")


def hover_state(x: float, y: float, yaw_deg: float) -> VehicleState:
    return VehicleState(
        time=0.0,
        position=np.array([x, y, 1.5]),
        velocity=np.zeros(3),
        roll=0.0,
        pitch=0.0,
        yaw=math.radians(yaw_deg),
        angular_rate=np.zeros(3),
        on_ground=False,
        armed=True,
    )


def stream_clouds(cosim: LidarCosim, source: VelodyneUdpSource, seconds: float) -> list[np.ndarray]:
    """Run ``cosim`` for ``seconds`` of wall time and return the clouds ``source`` decoded from its
    UDP packets; both are closed after."""
    clouds = []
    try:
        cosim.start()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            clouds += source.read_available()
            time.sleep(0.005)
    finally:
        cosim.stop()
        source.close()
    return clouds


def test_free_ports_are_outside_the_ephemeral_range_and_never_repeat():
    """The harness's ports for the companion's listeners: outside the range the kernel gives
    unbound senders (a port from it was once handed to the flight's own relay between the probe
    and the companion's bind, and the companion refused its link), bindable, each handed out once."""
    low, high = ephemeral_range()
    udp = [free_udp_port() for _ in range(50)]
    tcp = [free_tcp_port() for _ in range(50)]
    assert len(set(udp + tcp)) == 100
    for port, kind in [(p, socket.SOCK_DGRAM) for p in udp] + [(p, socket.SOCK_STREAM) for p in tcp]:
        assert 1024 <= port < 65536 and not low <= port <= high, port
        with socket.socket(socket.AF_INET, kind) as s:
            s.bind(("127.0.0.1", port))


def test_free_ports_keep_clear_of_the_ports_asked_to_avoid():
    """A Ray head given its GCS and client ports refuses to start when one lies among the ports it
    takes for itself (its worker range 10002-19999 sits below the ephemeral range too)."""
    low, _ = ephemeral_range()
    allowed = {1500, 1501, 1502, 1503, 1504, 1505}
    avoid = frozenset(range(1024, low)) - allowed
    ports = [free_tcp_port(avoid) for _ in range(3)]
    assert len(set(ports)) == 3 and set(ports) <= allowed, ports


@pytest.mark.parametrize("step", [0.2, 1.0])
def test_cosim_streams_revolutions_the_companion_decodes_into_the_right_scan(step):
    world = load_world("flightsim/worlds/two-pillars.json")
    state = hover_state(-4.5, 0.0, 0.0)  # room 12 x 8 m: the wall behind is 1.5 m away, East wall 10.5 m
    port = free_udp_port()
    source = VelodyneUdpSource("127.0.0.1", port)
    # the companion drops turns no VLP-16 makes: a 1° cast is sent as the 0.2° firings of 600 rpm
    cosim = LidarCosim(world, lambda: state, ("127.0.0.1", port), lidar=LidarConfig(azimuth_step_deg=step))
    cosim.revolution_packets(state)  # compile before timing anything
    clouds = stream_clouds(cosim, source, 1.05)
    assert 8 <= cosim.stats.revolutions <= 11  # 10 Hz, real time
    assert cosim.stats.packets == 75 * cosim.stats.revolutions  # 1800 firings / 24 per packet
    assert len(clouds) >= cosim.stats.revolutions - 2
    scan = scan_from_points(clouds[-1], ScanConfig())
    assert scan[180] * 10.0 == pytest.approx(1.5, abs=0.05)  # bin 180 = behind: the West wall
    assert scan[90] * 10.0 == pytest.approx(4.0, abs=0.05)  # left = North wall at y = 4
    assert scan[270] * 10.0 == pytest.approx(4.0, abs=0.05)


def test_external_pose_mirrors_ned_telemetry_into_the_world_frame():
    """Anchored on the ground facing East, the SITL's frame is rotated onto the world's start yaw."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from flightsim.sitl.external_sitl import ExternalPose

    world = dataclasses.replace(load_world("flightsim/worlds/two-pillars.json"), start_yaw_deg=90.0)
    pose = ExternalPose(world)
    pose.update(mavlink.MAVLink_local_position_ned_message(0, 5.0, 7.0, 0.0, 0.0, 0.0, 0.0))
    pose.update(mavlink.MAVLink_attitude_message(0, 0.0, 0.0, math.pi / 2, 0, 0, 0))  # facing East
    pose.anchor()
    pose.update(mavlink.MAVLink_local_position_ned_message(0, 6.0, 9.0, -1.5, 0.5, 0.0, -0.1))
    pose.update(mavlink.MAVLink_attitude_message(0, 0.1, 0.2, math.pi / 2, 0, 0, 0))
    state = pose.state()
    x0, y0, _ = world.start_position
    # moved N 1, E 2 in the SITL; its East is the world's start yaw (+y): E 2 → +y, N 1 → −x
    np.testing.assert_allclose(state.position, [x0 - 1.0, y0 + 2.0, 1.5], atol=1e-9)
    np.testing.assert_allclose(state.velocity[:2], [-0.5, 0.0], atol=1e-9)  # N 0.5 → −x
    assert state.yaw == pytest.approx(math.pi / 2, abs=1e-9)
    assert state.roll == pytest.approx(0.1) and state.pitch == pytest.approx(-0.2)  # FLU pitch: nose down
    assert not state.on_ground


def test_external_pose_prefers_ground_truth_over_the_estimate():
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from flightsim.sitl.external_sitl import ExternalPose

    world = load_world("flightsim/worlds/two-pillars.json")  # start yaw 0 (East)
    pose = ExternalPose(world)
    lat0, lon0 = 473977420, 85455940  # degE7
    pose.update(mavlink.MAVLink_local_position_ned_message(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    pose.update(mavlink.MAVLink_attitude_message(0, 0.0, 0.0, 0.3, 0, 0, 0))  # estimate: 0.3 rad off
    truth = mavlink.MAVLink_simstate_message(0, 0, math.pi / 2, 0, 0, 0, 0, 0, 0, lat0, lon0)
    assert pose.update(truth) == "truth"
    pose.anchor()
    # the estimate says nothing moved; the truth says 1 m north (and the heading is East)
    pose.update(mavlink.MAVLink_simstate_message(0, 0, math.pi / 2, 0, 0, 0, 0, 0, 0,
                                                 lat0 + round(1.0 / LATLON_TO_M), lon0))
    state = pose.state()
    x0, y0, _ = world.start_position
    assert state.position[:2] == pytest.approx([x0, y0 + 1.0], abs=0.02)
    assert state.yaw == pytest.approx(0.0, abs=1e-9)
    assert pose.truth_source == "SIMSTATE"


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_simulated_ground_truth_round_trips_through_the_external_mirror(personality):
    """What ``avoid-sim autopilot`` streams as truth (SIMSTATE / HIL_STATE_QUATERNION), read back by
    the external-SITL mirror, is where the simulated vehicle really is (start yaw rotated away)."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from flightsim.sitl.external_sitl import ExternalPose
    from flightsim.sitl.sim_autopilot.server import ground_truth_messages, make_autopilot

    def state(x, y, z, yaw):
        return VehicleState(time=0.0, position=np.array([x, y, z]), velocity=np.array([0.3, -0.2, 0.0]),
                            roll=0.0, pitch=0.0, yaw=yaw, angular_rate=np.zeros(3), on_ground=z < 0.1,
                            armed=True)

    autopilot = make_autopilot(personality, boot_time=0.0)
    start = state(0.0, 0.0, 0.0, math.radians(90.0))  # the SITL boots facing North
    autopilot.observe(start)
    world = load_world("flightsim/worlds/two-pillars.json")  # start yaw 0: East
    pose = ExternalPose(world)
    pose.update(mavlink.MAVLink_local_position_ned_message(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    pose.update(mavlink.MAVLink_attitude_message(0, 0.0, 0.0, 0.0, 0, 0, 0))
    truth = ground_truth_messages(personality, autopilot, start, 1.0)
    kinds = ["SIMSTATE", "SIM_STATE"] if personality == "ardupilot" else ["HIL_STATE_QUATERNION"]
    assert [m.get_type() for m in truth] == kinds
    assert [pose.update(wire(m)) for m in truth] == ["truth"] * len(truth)
    pose.anchor()
    # 2 m North of the start, turned 30° left
    # the estimate says 1.5 m up, the truth 0.5 m: the truth's altitude is what the world sees
    pose.update(mavlink.MAVLink_local_position_ned_message(0, 2.0, 0.0, -1.5, 0.0, 0.0, 0.0))
    moved = state(0.0, 2.0, 0.5, math.radians(120.0))
    for message in ground_truth_messages(personality, autopilot, moved, 2.0):
        pose.update(wire(message))
    mirrored = pose.state()
    x0, y0, _ = world.start_position
    assert mirrored.position[:2] == pytest.approx([x0 + 2.0, y0], abs=0.02)  # North became East
    assert mirrored.position[2] == pytest.approx(0.5, abs=0.002)
    assert pose.altitude_source == kinds[-1]
    assert mirrored.yaw == pytest.approx(math.radians(30.0), abs=1e-3)


@pytest.mark.parametrize("sitl_heading_deg", [0.0, 90.0, 200.0])
def test_mission_items_land_on_the_world_waypoints_in_a_turned_external_sitl(sitl_heading_deg):
    """``fly --autopilot external --mission``: the items uploaded from the anchored pose and its
    rotation, flown to in the SITL's own frame, are the world's waypoints in the mirrored world."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from companion.guidance.goal_frames import GlobalOrigin, global_to_local_ne, offset_global
    from flightsim.sitl.external_sitl import ExternalPose
    from flightsim.sitl.ground_station import mission_items

    world = dataclasses.replace(load_world("flightsim/worlds/two-pillars.json"), start_yaw_deg=-30.0,
                                waypoints=((4.0, 1.0, 2.0), (-2.0, 3.5, 1.0)))
    pose = ExternalPose(world)
    here = (473977420, 85455940)  # where the SITL stands, 3 m north and 1 m west of its EKF origin
    origin = GlobalOrigin(*(round(v) for v in offset_global(*here, -3.0, 1.0)), 500.0)
    pose.update(mavlink.MAVLink_local_position_ned_message(0, 3.0, -1.0, 0.0, 0.0, 0.0, 0.0))
    pose.update(mavlink.MAVLink_attitude_message(0, 0.0, 0.0, math.radians(sitl_heading_deg), 0, 0, 0))
    pose.update(mavlink.MAVLink_global_position_int_message(0, *here, 500000, 0, 0, 0, 0, 0))
    pose.anchor()
    home, rotation = pose.mission_frame()
    assert home == here
    for item, waypoint in zip(mission_items(world, home, rotation), world.waypoints, strict=True):
        assert item.frame == mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT and item.z == waypoint[2]
        north, east = global_to_local_ne(item.x, item.y, origin)  # where the SITL flies to
        pose.update(mavlink.MAVLink_local_position_ned_message(0, north, east, -waypoint[2], 0, 0, 0))
        assert pose.state().position == pytest.approx(waypoint, abs=0.02)


def test_mission_frame_needs_a_global_position():
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from flightsim.sitl.external_sitl import ExternalPose

    pose = ExternalPose(load_world("flightsim/worlds/two-pillars.json"))
    pose.update(mavlink.MAVLink_local_position_ned_message(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    pose.update(mavlink.MAVLink_attitude_message(0, 0.0, 0.0, 0.0, 0, 0, 0))
    assert pose.missing_estimate() == ["GLOBAL_POSITION_INT"]  # the harness waits for it too
    pose.anchor()
    with pytest.raises(RuntimeError, match="GLOBAL_POSITION_INT"):
        pose.mission_frame()


def test_ground_station_takes_either_spelling_of_a_connection_and_names_a_bad_one():
    """``--connect`` goes through companion/autopilot/connection.py: a MAVSDK URL works as its pymavlink
    spelling does (here against a real pymavlink peer on loopback), a bad one is one UserError."""
    from flightsim.sitl.ground_station import GroundStation
    from tests.companion.mavlink_peer import AutopilotPeer

    port = free_udp_port()
    gcs = GroundStation(f"udpin://127.0.0.1:{port}")  # MAVSDK's spelling of pymavlink's udpin:
    peer = AutopilotPeer(f"udpout:127.0.0.1:{port}")
    try:
        peer.heartbeat(armed=False)
        gcs.wait_heartbeat(timeout=5.0)
        gcs.pump(1.2)  # its next heartbeat (one a second) goes to the peer it now knows
        assert peer.wait_for("HEARTBEAT", timeout=1.0) is not None
        assert gcs.target_system == 1 and not gcs.armed
    finally:
        peer.close()
        gcs.close()
    for bad, why in (("tcp:127.0.0.1:70000", "port"), ("mavlink.example:5760", "expected"),
                     ("udpin:", "HOST:PORT")):
        with pytest.raises(UserError, match=why):
            GroundStation(bad)


def test_ground_station_takes_the_first_answer_to_a_command_it_sent_again():
    """Under load the ACK to NAV_TAKEOFF comes after the ground station has sent it again, together
    with the refusal of the repeat (the vehicle is already climbing): the command was accepted."""
    import threading

    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from flightsim.sitl.ground_station import GroundStation
    from tests.companion.mavlink_peer import AutopilotPeer

    port = free_udp_port()
    gcs = GroundStation(f"udpin:127.0.0.1:{port}")
    peer = AutopilotPeer(f"udpout:127.0.0.1:{port}")
    takeoff = mavlink.MAV_CMD_NAV_TAKEOFF
    seen: list[int] = []

    def late_autopilot() -> None:
        for _ in range(2):
            msg = peer.wait_for("COMMAND_LONG", timeout=5.0, condition=lambda m: m.command == takeoff)
            seen.append(msg.confirmation)
        peer.mav.command_ack_send(takeoff, mavlink.MAV_RESULT_ACCEPTED)  # the first, late
        peer.mav.command_ack_send(takeoff, mavlink.MAV_RESULT_TEMPORARILY_REJECTED)  # the repeat

    try:
        peer.heartbeat(armed=True)
        gcs.wait_heartbeat(timeout=5.0)
        answering = threading.Thread(target=late_autopilot)
        answering.start()
        result = gcs.command(takeoff, 0, 0, 0, 0, 0, 0, 1.5, timeout=3.0)
        answering.join(timeout=5.0)
    finally:
        peer.close()
        gcs.close()
    assert result == mavlink.MAV_RESULT_ACCEPTED
    assert seen == [0, 1]  # sent again, its confirmation counted up as the protocol asks


def wire(msg):
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    mav = mavlink.MAVLink(None, 1, 1)
    return mav.decode(bytearray(msg.pack(mav)))


def test_wait_for_position_says_how_long_every_5_s_and_names_what_never_came(caplog):
    """The external path waits as a pilot does: a progress line every 5 s, and at the timeout one
    line naming the messages that never arrived (a fake clock: this is the wait's own logic)."""
    import logging

    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from flightsim.sitl.external_sitl import ExternalPose, wait_for_position

    pose = ExternalPose(load_world("flightsim/worlds/two-pillars.json"))
    pose.update(mavlink.MAVLink_attitude_message(0, 0.0, 0.0, 0.0, 0, 0, 0))
    pose.update(mavlink.MAVLink_global_position_int_message(0, 0, 0, 0, 0, 0, 0, 0, 0))  # no fix yet
    clock = [0.0]

    def sleep(dt: float) -> None:
        clock[0] += dt
        if clock[0] >= 23.0:  # the EKF's origin arrives
            pose.update(mavlink.MAVLink_local_position_ned_message(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
            pose.update(mavlink.MAVLink_global_position_int_message(0, 473977420, 85455940, 0, 0, 0, 0, 0, 0))

    with caplog.at_level(logging.INFO, logger="flightsim.sitl.external_sitl"):
        waited = wait_for_position(pose, timeout=120.0, clock=lambda: clock[0], sleep=sleep)
    assert waited == pytest.approx(23.0, abs=0.06)
    notes = [r.getMessage() for r in caplog.records if "waiting for EKF origin" in r.getMessage()]
    assert [n.split(" (")[0] for n in notes] == [f"waiting for EKF origin: {s} s" for s in (5, 10, 15, 20)]

    late = ExternalPose(load_world("flightsim/worlds/two-pillars.json"))
    late.update(mavlink.MAVLink_attitude_message(0, 0.0, 0.0, 0.0, 0, 0, 0))
    clock[0] = 0.0
    with pytest.raises(RuntimeError) as exc:
        wait_for_position(late, timeout=8.0, clock=lambda: clock[0],
                          sleep=lambda dt: clock.__setitem__(0, clock[0] + dt))
    assert "no LOCAL_POSITION_NED / GLOBAL_POSITION_INT within 8 s" in str(exc.value)
    assert "\n" not in str(exc.value)
