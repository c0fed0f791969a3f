"""SET_POSITION_TARGET_LOCAL_NED as ArduCopter reads it: the type mask, the frame, and the target in
world ENU."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from flightsim.sitl.sim_autopilot.frames import body_to_world_xy, ned_to_enu, yaw_enu_to_ned, yaw_ned_to_enu

if TYPE_CHECKING:
    from flightsim.sitl.sim_autopilot.snapshot import VehicleSnapshot

# SET_POSITION_TARGET_* type mask bits (MAVLink POSITION_TARGET_TYPEMASK)
MASK_POS_IGNORE = 0b0000_0000_0111
MASK_VEL_IGNORE = 0b0000_0011_1000
MASK_VZ_IGNORE = 0b0000_0010_0000
MASK_ACC_IGNORE = 0b0001_1100_0000
MASK_FORCE_SET = 0b0010_0000_0000
MASK_YAW_IGNORE = 0b0100_0000_0000
MASK_YAW_RATE_IGNORE = 0b1000_0000_0000

BODY_FRAMES = (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED)
LOCAL_FRAMES = (
    mavlink.MAV_FRAME_LOCAL_NED,
    mavlink.MAV_FRAME_LOCAL_OFFSET_NED,
    mavlink.MAV_FRAME_BODY_NED,
    mavlink.MAV_FRAME_BODY_OFFSET_NED,
)


@dataclass
class ExternalTarget:
    """A decoded SET_POSITION_TARGET_LOCAL_NED, already in world ENU.

    :param velocity: (3,) m/s ENU, or None when velocity is ignored
    :param position: (3,) m ENU, or None when position is ignored
    :param vz_used: whether the vertical velocity component was given
    :param yaw: absolute yaw (ENU, rad) to hold, or None
    :param yaw_rate: ENU yaw rate (counter-clockwise, rad/s), or None
    :param time: clock time it arrived
    """

    velocity: np.ndarray | None
    position: np.ndarray | None
    vz_used: bool
    yaw: float | None
    yaw_rate: float | None
    time: float


def decode_position_target(msg: Any, snap: VehicleSnapshot, now: float) -> ExternalTarget | None:
    """Decode SET_POSITION_TARGET_LOCAL_NED the way ArduCopter does (None: invalid → stop).

    Body frames rotate position/velocity by the current heading; the offset frames (and BODY_NED)
    add the current position to a position target; yaw in a body frame is relative.
    """
    frame = msg.coordinate_frame
    if frame not in LOCAL_FRAMES:
        return None
    mask = msg.type_mask
    pos_ignore = bool(mask & MASK_POS_IGNORE)
    vel_ignore = bool(mask & MASK_VEL_IGNORE)
    acc_ignore = bool(mask & MASK_ACC_IGNORE)
    if (mask & MASK_FORCE_SET) and not acc_ignore:
        return None
    heading = yaw_enu_to_ned(snap.yaw)
    body = frame in BODY_FRAMES
    position = velocity = None
    if not pos_ignore:
        n, e, d = float(msg.x), float(msg.y), float(msg.z)
        if body:
            n, e = body_to_world_xy(n, e, heading)
        pos = ned_to_enu((n, e, d))
        if frame != mavlink.MAV_FRAME_LOCAL_NED:
            pos = pos + snap.position
        position = pos
    if not vel_ignore:
        vn, ve, vd = float(msg.vx), float(msg.vy), float(msg.vz)
        if not all(math.isfinite(v) and abs(v) < 1000.0 for v in (vn, ve, vd)):
            return None
        if body:
            vn, ve = body_to_world_xy(vn, ve, heading)
        velocity = ned_to_enu((vn, ve, vd))
    if pos_ignore and vel_ignore:
        return None  # acceleration-only targets are not modelled; ArduCopter would stop as well
    yaw = yaw_rate = None
    if not mask & MASK_YAW_IGNORE and math.isfinite(msg.yaw):
        yaw_ned = float(msg.yaw) + (heading if body else 0.0)
        yaw = yaw_ned_to_enu(yaw_ned)
    if not mask & MASK_YAW_RATE_IGNORE and math.isfinite(msg.yaw_rate):
        yaw_rate = -float(msg.yaw_rate)  # NED clockwise → ENU counter-clockwise
    return ExternalTarget(
        velocity=velocity,
        position=position,
        vz_used=not (mask & MASK_VZ_IGNORE),
        yaw=yaw,
        yaw_rate=yaw_rate,
        time=now,
    )
