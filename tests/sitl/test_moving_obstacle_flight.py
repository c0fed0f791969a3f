"""SITL with a moving obstacle, on both simulated autopilots: a walker crosses the point where the
companion holds the vehicle; the lidar packets carry it and the flight's clearance is judged
against it where it is (a static world would read the walls' 6 m the whole flight)."""

from __future__ import annotations

import dataclasses

import pytest

from flightsim.sitl.harness import FlightOptions, SitlFlight
from flightsim.worlds.moving import MovingObstacle, PathMotion
from tests.sitl.helpers import OPEN_ROOM, wait_for, write_constant_policy

pytestmark = pytest.mark.sitl

#: out and back along x = 0 at 1 m/s, through the start (0, -1.7) at about 6.7 s, 18.3 s, 31.7 s, …
WALKER = MovingObstacle(
    "cylinder", PathMotion(((0.0, 5.0), (0.0, -7.5)), 1.0), 1.8, radius=0.25, kind="pedestrian"
)


@pytest.mark.parametrize("autopilot", ["sim-ardupilot", "sim-px4"])
def test_a_walker_crossing_the_hover_point_comes_within_reach(tmp_path, autopilot):
    world = dataclasses.replace(OPEN_ROOM, name="open-room-walker", moving=(WALKER,))
    options = FlightOptions(
        autopilot=autopilot, world=world, workdir=tmp_path,
        policy=write_constant_policy(tmp_path / "hold.onnx", 0.0, 0.0),
    )  # fmt: skip
    with SitlFlight(options) as f:
        f.take_off()
        assert f.wait_engaged(25.0), f.companion_log()
        wait_for(lambda: f.recorder.min_clearance < 1.0, 40.0, "the walker to come within 1 m")
        report = f.report()
        assert report.engaged and report.min_clearance_m < 1.0
