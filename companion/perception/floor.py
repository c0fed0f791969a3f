"""Height above the floor from the lidar's downward lasers (pure).

Half of a VLP-16's lasers look below the horizon (-15° to -1°): at 1.5 m the -15° laser meets a flat
floor about 5.6 m out, the -11° one about 7.7 m out. Taken to the body frame (the scan's mount
transform) and levelled with the autopilot's roll and pitch, their returns lie on the floor or above
it, on whatever stands there (crates, benches, people), or on the walls. A level surface is told
from a wall by two lasers one above the other: the upper one meets a floor farther out at the same
height, a wall at the same distance higher up. The floor is the lowest level surface: a plane fitted
to the lowest level returns, which also takes up a tilt the attitude left (at 5.6 m, 3° of roll or
pitch missed is 0.3 m of height); its height under the body is the height above the floor. The
lidar says nothing about the floor when the plane rests on too few returns
(:data:`MIN_FLOOR_RETURNS`) or directions (:data:`MIN_SECTORS` of 36), or is too steep to be a floor
(a CAN rangefinder ring has no downward beams; a small room's walls hide the floor from the second
laser; flying too high): then :func:`floor_height` answers None, never a guess.

The autopilot's altitude is an estimate (barometer, GPS) that drifts: the real PX4 SIH flights were
off the truth by -1.08 to +0.82 m, while this height is measured against the floor the vehicle
flies over, the one a horizontal scan slice at the mission altitude is built for.
"""

from __future__ import annotations

import math

import numpy as np

from companion.perception.scan import ScanConfig

#: returns less than this below the body origin are not on the floor (the horizon lasers), m
MIN_DEPTH_M = 0.2
#: returns are grouped by direction (this wide, degrees) and laser (its elevation, to the degree)
AZIMUTH_BIN_DEG = 1.0
#: two lasers one above the other see a level surface when the upper one's return is this much
#: farther out at most this slope's height difference (0.1: 6°, the attitude's error allowed)
LEVEL_SLOPE = 0.1
MIN_RING_GAP_M = 0.3
#: directions around the vehicle the floor's coverage is counted in (10° each)
N_SECTORS = 36
#: a level surface more than this above the floor plane is something standing on it (a crate), m
ABOVE_PLANE_M = 0.15
#: the floor's returns lie within this of the plane (sensor noise, a floor not quite flat), m
ON_PLANE_M = 0.1
#: the floor may look tilted by at most this much (the attitude's error): its slope's tangent
MAX_SLOPE = 0.15
#: fewer floor returns than this are no measurement
MIN_FLOOR_RETURNS = 30
#: ... and they must come from at least this many of the 36 directions around the vehicle
MIN_SECTORS = 6


def level_rotation(roll: float, pitch: float) -> np.ndarray:
    """(3, 3) rotation from the body frame (FLU) to a level frame with the same heading (FLU).

    :param roll: MAVLink ATTITUDE roll (FRD: right side down positive), rad
    :param pitch: MAVLink ATTITUDE pitch (nose up positive), rad
    """
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    flip = np.diag([1.0, -1.0, -1.0])  # FLU <-> FRD
    return flip @ ry @ rx @ flip


def _fit_plane(xyz: np.ndarray) -> np.ndarray:
    """Least-squares z = a x + b y + c through ``xyz`` (N >= 3): (a, b, c)."""
    design = np.column_stack([xyz[:, 0], xyz[:, 1], np.ones(len(xyz))])
    return np.linalg.lstsq(design, xyz[:, 2], rcond=None)[0]


def _level_returns(sensor: np.ndarray, level: np.ndarray) -> np.ndarray:
    """Which returns lie on a level surface: in their direction, the next laser up meets the same
    surface farther out at (nearly) the same height. A wall or a crate's side is met by the next laser
    at the same distance, higher up."""
    elevation = np.round(np.degrees(np.arctan2(sensor[:, 2], np.hypot(sensor[:, 0], sensor[:, 1]))))
    azimuth = np.floor(np.degrees(np.arctan2(sensor[:, 1], sensor[:, 0])) / AZIMUTH_BIN_DEG)
    # one sortable key: direction, then elevation (within ±90°)
    keys = (azimuth.astype(np.int64) + 1000) * 256 + (elevation.astype(np.int64) + 128)
    groups, index = np.unique(keys, return_inverse=True)
    counts = np.bincount(index)
    distance = np.bincount(index, np.hypot(level[:, 0], level[:, 1])) / counts
    height = np.bincount(index, level[:, 2]) / counts
    on_level = np.zeros(len(groups), dtype=bool)
    # groups are sorted by direction, then elevation: a pair is the next group in the same direction
    same = groups[1:] // 256 == groups[:-1] // 256
    gap = distance[1:] - distance[:-1]
    flat = same & (gap > MIN_RING_GAP_M) & (np.abs(height[1:] - height[:-1]) < LEVEL_SLOPE * gap)
    on_level[:-1] |= flat
    on_level[1:] |= flat
    return on_level[index]


def floor_height(points: np.ndarray, scan: ScanConfig, roll: float, pitch: float,
                 min_returns: int = MIN_FLOOR_RETURNS) -> float | None:
    """The body origin's height above the floor, m, or None when the floor is not seen.

    :param points: ``(N, 3)`` returns in the sensor frame (FLU), metres, as the lidar source gives them
    :param scan: the mount transform (``mount_xyz``, ``mount_rpy_deg``) and ``min_range``
    :param roll: the vehicle's roll (MAVLink ATTITUDE), rad
    :param pitch: the vehicle's pitch (MAVLink ATTITUDE), rad
    :param min_returns: fewest floor returns that make a measurement
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    pts = pts[np.linalg.norm(pts, axis=1) >= scan.min_range]
    body = pts @ np.asarray(scan.rotation(), dtype=np.float64).T + np.asarray(scan.mount_xyz)
    level = body @ level_rotation(roll, pitch).T
    below = level[:, 2] < -MIN_DEPTH_M
    pts, level = pts[below], level[below]
    if len(level) < min_returns:
        return None
    flat = level[_level_returns(pts, level)]
    if len(flat) < min_returns:
        return None
    # the lowest level surface: start level at the lowest returns (a low quantile: one stray return
    # below the floor does not set it), drop what stands above the plane, let the plane take up the
    # tilt the attitude missed, and let in what each fit comes to pass through
    plane = np.array([0.0, 0.0, float(np.quantile(flat[:, 2], 0.02))])
    for _ in range(4):
        residual = flat[:, 2] - flat[:, :2] @ plane[:2] - plane[2]
        on = flat[np.abs(residual) < ABOVE_PLANE_M]
        if len(on) < min_returns:
            return None
        plane = _fit_plane(on)
    on = flat[np.abs(flat[:, 2] - flat[:, :2] @ plane[:2] - plane[2]) < ON_PLANE_M]
    sectors = np.unique((np.degrees(np.arctan2(on[:, 1], on[:, 0])) // (360.0 / N_SECTORS)) % N_SECTORS)
    if len(on) < min_returns or len(sectors) < MIN_SECTORS or math.hypot(plane[0], plane[1]) > MAX_SLOPE:
        return None
    return -float(_fit_plane(on)[2])
