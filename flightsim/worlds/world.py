"""Worlds: a walled room with boxes and cylinders, loaded from JSON or generated from a seed.

The JSON schema is the one in ``shared/worlds/README.md``: metres and degrees, x/y horizontal,
z up, yaw counter-clockwise from +x, room centred on the origin with 0.1 m thick walls whose inner
faces lie on x = ±size[0]/2 and y = ±size[1]/2, open above. Everything here is pure (no I/O but
:func:`load_world`), so the ray caster, the environment and the renderers share one geometry.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit

from companion.common.errors import UserError
from companion.common.userfile import load_user_file
from flightsim.worlds.moving import MovingObstacle, PathMotion, RandomWalk

WALL_THICKNESS = 0.1
DEFAULT_VEHICLE_RADIUS = 0.25


@dataclass(frozen=True)
class Box:
    """A box rotated about the vertical axis.

    :param center: box centre (x, y, z), metres
    :param size: full extents (sx, sy, sz), metres
    :param yaw_deg: rotation about z, degrees counter-clockwise
    """

    center: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw_deg: float = 0.0


@dataclass(frozen=True)
class Cylinder:
    """A vertical cylinder standing on the floor.

    :param center: axis position (x, y), metres
    :param radius: metres
    :param height: metres above the floor
    """

    center: tuple[float, float]
    radius: float
    height: float


Obstacle = Box | Cylinder


@dataclass(frozen=True)
class World:
    """A room, its obstacles, the vehicle's start pose and the waypoints to fly through.

    :param name: short identifier (file stem or ``gen-<seed>-d<difficulty>``)
    :param room_size: inner extents (sx, sy) of the room, metres
    :param room_height: wall height, metres
    :param obstacles: boxes and cylinders
    :param start_position: initial position (x, y, z); z is the flight altitude
    :param start_yaw_deg: initial heading, degrees counter-clockwise from +x
    :param waypoints: goals (x, y, z) visited in order; empty for an exploration world (fly on,
        avoid). Reaching one is decided by whoever flies the world (its acceptance radius).
    :param shortest_path_m: length of the shortest safe path from the start through every
        waypoint in order, as :func:`flightsim.worlds.planner.shortest_safe_path` found it for the radius
        the world was generated for. Set by the family generators; None for a world read from a
        file or without waypoints (plan it on demand). Not part of equality: it is derived.
    :param moving: obstacles that move (:mod:`flightsim.worlds.moving`); empty: a static world,
        which every part of the simulator treats exactly as before moving obstacles existed
    """

    name: str
    room_size: tuple[float, float]
    room_height: float
    obstacles: tuple[Obstacle, ...]
    start_position: tuple[float, float, float]
    start_yaw_deg: float
    waypoints: tuple[tuple[float, float, float], ...] = ()
    shortest_path_m: float | None = field(default=None, compare=False)
    moving: tuple[MovingObstacle, ...] = ()

    def clearance_at(self, position: Sequence[float] | np.ndarray, time: float) -> float:
        """:meth:`clearance` with the moving obstacles where they are at ``time`` (seconds since the
        start); a static world's is :meth:`clearance` itself."""
        static = self.clearance(position)
        if not self.moving:
            return static
        p = np.asarray(position, dtype=np.float64)[:3].reshape(1, 3)
        return min(static, min(float(m.clearance(p, time)[0]) for m in self.moving))

    def clearance(self, position: Sequence[float] | np.ndarray) -> float:
        """Distance from a point to the nearest wall or obstacle surface, metres (negative inside).

        Walls count by their horizontal distance while the point is below the wall top; obstacles
        by the true 3-D distance to the solid (so the horizontal distance while within their
        height). The floor does not count: the vehicle holds its altitude, and collision is
        ``clearance < vehicle radius``. Compiled (the environment calls this every step);
        :func:`clearances` is the vectorised numpy twin that the tests hold it to.
        """
        room, boxes, cylinders = self.packed
        x, y, z = float(position[0]), float(position[1]), float(position[2])
        return float(_clearance_kernel(x, y, z, room, boxes, cylinders))

    @cached_property
    def packed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The geometry as flat arrays for compiled kernels (computed once per world).

        :return: ``room`` (half x, half y, height); ``boxes`` ``(B, 8)``: centre xyz, half sizes,
            cos yaw, sin yaw; ``cylinders`` ``(C, 4)``: centre xy, radius, height
        """
        room = np.array([self.room_size[0] / 2.0, self.room_size[1] / 2.0, self.room_height])
        boxes = [
            (*o.center, *(v / 2.0 for v in o.size), *_cos_sin(o.yaw_deg))
            for o in self.obstacles
            if isinstance(o, Box)
        ]
        cylinders = [(*o.center, o.radius, o.height) for o in self.obstacles if not isinstance(o, Box)]
        return (
            room,
            np.array(boxes, dtype=np.float64).reshape(-1, 8),
            np.array(cylinders, dtype=np.float64).reshape(-1, 4),
        )


def _cos_sin(deg: float) -> tuple[float, float]:
    return math.cos(math.radians(deg)), math.sin(math.radians(deg))


@njit(cache=True)
def _clearance_kernel(x, y, z, room, boxes, cylinders):  # pragma: no cover - compiled
    best = wall_distance(x, y, z, room)
    for k in range(boxes.shape[0]):
        best = min(best, box_distance(x, y, z, boxes[k]))
    for k in range(cylinders.shape[0]):
        best = min(best, cylinder_distance(x, y, z, cylinders[k]))
    return best


@njit(cache=True, inline="always")
def wall_distance(x, y, z, room):  # pragma: no cover - compiled
    """Compiled: distance to the walls of a :attr:`World.packed` ``room`` (shared with the planner)."""
    best = min(room[0] - abs(x), room[1] - abs(y))
    if best > 0.0 and z > room[2]:
        best = math.hypot(best, z - room[2])
    return best


@njit(cache=True, inline="always")
def box_distance(x, y, z, b):  # pragma: no cover - compiled
    """Compiled: signed distance to one packed box row (centre, half sizes, cos, sin)."""
    dx, dy = x - b[0], y - b[1]
    qx = abs(b[6] * dx + b[7] * dy) - b[3]
    qy = abs(-b[7] * dx + b[6] * dy) - b[4]
    qz = abs(z - b[2]) - b[5]
    outside = math.sqrt(max(qx, 0.0) ** 2 + max(qy, 0.0) ** 2 + max(qz, 0.0) ** 2)
    return outside + min(max(qx, qy, qz), 0.0)


@njit(cache=True, inline="always")
def cylinder_distance(x, y, z, c):  # pragma: no cover - compiled
    """Compiled: signed distance to one packed cylinder row (centre xy, radius, height)."""
    qr = math.hypot(x - c[0], y - c[1]) - c[2]
    qz = abs(z - c[3] / 2.0) - c[3] / 2.0
    outside = math.hypot(max(qr, 0.0), max(qz, 0.0))
    return outside + min(max(qr, qz), 0.0)


# ----------------------------------------------------------------------------------------------
# geometry


def _wall_clearance(world: World, p: np.ndarray) -> np.ndarray:
    hx, hy = world.room_size[0] / 2.0, world.room_size[1] / 2.0
    dh = np.minimum(hx - np.abs(p[:, 0]), hy - np.abs(p[:, 1]))
    above = p[:, 2] - world.room_height
    over = (above > 0.0) & (dh > 0.0)
    return np.where(over, np.hypot(dh, np.maximum(above, 0.0)), dh)


def _box_sdf(box: Box, p: np.ndarray) -> np.ndarray:
    c, s = math.cos(math.radians(box.yaw_deg)), math.sin(math.radians(box.yaw_deg))
    d = p - np.asarray(box.center, dtype=np.float64)
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
    q = np.abs(local) - np.asarray(box.size, dtype=np.float64) / 2.0
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    inside = np.minimum(q.max(axis=1), 0.0)
    return outside + inside


def _cylinder_sdf(cyl: Cylinder, p: np.ndarray) -> np.ndarray:
    dr = np.hypot(p[:, 0] - cyl.center[0], p[:, 1] - cyl.center[1]) - cyl.radius
    dz = np.abs(p[:, 2] - cyl.height / 2.0) - cyl.height / 2.0
    outside = np.hypot(np.maximum(dr, 0.0), np.maximum(dz, 0.0))
    inside = np.minimum(np.maximum(dr, dz), 0.0)
    return outside + inside


def obstacle_clearance(obstacle: Obstacle, points: np.ndarray) -> np.ndarray:
    """Signed distance from each of ``points`` ``(N, 3)`` to one obstacle (negative inside)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return _box_sdf(obstacle, p) if isinstance(obstacle, Box) else _cylinder_sdf(obstacle, p)


