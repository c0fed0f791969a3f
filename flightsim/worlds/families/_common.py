"""What every family generator shares: the layout it returns, sampling clear points, walls as boxes."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from flightsim.worlds.world import FLIGHT_ALTITUDE, Box, Obstacle, World, clearances

ROOM_HEIGHT = 3.0
# generated starts and waypoints keep this much beyond the vehicle's radius from every surface, so
# they are never a test of precision in themselves
POINT_MARGIN = 0.4


@dataclass
class Layout:
    """A family's raw output: geometry and the horizontal start and waypoints (flown at altitude).

    :param room_size: inner extents (sx, sy), metres
    :param obstacles: boxes and cylinders
    :param start: (x, y) of the start
    :param waypoints: (x, y) of each waypoint, in visiting order
    """

    room_size: tuple[float, float]
    obstacles: list[Obstacle] = field(default_factory=list)
    start: tuple[float, float] = (0.0, 0.0)
    waypoints: list[tuple[float, float]] = field(default_factory=list)

    def world(self, name: str = "layout") -> World:
        """The geometry as a world (start as given, heading 0, no waypoints) for clearance checks."""
        start = (*self.start, FLIGHT_ALTITUDE)
        return World(name, self.room_size, ROOM_HEIGHT, tuple(self.obstacles), start, 0.0)  # type: ignore[arg-type]


def lerp(a: float, b: float, t: float) -> float:
    return a + (b - a) * t


def rnd(v: float) -> float:
    """Millimetres are plenty, and they keep saved worlds readable."""
    return round(float(v), 3)


def wall(x0: float, y0: float, x1: float, y1: float, height: float = ROOM_HEIGHT) -> Box:
    """An axis-aligned box covering the rectangle [x0, x1] × [y0, y1] from the floor up."""
    xa, xb, ya, yb = min(x0, x1), max(x0, x1), min(y0, y1), max(y0, y1)
    return Box(((xa + xb) / 2.0, (ya + yb) / 2.0, height / 2.0), (xb - xa, yb - ya, height))


def segment_wall(a: np.ndarray, b: np.ndarray, thickness: float, height: float = ROOM_HEIGHT) -> Box:
    """A wall of ``thickness`` along the segment a-b (any direction), from the floor up."""
    d = b - a
    yaw = math.degrees(math.atan2(d[1], d[0]))
    c = (a + b) / 2.0
    return Box((rnd(c[0]), rnd(c[1]), height / 2.0), (rnd(np.hypot(*d)), thickness, height), rnd(yaw))


def sample_clear(
    rng: np.random.Generator,
    world: World,
    lo: tuple[float, float],
    hi: tuple[float, float],
    min_clearance: float,
    *,
    away_from: list[tuple[float, float]] = (),  # type: ignore[assignment]
    min_distance: float = 0.0,
    tries: int = 256,
) -> tuple[float, float] | None:
    """A random point in the rectangle ``lo``-``hi`` at least ``min_clearance`` from every surface
    (at the flight altitude) and ``min_distance`` from every point in ``away_from``; None if none of
    ``tries`` candidates qualifies."""
    lo_a, hi_a = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    if np.any(hi_a < lo_a):
        return None
    cand = rng.uniform(lo_a, hi_a, size=(tries, 2))
    pts = np.column_stack([cand, np.full(tries, FLIGHT_ALTITUDE)])
    ok = clearances(world, pts) >= min_clearance
    for p in away_from:
        ok &= np.hypot(*(cand - np.asarray(p)).T) >= min_distance
    if not ok.any():
        return None
    c = cand[np.argmax(ok)]
    return (rnd(c[0]), rnd(c[1]))


def far_end_points(
    rng: np.random.Generator,
    layout: Layout,
    n: int,
    min_clearance: float,
    *,
    band: float = 2.5,
) -> list[tuple[float, float]] | None:
    """``n`` waypoints alternating between the room's two x ends, the first at the end away from
    the start: across-the-room flights that must pass whatever the family put in the middle."""
    world = layout.world()
    hx, hy = layout.room_size[0] / 2.0, layout.room_size[1] / 2.0
    side = -1.0 if layout.start[0] > 0 else 1.0
    out: list[tuple[float, float]] = []
    for _ in range(n):
        x_lo, x_hi = (hx - band, hx - 0.5) if side > 0 else (-hx + 0.5, -hx + band)
        p = sample_clear(rng, world, (x_lo, -hy + 0.5), (x_hi, hy - 0.5), min_clearance)
        if p is None:
            return None
        out.append(p)
        side = -side
    return out
