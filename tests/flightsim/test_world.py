"""World files (every loader error of shared/worlds/README.md), geometry and the generator."""

from __future__ import annotations

import copy
import json
import math
from importlib.resources import files
from pathlib import Path

import numpy as np
import pytest

from companion.common.errors import UserError
from flightsim.worlds.world import (
    Box,
    Cylinder,
    World,
    clearances,
    footprint_radius,
    generate_world,
    load_world,
    save_world,
    world_from_dict,
    world_to_dict,
)

EXAMPLE = {
    "name": "two-pillars",
    "room": {"size": [12.0, 8.0], "height": 3.0},
    "obstacles": [
        {"type": "box", "center": [2.0, 1.0, 1.5], "size": [1.0, 0.6, 3.0], "yaw_deg": 30.0},
        {"type": "cylinder", "center": [4.0, -1.5], "radius": 0.3, "height": 3.0},
    ],
    "start": {"position": [-4.5, 0.0, 1.5], "yaw_deg": 0.0},
}


def _write(tmp_path: Path, data: object) -> Path:
    path = tmp_path / "world.json"
    path.write_text(data if isinstance(data, str) else json.dumps(data))
    return path


def _load_modified(tmp_path: Path, edit) -> World:
    data = copy.deepcopy(EXAMPLE)
    edit(data)
    return load_world(_write(tmp_path, data))


# -- the shipped examples ----------------------------------------------------------------------


@pytest.mark.parametrize("name", ["two-pillars.json", "slalom.json"])
def test_shipped_examples_load(name: str) -> None:
    world = load_world(Path(str(files("flightsim") / "worlds" / name)))
    assert world.name == name.removesuffix(".json")
    assert world.clearance(world.start_position) > 0.25


def test_example_fields(tmp_path: Path) -> None:
    world = load_world(_write(tmp_path, EXAMPLE))
    assert world.room_size == (12.0, 8.0) and world.room_height == 3.0
    assert world.obstacles[0] == Box((2.0, 1.0, 1.5), (1.0, 0.6, 3.0), 30.0)
    assert world.obstacles[1] == Cylinder((4.0, -1.5), 0.3, 3.0)
    assert world.start_position == (-4.5, 0.0, 1.5) and world.start_yaw_deg == 0.0


def test_box_yaw_is_optional(tmp_path: Path) -> None:
    world = _load_modified(tmp_path, lambda d: d["obstacles"][0].pop("yaw_deg"))
    assert world.obstacles[0].yaw_deg == 0.0


def test_round_trip(tmp_path: Path) -> None:
    world = world_from_dict(EXAMPLE)
    assert world_from_dict(world_to_dict(world)) == world
    generated = generate_world(7, 0.8)
    save_world(generated, tmp_path / "g.json")
    assert load_world(tmp_path / "g.json") == generated


# -- every error the schema lists ------------------------------------------------------------


