"""Families built of walls: office, warehouse, staggered walls, concave traps, narrow gaps."""

from __future__ import annotations

import math

import numpy as np

from flightsim.worlds.families._common import (
    POINT_MARGIN,
    Layout,
    far_end_points,
    lerp,
    rnd,
    sample_clear,
    segment_wall,
    wall,
)
from flightsim.worlds.world import Box, Obstacle

THIN_WALL = 0.1
#: No cabinet stands within this of a doorway, either side of its wall, metres: a doorway keeps its
#: width (1.2-2 m) where the vehicle goes through it, and the way up to it
DOOR_APPROACH = 1.0


def gap_width(d: float, r: float) -> float:
    """The narrowest gap of the ``gaps`` family at difficulty ``d``: 2 × radius + 1.6 m at 0, down
    to 2 × radius + 0.6 m at 1 (0.3 m each side of the vehicle)."""
    return 2.0 * r + lerp(1.6, 0.6, d)


def gaps(rng: np.random.Generator, seed: int, d: float, r: float) -> Layout | None:
    """1-3 walls across the whole room, each with one opening; the narrowest is exactly
    :func:`gap_width`, the others up to 0.6 m wider. Walls 0.1-0.5 m thick (a thick one is a
    short tunnel). Flights cross every wall."""
    sx, sy = rnd(lerp(16.0, 22.0, rng.uniform())), rnd(lerp(8.0, 12.0, rng.uniform()))
    hx, hy = sx / 2.0, sy / 2.0
    n_walls = 1 + int(rng.integers(0, 1 + round(2 * d)))
    xs = np.linspace(-hx, hx, n_walls + 2)[1:-1] + rng.uniform(-0.8, 0.8, n_walls)
    narrowest = int(rng.integers(n_walls))
    obstacles: list[Obstacle] = []
    for k, x in enumerate(xs):
        width = gap_width(d, r) + (0.0 if k == narrowest else rng.uniform(0.0, 0.6))
        lo = rnd(rng.uniform(-hy + 0.4, hy - 0.4 - width))
        hi = lo + rnd(width)
        half_t = rnd(rng.uniform(0.1, lerp(0.2, 0.5, d)) / 2.0)
        obstacles += [
            wall(x - half_t, -hy - 0.05, x + half_t, lo),
            wall(x - half_t, hi, x + half_t, hy + 0.05),
        ]
    start = (rnd(-hx + rng.uniform(1.0, 1.8)), rnd(rng.uniform(-hy + 1.0, hy - 1.0)))
    layout = Layout((sx, sy), obstacles, start)
    waypoints = far_end_points(rng, layout, int(rng.integers(1, 3)), r + POINT_MARGIN + 0.3, band=1.8)
    if waypoints is None:
        return None
    layout.waypoints = waypoints
    return layout


def staggered(rng: np.random.Generator, seed: int, d: float, r: float) -> Layout | None:
    """2-5 walls across the room, each open at alternate ends (3 m down to 1.4 m), so the only
    way through is a zig-zag; flights cross every wall."""
    sx, sy = rnd(lerp(18.0, 24.0, rng.uniform())), rnd(lerp(8.0, 12.0, rng.uniform()))
    hx, hy = sx / 2.0, sy / 2.0
    n_walls = round(lerp(2, 5, d)) + int(rng.integers(0, 2))
    end = 2.5 + 2 * r  # free zone at each end of the room, for the start and the waypoints
    xs = np.linspace(-hx + end, hx - end, n_walls) + rng.uniform(-0.3, 0.3, n_walls)
    top_first = rng.uniform() < 0.5
    obstacles: list[Obstacle] = []
    for k, x in enumerate(xs):
        opening = rnd(lerp(3.0, max(1.4, 2 * r + 0.9), d) * rng.uniform(1.0, 1.15))
        half_t = 0.1
        if (k % 2 == 0) == top_first:  # open at +y
            obstacles.append(wall(x - half_t, -hy - 0.05, x + half_t, hy - opening))
        else:
            obstacles.append(wall(x - half_t, -hy + opening, x + half_t, hy + 0.05))
    start = (rnd(-hx + end / 2 + rng.uniform(-0.3, 0.3)), rnd(rng.uniform(-hy + 1.0, hy - 1.0)))
    layout = Layout((sx, sy), obstacles, start)
    waypoints = far_end_points(
        rng, layout, int(rng.integers(1, 3)), r + POINT_MARGIN + 0.3, band=end / 2 + 0.3
    )
    if waypoints is None:
        return None
    layout.waypoints = waypoints
    return layout


