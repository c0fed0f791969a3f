"""What the SITL harness observes during a flight: the companion's messages (setpoints, STATUSTEXTs,
heartbeats, commands, mission items reached) and the true pose (trajectory, clearance, collision),
filled from the autopilot's and the co-simulation's threads."""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from flightsim.worlds.world import DEFAULT_VEHICLE_RADIUS, World


@dataclass
class Recorder:
    """What the harness observes during a flight (filled from the autopilot's and cosim's threads)."""

    t0: float  # monotonic time of the autopilot's clock zero
    setpoint_times: list[float] = field(default_factory=list)  # monotonic arrival times (companion)
    setpoints: list[tuple[float, float, float]] = field(default_factory=list)  # (t, vx body, yaw rate)
    statustexts: list[tuple[float, str]] = field(default_factory=list)
    companion_heartbeats: list[float] = field(default_factory=list)
    companion_commands: list[tuple[float, str]] = field(default_factory=list)
    items_reached: list[int] = field(default_factory=list)  # the companion's MISSION_ITEM_REACHED seqs
    trajectory: list[tuple[float, float, float, float, float, float]] = field(default_factory=list)
    min_clearance: float = math.inf
    collision_time: float | None = None
    lock: threading.Lock = field(default_factory=threading.Lock)
    _chunks: dict[int, list[str]] = field(default_factory=dict)

    def on_companion_message(self, msg: Any, t_mono: float) -> None:
        kind = msg.get_type()
        with self.lock:
            if kind == "SET_POSITION_TARGET_LOCAL_NED":
                self.setpoint_times.append(t_mono)
                self.setpoints.append((t_mono, float(msg.vx), float(msg.yaw_rate)))
            elif kind == "STATUSTEXT":
                self._statustext(msg, t_mono)
            elif kind == "HEARTBEAT":
                self.companion_heartbeats.append(t_mono)
            elif kind in ("COMMAND_LONG", "COMMAND_INT", "SET_MODE"):
                self.companion_commands.append((t_mono, kind))
            elif kind == "MISSION_ITEM_REACHED":
                self.items_reached.append(int(msg.seq))

    def on_pose(self, t_mono: float, position: np.ndarray, yaw: float, speed: float, world: World) -> None:
        clearance = world.clearance_at(position, t_mono - self.t0) if position[2] > 0.3 else math.inf
        with self.lock:
            self.trajectory.append((t_mono, *map(float, position), float(yaw), float(speed)))
            if position[2] > 0.3:
                self.min_clearance = min(self.min_clearance, clearance)
                if clearance < DEFAULT_VEHICLE_RADIUS and self.collision_time is None:
                    self.collision_time = t_mono

    def _statustext(self, msg: Any, t_mono: float) -> None:
        """Join MAVLink 2 chunked STATUSTEXTs (same non-zero id; a chunk shorter than 50 ends it)."""
        if msg.id == 0:
            self.statustexts.append((t_mono, msg.text))
            return
        self._chunks.setdefault(msg.id, []).append(msg.text)
        if len(msg.text) < 50:
            self.statustexts.append((t_mono, "".join(self._chunks.pop(msg.id))))

    def texts(self, since: float = 0.0) -> list[str]:
        with self.lock:
            return [text for t, text in self.statustexts if t >= since]

    def first_text(self, mark: str, since: float) -> float | None:
        """Arrival time of the first STATUSTEXT containing ``mark`` at or after ``since``."""
        with self.lock:
            return next((t for t, text in self.statustexts if t >= since and mark in text), None)

    def setpoints_since(self, since: float) -> int:
        with self.lock:
            return sum(1 for t in self.setpoint_times if t >= since)
