"""SITL: missions through both simulated autopilots, the real companion process, a mission changed in flight.

No goal-conditioned policy exists yet: a constant policy flies a loop, and the in-flight mission
puts its waypoints on two points of that loop the vehicle has just passed. What is
tested is the plumbing: the ground station's uploads, the companion's downloads (the second one in
flight), its progress announcements, and the hold at completion that stops the vehicle.
"""

from __future__ import annotations

import dataclasses
import time

import pytest

from flightsim.sitl.ground_station import mission_items
from flightsim.sitl.harness import FlightOptions, SitlFlight
from tests.sitl.helpers import OPEN_ROOM, engage_mission, said, speed, wait_for, write_constant_policy

pytestmark = pytest.mark.sitl

FAR = dataclasses.replace(OPEN_ROOM, waypoints=((5.0, 5.0, 1.5),))  # never reached by the circle


@pytest.mark.parametrize("autopilot", ["sim-ardupilot", "sim-px4"])
def test_mission_changed_in_flight_tracked_to_completion(tmp_path, autopilot):
    # the circle's radius depends on how the autopilot answers; this tests the mission plumbing, so it
    # flies the ideal response (the calibrated one is flown by test_px4_flight, test_faults_ardupilot)
    options = FlightOptions(autopilot=autopilot, world=FAR, workdir=tmp_path, mission=True,
                            policy=write_constant_policy(tmp_path / "circle.onnx", 0.5, 0.4),
                            ideal_response=True)
    with SitlFlight(options) as f:
        engage_mission(f)
        wait_for(lambda: said(f, "goal: tracking"), 10.0, "the companion tracking the first mission")
        assert said(f, "mission downloaded: 1 items")
        wait_for(lambda: speed(f) > 0.6, 5.0, "the vehicle flying its circle")

        # the new mission's waypoints lie on the loop the vehicle is flying: two points it has just
        # passed, 2 s apart (where the loop lies depends on the response and the shield)
        first = tuple(f.server.state.position[:2])
        time.sleep(2.0)
        second = tuple(f.server.state.position[:2])
        on_loop = dataclasses.replace(OPEN_ROOM, waypoints=((*first, 1.5), (*second, 1.5)))
        f.pilot(lambda gcs: gcs.upload_mission(mission_items(on_loop, gcs.home_position())))
        wait_for(lambda: said(f, "mission downloaded: 2 items"), 10.0, "the download in flight")
        assert said(f, "mission changed")
        wait_for(lambda: said(f, "goal: complete, holding"), 30.0, "the mission's completion")
        assert said(f, "goal: reached item")
        wait_for(lambda: speed(f) < 0.15, 8.0, "the vehicle held at completion")
        assert f.server.autopilot.mode_name() in ("GUIDED", "OFFBOARD")  # on_complete = hold: mode untouched
        report = f.report()
        assert report.engaged and not report.collision
        assert any("complete" in t for t in report.goal_events)
