"""Frames for goals (pure): global waypoints to local NED metres, local NED to the body frame.

Local NED is the autopilot's own local frame, the one LOCAL_POSITION_NED is given in; its origin is
the EKF origin (GPS_GLOBAL_ORIGIN). Latitude/longitude offsets become metres on a local tangent
plane the way ArduPilot's ``Location::get_distance_NE`` does (equirectangular, longitude scaled by
cos(latitude)): over a mission's few hundred metres the error is millimetres, and the companion
then agrees with the autopilot about where a waypoint is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: Metres per 1e-7 degree of latitude (ArduPilot's LATLON_TO_M).
LATLON_TO_M = 0.011131884502145034


@dataclass(frozen=True)
class GlobalOrigin:
    """Where local NED (0, 0, 0) is on Earth.

    :param lat_e7: latitude, degrees × 1e7
    :param lon_e7: longitude, degrees × 1e7
    :param alt_amsl: altitude above mean sea level, metres
    """

    lat_e7: int
    lon_e7: int
    alt_amsl: float


def longitude_scale(lat_e7: float) -> float:
    """cos(latitude), floored as ArduPilot does so the poles stay finite."""
    return max(math.cos(math.radians(lat_e7 * 1e-7)), 0.01)


def global_to_local_ne(lat_e7: float, lon_e7: float, origin: GlobalOrigin) -> tuple[float, float]:
    """(north, east) metres of a latitude/longitude (× 1e7) from the origin."""
    north = (lat_e7 - origin.lat_e7) * LATLON_TO_M
    east = (lon_e7 - origin.lon_e7) * LATLON_TO_M * longitude_scale((lat_e7 + origin.lat_e7) / 2)
    return north, east


def offset_global(lat_e7: float, lon_e7: float, north: float, east: float) -> tuple[float, float]:
    """The latitude/longitude (× 1e7) ``north``/``east`` metres away (:func:`global_to_local_ne` inverted)."""
    new_lat = lat_e7 + north / LATLON_TO_M
    new_lon = lon_e7 + east / (LATLON_TO_M * longitude_scale((lat_e7 + new_lat) / 2))
    return new_lat, new_lon


def ned_to_body_flu(delta_ned: tuple[float, float, float], heading: float) -> tuple[float, float, float]:
    """A NED offset (target minus vehicle) in the body frame FLU (x forward, y left, z up), metres.

    :param heading: the vehicle's yaw, NED (clockwise from north), radians; roll and pitch are
        left out: a goal for a multirotor that flies level is a horizontal direction and a height
    """
    n, e, d = delta_ned
    c, s = math.cos(heading), math.sin(heading)
    forward = n * c + e * s
    right = -n * s + e * c
    return forward, -right, -d