@pytest.mark.parametrize(
    ("edit", "field", "words"),
    [
        (lambda d: d.pop("name"), "name", "missing"),
        (lambda d: d.pop("room"), "room", "missing"),
        (lambda d: d["room"].pop("height"), "room.height", "missing"),
        (lambda d: d.pop("start"), "start", "missing"),
        (lambda d: d["start"].pop("position"), "start.position", "missing"),
        (lambda d: d["start"].pop("yaw_deg"), "start.yaw_deg", "missing"),
        (lambda d: d["obstacles"][1].pop("radius"), "obstacles[1].radius", "missing"),
        (lambda d: d["obstacles"][0].pop("type"), "obstacles[0].type", "missing"),
        (lambda d: d.update(colour="red"), "colour", "unknown"),
        (lambda d: d["room"].update(floor=1), "room.floor", "unknown"),
        (lambda d: d["obstacles"][0].update(radius=1.0), "obstacles[0].radius", "unknown"),
        (lambda d: d["obstacles"][1].update(type="cone"), "obstacles[1].type", "'box' or 'cylinder'"),
        (lambda d: d.update(name=3), "name", "string"),
        (lambda d: d["room"].update(size="12x8"), "room.size", "list"),
        (lambda d: d["room"].update(size=[12.0]), "room.size", "2 numbers"),
        (lambda d: d["room"].update(height="3"), "room.height", "number"),
        (lambda d: d["obstacles"][1].update(radius=True), "obstacles[1].radius", "number"),
        (lambda d: d["obstacles"][0].update(center=[1, "a", 2]), "obstacles[0].center[1]", "number"),
        (lambda d: d.update(obstacles={}), "obstacles", "list"),
        (lambda d: d["obstacles"].append(5), "obstacles[2]", "object"),
        (lambda d: d.update(start=[0, 0, 1]), "start", "object"),
        (lambda d: d["room"].update(size=[12.0, 0.0]), "room.size[1]", "positive"),
        (lambda d: d["room"].update(height=-3.0), "room.height", "positive"),
        (lambda d: d["obstacles"][0].update(size=[1.0, -0.6, 3.0]), "obstacles[0].size[1]", "positive"),
        (lambda d: d["obstacles"][1].update(radius=0.0), "obstacles[1].radius", "positive"),
        (lambda d: d["obstacles"][1].update(height=0), "obstacles[1].height", "positive"),
        (lambda d: d["start"].update(position=[7.0, 0.0, 1.5]), "start.position", "outside the room"),
        (lambda d: d["start"].update(position=[0.0, 0.0, 3.5]), "start.position", "outside the room"),
        (lambda d: d["start"].update(position=[-5.9, 0.0, 1.5]), "start.position", "wall"),
        (lambda d: d["start"].update(position=[4.0, -1.5, 1.5]), "start.position", "inside obstacles[1]"),
        (lambda d: d["start"].update(position=[2.0, 1.0, 1.0]), "start.position", "inside obstacles[0]"),
        (lambda d: d["start"].update(position=[4.45, -1.5, 1.5]), "start.position", "closer than 0.25 m"),
    ],
)
def test_bad_field_is_named(tmp_path: Path, edit, field: str, words: str) -> None:
    with pytest.raises(UserError) as info:
        _load_modified(tmp_path, edit)
    message = str(info.value)
    assert f": {field}: " in message, message
    assert words in message, message
    assert "\n" not in message


def test_start_clear_of_short_obstacle_is_fine(tmp_path: Path) -> None:
    """Above a low box the start is clear: obstacles count only within their height."""
    low_box = {"type": "box", "center": [-4.5, 0, 0.5], "size": [1, 1, 1]}
    world = _load_modified(tmp_path, lambda d: d["obstacles"].append(low_box))
    assert world.clearance(world.start_position) == pytest.approx(0.5)


def test_empty_file(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="empty"):
        load_world(_write(tmp_path, "  \n"))


def test_invalid_json(tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"invalid JSON at line 1 column \d+"):
        load_world(_write(tmp_path, '{"name": "x",'))


def test_not_an_object(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="expected an object"):
        load_world(_write(tmp_path, "[1, 2]"))


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(UserError, match="not found"):
        load_world(tmp_path / "nope.json")


# -- geometry --------------------------------------------------------------------------------


def test_clearance_walls_and_obstacles() -> None:
    world = world_from_dict(EXAMPLE)
    assert world.clearance((-4.5, 0.0, 1.5)) == pytest.approx(1.5)  # west wall at x = -6
    assert world.clearance((0.0, 3.5, 1.5)) == pytest.approx(0.5)  # north wall at y = 4
    assert world.clearance((4.0, -1.0, 1.5)) == pytest.approx(0.2)  # cylinder r 0.3 at (4, -1.5)
    assert world.clearance((4.0, -1.5, 1.5)) < 0.0  # inside the cylinder
    # rotated box: along its local +x axis (30 deg) the face is 0.5 m from the centre
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    assert world.clearance((2.0 + 0.9 * c, 1.0 + 0.9 * s, 1.5)) == pytest.approx(0.4)
    # above the wall top the distance is to the wall's edge
    assert world.clearance((5.7, 0.0, 3.4)) == pytest.approx(0.5)


