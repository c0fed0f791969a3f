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
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import binary_dilation

from flightsim.worlds.planner import clearance_grid
from flightsim.worlds.world import World

SAFETY_EXTRA = 0.05  # metres beyond the sampling margins
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
    nx, ny = static_free.shape
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    centres = np.column_stack(
        [
            grid.origin[0] + (ii.ravel() + 0.5) * cell,
            grid.origin[1] + (jj.ravel() + 0.5) * cell,
            np.full(ii.size, z),
        ]
    )
    vehicle_speed = cell * math.sqrt(2.0) / dt
    fastest = max((m.speed for m in world.moving), default=0.0)
    needed = vehicle_radius + half_diagonal + (fastest + vehicle_speed) * dt / 2.0 + SAFETY_EXTRA
    times = np.arange(0.0, horizon + dt / 2.0, dt)
    free_chunk: np.ndarray | None = None

    def free_at(k: int) -> np.ndarray:
        nonlocal free_chunk
        if k % _CHUNK == 0 or free_chunk is None:
            chunk = times[k - k % _CHUNK : k - k % _CHUNK + _CHUNK]
            ok = np.ones((chunk.size, centres.shape[0]), dtype=bool)
            for m in world.moving:
                ok &= m.clearance_over_time(centres, chunk) >= needed
            free_chunk = ok.reshape(chunk.size, nx, ny) & static_free[None]
        return free_chunk[k % _CHUNK]

    reach = np.zeros((nx, ny), dtype=bool)
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
