"""The vehicle state a simulated autopilot sees each physics step.

Its own module so that the autopilot's parts (position targets, telemetry) read it without importing
the autopilot that holds it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class VehicleSnapshot:
    """The subset of the vehicle's state the autopilot uses (ENU, FLU), copied each physics step."""

    time: float = 0.0
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0
    angular_rate: np.ndarray = field(default_factory=lambda: np.zeros(3))
    on_ground: bool = True

    @classmethod
    def of(cls, state: Any) -> VehicleSnapshot:
        """Copy a :class:`flightsim.vehicle.quadrotor.VehicleState` (or anything with the same attributes)."""
        return cls(
            time=float(state.time),
            position=np.array(state.position, dtype=float),
            velocity=np.array(state.velocity, dtype=float),
            roll=float(state.roll),
            pitch=float(state.pitch),
            yaw=float(state.yaw),
            angular_rate=np.array(state.angular_rate, dtype=float),
            on_ground=bool(state.on_ground),
        )
