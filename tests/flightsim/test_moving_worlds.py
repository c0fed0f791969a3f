"""Worlds with motion: the schema and its one-line errors, the motions, the dynamic families and the
space-time feasibility check; the nine static families unchanged."""

from __future__ import annotations

import copy
import hashlib
import json
import re
from pathlib import Path

import numpy as np
import pytest

from companion.common.errors import UserError
from flightsim.worlds.families import ALL_FAMILIES, DYNAMIC_FAMILIES, FAMILIES, generate_family_world
from flightsim.worlds.families.dynamic import DYNAMIC_MIXES
from flightsim.worlds.moving import MovingObstacle, PathMotion, RandomWalk
from flightsim.worlds.planner import clearance_grid
from flightsim.worlds.space_time import (
    cell_centres,
    free_cells,
    mover_track,
    right_of_movers,
    sampling_margin,
    schedule,
    wait_and_go_time,
)
from flightsim.worlds.world import World, load_world, world_from_dict, world_to_dict

REPO = Path(__file__).resolve().parents[2]


def _docs_example() -> dict:
    text = (REPO / "docs" / "worlds.md").read_text()
    return json.loads(re.search(r"```json\n(.*?)```", text, re.S).group(1))


def test_the_documented_example_has_every_kind_of_motion(tmp_path: Path) -> None:
    path = tmp_path / "w.json"
    path.write_text(json.dumps(_docs_example()))
    world = load_world(path)
    kinds = [(m.kind, m.shape, type(m.motion).__name__) for m in world.moving]
    assert kinds == [
        ("pedestrian", "cylinder", "PathMotion"),
        ("drone", "cylinder", "RandomWalk"),
        ("forklift", "box", "PathMotion"),
    ]
    assert world.moving[1].base == 1.35 and world.moving[2].motion.loop
    assert world_from_dict(world_to_dict(world)) == world


def _edit(edit) -> World:
    data = copy.deepcopy(_docs_example())
    edit(data)
    return world_from_dict(data, path_for_messages="w.json")


@pytest.mark.parametrize(
    ("edit", "field", "words"),
    [
        (lambda d: d.update(moving={}), "moving", "list"),
        (lambda d: d["moving"].append(3), "moving[3]", "object"),
        (lambda d: d["moving"][0].pop("type"), "moving[0].type", "missing"),
        (lambda d: d["moving"][0].update(type="cone"), "moving[0].type", "'box' or 'cylinder'"),
        (lambda d: d["moving"][0].pop("path"), "moving[0]", "exactly one of 'path' and 'walk'"),
        (lambda d: d["moving"][0].update(walk=d["moving"][1]["walk"]), "moving[0]", "exactly one"),
        (lambda d: d["moving"][0].update(colour="red"), "moving[0].colour", "unknown"),
        (lambda d: d["moving"][0].update(radius=0.0), "moving[0].radius", "positive"),
        (lambda d: d["moving"][1].update(base=-1.0), "moving[1].base", "0 or more"),
        (lambda d: d["moving"][0]["path"].update(points=[[0.0, 1.0]]), "moving[0].path.points", "at least 2"),
        (
            lambda d: d["moving"][0]["path"]["points"].append([9.0, 0.0]),
            "moving[0].path.points[2]",
            "outside",
        ),
        (lambda d: d["moving"][0]["path"].update(speed=0), "moving[0].path.speed", "positive"),
        (lambda d: d["moving"][0]["path"].pop("speed"), "moving[0].path.speed", "missing"),
        (lambda d: d["moving"][2]["path"].update(loop="yes"), "moving[2].path.loop", "true or false"),
        (
            lambda d: d["moving"][1]["walk"].update(bounds=[[4.0, 3.0], [-1.0, -3.0]]),
            "moving[1].walk.bounds",
            "below",
        ),
        (lambda d: d["moving"][1]["walk"].update(bounds=[[0, 0]]), "moving[1].walk.bounds", "x_min"),
        (lambda d: d["moving"][1]["walk"].update(seed=1.5), "moving[1].walk.seed", "non-negative integer"),
        (lambda d: d["moving"][1]["walk"].update(seed=-1), "moving[1].walk.seed", "non-negative integer"),
        (lambda d: d["moving"][2].update(size=[1.0, 1.0]), "moving[2].size", "3 numbers"),
        (
            lambda d: d["moving"][0]["path"].update(points=[[-4.4, 0.0], [-4.4, 2.0]]),
            "start.position",
            "moving[0] at the start",
        ),
    ],
)
def test_bad_moving_field_is_named_in_one_line(edit, field: str, words: str) -> None:
    with pytest.raises(UserError) as info:
        _edit(edit)
    message = str(info.value)
    assert f"w.json: {field}: " in message, message
    assert words in message, message
    assert "\n" not in message