def test_vectorised_clearance_matches_scalar() -> None:
    world = generate_world(3, 1.0)
    pts = np.random.default_rng(0).uniform([-7, -5, 0], [7, 5, 3], size=(50, 3))
    many = clearances(world, pts)
    assert many == pytest.approx([world.clearance(p) for p in pts])


# -- generator -------------------------------------------------------------------------------


def test_generator_is_deterministic() -> None:
    assert generate_world(42, 0.3) == generate_world(42, 0.3)
    assert generate_world(42, 0.3) != generate_world(43, 0.3)


@pytest.mark.parametrize(("difficulty", "count"), [(0.0, 3), (0.5, 6), (1.0, 10)])
def test_generator_difficulty_scales_obstacles_and_room(difficulty: float, count: int) -> None:
    for seed in range(20):
        world = generate_world(seed, difficulty)
        assert len(world.obstacles) == count
        assert min(world.room_size) >= 10.0 and max(world.room_size) <= 24.0


def test_generated_start_is_clear_and_faces_free_space() -> None:
    for seed in range(30):
        for difficulty in (0.0, 1.0):
            world = generate_world(seed, difficulty)
            assert world.clearance(world.start_position) >= 1.5
            # at least 2 m of free flight straight ahead of the start heading
            yaw = math.radians(world.start_yaw_deg)
            ahead = np.asarray(world.start_position) + np.outer(
                np.linspace(0, 2.0, 21), [math.cos(yaw), math.sin(yaw), 0.0]
            )
            assert clearances(world, ahead).min() > 0.25


def test_generated_gaps_are_flyable() -> None:
    """At difficulty 1 every footprint keeps >= 1.2 m to every other one and to the walls."""
    for seed in range(30):
        world = generate_world(seed, 1.0)
        hx, hy = world.room_size[0] / 2, world.room_size[1] / 2
        feet = [(np.asarray(o.center[:2]), footprint_radius(o)) for o in world.obstacles]
        for i, (c, r) in enumerate(feet):
            assert min(hx - abs(c[0]), hy - abs(c[1])) - r >= 1.2 - 1e-6
            for c2, r2 in feet[i + 1 :]:
                assert np.hypot(*(c - c2)) - r - r2 >= 1.2 - 1e-3  # centres are rounded to 1 mm


def test_generator_rejects_bad_difficulty() -> None:
    with pytest.raises(ValueError, match="difficulty"):
        generate_world(1, 1.5)


def test_narrow_rooms_keep_gaps_and_a_clear_start() -> None:
    for seed in range(20):
        world = generate_world(seed, 1.0, room_width=6.0)
        assert world.room_size[1] == 6.0
        assert 1 <= len(world.obstacles) <= 10
        assert world.clearance(world.start_position) >= 1.5
        hx, hy = world.room_size[0] / 2, world.room_size[1] / 2
        for o in world.obstacles:
            c = np.asarray(o.center[:2])
            assert min(hx - abs(c[0]), hy - abs(c[1])) - footprint_radius(o) >= 1.2 - 1e-6
    with pytest.raises(ValueError, match="room_width"):
        generate_world(1, 0.5, room_width=4.0)


# -- waypoints -------------------------------------------------------------------------------

WAYPOINTS = [[5.0, 0.5, 1.5], [-3.0, 3.0, 1.5]]


def test_waypoints_load_in_order(tmp_path: Path) -> None:
    world = _load_modified(tmp_path, lambda d: d.update(waypoints=WAYPOINTS))
    assert world.waypoints == ((5.0, 0.5, 1.5), (-3.0, 3.0, 1.5))
    assert load_world(_write(tmp_path, EXAMPLE)).waypoints == ()  # optional: an exploration world


