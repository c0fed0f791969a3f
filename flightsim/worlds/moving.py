"""Moving obstacles: a cylinder or a box carried along a path or a bounded random walk.

A moving obstacle keeps its shape and heading; only its horizontal position changes with time, as a
pure function of the time since the episode began, so a world with motion stays deterministic and
any part of the simulator (ray cast, collision, render, feasibility check) can ask where every
obstacle is at any moment. A path that is not a loop is flown out and back; a random walk is a
loop of straight legs between points drawn from its own seed inside its bounds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import Literal

import numpy as np

# a random walk draws this many legs, then repeats them (a loop far longer than any episode)
WALK_LEGS = 256
# steady_for: a velocity is read over this, s, and counts as changed beyond this, m/s
_VELOCITY_DT = 1e-3
_STEADY_TOLERANCE = 1e-6


@dataclass(frozen=True)
class PathMotion:
    """Along a polyline at a constant speed.

    :param points: the path's corners (x, y), metres; at least two
    :param speed: m/s along the path
    :param loop: True: from the last point straight back to the first and round again;
        False: out to the last point and back the same way
    """

    points: tuple[tuple[float, float], ...]
    speed: float
    loop: bool = False


@dataclass(frozen=True)
class RandomWalk:
    """Straight legs between random points of a rectangle, at a constant speed.

    :param bounds: ``((x_min, y_min), (x_max, y_max))`` the obstacle's centre never leaves, metres
    :param speed: m/s
    :param seed: draws the points: the same seed, the same walk
    """

    bounds: tuple[tuple[float, float], tuple[float, float]]
    speed: float
    seed: int

    def corners(self) -> tuple[tuple[float, float], ...]:
        """The walk as the closed polyline it repeats."""
        rng = np.random.default_rng(self.seed)
        pts = rng.uniform(self.bounds[0], self.bounds[1], size=(WALK_LEGS, 2))
        return tuple((float(x), float(y)) for x, y in pts)


Motion = PathMotion | RandomWalk


@dataclass(frozen=True)
class MovingObstacle:
    """A shape that moves: a vertical cylinder or a z-rotated box, between ``base`` and ``base + height``.

    :param shape: ``"cylinder"`` or ``"box"``
    :param motion: where its centre goes (:class:`PathMotion` or :class:`RandomWalk`)
    :param height: metres from its bottom to its top
    :param radius: the cylinder's radius, metres (0 for a box)
    :param size: the box's horizontal extents (sx, sy), metres ((0, 0) for a cylinder)
    :param yaw_deg: the box's heading, degrees counter-clockwise from +x (kept while it moves)
    :param base: height of its bottom above the floor, metres (a drone flies, a walker stands)
    :param kind: what it stands for (``pedestrian``, ``drone``, ``forklift``, …); informative only
    """

    shape: Literal["cylinder", "box"]
    motion: Motion
    height: float
    radius: float = 0.0
    size: tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0
    base: float = 0.0
    kind: str = ""

    @property
    def speed(self) -> float:
        """Its speed, m/s (constant)."""
        return self.motion.speed

    @property
    def footprint_radius(self) -> float:
        """Radius of the smallest vertical cylinder around its footprint, metres."""
        return self.radius if self.shape == "cylinder" else 0.5 * math.hypot(*self.size)

    @cached_property
    def _track(self) -> tuple[np.ndarray, np.ndarray, float, bool]:
        """The closed or open polyline it follows: corners, cumulative lengths, total, loop."""
        if isinstance(self.motion, RandomWalk):
            corners, loop = self.motion.corners(), True
        else:
            corners, loop = self.motion.points, self.motion.loop
        pts = np.asarray((*corners, corners[0]) if loop else corners, dtype=np.float64)
        cumulative = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
        return pts, cumulative, float(cumulative[-1]), loop

    def positions(self, times: np.ndarray | float) -> np.ndarray:
        """Its centre (x, y) at each of ``times`` (seconds since the start), ``(T, 2)``."""
        t = np.atleast_1d(np.asarray(times, dtype=np.float64))
        pts, cumulative, total, loop = self._track
        if total <= 0.0:
            return np.repeat(pts[:1], t.size, axis=0)
        s = np.mod(self.speed * t, total if loop else 2.0 * total)
        if not loop:
            s = np.where(s > total, 2.0 * total - s, s)  # on the way back
        return np.column_stack([np.interp(s, cumulative, pts[:, 0]), np.interp(s, cumulative, pts[:, 1])])

    def steady_for(self, time: float, window: float, step: float = 0.01) -> float:
        """Seconds, up to ``window``, over which its velocity has not changed before ``time``: less
        than ``window`` where it turned within it (at a corner or an end of its path, at once, which
        no acceleration bound allows). Before the episode began it moved as it did at the start.

        :param step: the velocity is compared every ``step`` s back (each over the millisecond before)
        """
        back = np.arange(0.0, window + step / 2.0, step)
        times = time - back[back <= time - _VELOCITY_DT]
        if len(times) == 0:
            return float(window)
        velocity = (self.positions(times) - self.positions(times - _VELOCITY_DT)) / _VELOCITY_DT
        changed = np.hypot(*(velocity - velocity[0]).T) > _STEADY_TOLERANCE
        return float(back[np.argmax(changed)]) if changed.any() else float(window)

    def packed(self, times: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Its pose at each of ``times`` as the ray caster's rows, ``(T, 8)`` for a box (centre xyz,
        half sizes, cos yaw, sin yaw, as ``World.packed``) or ``(T, 5)`` for a cylinder (centre xy,
        radius, bottom z, top z).

        :param out: write the rows here (a ``(T, 8)`` or ``(T, 5)`` view) instead of a new array
        """
        if out is None:
            out = np.empty((np.size(times), 5 if self.shape == "cylinder" else 8))
        out[:, :2] = self.positions(times)
        out[:, 2:] = self._rest
        return out

    @cached_property
    def _rest(self) -> np.ndarray:
        """The row's columns after the centre xy, the same at every time."""
        if self.shape == "cylinder":
            return np.array([self.radius, self.base, self.base + self.height])
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        h = self.height / 2.0
        return np.array([self.base + h, self.size[0] / 2.0, self.size[1] / 2.0, h, c, s])

    def clearance(self, points: np.ndarray, time: float) -> np.ndarray:
        """Signed distance from each of ``points`` ``(N, 3)`` to the shape at ``time`` (negative inside)."""
        return self.clearance_over_time(points, np.array([time]))[0]

    def clearance_over_time(self, points: np.ndarray, times: np.ndarray) -> np.ndarray:
        """Signed distance from each of ``points`` ``(N, 3)`` to the shape at each of ``times``: (T, N)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return self.clearance_from(p[None], self.positions(times)[:, None])

    def clearance_from(self, points: np.ndarray, centres: np.ndarray) -> np.ndarray:
        """Signed distance from ``points`` ``(..., 3)`` to the shape with its centre at ``centres``
        (``(..., 2)``, broadcast against the points), ``(...)``: where a planner predicts it to be,
        not only where its track puts it."""
        p, c = np.asarray(points, dtype=np.float64), np.asarray(centres, dtype=np.float64)
        dx = p[..., 0] - c[..., 0]
        dy = p[..., 1] - c[..., 1]
        dz = np.broadcast_to(
            np.abs(p[..., 2] - (self.base + self.height / 2.0)) - self.height / 2.0, dx.shape
        )
        if self.shape == "cylinder":
            q = np.stack([np.hypot(dx, dy) - self.radius, dz], axis=-1)
        else:
            cos, sin = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
            qx = np.abs(cos * dx + sin * dy) - self.size[0] / 2.0
            qy = np.abs(-sin * dx + cos * dy) - self.size[1] / 2.0
            q = np.stack([qx, qy, dz], axis=-1)
        return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)


def pack_moving(moving: tuple[MovingObstacle, ...], times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every moving obstacle's pose at each of ``times``: boxes ``(T, B, 8)``, cylinders ``(T, C, 5)``."""
    t = np.asarray(times, dtype=np.float64)
    boxes = [m for m in moving if m.shape == "box"]
    cylinders = [m for m in moving if m.shape == "cylinder"]
    packed_boxes = np.empty((t.size, len(boxes), 8))
    packed_cylinders = np.empty((t.size, len(cylinders), 5))
    for k, m in enumerate(boxes):
        m.packed(t, packed_boxes[:, k])
    for k, m in enumerate(cylinders):
        m.packed(t, packed_cylinders[:, k])
    return packed_boxes, packed_cylinders