def office(rng: np.random.Generator, seed: int, d: float, r: float) -> Layout | None:
    """A floor of 2-3 × 3-4 rooms with thin (0.1 m) walls, joined by doorways 1.2-2 m wide: a
    random spanning tree of doors (so every room is reachable) plus extra doors, fewer at higher
    difficulty; cabinets along the walls from difficulty 0.3, clear of the doorways (within
    ``DOOR_APPROACH`` of one, a cabinet would narrow it below its width). Waypoints lie in other rooms."""
    cols, rows = 3 + int(rng.uniform() < d), 2 + int(rng.uniform() < d)
    sx, sy = rnd(cols * rng.uniform(4.5, 5.5)), rnd(rows * rng.uniform(4.2, 5.2))
    hx, hy = sx / 2.0, sy / 2.0
    xs = np.linspace(-hx, hx, cols + 1)  # wall lines, the outer ones are the room's
    ys = np.linspace(-hy, hy, rows + 1)
    # doors: between horizontally adjacent cells (c, r)-(c+1, r) on line x = xs[c+1], and so on
    edges = [((c, w), (c + 1, w)) for c in range(cols - 1) for w in range(rows)]
    edges += [((c, w), (c, w + 1)) for c in range(cols) for w in range(rows - 1)]
    doors = _spanning_tree(rng, cols * rows, [(a[0] * rows + a[1], b[0] * rows + b[1]) for a, b in edges])
    doors |= {k for k in range(len(edges)) if rng.uniform() < lerp(0.5, 0.1, d)}
    obstacles: list[Obstacle] = []
    keep_clear: list[tuple[float, float, float, float]] = []  # (x0, y0, x1, y1) before each doorway
    t = THIN_WALL / 2.0
    for k, (a, b) in enumerate(edges):
        vertical = a[1] == b[1]  # cells side by side in x: the wall between runs along y
        lo, hi = (ys[a[1]], ys[a[1] + 1]) if vertical else (xs[a[0]], xs[a[0] + 1])
        line = xs[b[0]] if vertical else ys[b[1]]
        spans = [(lo, hi)]
        if k in doors:
            narrow = max(lerp(1.6, 1.2, d), 2 * r + 0.7)  # a bigger vehicle gets wider doors
            width = rng.uniform(narrow, max(lerp(2.0, 1.6, d), narrow))
            s0 = rng.uniform(lo + 0.4, hi - 0.4 - width)
            spans = [(lo, s0), (s0 + width, hi)]
            across, along = (line - DOOR_APPROACH, line + DOOR_APPROACH), (s0, s0 + width)
            (x0, x1), (y0, y1) = (across, along) if vertical else (along, across)
            keep_clear.append((x0, y0, x1, y1))
        for s0, s1 in spans:
            s0, s1 = rnd(s0), rnd(s1)
            obstacles.append(
                wall(line - t, s0, line + t, s1) if vertical else wall(s0, line - t, s1, line + t)
            )
    layout = Layout((sx, sy), obstacles)
    world = layout.world()
    margin = r + POINT_MARGIN + 0.3
    stops: list[tuple[float, float]] = []
    cell = (int(rng.integers(cols)), int(rng.integers(rows)))
    for k in range(1 + int(rng.integers(1, 4))):
        if k > 0:  # the next room: not a neighbour of this one where the floor has such rooms
            others = [(c, w) for c in range(cols) for w in range(rows) if (c, w) != cell]
            far = [o for o in others if max(abs(o[0] - cell[0]), abs(o[1] - cell[1])) >= 2]
            pool = far or others
            cell = pool[int(rng.integers(len(pool)))]
        c, w = cell
        p = sample_clear(rng, world, (xs[c] + 0.5, ys[w] + 0.5), (xs[c + 1] - 0.5, ys[w + 1] - 0.5), margin)
        if p is None:
            return None
        stops.append(p)
    if d >= 0.3:  # cabinets against the walls, clear of the start and waypoints
        for _ in range(round(lerp(2, 8, d))):
            c, w = int(rng.integers(cols)), int(rng.integers(rows))
            along_x = rng.uniform() < 0.5
            length, depth = rng.uniform(0.8, 1.8), rng.uniform(0.4, 0.6)
            if along_x:
                x = rng.uniform(xs[c] + 0.2 + length / 2, xs[c + 1] - 0.2 - length / 2)
                y = ys[w] + t + depth / 2 if rng.uniform() < 0.5 else ys[w + 1] - t - depth / 2
                size = (length, depth)
            else:
                y = rng.uniform(ys[w] + 0.2 + length / 2, ys[w + 1] - 0.2 - length / 2)
                x = xs[c] + t + depth / 2 if rng.uniform() < 0.5 else xs[c + 1] - t - depth / 2
                size = (depth, length)
            height = rng.uniform(1.8, 2.2)
            cabinet = Box((rnd(x), rnd(y), rnd(height / 2)), (rnd(size[0]), rnd(size[1]), rnd(height)))
            clear_of_stops = min(math.hypot(x - p[0], y - p[1]) for p in stops) - max(size) / 2 > margin + 0.5
            if clear_of_stops and not _overlaps_any(x, y, size, keep_clear):
                obstacles.append(cabinet)
    layout.start, layout.waypoints = stops[0], stops[1:]
    return layout


