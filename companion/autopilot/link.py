"""The interface both autopilot links (ArduPilot via pymavlink, PX4 via MAVSDK) implement.

Pure: only the vehicle status record and the protocol live here, so the supervisor and the
application loop can be written (and tested) against one shape whichever autopilot is flying.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, Protocol

import numpy as np


class LandedState(IntEnum):
    """MAVLink ``MAV_LANDED_STATE`` (from EXTENDED_SYS_STATE), same numeric values."""

    UNDEFINED = 0
    ON_GROUND = 1
    IN_AIR = 2
    TAKEOFF = 3
    LANDING = 4


@dataclass
class VehicleStatus:
    """What the companion knows about the vehicle, as of the last :meth:`AutopilotLink.poll`.

    :param heartbeat_time: clock time the last autopilot HEARTBEAT arrived (None: never)
    :param armed: motors armed
    :param guided: in GUIDED (ArduPilot) / OFFBOARD (PX4), i.e. accepting the companion's setpoints
    :param mode: the autopilot's mode name, for logs and STATUSTEXT
    :param landed_state: from EXTENDED_SYS_STATE; None when the autopilot does not send it
    :param altitude: metres above home, up positive (None: not known yet)
    :param climb_rate: metres per second, up positive (None: not known yet)
    :param velocity_body: the measured horizontal velocity in the body frame, (forward, left) m/s,
        from the autopilot's velocity estimate turned by its heading (None: not known yet)
    :param velocity_time: clock time that measurement arrived (None: never); the supervisor HOLDs
        when it is too old, because the shield watches where the vehicle really goes
    """

    heartbeat_time: float | None = None
    armed: bool = False
    guided: bool = False
    mode: str = "UNKNOWN"
    landed_state: LandedState | None = None
    altitude: float | None = None
    climb_rate: float | None = None
    velocity_body: tuple[float, float] | None = None
    velocity_time: float | None = None


def body_velocity(v_north: float, v_east: float, yaw_ned: float) -> tuple[float, float] | None:
    """A NED horizontal velocity as (forward, left) in the body frame of a vehicle heading
    ``yaw_ned`` (radians clockwise from north); None when any input is not finite."""
    if not (math.isfinite(v_north) and math.isfinite(v_east) and math.isfinite(yaw_ned)):
        return None
    c, s = math.cos(yaw_ned), math.sin(yaw_ned)
    return (v_north * c + v_east * s, -(-v_north * s + v_east * c))


class AutopilotLink(Protocol):
    """One autopilot connection. Implementations hide the wire protocol and count what they do.

    ``counters`` holds per-link event counts (messages sent/received, malformed messages dropped, ...).
    """

    counters: dict[str, int]

    def poll(self) -> VehicleStatus:
        """Read whatever is waiting (never blocks) and return the updated status."""
        ...

    def send_velocity(self, forward: float, yaw_rate: float, lateral: float = 0.0,
                      vertical: float = 0.0) -> None:
        """Send one body-frame setpoint.

        :param forward: body x velocity, m/s
        :param yaw_rate: rad/s, FLU convention (counter-clockwise positive); the link converts to FRD
        :param lateral: body y velocity, m/s, left positive (a sideways model's command, the shield's
            brake and push, the drift hold); the link sends it as FRD (right positive)
        :param vertical: climb rate, m/s, up positive (toward a waypoint's height; zero holds the
            altitude); the link sends it down-positive
        """
        ...

    def send_obstacle_distance(self, sectors_cm: np.ndarray) -> None:
        """Send OBSTACLE_DISTANCE.

        :param sectors_cm: ``(72,)`` uint16 centimetres, from
            :func:`companion.autopilot.obstacle_distance.obstacle_distance_from_scan`
        """
        ...

    def send_heartbeat(self) -> None:
        """Send the companion's HEARTBEAT (MAV_TYPE_ONBOARD_CONTROLLER)."""
        ...

    def send_statustext(self, text: str, severity: int) -> None:
        """Send a STATUSTEXT (``severity`` is MAV_SEVERITY) so the pilot's GCS shows it."""
        ...

    def add_message_listener(self, listener: Callable[[Any], None], streams: tuple[str, ...] = ()) -> None:
        """Also hand every message from the autopilot to ``listener`` (maybe from another thread)
        and keep ``streams`` requested (the goal source: positions, the mission protocol)."""
        ...

    def send_message(self, msg: Any) -> None:
        """Send a pymavlink message built by the caller to the autopilot (mission requests, DO_SET_MODE)."""
        ...

    def close(self) -> None:
        """Release the connection."""
        ...
