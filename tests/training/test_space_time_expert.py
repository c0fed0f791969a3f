"""The space-time teacher (``space_time_expert``): it times its way past a walker pacing across a
corridor, where the teacher that demands a clear stop waits at the edge of the walker's beat until
the episode ends. (In a world without movers it is the robust teacher, command for command:
``tests/training/test_mover_expert.py``.)"""

from __future__ import annotations

import numpy as np

from flightsim.envs.nav_env import LidarNavEnv, NavEnvConfig
from flightsim.worlds.moving import MovingObstacle, PathMotion
from flightsim.worlds.world import World
from tests.training.test_path_expert import RADIUS
from training.controllers import TEACHERS
from training.space_time_expert import space_time_expert

WALKER_RADIUS = 0.25


def pacing_corridor() -> World:
    """A corridor 16 m long and 3 m wide, the waypoint 12 m ahead of the start, and a walker pacing
    across its whole width halfway, 1 m/s: no stop on the way leaves the walker's beat clear."""
    beat = PathMotion(((0.0, -1.2), (0.0, 1.2)), 1.0)
    walker = MovingObstacle("cylinder", beat, height=1.8, radius=WALKER_RADIUS, kind="pedestrian")
    return World(
        name="pacing", room_size=(16.0, 3.0), room_height=3.0, obstacles=(),
        start_position=(-6.0, 0.0, 1.5), start_yaw_deg=0.0, waypoints=((6.0, 0.0, 1.5),), moving=(walker,),
    )  # fmt: skip


def test_it_times_its_way_past_a_walker_pacing_across_a_corridor():
    """PX4's response, the sideways action: it reaches the waypoint, keeping more than its 0.3 m
    margin from the walker. (``mover_expert`` times out here after 34 s: every stop in the beat
    meets the walker carried on or turned back.)"""
    env = LidarNavEnv(NavEnvConfig(autopilot_response="px4", vehicle_radius=RADIUS, sideways=True))
    env.reset(seed=0, options={"world": pacing_corridor()})
    expert = space_time_expert(env)
    action, gap = expert.reset(), np.inf
    while True:
        _, _, terminated, truncated, info = env.step(action)
        walker = env.world.moving[0].positions(env.sim_time)[0]
        gap = min(gap, float(np.hypot(*(env.true_state.position[:2] - walker))) - RADIUS - WALKER_RADIUS)
        if terminated or truncated:
            break
        action = expert.act()
    assert info["success"] and not info["collision"], info
    assert gap > 0.3, gap


def test_it_is_a_teacher():
    assert TEACHERS["space_time_expert"] is space_time_expert
