"""The shield's obstacle memory: the returns of the last few scans, carried into the current body frame.

A thin pole can fall between two beams for a revolution, and a corner the vehicle has passed can
drop below the scan's height band; the memory keeps each return for ``memory_time`` seconds.

Carrying a return needs odometry: the position is integrated from the measured velocity less the
drift estimate, and the heading is the autopilot's (or the commanded yaw rates integrated). That
velocity is wrong by at most the envelope's ``estimate_error`` (m/s), and it is late by up to the
envelope's ``velocity_lag`` (s): integrated, a late velocity is off by that lag times how much the
velocity changed since. So a return carried for ``age`` seconds may truly lie up to
``estimate_error * age + velocity_lag * dv`` from where the memory puts it, ``dv`` the most the
measured velocity has differed from today's since that scan (m/s): each point carries that
inflation, and the gate subtracts it from the clearance. The real SITL flights hold it
(``tests/companion/test_envelope.py``). When the odometry is lost (no finite velocity), the memory
is dropped and only the current scan counts.

A return stands for a whole scan bin: the surface it hit may reach half a bin (0.5°) to either
side, and the VLP-16 measures range to within :data:`RANGE_ACCURACY_M`. Every point starts with
that inflation, ``r sin(0.5°) + RANGE_ACCURACY_M``.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from companion.perception.scan import N_BINS

_BIN_RAD = np.radians(np.arange(N_BINS) + 0.5)
#: the VLP-16's range accuracy (its datasheet's ±3 cm), m
RANGE_ACCURACY_M = 0.03
_HALF_BIN_SIN = float(np.sin(np.radians(0.5)))


def scan_points(ranges_m: np.ndarray, max_range: float) -> np.ndarray:
    """``(p, 2)`` body-frame points (forward, left) of the bins with a return (closer than ``max_range``).

    Bins that are not finite are read as a return at the vehicle itself (unknown = blocked).
    """
    r = np.asarray(ranges_m, dtype=np.float64)
    r = np.where(np.isfinite(r), r, 0.0)
    hit = r < max_range * (1.0 - 1e-6)
    return np.stack([r[hit] * np.cos(_BIN_RAD[hit]), r[hit] * np.sin(_BIN_RAD[hit])], axis=1)


def return_spans(points: np.ndarray) -> np.ndarray:
    """``(p,)`` how far each return of a scan may truly lie from its point, m: half its bin across
    and the range accuracy (the module doc)."""
    return np.hypot(points[:, 0], points[:, 1]) * _HALF_BIN_SIN + RANGE_ACCURACY_M


class ObstacleMemory:
    """The returns of the scans of the last ``memory_time`` seconds, in the current body frame.

    :param memory_time: how long a return is remembered, s (0: the current scan only)
    :param estimate_error: the velocity error bound of the odometry, m/s (the envelope's)
    :param velocity_lag: how late the measured velocity may be, s (the envelope's)
    """

    def __init__(self, memory_time: float, estimate_error: float, velocity_lag: float = 0.0) -> None:
        self.memory_time = float(memory_time)
        self.estimate_error = float(estimate_error)
        self.velocity_lag = float(velocity_lag)
        self._scans: deque[tuple[float, np.ndarray]] = deque()  # (time, points in the odometry frame)
        self._spans: deque[np.ndarray] = deque()  # each scan's points' own inflation, m
        self._velocities: deque[np.ndarray] = deque()  # the velocity each scan was carried by, odometry frame
        self._time = 0.0
        self._pose = np.zeros(3)  # x, y, heading of the body in the odometry frame

    def reset(self) -> None:
        """Forget every remembered return."""
        self._scans.clear()
        self._spans.clear()
        self._velocities.clear()

    def update(
        self,
        points: np.ndarray,
        dt: float,
        velocity: tuple[float, float] | None,
        heading: float | None,
        yaw_rate: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Add a scan's points and return every remembered point in the body frame with its inflation.

        :param points: ``(p, 2)`` the new scan's returns, body frame, m
        :param dt: time since the previous scan, s
        :param velocity: body velocity less the drift estimate, m/s; None or not finite: odometry lost
        :param heading: the heading, rad counter-clockwise (None: integrate ``yaw_rate``)
        :param yaw_rate: the yaw rate flown since the previous scan, rad/s (used without a heading)
        :return: ``(q, 2)`` points and ``(q,)`` inflation, m
        """
        step = dt if math.isfinite(dt) and dt > 0.0 else 0.0
        odometry = velocity is not None and all(math.isfinite(float(v)) for v in velocity)
        moved = np.zeros(2)
        if not odometry or self.memory_time <= 0.0:
            self.reset()
        else:
            c, s = math.cos(self._pose[2]), math.sin(self._pose[2])
            moved = np.array([c * velocity[0] - s * velocity[1], s * velocity[0] + c * velocity[1]])
            self._pose[:2] += moved * step
        self._pose[2] = (
            float(heading)
            if heading is not None and math.isfinite(heading)
            else (self._pose[2] + yaw_rate * step)
        )
        self._time += step
        while self._scans and self._time - self._scans[0][0] > self.memory_time + 1e-9:
            self._scans.popleft()
            self._velocities.popleft()
        x, y, h = self._pose
        c, s = math.cos(h), math.sin(h)
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        self._scans.append(
            (self._time, np.stack([x + c * pts[:, 0] - s * pts[:, 1], y + s * pts[:, 0] + c * pts[:, 1]], 1))
        )
        self._spans.append(return_spans(pts))
        self._velocities.append(moved)
        while len(self._spans) > len(self._scans):
            self._spans.popleft()
        # per scan, the most any velocity carried since differs from today's (a suffix maximum)
        changes = np.hypot(*(np.stack(self._velocities) - moved).T)
        since = np.maximum.accumulate(changes[::-1])[::-1]
        grown = [
            self.estimate_error * (self._time - t) + self.velocity_lag * dv
            for (t, _), dv in zip(self._scans, since, strict=True)
        ]
        counts = [len(p) for _, p in self._scans]
        world = np.concatenate([p for _, p in self._scans]) - np.array([x, y])
        body = np.stack([c * world[:, 0] + s * world[:, 1], -s * world[:, 0] + c * world[:, 1]], axis=1)
        return body, np.concatenate(self._spans) + np.repeat(grown, counts)
