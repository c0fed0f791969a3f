"""The shield's obstacle memory: returns carried by odometry, inflated by age, dropped without odometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.safety.obstacle_memory import RANGE_ACCURACY_M, ObstacleMemory, scan_points

E = 0.3
NONE = np.zeros((0, 2))


def _span(r: float) -> float:
    return r * math.sin(math.radians(0.5)) + RANGE_ACCURACY_M


def test_scan_points_are_the_bins_with_a_return() -> None:
    ranges = np.full(360, 10.0)
    ranges[0], ranges[90] = 2.0, np.nan
    pts = scan_points(ranges, 10.0)
    assert len(pts) == 2
    assert pts[0] == pytest.approx([2.0 * math.cos(math.radians(0.5)), 2.0 * math.sin(math.radians(0.5))])
    assert pts[1] == pytest.approx([0.0, 0.0], abs=1e-12)  # unknown reads as blocked, at the vehicle


def test_a_pole_missed_by_the_next_scans_is_still_there_where_odometry_carries_it() -> None:
    memory = ObstacleMemory(0.5, E)
    memory.update(np.array([[3.0, 0.0]]), 0.1, (1.0, 0.0), 0.0, 0.0)
    memory.update(NONE, 0.1, (1.0, 0.0), 0.0, 0.0)
    points, inflation = memory.update(NONE, 0.1, (1.0, 0.0), 0.0, 0.0)
    assert points == pytest.approx(np.array([[2.8, 0.0]]))  # flown 0.2 m towards it since
    assert inflation == pytest.approx([_span(3.0) + E * 0.2])


def test_a_turn_carries_the_pole_round() -> None:
    memory = ObstacleMemory(0.5, E)
    memory.update(np.array([[2.0, 0.0]]), 0.1, (0.0, 0.0), 0.0, 0.0)
    points, _ = memory.update(NONE, 0.1, (0.0, 0.0), math.pi / 2, 0.0)  # turned 90° to the left
    assert points == pytest.approx(np.array([[0.0, -2.0]]), abs=1e-12)  # now on the right
    points, _ = memory.update(NONE, 0.1, (0.0, 0.0), None, -math.pi / 2 / 0.1)  # no heading: the rate
    assert points == pytest.approx(np.array([[2.0, 0.0]]), abs=1e-12)


def test_returns_older_than_the_memory_are_forgotten() -> None:
    memory = ObstacleMemory(0.25, E)
    memory.update(np.array([[3.0, 0.0]]), 0.1, (0.0, 0.0), 0.0, 0.0)
    for _ in range(2):
        points, _ = memory.update(NONE, 0.1, (0.0, 0.0), 0.0, 0.0)
    assert len(points) == 1
    points, _ = memory.update(NONE, 0.1, (0.0, 0.0), 0.0, 0.0)
    assert len(points) == 0


@pytest.mark.parametrize("lost", [None, (math.nan, 0.0)])
def test_without_odometry_only_the_current_scan_counts(lost) -> None:
    memory = ObstacleMemory(0.5, E)
    memory.update(np.array([[3.0, 0.0]]), 0.1, (1.0, 0.0), 0.0, 0.0)
    points, inflation = memory.update(np.array([[5.0, 1.0]]), 0.1, lost, 0.0, 0.0)
    assert points == pytest.approx(np.array([[5.0, 1.0]]))
    assert inflation == pytest.approx([_span(math.hypot(5.0, 1.0))])


def test_a_velocity_change_since_a_scan_inflates_its_returns_by_the_lag() -> None:
    """A late velocity, integrated, is off by the lag times how much the velocity changed since: a
    return seen before a brake carries that on top of the estimate error's share."""
    memory = ObstacleMemory(0.5, E, velocity_lag=0.1)
    memory.update(np.array([[3.0, 0.0]]), 0.1, (2.0, 0.0), 0.0, 0.0)
    memory.update(np.array([[3.0, 0.0]]), 0.1, (1.0, 0.0), 0.0, 0.0)
    _, inflation = memory.update(NONE, 0.1, (0.5, 0.0), 0.0, 0.0)
    assert inflation == pytest.approx([_span(3.0) + E * 0.2 + 0.1 * 1.5, _span(3.0) + E * 0.1 + 0.1 * 0.5])
    steady = ObstacleMemory(0.5, E, velocity_lag=0.1)
    steady.update(np.array([[3.0, 0.0]]), 0.1, (1.0, 0.0), 0.0, 0.0)
    _, inflation = steady.update(NONE, 0.1, (1.0, 0.0), 0.0, 0.0)
    assert inflation == pytest.approx([_span(3.0) + E * 0.1])  # a steady velocity's lag costs nothing
