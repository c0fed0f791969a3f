"""The planner: lengths against answers worked out by hand, and paths that keep the radius."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from flightsim.worlds.planner import astar_cells, clearance_grid, cost_to_go, shortest_safe_path
from flightsim.worlds.world import Box, Cylinder, World, clearances

R = 0.25
ALT = 1.5


def _world(size, obstacles, start, waypoints) -> World:
    return World("hand", size, 3.0, tuple(obstacles), (*start, ALT), 0.0, tuple((*w, ALT) for w in waypoints))


def _samples(points: np.ndarray, step: float = 0.02) -> np.ndarray:
    """Points every ``step`` metres along a polyline, at the flight altitude."""
    out = []
    for a, b in itertools.pairwise(points):
        n = max(2, math.ceil(np.hypot(*(b - a)) / step))
        out.append(a + np.linspace(0.0, 1.0, n)[:, None] * (b - a))
    xy = np.concatenate(out)
    return np.column_stack([xy, np.full(len(xy), ALT)])


def _door_world(door_lo: float = 2.0, door_hi: float = 3.5) -> World:
    """A 0.2 m wall across a 20 × 10 m room at x = 0, with a door from y = door_lo to door_hi."""
    wall = (Box((0.0, (-5.0 + door_lo) / 2, 1.5), (0.2, door_lo + 5.0, 3.0)),
            Box((0.0, (door_hi + 5.0) / 2, 1.5), (0.2, 5.0 - door_hi, 3.0)))  # fmt: skip
    return _world((20.0, 10.0), wall, (-5.0, 0.0), [(5.0, 0.0)])


def test_straight_corridor_is_the_straight_line() -> None:
    world = _world((20.0, 4.0), [], (-8.0, 0.0), [(8.0, 0.0)])
    path = shortest_safe_path(world, vehicle_radius=R)
    assert path is not None
    assert path.length == pytest.approx(16.0, abs=1e-9)
    assert np.allclose(path.points, [[-8.0, 0.0], [8.0, 0.0]])  # pulled taut: no grid corners left
    assert path.leg_lengths == (pytest.approx(16.0),) and path.altitude == ALT


def test_wall_with_a_door_matches_the_tangent_and_arc_answer() -> None:
    """Around the door's lower jamb: tangent from the start to the jamb corner inflated by the
    radius, an arc, the 0.2 m straight across the wall's thickness, an arc, a tangent to the goal."""
    path = shortest_safe_path(_door_world(), vehicle_radius=R)
    assert path is not None
    corner = np.array([-0.1, 2.0])  # the jamb's corner on the start side; its mirror is at x = +0.1
    d = float(np.hypot(*(corner - (-5.0, 0.0))))
    tangent = math.sqrt(d * d - R * R)
    turn = math.atan2(corner[1], corner[0] + 5.0) + math.asin(R / d)  # from the tangent to level
    expected = 2 * (tangent + R * turn) + 0.2
    assert path.length == pytest.approx(expected, rel=0.005)
    assert path.length > expected - 0.01  # never shorter than the true shortest path (to a cell's slack)
    assert np.all(path.points[:, 1] > -0.5)  # through the door, not elsewhere


def test_path_keeps_the_radius_to_within_half_a_cell() -> None:
    world = _world(
        (14.0, 9.0),
        [
            Cylinder((0.0, 0.0), 1.0, 3.0),
            Box((3.0, 1.5, 1.5), (0.6, 4.0, 3.0), 25.0),
            Cylinder((-3.0, -1.0), 0.4, 3.0),
        ],
        (-6.0, -0.5),
        [(6.0, 0.5), (-5.0, 3.0)],
    )
    path = shortest_safe_path(world, vehicle_radius=R, resolution=0.1)
    assert path is not None
    assert clearances(world, _samples(path.points)).min() >= R - 0.05
    # and every waypoint is on the path, in order
    for w in world.waypoints:
        assert np.min(np.hypot(*(path.points - w[:2]).T)) < 1e-9
    assert path.length == pytest.approx(sum(path.leg_lengths))


def test_no_way_through_is_none() -> None:
    closed = _world((20.0, 10.0), [Box((0.0, 0.0, 1.5), (0.2, 10.0, 3.0))], (-5.0, 0.0), [(5.0, 0.0)])
    assert shortest_safe_path(closed, vehicle_radius=R) is None
    # a door narrower than the vehicle is no door
    assert shortest_safe_path(_door_world(2.0, 2.45), vehicle_radius=R) is None
    assert shortest_safe_path(_door_world(2.0, 2.65), vehicle_radius=R) is not None


