"""Families of free-standing obstacles: rooms, forest, pillars, mixed heights."""

from __future__ import annotations

import numpy as np

from companion.perception.scan import ScanConfig
from flightsim.worlds.families._common import (
    POINT_MARGIN,
    ROOM_HEIGHT,
    Layout,
    far_end_points,
    lerp,
    rnd,
    sample_clear,
)
from flightsim.worlds.world import (
    FLIGHT_ALTITUDE,
    Box,
    Cylinder,
    Obstacle,
    generate_world,
    obstacle_clearance,
)

# Mixed heights: a low obstacle's top stays this far below the bottom of the scan's height slice
# when the vehicle flies level at the flight altitude, so the lidar slice never sees it and the
# vehicle safely overflies it. The margin leaves room for the body's pitch while cruising.
LOW_OBSTACLE_MARGIN = 0.3
LOW_OBSTACLE_TOP = FLIGHT_ALTITUDE - ScanConfig().slice_height - LOW_OBSTACLE_MARGIN


def rooms(rng: np.random.Generator, seed: int, d: float, r: float) -> Layout | None:
    """Today's generated room (:func:`flightsim.worlds.world.generate_world`) with 1-4 waypoints, each at
    least a third of the room's length from the point before it."""
    base = generate_world(seed, d, r)
    layout = Layout(base.room_size, list(base.obstacles), base.start_position[:2])
    world = layout.world()
    hx, hy = base.room_size[0] / 2.0, base.room_size[1] / 2.0
    points: list[tuple[float, float]] = []
    for _ in range(int(rng.integers(1, 5))):
        last = points[-1] if points else layout.start
        p = sample_clear(
            rng, world, (-hx + 0.5, -hy + 0.5), (hx - 0.5, hy - 0.5), r + POINT_MARGIN + 0.3,
            away_from=[last], min_distance=max(base.room_size) / 3.0,
        )  # fmt: skip
        if p is None:
            return None
        points.append(p)
    layout.waypoints = points
    return layout


def forest(rng: np.random.Generator, seed: int, d: float, r: float) -> Layout | None:
    """Trunks of radius 0.05-0.4 m (log-uniform: thin ones are common and hard to see) from 0.05 to
    0.3 per m², at least 2 × radius + 0.35 m apart at the densest; flights cross the whole wood."""
    sx, sy = rnd(lerp(18.0, 22.0, rng.uniform())), rnd(lerp(11.0, 14.0, rng.uniform()))
    hx, hy = sx / 2.0, sy / 2.0
    start = (rnd(-hx + rng.uniform(1.0, 1.8)), rnd(rng.uniform(-hy + 1.5, hy - 1.5)))
    layout = Layout((sx, sy), [], start)
    n_wp = int(rng.integers(1, 4))
    clearing = max(1.0, r + POINT_MARGIN + 0.2)  # trunk-free around the start and waypoints
    waypoints = far_end_points(rng, layout, n_wp, clearing)
    if waypoints is None:
        return None
    density = lerp(0.05, 0.3, d) * rng.uniform(0.85, 1.15)
    gap = lerp(2.2, 2 * r + 0.35, d)  # between trunk surfaces
    clearings = np.asarray([start, *waypoints])
    centres, radii = np.empty((0, 2)), np.empty(0)
    for _ in range(round(density * sx * sy)):
        radius = float(np.exp(rng.uniform(np.log(0.05), np.log(0.4))))
        edge = radius + 0.3
        cand = rng.uniform([-hx + edge, -hy + edge], [hx - edge, hy - edge], (48, 2))
        ok = _distances(cand, clearings).min(axis=1) - radius >= clearing
        if len(radii):
            ok &= (_distances(cand, centres) - radii[None, :] - radius).min(axis=1) >= gap
        if ok.any():
            centres = np.vstack([centres, cand[np.argmax(ok)]])
            radii = np.append(radii, radius)
    trunks = zip(centres, radii, strict=True)
    layout.obstacles = [Cylinder((rnd(c[0]), rnd(c[1])), rnd(rad), ROOM_HEIGHT) for c, rad in trunks]
    layout.waypoints = waypoints
    return layout


def pillars(rng: np.random.Generator, seed: int, d: float, r: float) -> Layout | None:
    """A regular grid of square or round pillars filling the room (half a gap or more from the
    walls), the gap between neighbours from 2.5 m down to 2 × radius + 0.7 m, a few missing; the
    start and waypoints lie inside the grid, each waypoint half the grid's length or more from
    the point before it."""
    sx, sy = rnd(lerp(16.0, 22.0, rng.uniform())), rnd(lerp(11.0, 15.0, rng.uniform()))
    size = lerp(0.4, 0.9, d) * rng.uniform(0.8, 1.0)  # pillar width (diameter or side)
    gap = lerp(2.5, 2 * r + 0.7, d) * rng.uniform(1.0, 1.1)
    pitch = size + gap
    round_pillars = rng.uniform() < 0.5
    obstacles: list[Obstacle] = []
    xs, ys = _lattice(rng, sx, pitch, gap / 2 + size / 2), _lattice(rng, sy, pitch, gap / 2 + size / 2)
    for x in xs:
        for y in ys:
            if rng.uniform() < 0.05:
                continue  # a missing pillar
            if round_pillars:
                obstacles.append(Cylinder((rnd(x), rnd(y)), rnd(size / 2.0), ROOM_HEIGHT))
            else:
                side = rnd(size)
                obstacles.append(Box((rnd(x), rnd(y), ROOM_HEIGHT / 2.0), (side, side, ROOM_HEIGHT)))
    if len(obstacles) < 4:
        return None
    layout = Layout((sx, sy), obstacles)
    world = layout.world()
    margin = r + POINT_MARGIN + 0.2
    # inside the grid (not in the free band along the walls), so every flight crosses pillars
    centres = np.asarray([o.center[:2] for o in obstacles])
    lo, hi = centres.min(axis=0), centres.max(axis=0)
    start = sample_clear(rng, world, tuple(lo), (lo[0] + (hi[0] - lo[0]) / 4, hi[1]), margin)
    if start is None:
        return None
    layout.start = start
    stops = [start]
    for _ in range(int(rng.integers(1, 4))):
        p = sample_clear(
            rng, world, tuple(lo), tuple(hi), margin, away_from=[stops[-1]], min_distance=(hi[0] - lo[0]) / 2,
        )  # fmt: skip
        if p is None:
            return None
        stops.append(p)
    layout.waypoints = stops[1:]
    return layout


