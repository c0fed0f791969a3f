"""Scan matching recovers the vehicle's motion from two scans of a room."""

import math

import numpy as np
import pytest

from companion.perception.scan_motion import scan_motion

_THETA = np.radians(np.arange(360) + 0.5)


def room_scan(
    x: float,
    y: float,
    yaw: float,
    half: tuple[float, float] = (4.0, 3.0),
    pillar: tuple[float, float] = (1.5, 1.0),
) -> np.ndarray:
    """Ranges from pose (x, y, yaw) to the walls of a rectangle centred on the origin, with a pillar
    of radius 0.3 m at ``pillar`` so that the scene has corners and an edge."""
    a = yaw + _THETA
    dx, dy = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore"):
        tx = np.where(dx > 0, (half[0] - x) / dx, np.where(dx < 0, (-half[0] - x) / dx, np.inf))
        ty = np.where(dy > 0, (half[1] - y) / dy, np.where(dy < 0, (-half[1] - y) / dy, np.inf))
    r = np.minimum(tx, ty)
    px, py = pillar[0] - x, pillar[1] - y  # pillar: |p - t d| = 0.3
    b = px * dx + py * dy
    disc = b * b - (px * px + py * py - 0.09)
    hit = (disc >= 0) & (b > 0)
    return np.where(hit, np.minimum(r, b - np.sqrt(np.maximum(disc, 0.0))), r)


@pytest.mark.parametrize(
    ("dx", "dy", "dpsi"), [(0.0, 0.0, 0.0), (0.14, 0.0, 0.0), (0.05, -0.03, 0.0), (0.1, 0.03, 0.12)]
)
def test_scan_motion_recovers_a_move_and_turn(dx, dy, dpsi):
    x0, y0, yaw0 = -0.5, 0.2, 0.3
    c, s = math.cos(yaw0), math.sin(yaw0)
    before = room_scan(x0, y0, yaw0)
    after = room_scan(x0 + c * dx - s * dy, y0 + s * dx + c * dy, yaw0 + dpsi)
    rng = np.random.default_rng(1)
    after = after + rng.normal(0.0, 0.02, 360)  # the sensor's range noise
    ex, ey, epsi, used = scan_motion(before, after, turn_guess=dpsi * 0.8)
    assert used > 200
    assert ex == pytest.approx(dx, abs=0.01) and ey == pytest.approx(dy, abs=0.01)
    assert epsi == pytest.approx(dpsi, abs=0.005)


def test_scan_motion_reports_nothing_to_match_in_the_open():
    empty = np.full(360, np.inf)
    assert scan_motion(empty, empty) == (0.0, 0.0, 0.0, 0)
