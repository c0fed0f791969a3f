"""SITL: the companion flies uploaded missions with goal-layout policies, on both simulated autopilots.

- Heights: a real ONNX model that steers toward the goal's bearing (``echo_goal``) flies a mission
  whose waypoints lie 1.5 m above and then 0.5 m below the take-off height: the setpoints' vertical
  speed must take the vehicle there, through the firmware's calibrated response. It checks the
  companion's MISSION_ITEM_REACHED per item, with the item's own sequence number (ArduPilot's
  item 0 is home).

- The shipped policy (``models/policy.onnx``, the trained goal policy) flies the example world
  ``two-pillars`` as a mission through the calibrated ArduPilot response, as ``avoid-sim demo``
  does: every waypoint, no collision.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from flightsim.sitl.harness import FlightOptions, SitlFlight
from flightsim.worlds.world import load_world
from tests.onnx_models import write_policy
from tests.sitl.helpers import OPEN_ROOM, engage_mission, said, wait_for

pytestmark = pytest.mark.sitl

#: take-off at 1.5 m; the first waypoint 1.5 m higher, the second 0.5 m lower than the take-off
HEIGHTS = dataclasses.replace(OPEN_ROOM, name="open-heights", room_height=4.0,
                              waypoints=((0.0, 2.5, 3.0), (3.0, 2.5, 1.0)))


def _first_item(autopilot: str) -> int:
    return 1 if autopilot == "sim-ardupilot" else 0  # ArduPilot's mission item 0 is home


def _altitudes(f: SitlFlight) -> np.ndarray:
    with f.recorder.lock:
        return np.array([row[3] for row in f.recorder.trajectory if f.engaged_at and row[0] >= f.engaged_at])


@pytest.mark.parametrize("autopilot", ["sim-ardupilot", "sim-px4"])
def test_mission_climbs_and_descends_to_each_waypoint_height(tmp_path, autopilot):
    options = FlightOptions(autopilot=autopilot, world=HEIGHTS, workdir=tmp_path, mission=True,
                            policy=write_policy(tmp_path / "goal.onnx", kind="echo_goal"))
    with SitlFlight(options) as f:
        engage_mission(f)
        first = _first_item(autopilot)
        wait_for(lambda: said(f, f"reached item {first} (1/2)"), 30.0, "the first waypoint, 1.5 m up")
        assert _altitudes(f).max() > 2.3  # climbed to within its 1 m radius (3D)
        wait_for(lambda: said(f, "goal: complete, holding"), 30.0, "the second waypoint, 2 m lower")
        assert f.server.state.position[2] < 1.95  # descended to within 1 m of 1.0 m
        report = f.report()
        assert report.engaged and not report.collision
        wait_for(lambda: f.recorder.items_reached == [first, first + 1], 3.0, "MISSION_ITEM_REACHED per item")



def test_the_shipped_policy_completes_a_mission_between_two_pillars(tmp_path):
    root = Path(__file__).resolve().parents[2]
    world = load_world(root / "flightsim" / "worlds" / "two-pillars.json")
    options = FlightOptions(autopilot="sim-ardupilot", world=world, workdir=tmp_path, mission=True,
                            policy=root / "models" / "policy.onnx")
    with SitlFlight(options) as f:
        engage_mission(f)
        wait_for(lambda: said(f, "goal: complete, holding"), 60.0, "both waypoints")
        report = f.report()
        assert report.engaged and not report.collision