def clearances(world: World, points: np.ndarray) -> np.ndarray:
    """Vectorised :meth:`World.clearance` for ``(N, 3)`` points."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = _wall_clearance(world, p)
    for obstacle in world.obstacles:
        out = np.minimum(out, obstacle_clearance(obstacle, p))
    return out


def footprint_radius(obstacle: Obstacle) -> float:
    """Radius of the smallest vertical cylinder around the obstacle's footprint (for culling)."""
    if isinstance(obstacle, Box):
        return 0.5 * math.hypot(obstacle.size[0], obstacle.size[1])
    return obstacle.radius


def footprint_center(obstacle: Obstacle) -> tuple[float, float]:
    """The obstacle's horizontal centre (x, y)."""
    return (obstacle.center[0], obstacle.center[1])


# ----------------------------------------------------------------------------------------------
# loading and saving

_TOP_KEYS = {"name", "room", "obstacles", "start"}
_TOP_OPTIONAL = {"waypoints", "moving"}
_ROOM_KEYS = {"size", "height"}
_START_KEYS = {"position", "yaw_deg"}
_BOX_KEYS = {"type", "center", "size", "yaw_deg"}
_CYL_KEYS = {"type", "center", "radius", "height"}
_MOVING_CYL_KEYS = {"type", "radius", "height"}
_MOVING_BOX_KEYS = {"type", "size"}
_MOVING_OPTIONAL = {"base", "kind", "path", "walk"}
_PATH_KEYS = {"points", "speed"}
_WALK_KEYS = {"bounds", "speed", "seed"}