def _overlaps_any(
    x: float, y: float, size: tuple[float, float], boxes: list[tuple[float, float, float, float]]
) -> bool:
    """Whether the footprint centred at (x, y) of ``size`` overlaps any (x0, y0, x1, y1) box."""
    hx, hy = size[0] / 2.0, size[1] / 2.0
    return any(x + hx > x0 and x - hx < x1 and y + hy > y0 and y - hy < y1 for x0, y0, x1, y1 in boxes)


def _spanning_tree(rng: np.random.Generator, n: int, edges: list[tuple[int, int]]) -> set[int]:
    """Indices of ``edges`` forming a random spanning tree of ``n`` nodes (Kruskal on a shuffle)."""
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    chosen: set[int] = set()
    for k in rng.permutation(len(edges)):
        a, b = root(edges[k][0]), root(edges[k][1])
        if a != b:
            parent[a] = b
            chosen.add(int(k))
    return chosen


def warehouse(rng: np.random.Generator, seed: int, d: float, r: float) -> Layout | None:
    """Racks (1.0-1.2 m deep, 2.4-3 m tall) in rows along x, aisles 3 m down to 1.6 m between
    them, cross aisles at both ends (and through the middle when easy); pallets stacked against
    the racks narrow some aisles, never below 2 × radius + 0.6 m, also between two pallets facing
    each other across an aisle, and never stand in the middle cross aisle or within that width of
    it. Start and waypoints lie in
    different aisles, so flights go down one aisle, across, and up another."""
    aisle = lerp(3.0, max(1.6, 2 * r + 1.1), d) * rng.uniform(1.0, 1.1)
    depth = rng.uniform(1.0, 1.2)
    n_racks = int(rng.integers(3, 6))
    sy = rnd(n_racks * depth + (n_racks + 1) * aisle)
    sx = rnd(lerp(16.0, 24.0, rng.uniform()))
    hx, hy = sx / 2.0, sy / 2.0
    cross = lerp(3.0, 1.8, d) * rng.uniform(1.0, 1.1)
    x0, x1 = -hx + cross, hx - cross
    middle = rng.uniform() < 1.0 - d
    rack_ys = [-hy + aisle * (k + 1) + depth * (k + 0.5) for k in range(n_racks)]
    obstacles: list[Obstacle] = []
    mouths: dict[int, tuple[float, float, float, float]] = {}  # per rack, the gap in its row (x0, y0, x1, y1)
    for k, y in enumerate(rack_ys):
        height = rng.uniform(2.4, 3.0)
        runs = [(x0, x1)]
        if middle:
            mid = rng.uniform(-2.0, 2.0)
            runs = [(x0, mid - 1.0), (mid + 1.0, x1)]
            mouths[k] = (mid - 1.0, y - depth / 2, mid + 1.0, y + depth / 2)
        for a, b in runs:
            obstacles.append(wall(rnd(a), rnd(y - depth / 2), rnd(b), rnd(y + depth / 2), height=rnd(height)))
    aisle_ys = [-hy + aisle / 2 + k * (aisle + depth) for k in range(n_racks + 1)]
    narrow_to = 2 * r + 0.6 + 0.05
    # pallet footprints (x0, y0, x1, y1) per (aisle, rack face): one facing another across an
    # aisle must leave narrow_to between them, or the two would make a chicane narrower than that
    faces: dict[tuple[int, float], list[tuple[float, float, float, float]]] = {}
    for _ in range(round(lerp(0, 6, d))):
        k = int(rng.integers(n_racks))
        pallet_depth = min(rng.uniform(0.5, 0.9), aisle - narrow_to)
        if pallet_depth < 0.3:
            continue
        side = 1.0 if rng.uniform() < 0.5 else -1.0  # the rack face the pallet stands against
        y_face = rack_ys[k] + side * depth / 2
        x = rng.uniform(x0 + 0.6, x1 - 0.6)
        y = y_face + side * pallet_depth / 2
        height = rng.uniform(1.8, 2.4)
        size = (rnd(rng.uniform(0.8, 1.2)), rnd(pallet_depth))
        px, py = rnd(x), rnd(y)
        aisle_index = k + 1 if side > 0 else k  # aisle k lies below rack k
        footprint = (size[0] + 2 * narrow_to, size[1] + 2 * narrow_to)
        if _overlaps_any(px, py, footprint, faces.get((aisle_index, -side), [])):
            continue
        if k in mouths and _overlaps_any(px, py, footprint, [mouths[k]]):
            continue  # no rack to stand against there, and beside it a pallet would narrow the mouth
        half_x, half_y = size[0] / 2, size[1] / 2
        faces.setdefault((aisle_index, side), []).append((px - half_x, py - half_y, px + half_x, py + half_y))
        obstacles.append(Box((px, py, rnd(height / 2)), (*size, rnd(height))))
    layout = Layout((sx, sy), obstacles)
    world = layout.world()
    margin = min(r + POINT_MARGIN, aisle / 2 - 0.05)
    order = rng.permutation(len(aisle_ys))
    stops: list[tuple[float, float]] = []
    for k in order[: 1 + int(rng.integers(1, 4))]:
        y = aisle_ys[int(k)]
        p = sample_clear(rng, world, (x0 + 0.5, y - 0.1), (x1 - 0.5, y + 0.1), margin)
        if p is None:
            return None
        stops.append(p)
    layout.start, layout.waypoints = stops[0], stops[1:]
    return layout


