"""Feasibility among moving obstacles: space-time search for a vehicle that may wait.

The static planner (:func:`flightsim.worlds.planner.shortest_safe_path`) proves a way past the
static geometry. With moving obstacles that is not enough: one may stand in the way when the
vehicle gets there. :func:`wait_and_go_time` searches space and time together: a grid over the room
at the flight altitude, and at every time step the vehicle stays in its cell or moves to one of the
eight around it (at most ``cell · √2 / dt``, 1.4 m/s by default), entering only cells that the
static geometry and every moving obstacle (where it is at that time) leave clear by a margin. The
margins make a schedule found collision-free in continuous time too: half a cell diagonal for the
straight move between cell centres, and for the moving obstacles also what both sides can move
between two time samples. The waypoints are taken in order, each reached as early as possible
(waiting there is allowed where it is safe). A schedule proves the world can be flown; none within
the horizon rejects the layout (conservative: a faster or finer vehicle may still get through).

:func:`schedule` is the same search from any cell and time, kept step by step so that the way
itself can be read back: the space-time teacher (:mod:`training.space_time_expert`) flies it.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import binary_dilation

from flightsim.worlds.moving import MovingObstacle
from flightsim.worlds.planner import ClearanceGrid, clearance_grid
from flightsim.worlds.world import World

SAFETY_EXTRA = 0.05  # metres beyond the sampling margins
HEADING_DT = 0.1  # s over which right_of_movers reads a mover's heading
PASSING_SPEED = 0.3  # m/s: a mover slower than this has no side to pass on
VELOCITY_DT = 0.1  # s over which mover_state reads a mover's velocity
_NEIGHBOURS = np.ones((3, 3), dtype=bool)
_CHUNK = 32  # time steps whose clearances are computed at once


def wait_and_go_time(
    world: World,
    vehicle_radius: float,
    horizon: float,
    *,
    altitude: float | None = None,
    cell: float = 0.2,
    dt: float = 0.2,
) -> float | None:
    """The earliest time a waiting vehicle can be at the last waypoint, having visited each in order.

    :param world: the room, its static and moving obstacles, the start and the waypoints
    :param vehicle_radius: metres
    :param horizon: give up after this many seconds
    :param altitude: flight altitude, metres (default: the start's z)
    :param cell: grid cell size, metres
    :param dt: time step, seconds
    :return: seconds from the start to the last waypoint; None if no schedule within ``horizon``
    """
    z = float(world.start_position[2] if altitude is None else altitude)
    half_diagonal = cell * math.sqrt(2.0) / 2.0
    grid = clearance_grid(world, z, cell, cap=vehicle_radius + half_diagonal + cell)
    static_free = grid.clearance >= vehicle_radius + half_diagonal
    centres = cell_centres(grid, z)
    needed = vehicle_radius + sampling_margin(world, cell, dt)
    times = np.arange(0.0, horizon + dt / 2.0, dt)
    free_chunk: np.ndarray | None = None

    def free_at(k: int) -> np.ndarray:
        nonlocal free_chunk
        if k % _CHUNK == 0 or free_chunk is None:
            chunk = times[k - k % _CHUNK : k - k % _CHUNK + _CHUNK]
            free_chunk = free_cells(world, centres, chunk, needed, static_free)
        return free_chunk[k % _CHUNK]

    reach = np.zeros(static_free.shape, dtype=bool)
    reach[grid.cell(*world.start_position[:2])] = True
    reach &= free_at(0)
    targets = [grid.cell(*w[:2]) for w in world.waypoints]
    for k in range(1, times.size):
        if not targets:
            return float(times[k - 1])
        if not reach.any():
            return None
        reach = binary_dilation(reach, _NEIGHBOURS) & free_at(k)
        if reach[targets[0]]:  # reached as early as possible: go on from there alone
            target = targets.pop(0)
            reach[:] = False
            reach[target] = True
    return float(times[-1]) if not targets else None


def cell_centres(grid: ClearanceGrid, altitude: float) -> np.ndarray:
    """Every cell's centre at ``altitude``, ``(nx * ny, 3)`` in the grid's row-major order."""
    nx, ny = grid.clearance.shape
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    return np.column_stack(
        [
            grid.origin[0] + (ii.ravel() + 0.5) * grid.resolution,
            grid.origin[1] + (jj.ravel() + 0.5) * grid.resolution,
            np.full(ii.size, altitude),
        ]
    )


def sampling_margin(world: World, cell: float, dt: float) -> float:
    """Clearance beyond the vehicle's radius a cell centre must keep from every moving obstacle at
    every time sample, metres: half a cell diagonal (the straight move between centres) and what the
    fastest mover and the vehicle can close between two samples."""
    vehicle_speed = cell * math.sqrt(2.0) / dt
    fastest = max((m.speed for m in world.moving), default=0.0)
    return cell * math.sqrt(2.0) / 2.0 + (fastest + vehicle_speed) * dt / 2.0 + SAFETY_EXTRA


def mover_state(mover: MovingObstacle, time: float) -> tuple[np.ndarray, np.ndarray]:
    """``mover``'s centre (x, y) at ``time``, metres, and its velocity (vx, vy) over the
    ``VELOCITY_DT`` before, m/s: as a tracker reads it, from where it was, not where it will be."""
    before, now = mover.positions(np.array([time - VELOCITY_DT, time]))
    return now, (now - before) / VELOCITY_DT


def mover_track(mover: MovingObstacle, times: np.ndarray, *, constant_velocity: bool = False) -> np.ndarray:
    """Where ``mover``'s centre is at each of ``times``, ``(T, 2)``: on its true track, or carried on
    in a straight line at its velocity at ``times[0]`` (all that a frame of the tracker's knows: where
    each mover is now and how fast it goes, not where it will turn)."""
    if not constant_velocity:
        return mover.positions(times)
    now = float(times[0])
    here, velocity = mover_state(mover, now)
    return here + (np.asarray(times) - now)[:, None] * velocity


def free_cells(
    world: World,
    centres: np.ndarray,
    times: np.ndarray,
    needed: float,
    static_free: np.ndarray,
    *,
    constant_velocity: bool = False,
    growth: float = 0.0,
    growth_cap: float = 0.0,
) -> np.ndarray:
    """Which cells the vehicle may be in at each of ``times``: ``static_free`` and at least ``needed``
    metres from every moving obstacle where it is then, ``(T, nx, ny)``.

    :param centres: the cells' centres, :func:`cell_centres`
    :param needed: metres from each mover's surface
    :param static_free: ``(nx, ny)`` the cells the static world leaves free
    :param constant_velocity: each mover where :func:`mover_track` carries it on from ``times[0]``
        at its velocity then, instead of its true track
    :param growth: ``needed`` grows this much per second after ``times[0]`` (a prediction's error
        grows with how far ahead it reaches), m/s
    :param growth_cap: ``needed`` grows at most this much, metres
    """
    points = np.asarray(centres, dtype=np.float64).reshape(-1, 3)[None]
    needed_then = needed + np.minimum(growth * (np.asarray(times) - times[0]), growth_cap)[:, None]
    ok = np.ones((times.size, points.shape[1]), dtype=bool)
    for m in world.moving:
        track = mover_track(m, times, constant_velocity=constant_velocity)
        ok &= m.clearance_from(points, track[:, None]) >= needed_then
    return ok.reshape(times.size, *static_free.shape) & static_free[None]


def right_of_movers(
    world: World, centres: np.ndarray, times: np.ndarray, within: float, *, constant_velocity: bool = False
) -> np.ndarray:
    """The cells within ``within`` metres of a moving mover's centre and on its right (from its
    heading) at each of ``times``, ``(T, N)`` for ``centres`` ``(N, 3)``: where a vehicle that
    keeps right of an oncoming mover, as ships and most roads do, does not pass it.

    :param constant_velocity: each mover carried on from ``times[0]`` (:func:`mover_track`), heading
        where it heads then
    """
    points = np.asarray(centres, dtype=np.float64).reshape(-1, 3)[None, :, :2]
    right = np.zeros((times.size, points.shape[1]), dtype=bool)
    for m in world.moving:
        at = mover_track(m, times, constant_velocity=constant_velocity)
        if constant_velocity:
            step = np.broadcast_to(mover_state(m, float(times[0]))[1] * HEADING_DT, at.shape)
        else:
            step = m.positions(times + HEADING_DT) - at
        moving = np.hypot(step[:, 0], step[:, 1]) > PASSING_SPEED * HEADING_DT
        offset = points - at[:, None]
        near = np.hypot(offset[..., 0], offset[..., 1]) <= within
        on_right = offset[..., 0] * step[:, None, 1] - offset[..., 1] * step[:, None, 0] > 0.0
        right |= near & on_right & moving[:, None]
    return right


def schedule(free: np.ndarray, start: tuple[int, int], goal: tuple[int, int], cost: np.ndarray) -> np.ndarray:
    """The earliest way from ``start`` to ``goal`` through ``free`` cells, one cell per time step
    (staying put or moving to one of the eight around), ``(K, 2)`` cells from ``start`` on.

    The vehicle's own cell counts as free at the start even when a mover's margin covers it (it is
    there: the way leads out). When the goal cannot be reached within ``free``'s steps, the way
    ends, at the last step, in the reachable cell of least ``cost`` (the cost to the goal), so the
    vehicle still gets as near as the movers let it. Where no cell stays reachable it stays put.
    Read back from the end, a step keeps to its cell whenever that cell was reachable a step
    earlier (the vehicle gets to each place as early as it can and waits there), and otherwise
    comes from the neighbour of most ``cost`` (the most progress per step).

    :param free: ``(T, nx, ny)`` :func:`free_cells`
    :param start: the vehicle's cell at ``free``'s first time
    :param goal: the cell to reach
    :param cost: ``(nx, ny)`` each cell's cost to the goal (the tie-break, and where to end short)
    """
    steps, nx, ny = free.shape
    reach = np.zeros((nx, ny), dtype=bool)
    reach[start] = True
    reaches = [reach]
    end: tuple[int, int] | None = None
    for k in range(1, steps):
        reach = binary_dilation(reach, _NEIGHBOURS) & free[k]
        if not reach.any():
            reach = reaches[0].copy()  # trapped: hold where it is
        reaches.append(reach)
        if reach[goal]:
            end = goal
            break
    if end is None:
        nearest = np.unravel_index(np.argmin(np.where(reaches[-1], cost, np.inf)), cost.shape)
        end = (int(nearest[0]), int(nearest[1]))
    way = [end]
    for reach in reversed(reaches[:-1]):
        i, j = way[-1]
        if reach[i, j]:
            way.append((i, j))
            continue
        around = [
            (a, b)
            for a in range(max(i - 1, 0), min(i + 2, nx))
            for b in range(max(j - 1, 0), min(j + 2, ny))
            if reach[a, b]
        ]
        way.append(max(around, key=lambda c: cost[c]) if around else (i, j))
    return np.array(way[::-1], dtype=np.int64)
