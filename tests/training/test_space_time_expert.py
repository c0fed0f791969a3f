"""The space-time teacher (``space_time_expert``): it times its way past a walker pacing across a
corridor, where the teacher that demands a clear stop waits at the edge of the walker's beat until
the episode ends. (In a world without movers it is the robust teacher, command for command:
``tests/training/test_mover_expert.py``.)"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from companion.common.errors import UserError
from flightsim.envs.nav_env import LidarNavEnv, NavEnvConfig
from flightsim.worlds.moving import MovingObstacle, PathMotion
from flightsim.worlds.world import World
from tests.training.test_path_expert import RADIUS
from training.config import config_from_dict
from training.controllers import TEACHERS
from training.predictive_expert import PredictiveExpert
from training.space_time_expert import (
    KEEP_RIGHT,
    SPACE_TIME,
    SpaceTimeConfig,
    SpaceTimePath,
    keep_right_expert,
    present_expert,
    space_time_expert,
)

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


def head_on_room(lateral: float, east: bool) -> World:
    """A room 20 m by 6 m, the waypoint 12 m ahead of the start (to the east or to the west), and a
    walker coming straight at the vehicle, 1 m/s, along a line ``lateral`` metres to the left of the
    vehicle's nose's."""
    ahead = 1.0 if east else -1.0
    line = PathMotion(((7.0 * ahead, lateral * ahead), (-9.0 * ahead, lateral * ahead)), 1.0)
    walker = MovingObstacle("cylinder", line, height=1.8, radius=WALKER_RADIUS, kind="pedestrian")
    return World(
        name="head-on", room_size=(20.0, 6.0), room_height=3.0, obstacles=(),
        start_position=(-6.0 * ahead, 0.0, 1.5), start_yaw_deg=0.0 if east else 180.0,
        waypoints=((6.0 * ahead, 0.0, 1.5),), moving=(walker,),
    )  # fmt: skip


def passing_side(teacher, world: World) -> tuple[float, dict]:
    """How far to the left of the walker the vehicle is as they pass abreast (negative: to its
    right), and the episode's last info."""
    env = LidarNavEnv(NavEnvConfig(autopilot_response="px4", vehicle_radius=RADIUS, sideways=True))
    env.reset(seed=0, options={"world": world})
    ahead = 1.0 if world.start_yaw_deg == 0.0 else -1.0
    expert = teacher(env)
    action, side = expert.reset(), None
    while True:
        _, _, terminated, truncated, info = env.step(action)
        walker = env.world.moving[0].positions(env.sim_time)[0]
        here = env.true_state.position[:2]
        if side is None and ahead * (here[0] - walker[0]) >= 0.0:
            side = ahead * float(here[1] - walker[1])
        if terminated or truncated:
            return side, info
        action = expert.act()


def test_keep_right_passes_a_walker_coming_head_on_on_its_left_whichever_side_of_the_nose():
    """The walker's line a little left of the nose, then a little right, flying east and west: the
    keep-right teacher passes with the walker on its left every time and reaches the waypoint. The
    space-time teacher's side is its search's tie-break: here it passes with the walker on its
    right when flying west."""
    for east in (True, False):
        for lateral in (0.3, -0.3):
            side, info = passing_side(keep_right_expert, head_on_room(lateral, east))
            assert info["success"] and not info["collision"], (east, lateral, info)
            assert side < -(RADIUS + WALKER_RADIUS), (east, lateral, side)
    side, _ = passing_side(space_time_expert, head_on_room(-0.3, east=False))
    assert side > RADIUS + WALKER_RADIUS, side


def replans_kept(teacher: Callable[[LidarNavEnv], PredictiveExpert], world: World) -> tuple[int, int, dict]:
    """How many of an episode's replans kept the schedule being flown, of how many, and the
    episode's last info."""
    env = LidarNavEnv(NavEnvConfig(autopilot_response="px4", vehicle_radius=RADIUS, sideways=True))
    env.reset(seed=0, options={"world": world})
    expert = teacher(env)
    path = expert._path_expert
    replan, starts = path._replan, []

    def recorded() -> None:
        replan()
        starts.append(path._times[0] < env.sim_time - 1e-9)  # a new schedule starts now

    path._replan = recorded
    action = expert.reset()
    while True:
        _, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            return sum(starts), len(starts), info
        action = expert.act()


