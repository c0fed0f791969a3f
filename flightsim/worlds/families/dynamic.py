"""Moving obstacles for the dynamic families: walkers, other drones and forklifts in a static layout.

A dynamic family is a static family's world (generated exactly as that family generates it, from the
same seed) with moving obstacles added. Each kind moves as such things do:

- pedestrians: cylinders 0.25 m in radius, 1.8 m tall, walking 0.5-1.5 m/s out and back between two
  points in the clear;
- drones: discs 0.3-0.5 m in radius, 0.3 m tall at the flight altitude, 1-3 m/s, flying head-on
  down the vehicle's first leg or across it, or wandering (a bounded random walk) in the open;
- forklifts: boxes 1.2 × 0.8 × 2 m, 1-2 m/s out and back along an aisle (an axis-parallel run).

No path or walk comes near the start or a waypoint (so the vehicle can always wait there), and
every moving obstacle keeps clear of the static geometry along its whole track.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flightsim.worlds.families._common import lerp, rnd
from flightsim.worlds.moving import MovingObstacle, PathMotion, RandomWalk
from flightsim.worlds.world import FLIGHT_ALTITUDE, World, clearances

PEDESTRIAN_RADIUS = 0.25
PEDESTRIAN_HEIGHT = 1.8
DRONE_HEIGHT = 0.3
FORKLIFT_SIZE = (1.2, 0.8, 2.0)
# a track keeps this far beyond the obstacle's footprint from static geometry, and this far from
# the start and the waypoints beyond the vehicle's radius and its own footprint
TRACK_MARGIN = 0.1
STOP_MARGIN = 0.6


@dataclass(frozen=True)
class DynamicMix:
    """How many of each kind a dynamic family adds, at difficulty 0 and at difficulty 1."""

    pedestrians: tuple[int, int] = (0, 0)
    drones: tuple[int, int] = (0, 0)
    forklifts: tuple[int, int] = (0, 0)


DYNAMIC_MIXES: dict[str, DynamicMix] = {
    "warehouse": DynamicMix(pedestrians=(1, 2), forklifts=(1, 2)),
    "office": DynamicMix(pedestrians=(2, 4)),
    "forest": DynamicMix(pedestrians=(1, 2), drones=(1, 2)),
    "rooms": DynamicMix(pedestrians=(1, 2), drones=(1, 3)),
}


def add_moving(
    world: World,
    rng: np.random.Generator,
    d: float,
    vehicle_radius: float,
    first_leg: np.ndarray,
    family: str,
) -> World | None:
    """``world`` with the moving obstacles of ``family``'s mix at difficulty ``d``; None if a track
    could not be placed.

    :param first_leg: ``(2, 2)`` the start and the end of the planned path's first straight run,
        where a head-on or crossing drone flies
    """
    mix = DYNAMIC_MIXES[family]
    stops = np.asarray([world.start_position[:2], *(w[:2] for w in world.waypoints)], dtype=np.float64)
    placer = _Placer(world, rng, stops, vehicle_radius)
    moving: list[MovingObstacle] = []
    for _ in range(round(lerp(*mix.pedestrians, d))):
        moving.append(placer.pedestrian())
    for k in range(round(lerp(*mix.drones, d))):
        moving.append(placer.drone(first_leg, style=k % 3))
    for _ in range(round(lerp(*mix.forklifts, d))):
        moving.append(placer.forklift())
    if any(m is None for m in moving):
        return None
    return World(
        world.name, world.room_size, world.room_height, world.obstacles, world.start_position,
        world.start_yaw_deg, world.waypoints, world.shortest_path_m, tuple(moving),
    )  # fmt: skip


class _Placer:
    """Draws tracks clear of the static geometry and of the start and waypoints."""

    def __init__(
        self, world: World, rng: np.random.Generator, stops: np.ndarray, vehicle_radius: float
    ) -> None:
        self.world, self.rng, self.stops, self.r = world, rng, stops, vehicle_radius
        self.hx, self.hy = world.room_size[0] / 2.0, world.room_size[1] / 2.0
        self.lanes: list[tuple[np.ndarray, float]] = []  # forklift tracks (points along, footprint)

    def _clear(self, a: np.ndarray, b: np.ndarray, footprint: float) -> bool:
        """Whether a footprint moving along a-b stays clear of the geometry and the stops."""
        n = max(2, int(np.hypot(*(b - a)) / 0.1) + 1)
        s = np.linspace(0.0, 1.0, n)[:, None]
        xy = a + s * (b - a)
        pts = np.column_stack([xy, np.full(n, FLIGHT_ALTITUDE)])
        if np.any(clearances(self.world, pts) < footprint + TRACK_MARGIN):
            return False
        gaps = np.hypot(xy[:, None, 0] - self.stops[None, :, 0], xy[:, None, 1] - self.stops[None, :, 1])
        return bool(np.all(gaps >= footprint + self.r + STOP_MARGIN))

    def _segment(
        self, footprint: float, length: tuple[float, float], axis: int | None = None, tries: int = 200
    ):
        """A random clear segment (a, b) of a length in ``length``, along x or y if ``axis`` is 0 or 1."""
        for _ in range(tries):
            a = self.rng.uniform(
                [-self.hx + footprint, -self.hy + footprint], [self.hx - footprint, self.hy - footprint]
            )
            angle = (0.0, math.pi / 2.0)[axis] if axis is not None else self.rng.uniform(0.0, math.pi)
            angle += math.pi * int(self.rng.integers(2))
            b = a + self.rng.uniform(*length) * np.array([math.cos(angle), math.sin(angle)])
            if self._clear(a, b, footprint):
                return a, b
        return None

    @staticmethod
    def _path(a: np.ndarray, b: np.ndarray, speed: float) -> PathMotion:
        return PathMotion(((rnd(a[0]), rnd(a[1])), (rnd(b[0]), rnd(b[1]))), rnd(speed))

    def pedestrian(self) -> MovingObstacle | None:
        seg = self._segment(PEDESTRIAN_RADIUS, (3.0, 8.0))
        if seg is None:
            return None
        motion = self._path(*seg, self.rng.uniform(0.5, 1.5))
        return MovingObstacle(
            "cylinder", motion, PEDESTRIAN_HEIGHT, radius=PEDESTRIAN_RADIUS, kind="pedestrian"
        )

    def drone(self, first_leg: np.ndarray, style: int) -> MovingObstacle | None:
        """``style`` 0: head-on down the first leg; 1: across it (either where the leg leaves no clear
        run: out and back anywhere in the open); 2: a random walk in the open (or, without a clear
        rectangle for it, out and back)."""
        radius = rnd(self.rng.uniform(0.3, 0.5))
        speed = self.rng.uniform(1.0, 3.0)
        base = FLIGHT_ALTITUDE - DRONE_HEIGHT / 2.0
        a, b = first_leg
        along = (b - a) / max(float(np.hypot(*(b - a))), 1e-9)
        seg = None
        keep_off = radius + self.r + STOP_MARGIN + 0.05  # from the start and the leg's end
        if style == 0 and np.hypot(*(b - a)) > 2.0 * keep_off + 2.0:
            seg = (b - along * keep_off, a + along * keep_off)
        elif style == 1:
            mid, across = (a + b) / 2.0, np.array([-along[1], along[0]])
            half = self.rng.uniform(2.0, 4.0)
            seg = (mid + across * half, mid - across * half)
        if seg is not None:
            seg = self._trimmed(*seg, radius)
        if style == 2:
            walker = self._walking_drone(radius, speed, base)
            if walker is not None:
                return walker
        if seg is None:  # no clear run along or across the leg, or room to wander: anywhere in the open
            seg = self._segment(radius, (3.0, 8.0))
        if seg is None:
            return None
        return MovingObstacle(
            "cylinder", self._path(*seg, speed), DRONE_HEIGHT, radius=radius, base=base, kind="drone"
        )

    def _trimmed(self, a: np.ndarray, b: np.ndarray, footprint: float):
        """The longest clear part of a-b starting from a, at least 2 m long, or None."""
        length = float(np.hypot(*(b - a)))
        for keep in np.arange(length, 1.99, -0.25):
            end = a + (b - a) * keep / length
            if self._clear(a, end, footprint):
                return a, end
            start = b + (a - b) * keep / length
            if self._clear(start, b, footprint):
                return start, b
        return None

    def _walking_drone(self, radius: float, speed: float, base: float) -> MovingObstacle | None:
        """A random walk in a clear rectangle (its whole area checked, as the walk may go anywhere)."""
        for _ in range(100):
            half = self.rng.uniform([0.8, 0.8], [2.5, 2.5])
            c = self.rng.uniform(
                [-self.hx + half[0], -self.hy + half[1]], [self.hx - half[0], self.hy - half[1]]
            )
            lo, hi = c - half, c + half
            gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 12), np.linspace(lo[1], hi[1], 12))
            corners = np.column_stack([gx.ravel(), gy.ravel()])
            pts = np.column_stack([corners, np.full(len(corners), FLIGHT_ALTITUDE)])
            if np.any(clearances(self.world, pts) < radius + TRACK_MARGIN + 0.3):
                continue
            gaps = np.hypot(
                corners[:, None, 0] - self.stops[None, :, 0], corners[:, None, 1] - self.stops[None, :, 1]
            )
            if np.any(gaps < radius + self.r + STOP_MARGIN + 0.3):
                continue
            walk = RandomWalk(
                ((rnd(lo[0]), rnd(lo[1])), (rnd(hi[0]), rnd(hi[1]))),
                rnd(speed),
                int(self.rng.integers(2**31)),
            )
            return MovingObstacle("cylinder", walk, DRONE_HEIGHT, radius=radius, base=base, kind="drone")
        return None

    def forklift(self) -> MovingObstacle | None:
        sx, sy, height = FORKLIFT_SIZE
        footprint = 0.5 * math.hypot(sx, sy)
        axis = int(self.rng.integers(2))
        for _ in range(20):  # two forklifts never share a lane: they would drive through each other
            seg = self._segment(footprint, (4.0, 10.0), axis=axis)
            if seg is None:
                axis = 1 - axis
                continue
            along = seg[0] + np.linspace(0.0, 1.0, 50)[:, None] * (seg[1] - seg[0])
            if all(_distance(along, lane) >= footprint + other for lane, other in self.lanes):
                self.lanes.append((along, footprint))
                break
        else:
            return None
        motion = self._path(*seg, self.rng.uniform(1.0, 2.0))
        yaw = 0.0 if axis == 0 else 90.0
        return MovingObstacle("box", motion, height, size=(sx, sy), yaw_deg=yaw, kind="forklift")


def _distance(a: np.ndarray, b: np.ndarray) -> float:
    """Smallest distance between two sets of points ``(N, 2)`` and ``(M, 2)``."""
    return float(np.min(np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])))
