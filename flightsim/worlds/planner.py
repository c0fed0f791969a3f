"""Shortest safe path through a world's waypoints: grid A* over obstacles inflated by the radius.

The planner proves a generated world feasible and measures the path a perfect pilot would fly, the
denominator of SPL. It plans in the horizontal plane at one flight altitude, as the vehicle flies:
a grid cell is free when :meth:`World.clearance` at its centre (at that altitude) is at least the
vehicle's radius, so an obstacle the vehicle overflies (its top well below the altitude) is free
space and a beam floating at the altitude is not, exactly as collision decides. A* runs
8-connected (no corner cutting), then a line-of-sight pass pulls the cell path taut, so lengths
come out within about a cell of the true any-angle shortest path. Everything is numba-compiled:
a generator runs it for every world it makes, and training makes worlds on every reset.
"""

from __future__ import annotations

import heapq
import itertools
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from flightsim.worlds.world import (
    Box,
    World,
    box_distance,
    cylinder_distance,
    footprint_radius,
    wall_distance,
)


@dataclass(frozen=True)
class PlannedPath:
    """A collision-free polyline from the start through every waypoint in order.

    :param points: ``(N, 2)`` corners (x, y), metres: the start first, each waypoint among them,
        the last waypoint last
    :param length: total length, metres
    :param leg_lengths: length of each leg (start → waypoint 0, waypoint 0 → 1, …)
    :param altitude: the flight altitude the path was planned at, metres
    """

    points: np.ndarray
    length: float
    leg_lengths: tuple[float, ...]
    altitude: float


@dataclass(frozen=True)
class ClearanceGrid:
    """Clearance at each cell centre of a grid over the room, at one altitude.

    :param clearance: ``(nx, ny)`` metres to the nearest surface, capped at ``cap``
    :param origin: (x, y) of the grid's lower-left corner (the room's inner corner)
    :param resolution: cell size, metres
    """

    clearance: np.ndarray
    origin: tuple[float, float]
    resolution: float

    def cell(self, x: float, y: float) -> tuple[int, int]:
        """The cell that holds (x, y), clamped into the grid."""
        nx, ny = self.clearance.shape
        i = min(max(int((x - self.origin[0]) / self.resolution), 0), nx - 1)
        j = min(max(int((y - self.origin[1]) / self.resolution), 0), ny - 1)
        return i, j


def clearance_grid(world: World, altitude: float, resolution: float, cap: float) -> ClearanceGrid:
    """Rasterise :meth:`World.clearance` at ``altitude`` (values above ``cap`` become ``cap``).

    Each obstacle only touches the cells within ``cap`` of its footprint, so the cost is the
    room's cell count plus the obstacles' inflated areas, not their product.
    """
    hx, hy = world.room_size[0] / 2.0, world.room_size[1] / 2.0
    nx, ny = max(1, math.ceil(2 * hx / resolution)), max(1, math.ceil(2 * hy / resolution))
    room, boxes, cylinders = world.packed
    reach = np.array([footprint_radius(o) for o in world.obstacles if isinstance(o, Box)] or [0.0])
    grid = _clearance_grid_kernel(
        nx, ny, resolution, -hx, -hy, float(altitude), float(cap), room, boxes, reach, cylinders
    )
    return ClearanceGrid(grid, (-hx, -hy), resolution)


