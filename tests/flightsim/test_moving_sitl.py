"""SITL co-simulation of moving obstacles: the VLP-16 packets show them where they are at the
flight's time, and the flight recorder judges collisions against them there."""

from __future__ import annotations

import numpy as np
import pytest

from companion.lidar.velodyne import VelodyneUdpSource
from companion.perception.scan import ScanConfig, scan_from_points
from flightsim.envs.raycast import LidarConfig
from flightsim.sitl.companion_setup import free_udp_port
from flightsim.sitl.cosim import LidarCosim
from flightsim.sitl.flight_recorder import Recorder
from flightsim.worlds.moving import MovingObstacle, PathMotion
from flightsim.worlds.world import World
from tests.flightsim.test_sim_autopilot_harness import hover_state, stream_clouds

#: a walker coming down the room's x axis at 1 m/s toward a vehicle hovering at x = -5 facing +x
WALKER = MovingObstacle("cylinder", PathMotion(((5.0, 0.0), (-5.0, 0.0)), 1.0), 1.8, radius=0.25)
WORLD = World("walker", (16.0, 10.0), 3.0, (), (-5.0, 0.0, 1.5), 0.0, moving=(WALKER,))


def _ahead_over_udp(world_time: float) -> float:
    """Stream the world at a frozen ``world_time`` through real UDP packets; the decoded scan's
    range straight ahead, metres."""
    state = hover_state(-5.0, 0.0, 0.0)
    port = free_udp_port()
    source = VelodyneUdpSource("127.0.0.1", port)
    cosim = LidarCosim(
        WORLD, lambda: state, ("127.0.0.1", port), lidar=LidarConfig(azimuth_step_deg=1.0),
        world_time=lambda: world_time,
    )  # fmt: skip
    cosim.revolution_packets(state, world_time)  # compile before streaming
    clouds = stream_clouds(cosim, source, 0.6)
    assert clouds, "no revolution decoded"
    scan = scan_from_points(clouds[-1], ScanConfig())
    return float(scan[[358, 359, 0, 1]].min()) * 10.0


def test_the_packets_show_the_walker_where_it_is_at_the_flights_time() -> None:
    # each revolution ends 0.1 s after the time it is cast at: the walker is 0.1 m further on
    assert _ahead_over_udp(0.0) == pytest.approx(10.0 - 0.1 - 0.25, abs=0.06)
    assert _ahead_over_udp(4.0) == pytest.approx(6.0 - 0.1 - 0.25, abs=0.06)


def test_the_recorder_judges_collisions_against_the_walker_where_it_is() -> None:
    recorder = Recorder(t0=100.0)
    position = np.array([-2.0, 0.0, 1.5])
    recorder.on_pose(102.0, position, 0.0, 0.0, WORLD)  # walker at x = 3: 4.75 m off
    assert recorder.collision_time is None and recorder.min_clearance == pytest.approx(4.75)
    recorder.on_pose(106.9, position, 0.0, 0.0, WORLD)  # walker at x = -1.9: inside
    assert recorder.collision_time == 106.9


def test_the_dynamic_demo_set_is_each_dynamic_family_at_a_validation_seed() -> None:
    from flightsim.envs import seeds
    from flightsim.sitl.demo import dynamic_worlds
    from flightsim.worlds.families import DYNAMIC_FAMILIES

    worlds = dynamic_worlds()
    assert [w.name.rsplit("-", 2)[0] for w in worlds] == list(DYNAMIC_FAMILIES)
    assert all(w.moving for w in worlds)
    assert all(int(w.name.rsplit("-", 2)[1]) in seeds.VALIDATION for w in worlds)


def test_the_flight_plot_draws_the_movers_where_they_were_at_the_last_pose(tmp_path) -> None:
    from flightsim.sitl.flight_report import plot_flight

    traj = np.array([[100.0 + t, -5.0, 0.0, 1.5, 0.0, 0.0] for t in np.arange(0.0, 8.0, 0.1)])
    purple = []
    for world_t0 in (None, 100.0):
        fig = plot_flight(WORLD, traj, 100.0, None, tmp_path / "f.png", "t", world_t0=world_t0)
        lines = [line for line in fig.axes[0].get_lines() if line.get_color() == "#8e44ad"]
        purple.append(lines[0].get_xydata())
    preview, trail = purple
    assert preview[-1, 0] == pytest.approx(-5.0)  # the 10 s track ahead from the start: to x = -5
    assert trail[0, 0] == pytest.approx(5.0) and trail[-1, 0] == pytest.approx(5.0 - 7.9, abs=1e-6)