class _Reader:
    """Field-by-field checks that name the offending field in every message."""

    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, key: str, message: str) -> UserError:
        return UserError(f"world {self.source}: {key}: {message}")

    def table(self, value: Any, key: str, required: set[str], optional: set[str] = frozenset()) -> dict:
        if not isinstance(value, dict):
            raise self.fail(key, f"expected an object, got {type(value).__name__}")
        prefix = f"{key}." if key else ""
        for name in sorted(value):
            if name not in required and name not in optional:
                raise self.fail(f"{prefix}{name}", "unknown field")
        for name in sorted(required):
            if name not in value:
                raise self.fail(f"{prefix}{name}", "missing field")
        return value

    def number(self, value: Any, key: str, positive: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(key, f"expected a number, got {type(value).__name__} {value!r}")
        if not math.isfinite(value):
            raise self.fail(key, f"must be finite, got {value!r}")
        if positive and value <= 0:
            raise self.fail(key, f"must be positive, got {value!r}")
        return float(value)

    def vector(self, value: Any, key: str, n: int, positive: bool = False) -> tuple[float, ...]:
        if not isinstance(value, list):
            raise self.fail(key, f"expected a list of {n} numbers, got {type(value).__name__}")
        if len(value) != n:
            raise self.fail(key, f"expected {n} numbers, got {len(value)}")
        return tuple(self.number(v, f"{key}[{i}]", positive) for i, v in enumerate(value))

    def string(self, value: Any, key: str) -> str:
        if not isinstance(value, str) or not value:
            raise self.fail(key, f"expected a non-empty string, got {value!r}")
        return value


def world_from_dict(
    data: Any,
    *,
    path_for_messages: str = "<dict>",
    vehicle_radius: float = DEFAULT_VEHICLE_RADIUS,
) -> World:
    """Build a :class:`World` from the parsed JSON, checking every field.

    :param data: the parsed JSON document
    :param path_for_messages: how to name the source in error messages
    :param vehicle_radius: the start and every waypoint must be at least this far from every wall
        and obstacle
    :raises UserError: naming the offending field
    """
    r = _Reader(path_for_messages)
    top = r.table(data, "", _TOP_KEYS, _TOP_OPTIONAL)
    name = r.string(top["name"], "name")
    room = r.table(top["room"], "room", _ROOM_KEYS)
    room_size = r.vector(room["size"], "room.size", 2, positive=True)
    room_height = r.number(room["height"], "room.height", positive=True)
    if not isinstance(top["obstacles"], list):
        raise r.fail("obstacles", f"expected a list, got {type(top['obstacles']).__name__}")
    obstacles: list[Obstacle] = []
    for i, item in enumerate(top["obstacles"]):
        key = f"obstacles[{i}]"
        if not isinstance(item, dict):
            raise r.fail(key, f"expected an object, got {type(item).__name__}")
        kind = item.get("type")
        if kind == "box":
            item = r.table(item, key, _BOX_KEYS - {"yaw_deg"}, {"yaw_deg"})
            obstacles.append(
                Box(
                    center=r.vector(item["center"], f"{key}.center", 3),
                    size=r.vector(item["size"], f"{key}.size", 3, positive=True),
                    yaw_deg=r.number(item.get("yaw_deg", 0.0), f"{key}.yaw_deg"),
                )
            )
        elif kind == "cylinder":
            item = r.table(item, key, _CYL_KEYS)
            obstacles.append(
                Cylinder(
                    center=r.vector(item["center"], f"{key}.center", 2),
                    radius=r.number(item["radius"], f"{key}.radius", positive=True),
                    height=r.number(item["height"], f"{key}.height", positive=True),
                )
            )
        elif "type" not in item:
            raise r.fail(f"{key}.type", "missing field")
        else:
            raise r.fail(f"{key}.type", f"must be 'box' or 'cylinder', got {kind!r}")
    start = r.table(top["start"], "start", _START_KEYS)
    position = r.vector(start["position"], "start.position", 3)
    yaw = r.number(start["yaw_deg"], "start.yaw_deg")
    waypoints = top.get("waypoints", [])
    if not isinstance(waypoints, list):
        raise r.fail("waypoints", f"expected a list of [x, y, z], got {type(waypoints).__name__}")
    goals = tuple(r.vector(w, f"waypoints[{i}]", 3) for i, w in enumerate(waypoints))
    moving_items = top.get("moving", [])
    if not isinstance(moving_items, list):
        raise r.fail("moving", f"expected a list, got {type(moving_items).__name__}")
    moving = tuple(
        _moving_from_dict(r, item, f"moving[{i}]", room_size) for i, item in enumerate(moving_items)
    )
    world = World(name, room_size, room_height, tuple(obstacles), position, yaw, goals, moving=moving)  # type: ignore[arg-type]
    _check_clear(world, r, "start.position", world.start_position, vehicle_radius)
    p0 = np.asarray([world.start_position], dtype=np.float64)
    for i, m in enumerate(world.moving):
        if m.clearance(p0, 0.0)[0] < vehicle_radius:
            raise r.fail("start.position", f"closer than {vehicle_radius:g} m to moving[{i}] at the start")
    for i, goal in enumerate(world.waypoints):
        _check_clear(world, r, f"waypoints[{i}]", goal, vehicle_radius)
    return world


def _moving_from_dict(r: _Reader, item: Any, key: str, room_size: tuple[float, ...]) -> MovingObstacle:
    """One entry of ``moving``: a shape and exactly one of ``path`` or ``walk``."""
    if not isinstance(item, dict):
        raise r.fail(key, f"expected an object, got {type(item).__name__}")
    shape = item.get("type")
    if shape not in ("cylinder", "box"):
        if "type" not in item:
            raise r.fail(f"{key}.type", "missing field")
        raise r.fail(f"{key}.type", f"must be 'box' or 'cylinder', got {shape!r}")
    if shape == "cylinder":
        item = r.table(item, key, _MOVING_CYL_KEYS, _MOVING_OPTIONAL)
        radius, size, yaw = r.number(item["radius"], f"{key}.radius", positive=True), (0.0, 0.0), 0.0
        height = r.number(item["height"], f"{key}.height", positive=True)
    else:
        item = r.table(item, key, _MOVING_BOX_KEYS, _MOVING_OPTIONAL | {"yaw_deg"})
        sx, sy, height = r.vector(item["size"], f"{key}.size", 3, positive=True)
        radius, size, yaw = 0.0, (sx, sy), r.number(item.get("yaw_deg", 0.0), f"{key}.yaw_deg")
    base = r.number(item.get("base", 0.0), f"{key}.base")
    if base < 0.0:
        raise r.fail(f"{key}.base", f"must be 0 or more, got {base:g}")
    kind = r.string(item["kind"], f"{key}.kind") if "kind" in item else ""
    if ("path" in item) == ("walk" in item):
        raise r.fail(key, "give exactly one of 'path' and 'walk'")
    hx, hy = room_size[0] / 2.0, room_size[1] / 2.0

    def inside(point: tuple[float, ...], where: str) -> tuple[float, float]:
        if not (abs(point[0]) < hx and abs(point[1]) < hy):
            raise r.fail(where, f"({point[0]:g}, {point[1]:g}) is outside the room")
        return (point[0], point[1])

    motion: PathMotion | RandomWalk
    if "path" in item:
        path = r.table(item["path"], f"{key}.path", _PATH_KEYS, {"loop"})
        points = path["points"]
        if not isinstance(points, list) or len(points) < 2:
            raise r.fail(f"{key}.path.points", "expected a list of at least 2 [x, y]")
        corners = tuple(
            inside(r.vector(p, f"{key}.path.points[{j}]", 2), f"{key}.path.points[{j}]")
            for j, p in enumerate(points)
        )
        loop = path.get("loop", False)
        if not isinstance(loop, bool):
            raise r.fail(f"{key}.path.loop", f"expected true or false, got {loop!r}")
        motion = PathMotion(corners, r.number(path["speed"], f"{key}.path.speed", positive=True), loop)
    else:
        walk = r.table(item["walk"], f"{key}.walk", _WALK_KEYS)
        bounds = walk["bounds"]
        if not isinstance(bounds, list) or len(bounds) != 2:
            raise r.fail(f"{key}.walk.bounds", "expected [[x_min, y_min], [x_max, y_max]]")
        lo = inside(r.vector(bounds[0], f"{key}.walk.bounds[0]", 2), f"{key}.walk.bounds[0]")
        hi = inside(r.vector(bounds[1], f"{key}.walk.bounds[1]", 2), f"{key}.walk.bounds[1]")
        if not (lo[0] < hi[0] and lo[1] < hi[1]):
            raise r.fail(f"{key}.walk.bounds", "the first corner must be below the second in x and y")
        seed = walk["seed"]
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise r.fail(f"{key}.walk.seed", f"expected a non-negative integer, got {seed!r}")
        motion = RandomWalk((lo, hi), r.number(walk["speed"], f"{key}.walk.speed", positive=True), seed)
    return MovingObstacle(shape, motion, height, radius, size, yaw, base, kind)


def moving_to_dict(m: MovingObstacle) -> dict[str, Any]:
    """One moving obstacle in the documented schema (inverse of the loader's ``moving`` entries)."""
    if m.shape == "cylinder":
        item: dict[str, Any] = {"type": "cylinder", "radius": m.radius, "height": m.height}
    else:
        item = {"type": "box", "size": [*m.size, m.height], "yaw_deg": m.yaw_deg}
    if m.base:
        item["base"] = m.base
    if m.kind:
        item["kind"] = m.kind
    if isinstance(m.motion, PathMotion):
        item["path"] = {
            "points": [list(p) for p in m.motion.points],
            "speed": m.motion.speed,
            "loop": m.motion.loop,
        }
    else:
        item["walk"] = {
            "bounds": [list(b) for b in m.motion.bounds],
            "speed": m.motion.speed,
            "seed": m.motion.seed,
        }
    return item


def _check_clear(
    world: World, r: _Reader, key: str, point: tuple[float, float, float], vehicle_radius: float
) -> None:
    """The start or a waypoint must be inside the room and clear of everything by the radius."""
    x, y, z = point
    hx, hy = world.room_size[0] / 2.0, world.room_size[1] / 2.0
    where = f"({x:g}, {y:g}, {z:g})"
    if not (abs(x) < hx and abs(y) < hy and 0.0 < z < world.room_height):
        raise r.fail(key, f"{where} is outside the room")
    p = np.asarray([point], dtype=np.float64)
    if _wall_clearance(world, p)[0] < vehicle_radius:
        raise r.fail(key, f"{where} is closer than {vehicle_radius:g} m to a wall")
    for i, obstacle in enumerate(world.obstacles):
        d = obstacle_clearance(obstacle, p)[0]
        if d < 0.0:
            raise r.fail(key, f"{where} is inside obstacles[{i}]")
        if d < vehicle_radius:
            raise r.fail(key, f"{where} is closer than {vehicle_radius:g} m to obstacles[{i}]")


def load_world(path: str | Path, *, vehicle_radius: float = DEFAULT_VEHICLE_RADIUS) -> World:
    """Read and check a world JSON file.

    :param path: the file
    :param vehicle_radius: the start must be clear of all geometry by this much
    :raises UserError: missing/empty/invalid file or any bad field, naming it
    """
    path = Path(path)
    data = load_user_file(path, "world", _parse_json)
    return world_from_dict(data, path_for_messages=str(path), vehicle_radius=vehicle_radius)


def _parse_json(text: str) -> Any:
    if not text.strip():
        raise ValueError("file is empty")
    return json.loads(text)


def world_to_dict(world: World) -> dict[str, Any]:
    """The world as a JSON-ready dict in the documented schema (inverse of :func:`world_from_dict`)."""
    obstacles: list[dict[str, Any]] = []
    for o in world.obstacles:
        if isinstance(o, Box):
            item = {"type": "box", "center": list(o.center), "size": list(o.size), "yaw_deg": o.yaw_deg}
        else:
            item = {"type": "cylinder", "center": list(o.center), "radius": o.radius, "height": o.height}
        obstacles.append(item)
    data: dict[str, Any] = {
        "name": world.name,
        "room": {"size": list(world.room_size), "height": world.room_height},
        "obstacles": obstacles,
        "start": {"position": list(world.start_position), "yaw_deg": world.start_yaw_deg},
    }
    if world.waypoints:  # an exploration world's file stays in the original schema
        data["waypoints"] = [list(w) for w in world.waypoints]
    if world.moving:
        data["moving"] = [moving_to_dict(m) for m in world.moving]
    return data


def save_world(world: World, path: str | Path) -> None:
    """Write ``world`` as an indented JSON file loadable by :func:`load_world`."""
    Path(path).write_text(json.dumps(world_to_dict(world), indent=2) + "\n", encoding="utf-8")


# ----------------------------------------------------------------------------------------------
# generation

START_CLEARANCE = 1.5  # generated starts are this far from every surface
FLIGHT_ALTITUDE = 1.5
_ROOM_HEIGHT = 3.0


def _lerp(a: float, b: float, t: float) -> float:
    return a + (b - a) * t


def _round(v: float) -> float:
    return round(float(v), 3)


def generate_world(
    seed: int,
    difficulty: float,
    vehicle_radius: float = DEFAULT_VEHICLE_RADIUS,
    *,
    room_width: float | None = None,
) -> World:
    """A random room for training or evaluation, deterministic for ``(seed, difficulty)``.

    Difficulty 0 is 3 obstacles in a big room (about 23 × 16 m) with wide gaps; difficulty 1 is 10
    obstacles in a small room (about 13 × 10.6 m) with gaps down to 1.2 m between footprints. Every
    obstacle keeps that gap to every other obstacle and to the walls, so free space is connected
    and a sensible policy can always fly on. The start is at least 1.5 m from every surface and
    faces the direction with the longest free run (ties broken toward the room centre).

    :param seed: non-negative integer
    :param difficulty: 0.0 (easy) … 1.0 (hard)
    :param vehicle_radius: used to decide how far the start's heading is free
    :param room_width: make the room this narrow (its y extent, metres; 6 m and up): corridors and
        small rooms like the example worlds, which the default sizes never produce. Obstacles that
        no longer fit with their gap are left out.
    """
    if not 0.0 <= difficulty <= 1.0:
        raise ValueError(f"difficulty must be in [0, 1], got {difficulty}")
    if room_width is not None and room_width < 6.0:
        raise ValueError(f"room_width must be at least 6 m, got {room_width}")
    rng = np.random.default_rng(seed)
    d = float(difficulty)
    sx = _lerp(24.0, 14.0, d) * rng.uniform(0.9, 1.0)
    sy = _lerp(17.0, 11.2, d) * rng.uniform(0.9, 1.0)
    if room_width is not None:
        sy = float(room_width)
    n_obstacles = round(3 + 7 * d)
    gap = _lerp(2.5, 1.2, d)
    hx, hy = sx / 2.0, sy / 2.0

    margin = START_CLEARANCE + 0.2
    start = np.array([rng.uniform(-hx + margin, hx - margin), rng.uniform(-hy + margin, hy - margin)])

    placed: list[tuple[Obstacle, np.ndarray, float]] = []
    for _ in range(4):  # a crowded layout can leave no room for the last ones: lay out again
        layout = _place_obstacles(rng, d, n_obstacles, gap, (hx, hy), start)
        if len(layout) > len(placed):
            placed = layout
        if len(placed) == n_obstacles:
            break
    obstacles = tuple(o for o, _, _ in placed)
    position = (_round(start[0]), _round(start[1]), FLIGHT_ALTITUDE)
    world = World(f"gen-{seed}-d{d:.2f}", (_round(sx), _round(sy)), _ROOM_HEIGHT, obstacles, position, 0.0)
    yaw = _best_heading(world, vehicle_radius)
    return World(world.name, world.room_size, world.room_height, obstacles, position, yaw)


def _place_obstacles(
    rng: np.random.Generator,
    d: float,
    n: int,
    gap: float,
    half_room: tuple[float, float],
    start: np.ndarray,
) -> list[tuple[Obstacle, np.ndarray, float]]:
    """Up to ``n`` obstacles with footprints ``gap`` apart and from the walls, clear of the start."""
    hx, hy = half_room
    placed: list[tuple[Obstacle, np.ndarray, float]] = []
    for _ in range(n):
        for shrink in (1.0, 1.0, 1.0, 0.8, 0.8, 0.6, 0.6, 0.4):
            obstacle = _random_obstacle(rng, d, shrink)
            rad = footprint_radius(obstacle)
            lo, hi = np.array([-hx, -hy]) + rad + gap, np.array([hx, hy]) - rad - gap
            if np.any(hi <= lo):
                continue
            cand = rng.uniform(lo, hi, size=(64, 2))
            ok = np.hypot(*(cand - start).T) - rad >= START_CLEARANCE + 0.3
            for _, oc, orad in placed:
                ok &= np.hypot(*(cand - oc).T) - rad - orad >= gap
            if ok.any():
                c = cand[np.argmax(ok)]
                placed.append((_moved(obstacle, c), c, rad))
                break
    return placed


def _random_obstacle(rng: np.random.Generator, d: float, shrink: float) -> Obstacle:
    height = _round(rng.uniform(2.2, _ROOM_HEIGHT))
    if rng.uniform() < 0.5:
        radius = _round(rng.uniform(0.2, _lerp(0.5, 0.7, d)) * shrink)
        return Cylinder((0.0, 0.0), radius, height)
    sx = _round(rng.uniform(0.3, _lerp(1.5, 2.2, d)) * shrink)
    sy = _round(rng.uniform(0.3, _lerp(1.0, 1.5, d)) * shrink)
    return Box((0.0, 0.0, height / 2.0), (sx, sy, height), _round(rng.uniform(0.0, 180.0)))


def _moved(obstacle: Obstacle, c: np.ndarray) -> Obstacle:
    x, y = _round(c[0]), _round(c[1])
    if isinstance(obstacle, Box):
        return Box((x, y, obstacle.center[2]), obstacle.size, obstacle.yaw_deg)
    return Cylinder((x, y), obstacle.radius, obstacle.height)


def _best_heading(world: World, vehicle_radius: float, reach: float = 6.0, step: float = 0.25) -> float:
    """Heading (degrees, multiple of 10) with the longest free straight run from the start."""
    headings = np.radians(np.arange(0.0, 360.0, 10.0))
    steps = np.arange(step, reach + 1e-9, step)
    x0, y0, z0 = world.start_position
    px = x0 + np.cos(headings)[:, None] * steps[None, :]
    py = y0 + np.sin(headings)[:, None] * steps[None, :]
    pts = np.stack([px.ravel(), py.ravel(), np.full(px.size, z0)], axis=1)
    blocked = (clearances(world, pts) < vehicle_radius + 0.1).reshape(px.shape)
    first = np.where(blocked.any(axis=1), blocked.argmax(axis=1), steps.size)
    free = first * step  # metres of free run, to the sampling step
    to_centre = math.atan2(-y0, -x0)
    off_centre = np.abs((headings - to_centre + np.pi) % (2 * np.pi) - np.pi)
    best = np.lexsort((off_centre, -np.round(free, 1)))[0]
    return float(round(np.degrees(headings[best])))
