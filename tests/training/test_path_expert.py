"""The privileged teacher: its path keeps clear of obstacles, it plans around them, it stops in
time, it cancels the autopilot's velocity-estimate error, and it reaches goals in real
LidarNav-v0 worlds through a lagging autopilot."""

from __future__ import annotations

import math
import multiprocessing
import zlib
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np
import pytest

from companion.perception.drift import DriftHoldConfig
from flightsim.envs.nav_env import LidarNavEnv, NavEnvConfig
from flightsim.vehicle.autopilot_response import _S_BX, _S_BY
from flightsim.worlds.families import FAMILIES
from flightsim.worlds.world import Box, World, clearances
from training.config import load_train_config
from training.path_expert import PathExpert, PathExpertConfig, _stopping_speed

RADIUS = 0.25


def corridor(width: float) -> World:
    """A 20 × 12 m room cut by a 2 m-thick wall at x = 0 with one gap of ``width`` centred at
    y = 3; the start and the waypoint face each other through the wall at y = 0."""
    low, high = 3.0 - width / 2, 3.0 + width / 2
    return World(
        name="corridor",
        room_size=(20.0, 12.0),
        room_height=3.0,
        obstacles=(
            Box((0.0, (-6.0 + low) / 2, 1.5), (2.0, low + 6.0, 3.0)),
            Box((0.0, (high + 6.0) / 2, 1.5), (2.0, 6.0 - high, 3.0)),
        ),
        start_position=(-8.0, 0.0, 1.5),
        start_yaw_deg=0.0,
        waypoints=((8.0, 0.0, 1.5),),
    )


def env_for(world: World, response: str = "ideal") -> LidarNavEnv:
    env = LidarNavEnv(NavEnvConfig(autopilot_response=response, vehicle_radius=RADIUS))
    env.reset(seed=0, options={"world": world})
    return env


def fly(env: LidarNavEnv, expert: Any) -> dict:
    return fly_recording(env, expert)[0]


def fly_recording(env: LidarNavEnv, expert: Any) -> tuple[dict, np.ndarray]:
    """Fly ``expert`` to the episode's end: the last step's info and every action it chose."""
    actions = [expert.reset()]
    while True:
        _, _, terminated, truncated, info = env.step(actions[-1])
        if terminated or truncated:
            return info, np.array(actions)
        actions.append(expert.act())


def test_the_path_goes_through_the_gap_and_prefers_its_middle():
    env = env_for(corridor(width=2.0))
    expert = PathExpert(env)
    expert.reset()
    path = expert._path
    assert np.allclose(path[0], (-8.0, 0.0)) and np.allclose(path[-1], (8.0, 0.0))
    at_wall = path[np.abs(path[:, 0]) < 1.0]
    assert len(at_wall) and np.all(np.abs(at_wall[:, 1] - 3.0) < 0.3)  # the gap's middle, not its edge
    points = np.column_stack([path, np.full(len(path), 1.5)])
    assert clearances(env.world, points).min() >= RADIUS


def test_the_stopping_speed_stops_within_the_free_run():
    for free, accel, lag in ((0.0, 1.5, 0.3), (1.0, 1.5, 0.3), (3.0, 2.5, 0.8)):
        v = _stopping_speed(free, accel, lag)
        assert v * lag + v * v / (2 * accel) == pytest.approx(free)


def test_it_asks_for_the_estimate_error_on_top_of_its_speed():
    """The autopilot flies its erroneous estimate (reported = true + error) to the command, so the
    true velocity falls short by the error; the teacher adds the error's share along its nose."""
    env = env_for(corridor(width=2.0), response="px4")
    expert = PathExpert(env, PathExpertConfig(velocity_gain=0.0, clearance_speed_gain=0.0, min_speed=0.5))
    expert.reset()

    def forward_with(error_east: float) -> float:
        env._response._x[[_S_BX, _S_BY]] = (error_east, 0.0)
        expert._forward = 1.0  # no ramp in the way
        return float(expert.act()[0]) * env.config.max_speed

    assert forward_with(0.3) - forward_with(0.0) == pytest.approx(0.3, abs=0.02)  # the nose points East
    assert forward_with(0.0) == pytest.approx(0.5, abs=0.02)


def test_with_the_drift_features_it_makes_up_for_the_estimate_the_student_sees():
    """Its labels must follow from what the student sees: the drift estimate in the frame, not the
    simulator's true error (which the student cannot see)."""
    env = LidarNavEnv(NavEnvConfig(autopilot_response="px4", vehicle_radius=RADIUS, drift=True))
    env.reset(seed=0, options={"world": corridor(width=2.0)})
    expert = PathExpert(env, PathExpertConfig(velocity_gain=0.0, clearance_speed_gain=0.0, min_speed=0.5))
    expert.reset()

    def forward_with(seen_forward: float, true_east: float) -> float:
        env._drift.bias = np.array([seen_forward, 0.0])
        env._response._x[[_S_BX, _S_BY]] = (true_east, 0.0)
        expert._forward = 1.0  # no ramp in the way
        return float(expert.act()[0]) * env.config.max_speed

    assert forward_with(0.3, 0.0) - forward_with(0.0, 0.0) == pytest.approx(0.3, abs=0.02)  # nose East
    assert forward_with(0.0, 0.3) == pytest.approx(forward_with(0.0, 0.0), abs=1e-6)


