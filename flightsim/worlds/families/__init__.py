"""World families for goal-directed flight: one generator per kind of clutter, each with waypoints.

``generate_family_world(family, seed, difficulty)`` is deterministic in its three arguments. Each
family lays out its geometry, a start and 1-4 waypoints; the planner then proves the world
feasible (a safe path through every waypoint in order exists for the vehicle's radius) and its
length becomes :attr:`World.shortest_path_m`. A layout the planner rejects, or one a family could
not place, is laid out again from a seed derived from (seed, attempt), so the result stays
deterministic. The start heading is the bearing of the path's first leg turned by up to
±90° × difficulty, so harder worlds also ask the pilot to find the way before flying it.

The dynamic families (:data:`DYNAMIC_FAMILIES`, ``<family>-dynamic``) take the static family's world
for the same arguments unchanged and add moving obstacles (:mod:`flightsim.worlds.families.dynamic`);
:func:`flightsim.worlds.space_time.wait_and_go_time` then proves that a vehicle that may wait can
get through them to every waypoint within the episode's time, or the motion is drawn again. They are
not among :data:`FAMILIES`, the default training and evaluation set.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from flightsim.worlds.families._common import POINT_MARGIN, ROOM_HEIGHT, Layout
from flightsim.worlds.families.dynamic import DYNAMIC_MIXES, add_moving
from flightsim.worlds.families.open_spaces import forest, mixed, pillars, rooms
from flightsim.worlds.families.structures import gaps, office, staggered, traps, warehouse
from flightsim.worlds.planner import shortest_safe_path
from flightsim.worlds.space_time import wait_and_go_time
from flightsim.worlds.world import DEFAULT_VEHICLE_RADIUS, FLIGHT_ALTITUDE, World, clearances

FamilyLayout = Callable[[np.random.Generator, int, float, float], "Layout | None"]

_GENERATORS: dict[str, FamilyLayout] = {
    "rooms": rooms,
    "forest": forest,
    "office": office,
    "warehouse": warehouse,
    "pillars": pillars,
    "staggered": staggered,
    "traps": traps,
    "gaps": gaps,
    "mixed": mixed,
}
FAMILIES: tuple[str, ...] = tuple(_GENERATORS)
DYNAMIC_SUFFIX = "-dynamic"
DYNAMIC_FAMILIES: tuple[str, ...] = tuple(f"{f}{DYNAMIC_SUFFIX}" for f in DYNAMIC_MIXES)
ALL_FAMILIES: tuple[str, ...] = FAMILIES + DYNAMIC_FAMILIES
MAX_ATTEMPTS = 50


def generate_family_world(
    family: str,
    seed: int,
    difficulty: float,
    *,
    vehicle_radius: float = DEFAULT_VEHICLE_RADIUS,
) -> World:
    """A world of ``family`` with a start and waypoints, proven feasible by the planner.

    :param family: one of :data:`ALL_FAMILIES`
    :param seed: non-negative integer
    :param difficulty: 0.0 (easy) … 1.0 (hard): density, gap widths, trap counts, as each family says
    :param vehicle_radius: the radius the world must be feasible for, metres
    :raises ValueError: unknown family or difficulty outside [0, 1]
    """
    if family not in ALL_FAMILIES:
        raise ValueError(f"unknown world family {family!r}; expected one of {', '.join(ALL_FAMILIES)}")
    if not 0.0 <= difficulty <= 1.0:
        raise ValueError(f"difficulty must be in [0, 1], got {difficulty}")
    if seed < 0:
        raise ValueError(f"seed must be non-negative, got {seed}")
    d = float(difficulty)
    if family in DYNAMIC_FAMILIES:
        return _dynamic_world(family, seed, d, vehicle_radius)
    family_index = FAMILIES.index(family)
    for attempt in range(MAX_ATTEMPTS):
        rng = np.random.default_rng([seed, family_index, attempt])
        # the rooms family reuses generate_world, whose own seed is the caller's on the first try
        layout_seed = seed if attempt == 0 else int(rng.integers(2**31))
        layout = _GENERATORS[family](rng, layout_seed, d, vehicle_radius)
        if layout is None or not layout.waypoints:
            continue
        world = _to_world(f"{family}-{seed}-d{d:.2f}", layout)
        if not _points_clear(world, vehicle_radius + POINT_MARGIN):
            continue
        path = shortest_safe_path(world, vehicle_radius=vehicle_radius)
        if path is None:
            continue
        first = path.points[1] - path.points[0]
        yaw = math.degrees(math.atan2(first[1], first[0])) + rng.uniform(-90.0, 90.0) * d
        return dataclasses.replace(world, start_yaw_deg=round(yaw % 360.0, 1), shortest_path_m=path.length)
    raise RuntimeError(f"{family} seed {seed} difficulty {d}: no feasible layout in {MAX_ATTEMPTS} attempts")


def _dynamic_world(family: str, seed: int, d: float, vehicle_radius: float) -> World:
    """The static family's world with moving obstacles a waiting vehicle is proven to get past."""
    base = family.removesuffix(DYNAMIC_SUFFIX)
    static = generate_family_world(base, seed, d, vehicle_radius=vehicle_radius)
    path = shortest_safe_path(static, vehicle_radius=vehicle_radius)
    if path is None:  # generate_family_world proved it feasible; the planner is deterministic
        raise RuntimeError(f"{base} seed {seed}: the static path vanished")
    horizon = 10.0 + 2.0 * path.length  # the goal env's time limit
    for attempt in range(MAX_ATTEMPTS):
        rng = np.random.default_rng([seed, ALL_FAMILIES.index(family), attempt])
        world = add_moving(static, rng, d, vehicle_radius, path.points[:2], base)
        if world is None:
            continue
        if wait_and_go_time(world, vehicle_radius, horizon) is not None:
            return dataclasses.replace(world, name=f"{family}-{seed}-d{d:.2f}")
    raise RuntimeError(f"{family} seed {seed} difficulty {d}: no feasible motion in {MAX_ATTEMPTS} attempts")


def _to_world(name: str, layout: Layout) -> World:
    start = (layout.start[0], layout.start[1], FLIGHT_ALTITUDE)
    waypoints = tuple((x, y, FLIGHT_ALTITUDE) for x, y in layout.waypoints)
    return World(name, layout.room_size, ROOM_HEIGHT, tuple(layout.obstacles), start, 0.0, waypoints)


def _points_clear(world: World, clearance: float) -> bool:
    """Start and every waypoint inside the room and at least ``clearance`` from every surface."""
    pts = np.asarray([world.start_position, *world.waypoints], dtype=np.float64)
    return bool(np.all(clearances(world, pts) >= clearance))


__all__ = ["ALL_FAMILIES", "DYNAMIC_FAMILIES", "FAMILIES", "generate_family_world"]
