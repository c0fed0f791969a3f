"""Frames and the simulated vehicle's place on Earth, for both simulated autopilots.

The vehicle works in world ENU (x East, y North, z Up; yaw counter-clockwise from East, body FLU),
MAVLink in NED (x North, y East, z Down; yaw clockwise from North, body FRD).
"""

from __future__ import annotations

import math

import numpy as np

from flightsim.vehicle.control import wrap_angle

#: Where the simulated vehicle's home is on Earth (the global positions and mission home it reports).
HOME_LAT_DEG = 47.397742
HOME_LON_DEG = 8.545594
HOME_ALT_AMSL_M = 488.0
EARTH_RADIUS_M = 6_378_137.0


def ned_to_enu(v: np.ndarray | tuple[float, float, float]) -> np.ndarray:
    """(north, east, down) → (east, north, up)."""
    n, e, d = v
    return np.array([e, n, -d], dtype=float)


def enu_to_ned(v: np.ndarray) -> np.ndarray:
    """(east, north, up) → (north, east, down)."""
    return np.array([v[1], v[0], -v[2]], dtype=float)


def yaw_enu_to_ned(yaw_enu: float) -> float:
    """ENU yaw (CCW from East) → NED heading (CW from North), wrapped to [-π, π)."""
    return wrap_angle(math.pi / 2.0 - yaw_enu)


def yaw_ned_to_enu(yaw_ned: float) -> float:
    """NED heading (CW from North) → ENU yaw (CCW from East), wrapped to [-π, π)."""
    return wrap_angle(math.pi / 2.0 - yaw_ned)


def body_to_world_xy(forward: float, right: float, yaw_ned: float) -> tuple[float, float]:
    """Rotate a body FRD horizontal vector by the NED heading into (north, east)."""
    c, s = math.cos(yaw_ned), math.sin(yaw_ned)
    return forward * c - right * s, forward * s + right * c


def lat_lon(rel_enu: np.ndarray) -> tuple[int, int]:
    """Latitude and longitude (degE7) of a point ``rel_enu`` metres (ENU) from home."""
    lat = HOME_LAT_DEG + math.degrees(rel_enu[1] / EARTH_RADIUS_M)
    east_radius = EARTH_RADIUS_M * math.cos(math.radians(HOME_LAT_DEG))
    lon = HOME_LON_DEG + math.degrees(rel_enu[0] / east_radius)
    return round(lat * 1e7), round(lon * 1e7)