def mixed(rng: np.random.Generator, seed: int, d: float, r: float) -> Layout | None:
    """Mixed heights: low boxes and cylinders whose tops stay below the scan slice (the lidar
    never sees them and the vehicle overflies them: half lie on the straight line to a waypoint),
    beams floating across flight level on no support (only the slice sees them), and a few
    full-height obstacles."""
    sx, sy = rnd(lerp(16.0, 22.0, rng.uniform())), rnd(lerp(11.0, 15.0, rng.uniform()))
    hx, hy = sx / 2.0, sy / 2.0
    start = (rnd(-hx + rng.uniform(1.0, 2.0)), rnd(rng.uniform(-hy + 1.5, hy - 1.5)))
    layout = Layout((sx, sy), [], start)
    waypoints = far_end_points(rng, layout, int(rng.integers(1, 4)), max(1.0, r + POINT_MARGIN + 0.2))
    if waypoints is None:
        return None
    stops = np.asarray([start, *waypoints])
    obstacles: list[Obstacle] = []

    def spot() -> np.ndarray:
        if rng.uniform() < 0.5:  # on the straight line of some leg, where a goal-seeker flies
            k = int(rng.integers(len(stops) - 1))
            return stops[k] + rng.uniform(0.25, 0.75) * (stops[k + 1] - stops[k]) + rng.normal(0.0, 0.3, 2)
        return rng.uniform([-hx + 1.0, -hy + 1.0], [hx - 1.0, hy - 1.0])

    for _ in range(round(lerp(3, 10, d))):  # low: safe to overfly
        c, top = spot(), rng.uniform(0.2, LOW_OBSTACLE_TOP)
        if rng.uniform() < 0.5:
            obstacles.append(Cylinder((rnd(c[0]), rnd(c[1])), rnd(rng.uniform(0.2, 0.8)), rnd(top)))
        else:
            size = (rnd(rng.uniform(0.5, 2.5)), rnd(rng.uniform(0.5, 2.0)), rnd(top))
            obstacles.append(Box((rnd(c[0]), rnd(c[1]), size[2] / 2.0), size, rnd(rng.uniform(0.0, 180.0))))
    placed = 0
    for _ in range(40):  # beams: at flight level, clear of the start and waypoints
        if placed >= round(lerp(2, 5, d)):
            break
        c = spot()
        length, thick = rng.uniform(2.0, lerp(3.5, 6.0, d)), rng.uniform(0.15, 0.4)
        beam = Box(
            (rnd(c[0]), rnd(c[1]), rnd(FLIGHT_ALTITUDE + rng.uniform(-0.1, 0.1))),
            (rnd(length), rnd(thick), rnd(rng.uniform(0.2, 0.4))),
            rnd(rng.uniform(0.0, 180.0)),
        )
        if _clear_of(beam, stops, r + POINT_MARGIN + 0.5):
            obstacles.append(beam)
            placed += 1
    for _ in range(round(lerp(2, 5, d))):  # full height
        c = rng.uniform([-hx + 1.0, -hy + 1.0], [hx - 1.0, hy - 1.0])
        pillar = Cylinder((rnd(c[0]), rnd(c[1])), rnd(rng.uniform(0.2, 0.6)), ROOM_HEIGHT)
        if _clear_of(pillar, stops, r + POINT_MARGIN + 0.5):
            obstacles.append(pillar)
    layout.obstacles = obstacles
    layout.waypoints = waypoints
    return layout


def _lattice(rng: np.random.Generator, extent: float, pitch: float, margin: float) -> np.ndarray:
    """Evenly spaced centres across a room of ``extent``, each at least ``margin`` from its walls,
    the row shifted at random within the slack left over."""
    usable = extent - 2 * margin
    if usable < 0:
        return np.empty(0)
    n = int(usable // pitch) + 1
    slack = usable - (n - 1) * pitch
    return -extent / 2 + margin + rng.uniform(0.0, slack) + pitch * np.arange(n)


def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(len(a), len(b))`` distances between two sets of points (x, y)."""
    return np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])


def _clear_of(obstacle: Obstacle, points: np.ndarray, clearance: float) -> bool:
    pts = np.column_stack([points, np.full(len(points), FLIGHT_ALTITUDE)])
    return bool(np.all(obstacle_clearance(obstacle, pts) >= clearance))