def test_the_keep_right_teacher_keeps_the_schedule_it_flies_while_that_stays_good():
    """Head-on with a walker: the space-time teacher starts a new schedule at every replan; the
    keep-right teacher keeps the one it flies at most replans and still reaches the waypoint clear,
    and keeps none once the vehicle must be within a centimetre of where that puts it."""
    world = head_on_room(0.3, east=False)
    kept, replans, info = replans_kept(space_time_expert, world)
    assert kept == 0 and replans > 20 and info["success"]
    kept, replans, info = replans_kept(keep_right_expert, world)
    assert kept > replans / 2, (kept, replans)
    assert info["success"] and not info["collision"], info
    tight = SpaceTimeConfig(keep_right=KEEP_RIGHT, commit_slack_s=1.0, commit_off=0.01)

    def close_follower(env: LidarNavEnv) -> PredictiveExpert:
        return PredictiveExpert(env, SPACE_TIME, path=SpaceTimePath(env, tight))

    assert replans_kept(close_follower, world)[0] == 0


def test_keep_right_is_a_teacher_and_its_labels_are_not_mirrored():
    assert TEACHERS["keep_right_expert"] is keep_right_expert
    refused = r"teacher keep_right_expert passes movers on one side.*set pretrain.mirror = false"
    with pytest.raises(UserError, match=refused):
        config_from_dict({"env_id": "flightsim/LidarNav-v0", "pretrain": {
            "method": "dagger", "steps": 100, "teacher": "keep_right_expert", "mirror": True}})  # fmt: skip


def crossing_room(turn_at: float) -> World:
    """A room 16 m by 8 m, the waypoint 10 m ahead, and a walker crossing the way 4 m ahead from the
    right at 1 m/s, from 2.5 m off the line; it turns back ``turn_at`` seconds after the start."""
    line = PathMotion(((0.0, -2.5), (0.0, -2.5 + turn_at)), 1.0)
    walker = MovingObstacle("cylinder", line, height=1.8, radius=WALKER_RADIUS, kind="pedestrian")
    return World(
        name="crossing", room_size=(16.0, 8.0), room_height=3.0, obstacles=(),
        start_position=(-4.0, 0.0, 1.5), start_yaw_deg=0.0, waypoints=((6.0, 0.0, 1.5),), moving=(walker,),
    )  # fmt: skip


def labels_until(
    teacher: Callable[[LidarNavEnv], PredictiveExpert], world: World, until: float
) -> np.ndarray:
    """The teacher's labels, flying them, at every step until ``until`` seconds, ``(steps, 3)``."""
    env = LidarNavEnv(NavEnvConfig(autopilot_response="px4", vehicle_radius=RADIUS, sideways=True))
    env.reset(seed=0, options={"world": world})
    expert = teacher(env)
    labels = [expert.reset()]
    while env.sim_time < until - 1e-9:
        env.step(labels[-1])
        labels.append(expert.act())
    return np.array(labels)


def test_the_present_teachers_labels_are_the_same_while_what_the_student_sees_is():
    """The same walker crossing, turning back after 2 s in one world and after 6 s in the other:
    until it turns, every frame of the two is the same, and so are the present teacher's labels.
    The keep-right teacher, reading the walker's track, labels the two differently from the start."""
    soon, late = crossing_room(2.0), crossing_room(6.0)
    np.testing.assert_array_equal(
        labels_until(present_expert, soon, 2.0), labels_until(present_expert, late, 2.0)
    )
    privileged = np.abs(
        labels_until(keep_right_expert, soon, 2.0) - labels_until(keep_right_expert, late, 2.0)
    )
    assert privileged[0].max() > 0.5, privileged


def test_the_present_teacher_passes_a_walker_coming_head_on_on_its_left():
    """A walker on a straight line is where a constant velocity carries it: the present teacher keeps
    right of it as the keep-right teacher does, and reaches the waypoint."""
    for lateral in (0.3, -0.3):
        side, info = passing_side(present_expert, head_on_room(lateral, east=True))
        assert info["success"] and not info["collision"], (lateral, info)
        assert side < -(RADIUS + WALKER_RADIUS), (lateral, side)


def test_the_present_teacher_is_a_teacher_and_its_labels_are_not_mirrored():
    assert TEACHERS["present_expert"] is present_expert
    with pytest.raises(UserError, match=r"teacher present_expert passes movers on one side"):
        config_from_dict({"env_id": "flightsim/LidarNav-v0", "pretrain": {
            "method": "dagger", "steps": 100, "teacher": "present_expert", "mirror": True}})  # fmt: skip
