"""The scan as MAVLink OBSTACLE_DISTANCE sectors, so the autopilot's own avoidance is a second layer.

Message layout (sent by the autopilot links): 72 sectors, ``increment`` 5°, ``angle_offset`` 0,
``frame`` MAV_FRAME_BODY_FRD, ``min_distance`` 10 cm, ``max_distance`` 1000 cm, no return =
``max_distance + 1``.

Sector geometry, as ArduPilot reads it (``AP_Proximity_MAV::handle_obstacle_distance_msg``): the
value of sector ``j`` is placed at ``mid_angle = j × increment + angle_offset`` degrees CLOCKWISE
from forward, i.e. sector ``j`` is *centred* on ``j × 5°`` clockwise and spans ``[5j − 2.5°,
5j + 2.5°)``. Values below ``min_distance`` or above ``max_distance`` (and 0, 65535) are ignored
there, which is why a too-close return is reported as ``min_distance`` rather than dropped.

Scan bin ``i`` spans ``[i°, i+1°)`` COUNTER-clockwise from forward, i.e. ``(−i−1°, −i°]``
clockwise. Sector edges at ``±2.5°`` cut bins in half, so each sector takes the minimum over every
bin that overlaps it: 6 bins, ``(−5j − 3) … (−5j + 2) mod 360``, covering exactly ``[−3°, +3°)``
counter-clockwise around the sector's centre. A bin on an edge feeds both neighbours, so no return
is ever lost and each sector's window is centred on the angle ArduPilot assigns it.

What is sent is the scan and nothing else: the horizontal slice the policy sees (points outside
``slice_height`` never reach it), and only while the vehicle is airborne
(:func:`obstacle_distance_allowed`): on the ground and during take-off the slice still cuts the
floor, and real SITL runs showed OBSTACLE_DISTANCE of 0.10-0.29 m all round during take-off.
"""

from __future__ import annotations

import numpy as np

from companion.autopilot.link import LandedState, VehicleStatus
from companion.perception.scan import N_BINS

N_SECTORS = 72
SECTOR_DEG = 5
UNKNOWN_CM = 65535  # MAVLink: "UINT16_MAX for unknown/not used"

# _SECTOR_BINS[j] = the 6 counter-clockwise scan bins overlapping sector j (centred on 5j° clockwise).
_SECTOR_BINS = (-SECTOR_DEG * np.arange(N_SECTORS)[:, None] + np.arange(-3, 3)[None, :]) % N_BINS


def obstacle_distance_from_scan(
    scan: np.ndarray, max_range: float, min_cm: int = 10, max_cm: int = 1000
) -> np.ndarray:
    """Min-pool a 360-bin scan into the 72 OBSTACLE_DISTANCE distances (centimetres).

    :param scan: ``(360,)`` normalised ranges (range / max_range, 1.0 = no return), bins
        counter-clockwise from forward
    :param max_range: metres that 1.0 stands for
    :param min_cm: the message's ``min_distance``; closer returns are reported at this value
    :param max_cm: the message's ``max_distance``; no return, or a return beyond it, is ``max_cm + 1``
    :return: ``(72,)`` uint16, sector ``j`` centred on ``j × 5°`` clockwise from forward; a
        non-finite bin makes its sectors "unknown" (65535)
    """
    values = np.asarray(scan, dtype=np.float64).reshape(-1)
    if values.shape[0] != N_BINS:
        raise ValueError(f"obstacle_distance_from_scan expects {N_BINS} bins, got {values.shape[0]}")
    if not 0 < min_cm <= max_cm < UNKNOWN_CM - 1:
        raise ValueError(f"need 0 < min_cm <= max_cm < {UNKNOWN_CM - 1}, got {min_cm}, {max_cm}")
    pooled = values[_SECTOR_BINS]
    nearest = pooled.min(axis=1)
    unknown = ~np.isfinite(pooled).all(axis=1)
    no_return = nearest >= 1.0
    with np.errstate(invalid="ignore"):
        # floor: never report an obstacle farther than it is
        cm = np.floor(np.nan_to_num(nearest, nan=0.0) * max_range * 100.0)
    out = np.clip(cm, min_cm, max_cm + 1).astype(np.uint16)  # beyond max_cm also reads "no obstacle"
    out[no_return] = max_cm + 1
    out[unknown] = UNKNOWN_CM
    return out


def sector_distances(sectors_cm: np.ndarray) -> list[int]:
    """The 72 sector values as the plain ints a MAVLink encoder takes; anything else is a bug.

    :param sectors_cm: ``(72,)`` centimetres, as :func:`obstacle_distance_from_scan` returns them
    """
    distances = [int(v) for v in np.asarray(sectors_cm, dtype=np.uint16).reshape(-1)]
    if len(distances) != N_SECTORS:
        raise ValueError(f"OBSTACLE_DISTANCE needs {N_SECTORS} sectors, got {len(distances)}")
    return distances


def obstacle_distance_allowed(status: VehicleStatus, min_altitude: float) -> bool:
    """Whether OBSTACLE_DISTANCE may go out: the vehicle is airborne (landed state IN_AIR where the
    autopilot reports it, never TAKEOFF) and at least ``min_altitude`` metres above home."""
    if status.landed_state is not None and status.landed_state is not LandedState.IN_AIR:
        return False
    return status.altitude is not None and status.altitude >= min_altitude
