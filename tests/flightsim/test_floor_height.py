"""The height above the floor from the VLP-16's downward lasers, on the project's own ray-cast VLP-16
(a real room: floor, walls, crates), tilted as a vehicle flies: the lowest surface seen is the floor,
crates below do not lift it, and where the floor is not seen there is no answer."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.perception.floor import floor_height
from companion.perception.scan import ScanConfig
from flightsim.envs.raycast import LidarConfig, VLP16Raycaster
from flightsim.vehicle.quadrotor import VehicleState
from flightsim.worlds.world import Box, load_world

SCAN = dataclasses.replace(ScanConfig(), mount_xyz=(0.05, 0.0, 0.1))


def cloud(world, height: float, roll_deg: float = 0.0, pitch_deg: float = 0.0, noise: float = 0.0):
    """The sensor-frame cloud of a vehicle ``height`` m up, tilted (FLU roll, pitch)."""
    state = VehicleState(time=0.0, position=np.array([0.0, 0.0, height]), velocity=np.zeros(3),
                         roll=math.radians(roll_deg), pitch=math.radians(pitch_deg), yaw=0.3,
                         angular_rate=np.zeros(3), on_ground=False, armed=True)
    rotation = state.rotation()
    caster = VLP16Raycaster(LidarConfig(azimuth_step_deg=0.4, noise_std=noise))
    position = state.position + rotation @ np.asarray(SCAN.mount_xyz)
    grid = caster.cast_points(world, position, rotation @ SCAN.rotation(), rng=np.random.default_rng(3))
    return grid, math.radians(roll_deg), -math.radians(pitch_deg)  # MAVLink pitch: nose up positive


@pytest.mark.parametrize(("height", "roll", "pitch", "hall"), [
    (1.5, 0.0, 0.0, False), (0.47, 0.0, 0.0, False), (1.5, 4.0, -6.0, False), (2.8, -5.0, 8.0, True),
])  # fmt: skip
def test_height_above_the_floor_is_measured_through_the_tilt(height, roll, pitch, hall):
    """In the 12 m x 8 m room and, 2.8 m up, a 30 m hall (in the room its walls hide the floor)."""
    world = load_world("flightsim/worlds/two-pillars.json")
    if hall:
        world = dataclasses.replace(world, room_size=(30.0, 30.0))
    points, r, p = cloud(world, height, roll, pitch, noise=0.01)
    assert floor_height(points, SCAN, r, p) == pytest.approx(height, abs=0.03)


def test_crates_and_benches_below_do_not_lift_the_floor():
    """A warehouse floor: crates (0.6 m) and benches (0.9 m) all around, the floor between them."""
    world = dataclasses.replace(load_world("flightsim/worlds/two-pillars.json"), room_size=(30.0, 30.0))
    crates = tuple(Box(center=(x, y, 0.3), size=(1.2, 1.2, 0.6)) for x in (-6.0, -3.0, 3.0, 6.0)
                   for y in (-6.0, -3.0, 3.0, 6.0))
    benches = tuple(Box(center=(0.0, y, 0.45), size=(3.0, 0.8, 0.9)) for y in (-5.0, 5.0))
    cluttered = dataclasses.replace(world, obstacles=world.obstacles + crates + benches)
    points, r, p = cloud(cluttered, 1.5, 3.0, -2.0, noise=0.01)
    assert floor_height(points, SCAN, r, p) == pytest.approx(1.5, abs=0.03)


def test_walls_that_hide_the_floor_are_no_floor():
    """2.8 m up in the 12 m x 8 m room the downward lasers meet only walls (a level ring of them in a
    square room looks like a floor to one laser): no answer, not the walls' height."""
    world = load_world("flightsim/worlds/two-pillars.json")
    points, r, p = cloud(world, 2.8)
    assert floor_height(points, SCAN, r, p) is None


def test_no_floor_in_sight_is_no_answer():
    world = load_world("flightsim/worlds/two-pillars.json")
    points, r, p = cloud(world, 1.5)
    level = points[points[:, 2] > -0.05]  # the horizon lasers only: a ring of rangefinders
    assert floor_height(level, SCAN, r, p) is None
    assert floor_height(np.zeros((0, 3), np.float32), SCAN, 0.0, 0.0) is None
