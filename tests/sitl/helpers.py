"""Shared helpers for the simulated-autopilot tests: MAVLink wire round-trips and a fake-clock flight loop."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from flightsim.sim_autopilot.common import SimAutopilot, VehicleSnapshot

GCS = (255, 190)
COMPANION = (1, 191)
BODY_VEL_YAWRATE_MASK = 0x05C7


def wire(msg: Any, source: tuple[int, int] = GCS) -> Any:
    """Pack ``msg`` as ``source`` would and decode it again, so it carries real header fields."""
    mav = mavlink.MAVLink(None, *source)
    return mav.decode(bytearray(msg.pack(mav)))


def command(cmd: int, *params: float, source: tuple[int, int] = GCS) -> Any:
    p = [*params, *([0.0] * (7 - len(params)))]
    return wire(mavlink.MAVLink_command_long_message(1, 1, cmd, 0, *p), source)


def body_velocity(
    forward: float,
    yaw_rate_frd: float = 0.0,
    frame: int = mavlink.MAV_FRAME_BODY_OFFSET_NED,
    mask: int = BODY_VEL_YAWRATE_MASK,
) -> Any:
    return wire(
        mavlink.MAVLink_set_position_target_local_ned_message(
            0, 1, 1, frame, mask, 0, 0, 0, forward, 0, 0, 0, 0, 0, 0, yaw_rate_frd
        ),
        COMPANION,
    )


def acks(out: list[Any]) -> list[tuple[int, int]]:
    return [(o.message.command, o.message.result) for o in out if o.message.get_type() == "COMMAND_ACK"]


def airborne(x: float = 0.0, y: float = 0.0, z: float = 1.5, yaw: float = 0.0) -> VehicleSnapshot:
    """A hovering vehicle (world ENU) for logic tests that need no physics."""
    return VehicleSnapshot(time=0.0, position=np.array([x, y, z]), yaw=yaw, on_ground=False)


def on_ground() -> VehicleSnapshot:
    return VehicleSnapshot(time=0.0, position=np.array([0.0, 0.0, 0.08]), on_ground=True)


def fly(
    ap: SimAutopilot, vehicle: Any, t: float, duration: float, dt: float = 3 / 120, each: Any = None
) -> float:
    """Fly the real vehicle under ``ap`` for ``duration`` s of sim time from ``t``; returns the end time."""
    for _ in range(math.ceil(duration / dt)):
        t += dt
        if each is not None:
            each(t)
        armed, setpoint = ap.flight_command(t)
        if armed != vehicle.state.armed:
            vehicle.set_armed(armed)
        ap.observe(vehicle.step(setpoint, dt))
        ap.tick(t)
    return t