@pytest.mark.parametrize(
    ("waypoints", "field", "words"),
    [
        ({"x": 1}, "waypoints", "list"),
        ([[5.0, 0.5, 1.5], "a"], "waypoints[1]", "list of 3 numbers"),
        ([[5.0, 0.5]], "waypoints[0]", "3 numbers"),
        ([[5.0, 0.5, 1.5], [1.0, None, 1.5]], "waypoints[1][1]", "number"),
        ([[5.0, 0.5, 1.5], [1.0, 0.0, math.inf]], "waypoints[1][2]", "finite"),
        ([[5.0, 0.5, 1.5], [7.0, 0.0, 1.5]], "waypoints[1]", "outside the room"),
        ([[5.0, 0.5, 0.0]], "waypoints[0]", "outside the room"),
        ([[5.0, 0.5, 1.5], [0.0, 0.0, 3.2]], "waypoints[1]", "outside the room"),
        ([[5.0, 0.5, 1.5], [0.0, 3.9, 1.5]], "waypoints[1]", "closer than 0.25 m to a wall"),
        ([[4.0, -1.5, 1.5]], "waypoints[0]", "inside obstacles[1]"),
        ([[5.0, 0.5, 1.5], [2.0, 1.0, 1.5]], "waypoints[1]", "inside obstacles[0]"),
        ([[5.0, 0.5, 1.5], [4.0, -1.0, 1.5]], "waypoints[1]", "closer than 0.25 m to obstacles[1]"),
    ],
)
def test_bad_waypoint_is_named_with_its_index(tmp_path: Path, waypoints, field: str, words: str) -> None:
    with pytest.raises(UserError) as info:
        _load_modified(tmp_path, lambda d: d.update(waypoints=waypoints))
    message = str(info.value)
    assert f": {field}: " in message, message
    assert words in message, message
    assert "\n" not in message


def test_waypoint_clearance_uses_the_callers_radius(tmp_path: Path) -> None:
    data = copy.deepcopy(EXAMPLE)
    data["waypoints"] = [[4.0, -0.9, 1.5]]  # 0.3 m from the cylinder's surface
    assert load_world(_write(tmp_path, data)).waypoints == ((4.0, -0.9, 1.5),)
    with pytest.raises(UserError, match=r": waypoints\[0\]: .*closer than 0.4 m to obstacles\[1\]"):
        load_world(_write(tmp_path, data), vehicle_radius=0.4)


def test_waypoint_over_a_low_obstacle_is_clear(tmp_path: Path) -> None:
    """Clear means by the 3-D distance: a waypoint 0.8 m above a low box is fine."""
    low_box = {"type": "box", "center": [0.0, -2.0, 0.35], "size": [2.0, 2.0, 0.7]}
    world = _load_modified(
        tmp_path, lambda d: (d["obstacles"].append(low_box), d.update(waypoints=[[0, -2, 1.5]]))
    )
    assert world.clearance(world.waypoints[0]) == pytest.approx(0.8)


def test_waypoints_round_trip(tmp_path: Path) -> None:
    data = copy.deepcopy(EXAMPLE)
    data["waypoints"] = WAYPOINTS
    world = world_from_dict(data)
    assert world_to_dict(world)["waypoints"] == WAYPOINTS
    save_world(world, tmp_path / "w.json")
    assert load_world(tmp_path / "w.json") == world
    assert "waypoints" not in world_to_dict(world_from_dict(EXAMPLE))  # exploration files keep the old schema


def test_shortest_path_is_derived_not_identity() -> None:
    world = world_from_dict(EXAMPLE)
    planned = World(*(getattr(world, f) for f in ("name", "room_size", "room_height", "obstacles")),
                    world.start_position, world.start_yaw_deg, shortest_path_m=12.5)  # fmt: skip
    assert planned == world and planned.shortest_path_m == 12.5 and world.shortest_path_m is None


@pytest.mark.parametrize("name", ["two-pillars.json", "slalom.json"])
def test_shipped_examples_have_feasible_waypoints(name: str) -> None:
    from flightsim.worlds.planner import shortest_safe_path

    world = load_world(Path(str(files("flightsim") / "worlds" / name)))
    assert 1 <= len(world.waypoints) <= 4
    assert shortest_safe_path(world, vehicle_radius=0.25) is not None
