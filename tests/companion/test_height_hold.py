"""The height hold's logic (pure; the flight itself is tests/sitl/test_height_hold.py): the lidar's
height above the floor against the autopilot's estimate, the tolerance and its hysteresis, the
floor out of sight, and the climb it asks for."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.autopilot.mavlink_adapter import mavlink
from companion.config import FixedWaypointConfig, GoalConfig
from companion.guidance.goal_source import FLOOR_LOST_REVOLUTIONS, GoalSource
from companion.perception.scan import ScanConfig


def floor_ring(height: float) -> np.ndarray:
    """A revolution's downward returns off a flat floor ``height`` m below the sensor."""
    az = np.radians(np.arange(0.0, 360.0, 1.0))
    rings = []
    for elevation in (-15.0, -13.0, -11.0):
        d = height / math.tan(math.radians(-elevation))
        rings.append(np.stack([d * np.cos(az), d * np.sin(az), np.full_like(az, -height)], axis=1))
    return np.concatenate(rings).astype(np.float32)


def source(**goal) -> tuple[GoalSource, list[float]]:
    clock = [0.0]
    waypoint = FixedWaypointConfig(10.0, 0.0, -1.5)
    config = GoalConfig(source="fixed", waypoints=(waypoint,), route=False, **goal)
    return GoalSource(config, (1, 191), True, lambda: clock[0], lambda request: None), clock


def estimate(goal: GoalSource, t: float, height: float) -> None:
    """The autopilot says it is ``height`` m above home (and at that down coordinate), level."""
    goal.on_message(mavlink.MAVLink_local_position_ned_message(0, 0.0, 0.0, -height, 0.0, 0.0, 0.0))
    goal.on_message(mavlink.MAVLink_attitude_message(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    mm = round(height * 1000)
    goal.on_message(mavlink.MAVLink_global_position_int_message(0, 473977420, 85455940, 488000 + mm, mm,
                                                                0, 0, 0, 0))
    goal.step(True)


def test_a_drifted_estimate_is_flown_on_the_lidars_height_and_the_pilot_is_told():
    goal, _clock = source()
    estimate(goal, 0.0, 1.5)
    for _ in range(5):
        goal.observe_cloud(floor_ring(0.6), ScanConfig())  # truly 0.6 m up: the estimate is 0.9 m high
    assert goal.height_correction == pytest.approx(0.9, abs=0.01)
    said = goal.drain_announcements()
    told = "autopilot altitude 1.50 m, lidar 0.60 m over the floor: holding the lidar's"
    assert any(told in s for s in said)
    out = goal.step(True)
    assert out.vertical_speed == pytest.approx(0.5)  # climbs toward the waypoint's 1.5 m (bounded)
    # the autopilot's altitude agrees within the tolerance: no correction
    goal2, _ = source()
    estimate(goal2, 0.0, 1.5)
    for _ in range(5):
        goal2.observe_cloud(floor_ring(1.3), ScanConfig())
    assert goal2.height_correction == 0.0 and goal2.step(True).vertical_speed == 0.0


def test_hysteresis_and_the_floor_out_of_sight():
    goal, _ = source(height_tolerance=0.3)
    estimate(goal, 0.0, 1.5)
    for _ in range(5):
        goal.observe_cloud(floor_ring(1.0), ScanConfig())  # 0.5 m off: engaged
    assert goal.height_correction == pytest.approx(0.5, abs=0.01)
    for _ in range(5):
        goal.observe_cloud(floor_ring(1.3), ScanConfig())  # 0.2 m off: above half the tolerance, held
    assert goal.height_correction == pytest.approx(0.2, abs=0.01)
    goal.drain_announcements()
    for _ in range(FLOOR_LOST_REVOLUTIONS):
        goal.observe_cloud(np.zeros((0, 3), np.float32), ScanConfig())
    assert goal.height_correction == 0.0
    said = goal.drain_announcements()
    assert "height: floor not in sight: flying the autopilot's altitude" in said
    assert "height: floor not in sight" in said


def test_height_hold_off_leaves_the_estimate_alone():
    goal, _ = source(height_hold=False)
    estimate(goal, 0.0, 1.5)
    for _ in range(5):
        goal.observe_cloud(floor_ring(0.6), ScanConfig())
    assert goal.height_correction == 0.0
    assert not any("height" in s for s in goal.drain_announcements())
    assert goal.step(True).vertical_speed == 0.0