def shortest_safe_path(
    world: World,
    *,
    vehicle_radius: float,
    altitude: float | None = None,
    resolution: float = 0.1,
) -> PlannedPath | None:
    """The shortest path from the start through every waypoint in order that keeps the radius.

    :param world: the room, obstacles, start and waypoints (a world without waypoints has nothing
        to plan: the result is None)
    :param vehicle_radius: clearance every point of the path keeps from walls and obstacles, metres
    :param altitude: flight altitude, metres (default: the start's z; waypoint z is not used)
    :param resolution: grid cell size, metres
    :return: the path, or None when some waypoint cannot be reached
    """
    if not world.waypoints:
        return None
    z = float(world.start_position[2] if altitude is None else altitude)
    grid = clearance_grid(world, z, resolution, cap=vehicle_radius + resolution)
    free = grid.clearance >= vehicle_radius
    stops = [world.start_position[:2], *(w[:2] for w in world.waypoints)]
    points: list[np.ndarray] = [np.asarray(stops[0], dtype=np.float64)[None, :]]
    legs: list[float] = []
    for a, b in itertools.pairwise(stops):
        leg = _plan_leg(grid, free, np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
        if leg is None:
            return None
        legs.append(float(np.sum(np.hypot(*np.diff(leg, axis=0).T))))
        points.append(leg[1:])
    return PlannedPath(np.concatenate(points), float(sum(legs)), tuple(legs), z)


def _plan_leg(grid: ClearanceGrid, free: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """One leg's taut polyline ``(N, 2)`` from ``a`` to ``b``, or None if no free route joins them."""
    ia, ib = grid.cell(*a), grid.cell(*b)
    # the endpoints are known clear (the loader or generator checked them); their cells may still
    # read blocked when the point sits less than half a cell from the inflated boundary
    passable = free.copy()
    passable[ia] = passable[ib] = True
    cells = astar_cells(np.where(passable, 1.0, np.inf), ia[0], ia[1], ib[0], ib[1])
    if cells.shape[0] == 0:
        return None
    centres = (cells + 0.5) * grid.resolution + np.asarray(grid.origin)
    polyline = np.concatenate([a[None, :], centres[1:-1], b[None, :]]) if len(cells) > 1 else np.stack([a, b])
    return _pull_taut(polyline, passable, np.asarray(grid.origin), grid.resolution)


# ----------------------------------------------------------------------------------------------
# compiled kernels


@njit(cache=True)
def _clearance_grid_kernel(
    nx, ny, res, ox, oy, z, cap, room, boxes, box_reach, cylinders
):  # pragma: no cover
    """Compiled: the clearance grid of :func:`clearance_grid`."""
    grid = np.empty((nx, ny), dtype=np.float64)
    for i in range(nx):
        x = ox + (i + 0.5) * res
        for j in range(ny):
            grid[i, j] = min(wall_distance(x, oy + (j + 0.5) * res, z, room), cap)
    for k in range(boxes.shape[0]):
        _stamp(grid, res, ox, oy, z, boxes[k], box_reach[k] + cap, True)
    for k in range(cylinders.shape[0]):
        _stamp(grid, res, ox, oy, z, cylinders[k], cylinders[k, 2] + cap, False)
    return grid


@njit(cache=True)
def _stamp(grid, res, ox, oy, z, row, reach, is_box):  # pragma: no cover - compiled
    """Lower the cells within ``reach`` of one obstacle's centre to their distance to it."""
    nx, ny = grid.shape
    i0 = max(int((row[0] - reach - ox) / res), 0)
    i1 = min(int((row[0] + reach - ox) / res) + 1, nx)
    j0 = max(int((row[1] - reach - oy) / res), 0)
    j1 = min(int((row[1] + reach - oy) / res) + 1, ny)
    for i in range(i0, i1):
        x = ox + (i + 0.5) * res
        for j in range(j0, j1):
            y = oy + (j + 0.5) * res
            d = box_distance(x, y, z, row) if is_box else cylinder_distance(x, y, z, row)
            if d < grid[i, j]:
                grid[i, j] = d


_SQRT2 = math.sqrt(2.0)


@njit(cache=True)
def astar_cells(costs, si, sj, gi, gj):  # pragma: no cover - compiled
    """8-connected A* over per-cell cost factors (``inf``: blocked): a step costs its length (1 or
    √2 cells) × the mean of its two cells' factors, so all-ones is the plain shortest grid path.
    Octile heuristic, no corner cutting past a blocked cell. The cell path ``(N, 2)``, empty if none.
    """
    nx, ny = costs.shape
    g = np.full(nx * ny, np.inf)
    parent = np.full(nx * ny, -1, dtype=np.int64)
    closed = np.zeros(nx * ny, dtype=np.bool_)
    start, goal = si * ny + sj, gi * ny + gj
    g[start] = 0.0
    heap = [(0.0, start)]
    di = (1, -1, 0, 0, 1, 1, -1, -1)
    dj = (0, 0, 1, -1, 1, -1, 1, -1)
    while heap:
        _, cur = heapq.heappop(heap)
        if closed[cur]:
            continue
        closed[cur] = True
        if cur == goal:
            break
        ci, cj = cur // ny, cur % ny
        for k in range(8):
            ni, nj = ci + di[k], cj + dj[k]
            if ni < 0 or nj < 0 or ni >= nx or nj >= ny or not np.isfinite(costs[ni, nj]):
                continue
            if k >= 4 and not (np.isfinite(costs[ci + di[k], cj]) and np.isfinite(costs[ci, cj + dj[k]])):
                continue  # a diagonal step may not cut a blocked corner
            nxt = ni * ny + nj
            cost = g[cur] + (1.0 if k < 4 else _SQRT2) * 0.5 * (costs[ci, cj] + costs[ni, nj])
            if cost < g[nxt]:
                g[nxt] = cost
                parent[nxt] = cur
                ai, aj = abs(ni - gi), abs(nj - gj)
                h = max(ai, aj) + (_SQRT2 - 1.0) * min(ai, aj)
                heapq.heappush(heap, (cost + h, nxt))
    if not closed[goal]:
        return np.empty((0, 2), dtype=np.int64)
    n = 1
    cur = goal
    while cur != start:
        cur = parent[cur]
        n += 1
    cells = np.empty((n, 2), dtype=np.int64)
    cur = goal
    for k in range(n - 1, -1, -1):
        cells[k, 0], cells[k, 1] = cur // ny, cur % ny
        cur = parent[cur]
    return cells


@njit(cache=True)
def cost_to_go(costs, gi, gj):  # pragma: no cover - compiled
    """Every cell's cost of the cheapest path to cell ``(gi, gj)``, in cells, under the step costs of
    :func:`astar_cells` (Dijkstra from the goal; ``inf`` where the goal cannot be reached). A
    planner that scores many candidate end points reads them all from one search."""
    nx, ny = costs.shape
    dist = np.full((nx, ny), np.inf)
    dist[gi, gj] = 0.0
    heap = [(0.0, gi * ny + gj)]
    di = (1, -1, 0, 0, 1, 1, -1, -1)
    dj = (0, 0, 1, -1, 1, -1, 1, -1)
    while heap:
        d, cur = heapq.heappop(heap)
        ci, cj = cur // ny, cur % ny
        if d > dist[ci, cj]:
            continue
        for k in range(8):
            ni, nj = ci + di[k], cj + dj[k]
            if ni < 0 or nj < 0 or ni >= nx or nj >= ny or not np.isfinite(costs[ni, nj]):
                continue
            if k >= 4 and not (np.isfinite(costs[ci + di[k], cj]) and np.isfinite(costs[ci, cj + dj[k]])):
                continue
            cost = d + (1.0 if k < 4 else _SQRT2) * 0.5 * (costs[ci, cj] + costs[ni, nj])
            if cost < dist[ni, nj]:
                dist[ni, nj] = cost
                heapq.heappush(heap, (cost, ni * ny + nj))
    return dist


@njit(cache=True)
def _visible(free, origin, res, ax, ay, bx, by):  # pragma: no cover - compiled
    """True if every sample of segment a-b (at most a quarter cell apart) lies in a free cell."""
    nx, ny = free.shape
    n = int(math.hypot(bx - ax, by - ay) / (0.25 * res)) + 1
    for k in range(n + 1):
        t = k / n
        i = int((ax + t * (bx - ax) - origin[0]) / res)
        j = int((ay + t * (by - ay) - origin[1]) / res)
        if i < 0 or j < 0 or i >= nx or j >= ny or not free[i, j]:
            return False
    return True


@njit(cache=True)
def _pull_taut(points, free, origin, res):  # pragma: no cover - compiled
    """Drop every corner the path can see past: from each kept corner, jump to the farthest visible one."""
    n = points.shape[0]
    keep = [0]
    anchor = 0
    while anchor < n - 1:
        nxt = anchor + 1
        for j in range(n - 1, anchor + 1, -1):
            if _visible(free, origin, res, points[anchor, 0], points[anchor, 1], points[j, 0], points[j, 1]):
                nxt = j
                break
        keep.append(nxt)
        anchor = nxt
    out = np.empty((len(keep), 2))
    for k in range(len(keep)):
        out[k] = points[keep[k]]
    return out