def test_it_makes_up_only_for_the_drift_the_setpoint_does_not_hold():
    """With ``drift_hold`` the setpoint already carries the drift estimate beyond the deadband;
    the teacher making up for all of it as well would fly the held part twice."""
    hold = DriftHoldConfig(forward=0.6, lateral=0.6, deadband=0.1)
    config = NavEnvConfig(autopilot_response="px4", vehicle_radius=RADIUS, drift=True, drift_hold=True,
                          drift_hold_limits=hold)
    env = LidarNavEnv(config)
    env.reset(seed=0, options={"world": corridor(width=2.0)})
    expert = PathExpert(env, PathExpertConfig(velocity_gain=0.0, clearance_speed_gain=0.0, min_speed=0.5))
    expert.reset()

    def forward_with(seen_forward: float) -> float:
        env._drift.bias = np.array([seen_forward, 0.0])
        expert._forward = 1.0  # no ramp in the way
        return float(expert.act()[0]) * env.config.max_speed

    assert forward_with(0.3) - forward_with(0.0) == pytest.approx(0.1, abs=0.02)  # the deadband's part
    env._drift.bias = np.array([0.3, 0.0])
    assert env.drift_held() == pytest.approx((0.2, 0.0))  # the rest is held by the setpoint


@pytest.mark.parametrize("response", ["px4", "ardupilot"])
def test_it_reaches_the_goal_through_the_gap_with_a_real_autopilot_response(response):
    env = env_for(corridor(width=1.4), response=response)
    info = fly(env, PathExpert(env))
    assert info["success"], info
    assert info["min_distance"] > RADIUS


def test_it_reaches_most_validation_goals_through_random_autopilots():
    """Two validation worlds per family (seeds 500,006-7, difficulty 0 and 1; the teacher was tuned
    on 500,000-5), the random response: to be worth imitating, the teacher must do far better than
    the classical baseline (47 % on the test worlds; 16 of these 18 when this was written, 14 since
    it makes up for the drift estimate, 13 since the setpoint holds the sideways drift: staggered
    500,007, a PX4 draw with a 0.3 m/s estimate error, now collides, while the robust teacher now
    reaches it). The env is training's (nav.toml: noise, wind, mass, mount error, the drift hold)."""
    assert validation_successes(PathExpert) >= 13


def validation_successes(teacher: Callable[[LidarNavEnv], Any]) -> int:
    """Episodes of ``teacher`` (built on the env) that reach every waypoint: two validation worlds
    per family (seeds 500,006-7, difficulty 0 and 1) in training's env (nav.toml), flown two at a
    time (each episode is its own, so the count is the same as flown one by one)."""
    episodes = [(teacher, family, seed, float(k)) for family in FAMILIES
                for k, seed in enumerate((500_006, 500_007))]  # fmt: skip
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("forkserver")) as pool:
        return sum(pool.map(_validation_success, episodes))


def _validation_success(episode: tuple[Callable[[LidarNavEnv], Any], str, int, float]) -> bool:
    """One of :func:`validation_successes`' episodes, in a worker."""
    teacher, family, seed, difficulty = episode
    env = LidarNavEnv(load_train_config("training/configs/nav.toml").env_config())
    options = {"family": family, "world_seed": seed, "difficulty": difficulty}
    env.reset(seed=zlib.crc32(f"{family}/{seed}".encode()), options=options)
    return bool(fly(env, teacher(env))["success"])


def test_a_tighter_margin_is_taken_when_it_is_the_only_way():
    env = env_for(corridor(width=2 * RADIUS + 0.3))
    expert = PathExpert(env, PathExpertConfig(preferred_margin=1.0))
    expert.reset()
    assert math.isclose(expert._path[-1][0], 8.0) and len(expert._path) > 2
    points = np.column_stack([expert._path, np.full(len(expert._path), 1.5)])
    assert clearances(env.world, points).min() >= RADIUS


@pytest.mark.parametrize("response", ["px4", "ardupilot"])
def test_with_a_sideways_action_it_flies_the_gap_sooner_and_its_nose_swings_less(response):
    """With the env's ``sideways`` it flies its whole command in the body frame and no longer
    corrects a sideways error with its nose: through the corridor's gap it arrives in fewer steps
    (128-142 against 150-163 when written) and its yaw label changes far less from step to step
    (0.02 against 0.10-0.14 of the top rate)."""
    flights = {}
    for sideways in (False, True):
        env = LidarNavEnv(NavEnvConfig(autopilot_response=response, vehicle_radius=RADIUS, sideways=sideways))
        env.reset(seed=0, options={"world": corridor(width=1.4)})
        info, actions = fly_recording(env, PathExpert(env))
        assert info["success"], (sideways, info)
        flights[sideways] = (info["steps"], actions)
    (nose_steps, nose), (side_steps, side) = flights[False], flights[True]
    assert side.shape[1] == 3 and np.abs(side[:, 2]).max() > 0.5
    assert side_steps < nose_steps
    assert np.abs(np.diff(side[:, 1])).mean() < 0.5 * np.abs(np.diff(nose[:, 1])).mean()