def traps(rng: np.random.Generator, seed: int, d: float, r: float) -> Layout | None:
    """Concave traps between start and goal: U and L shapes (1 when easy, 2-3 when hard; walls
    2.5-4 m wide, 1.5-3 m deep) on the straight line, their open side toward the start, so a
    pilot that heads straight for the goal flies into the cup and must back out."""
    sx, sy = rnd(lerp(16.0, 22.0, rng.uniform())), rnd(lerp(11.0, 15.0, rng.uniform()))
    hx, hy = sx / 2.0, sy / 2.0
    start = np.array([-hx + rng.uniform(1.0, 2.0), rng.uniform(-hy + 2.0, hy - 2.0)])
    goal = np.array([hx - rng.uniform(1.0, 2.0), rng.uniform(-hy + 2.0, hy - 2.0)])
    n_traps = 1 + int(rng.integers(math.floor(d + 0.5), 1 + math.floor(2 * d + 0.5)))  # 1, 1-2, 2-3
    obstacles: list[Obstacle] = []
    centres: list[np.ndarray] = []
    for k in range(n_traps):
        t = (k + 1) / (n_traps + 1) + rng.uniform(-0.05, 0.05)
        centre = start + t * (goal - start)
        if any(np.hypot(*(centre - c)) < 4.5 for c in centres):
            continue
        width, deep = rng.uniform(2.5, 4.0), rng.uniform(1.5, 3.0)
        heading = math.atan2(*(goal - start)[::-1]) + rng.uniform(-0.35, 0.35) * (1.0 - d)
        u = np.array([math.cos(heading), math.sin(heading)])  # from the open side to the back
        v = np.array([-u[1], u[0]])
        back = centre + u * deep / 2
        mouth = centre - u * deep / 2
        walls = [(back - v * width / 2, back + v * width / 2)]
        sides = [1.0, -1.0] if rng.uniform() < lerp(0.4, 0.8, d) else [rng.choice([1.0, -1.0])]  # U or L
        walls += [(mouth + s * v * width / 2, back + s * v * width / 2) for s in sides]
        obstacles += [segment_wall(a, b, 0.15) for a, b in walls]
        centres.append(centre)
    layout = Layout((sx, sy), obstacles, (rnd(start[0]), rnd(start[1])), [(rnd(goal[0]), rnd(goal[1]))])
    if rng.uniform() < 0.5:  # and back again, through the traps' backs
        back_home = far_end_points(
            rng, Layout((sx, sy), obstacles, layout.waypoints[0]), 1, r + POINT_MARGIN + 0.3
        )
        if back_home is None:
            return None
        layout.waypoints += back_home
    return layout
