"""The interface both autopilot links (ArduPilot via pymavlink, PX4 via MAVSDK) implement.

Pure: only the vehicle status record and the protocol live here, so the supervisor and the
application loop can be written (and tested) against one shape whichever autopilot is flying.
"""

from __future__ import annotations

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
    """

    heartbeat_time: float | None = None
    armed: bool = False
    guided: bool = False
    mode: str = "UNKNOWN"
    landed_state: LandedState | None = None
    altitude: float | None = None
    climb_rate: float | None = None


class AutopilotLink(Protocol):
    """One autopilot connection. Implementations hide the wire protocol and count what they do.

    ``counters`` holds per-link event counts (messages sent/received, malformed messages dropped, ...).
    """

    counters: dict[str, int]

    def poll(self) -> VehicleStatus:
        """Read whatever is waiting (never blocks) and return the updated status."""
        ...

    def send_velocity(self, forward: float, yaw_rate: float) -> None:
        """Send one body-frame setpoint.

        :param forward: body x velocity, m/s (lateral and vertical velocity are zero)
        :param yaw_rate: rad/s, FLU convention (counter-clockwise positive); the link converts to FRD
        """
        ...

    def send_obstacle_distance(self, sectors_cm: np.ndarray) -> None:
        """Send OBSTACLE_DISTANCE.

        :param sectors_cm: ``(72,)`` uint16 centimetres, from
            :func:`companion.obstacle_distance.obstacle_distance_from_scan`
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
