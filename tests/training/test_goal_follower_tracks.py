"""``goal_follower_tracks`` flies a dynamic world the plain goal follower crashes in (a drone in
rooms-dynamic-500300, a validation seed), on the tracker's movers as LidarNav-v0 gives the shield,
through ArduPilot's response; the config's sideways part flies its sidesteps."""

from __future__ import annotations

import pytest

from companion.common.errors import UserError
from training.config import load_train_config
from training.controllers import ControllerSpec, build_controller
from training.episodes import NAV_ENV_ID, goal_worlds, make_tasks, run_task

FAMILY = "rooms-dynamic"
SEED = 500_300


def _config(*extra: str):
    overrides = [f'env.families=["{FAMILY}"]', 'env.autopilot_response="ardupilot"', *extra]
    return load_train_config("training/configs/nav.toml", overrides)


def _fly(kind: str):
    config = _config()
    # the first of five, as ``avoid-train evaluate --first-seed 500300 --seeds 5`` flies it (difficulty 0.1)
    world = goal_worlds([FAMILY], SEED, 5, tuple(config.env_config().difficulty_range))[:1]
    (task,) = make_tasks([ControllerSpec(kind)], world, 1, config.env, NAV_ENV_ID)
    return run_task(task)


def test_the_plain_goal_follower_collides_with_the_mover_and_the_tracks_one_does_not() -> None:
    plain = _fly("goal_follower")
    assert plain.collision
    # the drone it hit, and at its speed: the report counts it against the shield's 1.5 m/s bound
    world = goal_worlds([FAMILY], SEED, 5, tuple(_config().env_config().difficulty_range))[0].world(0.25)
    drones = {m.speed for m in world.moving if m.kind == "drone"}
    assert plain.collision_mover_speed in drones
    tracks = _fly("goal_follower_tracks")
    assert not tracks.collision
    assert tracks.success


def test_it_needs_the_tracker() -> None:
    env_config = _config("env.tracking=false").env_config()
    with pytest.raises(UserError, match=r"goal_follower_tracks .* env\.tracking = true"):
        build_controller(ControllerSpec("goal_follower_tracks"), env_config, seed=0, movers=dict)