def test_a_bad_moving_world_file_exits_with_one_line(tmp_path: Path) -> None:
    """``avoid-sim fly --world`` reads the file before it starts anything: exit 2, one line."""
    import subprocess
    import sys

    data = _docs_example()
    data["moving"][0]["path"]["speed"] = -1
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    done = subprocess.run(
        [sys.executable, "-m", "flightsim", "fly", "--world", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=REPO,
    )
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "moving[0].path.speed" in lines[0] and "Traceback" not in done.stderr


# -- motion ----------------------------------------------------------------------------------


def _walker(points, speed, loop=False) -> MovingObstacle:
    return MovingObstacle("cylinder", PathMotion(tuple(points), speed, loop), 1.8, radius=0.25)


def test_a_path_goes_out_and_back_at_its_speed() -> None:
    m = _walker([(0.0, 0.0), (4.0, 0.0)], 2.0)
    xy = m.positions(np.array([0.0, 1.0, 2.0, 3.0, 4.0, 5.0]))
    np.testing.assert_allclose(xy[:, 0], [0.0, 2.0, 4.0, 2.0, 0.0, 2.0])
    np.testing.assert_allclose(xy[:, 1], 0.0)


def test_a_loop_goes_round() -> None:
    m = _walker([(0.0, 0.0), (2.0, 0.0), (2.0, 2.0)], 1.0, loop=True)
    total = 4.0 + np.hypot(2.0, 2.0)
    np.testing.assert_allclose(m.positions([0.0, 3.0, total, total + 1.0]), [[0, 0], [2, 1], [0, 0], [1, 0]])


def test_a_random_walk_is_seeded_bounded_and_keeps_its_speed() -> None:
    walk = RandomWalk(((-2.0, -1.0), (3.0, 2.0)), 1.5, seed=4)
    m = MovingObstacle("cylinder", walk, 0.3, radius=0.4, base=1.35)
    t = np.arange(0.0, 300.0, 0.05)
    xy = m.positions(t)
    assert np.all(xy >= np.array([-2.0, -1.0])) and np.all(xy <= np.array([3.0, 2.0]))
    steps = np.hypot(*np.diff(xy, axis=0).T)
    assert steps.max() <= 1.5 * 0.05 + 1e-9
    assert steps.mean() > 0.9 * 1.5 * 0.05  # corners cut a little, nothing more
    np.testing.assert_array_equal(MovingObstacle("cylinder", walk, 0.3, radius=0.4).positions(t), xy)
    other = MovingObstacle("cylinder", RandomWalk(walk.bounds, 1.5, seed=5), 0.3, radius=0.4)
    assert not np.allclose(other.positions(t), xy)


def test_clearance_follows_the_shape_in_time_and_height() -> None:
    drone = MovingObstacle("cylinder", PathMotion(((0.0, 0.0), (4.0, 0.0)), 1.0), 0.3, radius=0.5, base=1.35)
    p = np.array([[2.0, 0.0, 1.5], [2.0, 0.0, 0.5]])
    np.testing.assert_allclose(drone.clearance(p, 0.0), [1.5, np.hypot(1.5, 0.85)])
    np.testing.assert_allclose(drone.clearance(p, 2.0), [-0.15, 0.85])
    box = MovingObstacle("box", PathMotion(((0.0, 0.0), (0.0, 4.0)), 1.0), 2.0, size=(1.2, 0.8), yaw_deg=90.0)
    np.testing.assert_allclose(box.clearance(np.array([[1.0, 1.0, 1.0]]), 1.0), [0.6])


def test_world_clearance_at_a_time() -> None:
    world = World(
        "w", (10.0, 10.0), 3.0, (), (-3.0, 0.0, 1.5), 0.0, moving=(_walker([(0, -3), (0, 3)], 1.0),)
    )
    assert world.clearance_at((0.0, 0.0, 1.5), 3.0) == pytest.approx(-0.25)
    assert world.clearance_at((0.0, 0.0, 1.5), 0.0) == pytest.approx(2.75)
    static = World("w", (10.0, 10.0), 3.0, (), (-3.0, 0.0, 1.5), 0.0)
    assert static.clearance_at((1.0, 2.0, 1.5), 7.0) == static.clearance((1.0, 2.0, 1.5))


# -- families ----------------------------------------------------------------------------------

# world_to_dict and the shortest path of validation seeds 500000-500001 at difficulties 0.2 and 0.9,
# generated by the nine families before moving obstacles existed: adding them changed none
STATIC_FAMILY_HASHES = {
    "rooms": "ec2fc8d4d50294c6",
    "forest": "9ea4736ca1420bcd",
    "office": "d66c3e34d30f9044",
    "warehouse": "91e573cb88d29260",
    "pillars": "1a2299b0b3e07c6a",
    "staggered": "290c6302f86ac1fd",
    "traps": "1007fdb61137ef16",
    "gaps": "475ecafa7a04255e",
    "mixed": "bd65a37bed1c5b9a",
}


@pytest.mark.parametrize("family", FAMILIES)
def test_the_static_families_generate_what_they_did(family: str) -> None:
    h = hashlib.sha256()
    for seed in (500000, 500001):
        for d in (0.2, 0.9):
            world = generate_family_world(family, seed, d)
            assert not world.moving
            h.update(json.dumps(world_to_dict(world), sort_keys=True).encode())
            h.update(repr(world.shortest_path_m).encode())
    assert h.hexdigest()[:16] == STATIC_FAMILY_HASHES[family]


def test_the_dynamic_families_are_named_and_not_default() -> None:
    assert DYNAMIC_FAMILIES == ("warehouse-dynamic", "office-dynamic", "forest-dynamic", "rooms-dynamic")
    assert not set(DYNAMIC_FAMILIES) & set(FAMILIES)
    assert ALL_FAMILIES == FAMILIES + DYNAMIC_FAMILIES


SPEEDS = {"pedestrian": (0.5, 1.5), "drone": (1.0, 3.0), "forklift": (1.0, 2.0)}


@pytest.mark.parametrize("family", DYNAMIC_FAMILIES)
@pytest.mark.parametrize("difficulty", [0.0, 1.0])
def test_dynamic_worlds_are_the_static_world_with_feasible_motion(family: str, difficulty: float) -> None:
    base = family.removesuffix("-dynamic")
    mix = DYNAMIC_MIXES[base]
    for seed in (500000, 500001, 500002):
        world = generate_family_world(family, seed, difficulty)
        static = generate_family_world(base, seed, difficulty)
        assert world.name == f"{family}-{seed}-d{difficulty:.2f}"
        assert world.obstacles == static.obstacles and world.waypoints == static.waypoints
        assert world.start_position == static.start_position and world.start_yaw_deg == static.start_yaw_deg
        kinds = [m.kind for m in world.moving]
        i = int(difficulty)
        assert kinds.count("pedestrian") == mix.pedestrians[i]
        assert kinds.count("drone") == mix.drones[i] and kinds.count("forklift") == mix.forklifts[i]
        for m in world.moving:
            lo, hi = SPEEDS[m.kind]
            assert lo <= m.speed <= hi, m
            if m.kind == "pedestrian":
                assert (m.radius, m.height, m.base) == (0.25, 1.8, 0.0)
            elif m.kind == "drone":
                assert 0.3 <= m.radius <= 0.5 and m.base < 1.5 < m.base + m.height
            else:
                assert m.shape == "box"
        horizon = 10.0 + 2.0 * world.shortest_path_m
        assert wait_and_go_time(world, 0.25, horizon) is not None
        assert world == generate_family_world(family, seed, difficulty)


def test_head_on_and_crossing_drones_fly_the_first_leg() -> None:
    """Some rooms-dynamic drone flies along the start's first leg (head-on) in the open rooms."""
    found = 0
    for seed in range(500000, 500006):
        world = generate_family_world("rooms-dynamic", seed, 0.0)
        start = np.asarray(world.start_position[:2])
        for m in world.moving:
            if m.kind == "drone" and isinstance(m.motion, PathMotion):
                a, b = np.asarray(m.motion.points)
                (ux, uy), (vx, vy) = b - a, start - a
                gap = abs(ux * vy - uy * vx) / np.hypot(ux, uy)
                found += gap < 0.05  # the start on its line: it comes straight at the vehicle
    assert found >= 2


# -- space-time feasibility ----------------------------------------------------------------------


def _corridor(moving: tuple[MovingObstacle, ...]) -> World:
    """A 10 m corridor 2 m wide: from one end to the other, nothing to step aside into."""
    return World("corridor", (10.0, 2.0), 3.0, (), (-4.0, 0.0, 1.5), 0.0, ((4.0, 0.0, 1.5),), moving=moving)


def test_space_time_search_waits_for_a_walker_to_clear_the_way() -> None:
    free = wait_and_go_time(_corridor(()), 0.25, 60.0)
    assert free == pytest.approx(8.0 / 1.0, abs=0.5)  # straight at 1 m/s (cells along the axis)
    crossing = MovingObstacle("box", PathMotion(((0.0, -6.0), (0.0, 6.0)), 1.5), 2.0, size=(0.6, 2.0))
    # a door across the corridor, sliding out of it and back: blocking it from 2.2 s to 5.8 s, …
    waited = wait_and_go_time(_corridor((crossing,)), 0.25, 60.0)
    assert waited is not None and waited > free + 0.5


def test_space_time_search_rejects_a_corridor_blocked_for_good() -> None:
    """A forklift pacing the whole corridor head-on: no way past it, waiting or not."""
    pacing = MovingObstacle("box", PathMotion(((-1.5, 0.0), (2.5, 0.0)), 1.0), 2.0, size=(1.2, 1.6))
    assert wait_and_go_time(_corridor((pacing,)), 0.25, 60.0) is None
    assert wait_and_go_time(_corridor(()), 0.25, 60.0) is not None


def _corridor_schedule(world: World, horizon: float) -> tuple[np.ndarray, np.ndarray, tuple[int, int], float]:
    """The schedule from the corridor's start to its waypoint (0.2 m cells, 0.2 s steps), the free
    cells it searched, the goal's cell, and the x of the grid's first column of cells (metres)."""
    grid = clearance_grid(world, 1.5, 0.2, 1.0)
    static_free = grid.clearance >= 0.25 + 0.2 * np.sqrt(2.0) / 2.0
    times = np.arange(0.0, horizon, 0.2)
    needed = 0.25 + sampling_margin(world, 0.2, 0.2)
    free = free_cells(world, cell_centres(grid, 1.5), times, needed, static_free)
    start, goal = grid.cell(-4.0, 0.0), grid.cell(4.0, 0.0)
    to_goal = np.abs(np.arange(free.shape[1]) - goal[0])[:, None] + np.zeros(free.shape[2])
    return schedule(free, start, goal, to_goal), free, goal, grid.origin[0]


def test_schedule_waits_for_the_door_and_every_step_is_free_and_a_neighbour() -> None:
    """The sliding door of the corridor: the schedule reaches the waypoint later than the empty
    corridor's, every step moves at most one cell, and every cell after the start is free then."""
    empty, _, goal, _ = _corridor_schedule(_corridor(()), 30.0)
    assert tuple(empty[-1]) == goal and len(empty) == pytest.approx(41, abs=2)  # 8 m at 1 m/s
    door = MovingObstacle("box", PathMotion(((0.0, -6.0), (0.0, 6.0)), 1.5), 2.0, size=(0.6, 2.0))
    way, free, goal, _ = _corridor_schedule(_corridor((door,)), 30.0)
    assert tuple(way[-1]) == goal and len(way) > len(empty) + 2
    assert np.abs(np.diff(way, axis=0)).max() <= 1
    assert all(free[k, i, j] for k, (i, j) in enumerate(way) if k > 0)


def test_schedule_ends_where_the_movers_let_it_get_nearest() -> None:
    """The forklift pacing the corridor for good: no way to the waypoint, so the schedule ends in
    the reachable cell nearest it: right behind the forklift, which it follows into its beat."""
    pacing = MovingObstacle("box", PathMotion(((-1.5, 0.0), (2.5, 0.0)), 1.0), 2.0, size=(1.2, 1.6))
    way, free, goal, x0 = _corridor_schedule(_corridor((pacing,)), 20.0)
    assert tuple(way[-1]) != goal
    assert all(free[k, i, j] for k, (i, j) in enumerate(way) if k > 0)
    end_x = x0 + (way[-1][0] + 0.5) * 0.2
    # a cell keeps the radius and the sampling margin (0.68 m) from the forklift's back (0.6 m)
    behind = float(pacing.positions(0.2 * (len(way) - 1))[0, 0]) - 0.6 - 0.68
    assert behind - 0.4 < end_x <= behind
    assert all(free[k, i, j] for k, (i, j) in enumerate(way) if k > 0)


def test_avoid_sim_worlds_saves_dynamic_worlds_that_load_back(tmp_path, capsys) -> None:
    from flightsim.__main__ import main

    assert main(["worlds", "--save", str(tmp_path), "--family", "rooms-dynamic", "--seed", "500020"]) == 0
    assert "moving" in capsys.readouterr().out
    saved = load_world(tmp_path / "rooms-dynamic-500020-d0.50.json")
    assert saved == generate_family_world("rooms-dynamic", 500020, 0.5) and saved.moving


def test_right_of_movers_marks_the_near_cells_on_a_moving_movers_right_only() -> None:
    """A walker heading east from the room's middle at 1 m/s: 1 m south of it (its right) is
    marked, 1 m north and 4 m south are not; a second later the marks have moved east with it. A
    walker standing still has no side."""
    walking = MovingObstacle("cylinder", PathMotion(((0.0, 0.0), (8.0, 0.0)), 1.0), 1.8, radius=0.25)
    standing = MovingObstacle("cylinder", PathMotion(((0.0, 0.0), (0.0, 0.0)), 1.0), 1.8, radius=0.25)

    def room(walker: MovingObstacle) -> World:
        start, waypoint = (-4.0, 0.0, 1.5), (4.0, 0.0, 1.5)
        return World("open", (20.0, 12.0), 3.0, (), start, 0.0, (waypoint,), moving=(walker,))

    cells = np.array([[0.0, -1.0], [0.0, 1.0], [0.0, -4.0], [-2.5, -1.0], [3.0, -1.0]])
    cells = np.column_stack([cells, np.full(len(cells), 1.5)])
    right = right_of_movers(room(walking), cells, np.array([0.0, 1.0]), within=3.0)
    assert right.tolist() == [[True, False, False, True, False], [True, False, False, False, True]]
    assert not right_of_movers(room(standing), cells, np.array([0.0, 1.0]), within=3.0).any()


def test_constant_velocity_carries_a_mover_on_past_where_it_turns_back() -> None:
    """A walker pacing from x = 0 to 2 m at 1 m/s, read at 1 s: its track turns back at 2 s; carried
    on at its velocity then, it is at x = 3 m at 3 s. The free cells and its right side follow that
    straight line; a clearance growing 0.1 m/s from now, up to its cap, frees fewer cells later."""
    walker = MovingObstacle("cylinder", PathMotion(((0.0, 0.0), (2.0, 0.0)), 1.0), 1.8, radius=0.25)
    world = World("open", (20.0, 12.0), 3.0, (), (-4.0, 0.0, 1.5), 0.0, ((4.0, 0.0, 1.5),), moving=(walker,))
    times = np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(mover_track(walker, times), [[1.0, 0.0], [2.0, 0.0], [1.0, 0.0]])
    np.testing.assert_allclose(
        mover_track(walker, times, constant_velocity=True), [[1, 0], [2, 0], [3, 0]], atol=1e-9
    )
    cells = np.array([[3.0, 0.0, 1.5], [3.0, -1.0, 1.5], [1.0, 0.6, 1.5]])
    static_free = np.ones((3, 1), dtype=bool)
    true_free = free_cells(world, cells, times, 0.3, static_free)[:, :, 0]
    carried_free = free_cells(world, cells, times, 0.3, static_free, constant_velocity=True)[:, :, 0]
    assert true_free[2, 0] and not carried_free[2, 0]  # at 3 s: the walker is back at 1 m, or at 3 m
    # (1, 0.6) at 3 s, the walker back at (1, 0): 0.35 m from it, free; with 0.2 m of growth, not
    assert true_free[2, 2]
    assert not free_cells(world, cells, times, 0.3, static_free, growth=0.1, growth_cap=1.0)[2, 2, 0]
    assert free_cells(world, cells, times, 0.3, static_free, growth=0.1, growth_cap=0.04)[2, 2, 0]
    right_true = right_of_movers(world, cells, times, within=3.0)
    right_carried = right_of_movers(world, cells, times, within=3.0, constant_velocity=True)
    assert not right_true[2, 1] and right_carried[2, 1]  # (3, -1) at 3 s: its right only heading east