def test_a_world_without_waypoints_has_no_path() -> None:
    assert shortest_safe_path(_world((10.0, 10.0), [], (0.0, 0.0), []), vehicle_radius=R) is None


@pytest.mark.parametrize(
    ("bottom", "top", "blocks"),
    [
        (0.0, 0.7, False),  # low: overflown with 0.8 m to spare
        (0.0, ALT - R + 0.01, True),  # just too high to clear by the radius
        (1.4, 1.6, True),  # a beam at flight level, floating
        (ALT + R + 0.01, 2.5, False),  # a beam just above the vehicle
        (0.0, 3.0, True),  # full height
    ],
)
def test_heights_count_exactly_as_collision_does(bottom: float, top: float, blocks: bool) -> None:
    """A wall across the room, only its height varies: the planner agrees with World.clearance."""
    barrier = Box((0.0, 0.0, (bottom + top) / 2), (0.4, 10.0, top - bottom))
    world = _world((20.0, 10.0), [barrier], (-5.0, 0.0), [(5.0, 0.0)])
    path = shortest_safe_path(world, vehicle_radius=R)
    assert (path is None) == blocks
    assert (world.clearance((0.0, 0.0, ALT)) < R) == blocks
    if not blocks:
        assert path.length == pytest.approx(10.0)


def test_altitude_argument_plans_at_that_height() -> None:
    beam = Box((0.0, 0.0, 2.4), (0.4, 10.0, 0.4))  # 2.2 to 2.6 m
    world = _world((20.0, 10.0), [beam], (-5.0, 0.0), [(5.0, 0.0)])
    assert shortest_safe_path(world, vehicle_radius=R) is not None
    assert shortest_safe_path(world, vehicle_radius=R, altitude=2.4) is None


def test_finer_grid_agrees() -> None:
    world = _door_world()
    coarse = shortest_safe_path(world, vehicle_radius=R, resolution=0.1)
    fine = shortest_safe_path(world, vehicle_radius=R, resolution=0.05)
    assert coarse is not None and fine is not None
    assert fine.length == pytest.approx(coarse.length, rel=0.005)


def test_clearance_grid_matches_world_clearance() -> None:
    world = _world(
        (12.0, 8.0),
        [Box((2.0, 1.0, 1.5), (1.0, 0.6, 3.0), 30.0), Cylinder((-3.0, -1.5), 0.3, 3.0)],
        (-5.0, 0.0),
        [],
    )
    grid = clearance_grid(world, ALT, 0.1, cap=1.0)
    nx, ny = grid.clearance.shape
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    centres = np.column_stack(
        [(i.ravel() + 0.5) * 0.1 - 6.0, (j.ravel() + 0.5) * 0.1 - 4.0, np.full(i.size, ALT)]
    )
    exact = np.minimum(clearances(world, centres), 1.0)
    assert grid.clearance.ravel() == pytest.approx(exact, abs=1e-9)


def _path_cost(costs: np.ndarray, cells: np.ndarray) -> float:
    steps = np.diff(cells, axis=0)
    lengths = np.where(np.abs(steps).sum(axis=1) == 2, math.sqrt(2.0), 1.0)
    factors = 0.5 * (costs[cells[:-1, 0], cells[:-1, 1]] + costs[cells[1:, 0], cells[1:, 1]])
    return float((lengths * factors).sum())


def test_cost_to_go_is_the_a_star_path_cost_from_every_start() -> None:
    rng = np.random.default_rng(4)
    costs = 1.0 + rng.uniform(0.0, 3.0, (30, 25))
    costs[rng.uniform(size=costs.shape) < 0.2] = np.inf
    costs[7, 3] = costs[20, 20] = 1.0
    to_goal = cost_to_go(costs, 20, 20)
    assert to_goal[20, 20] == 0.0
    reachable = 0
    for i, j in itertools.product(range(0, 30, 3), range(0, 25, 3)):
        if not np.isfinite(costs[i, j]):
            assert not np.isfinite(to_goal[i, j])
            continue
        cells = astar_cells(costs, i, j, 20, 20)
        if len(cells) == 0:
            assert not np.isfinite(to_goal[i, j])
            continue
        reachable += 1
        assert to_goal[i, j] == pytest.approx(_path_cost(costs, cells), rel=1e-9)
    assert reachable > 30
