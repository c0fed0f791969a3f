"""The batched env is the single env: same seeds and actions give the same episodes, bit for bit.

N separate gymnasium envs and one batch of N step side by side through resets, collisions,
waypoint switches, time limits, domain randomisation (noise, dropout, mount error, mass, wind),
random autopilot responses, the shield and scan latency; observations, rewards, episode ends and
infos are compared exactly (no tolerance: the batch repeats the single env's float operations).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest

from flightsim.envs.batch_env import BatchedEnvs
from flightsim.envs.env import EnvConfig, LidarAvoidEnv
from flightsim.envs.nav_env import LidarNavEnv
from training.config import load_train_config
from training.vec_env import TrainingWorlds


def _assert_same_info(single: dict, batched: dict, where: str) -> None:
    assert single.keys() == batched.keys(), where
    for key, value in single.items():
        assert np.array_equal(np.asarray(value), np.asarray(batched[key])), f"{where}: info[{key!r}]"


def _goal_seeker(observations: list[np.ndarray], rng: np.random.Generator, width: int) -> np.ndarray:
    """Turn toward the goal and fly at it, noisily: reaches waypoints and hits things (``width`` 3:
    an env with ``sideways``, whose third part is noise alone)."""
    actions = []
    for obs in observations:
        cos, sin = (obs[360], obs[361]) if obs.size > 360 else (1.0, 0.0)
        actions.append([1.0 if cos > 0.8 else 0.3 * cos, 3.0 * sin, 0.0][:width])
    return (np.array(actions) + rng.normal(0.0, 0.4, (len(observations), width))).astype(np.float32)


def _run_side_by_side(make: list[Callable[[], gym.Env]], steps: int) -> dict[str, int]:
    """Step N single envs and a batch of N with the same seeds and actions; compare every step."""
    singles = [m() for m in make]
    batch = BatchedEnvs([m() for m in make])
    events = {"resets": 0, "collisions": 0, "truncations": 0, "waypoints": 0, "successes": 0}
    observations = []
    for i, env in enumerate(singles):
        obs, info = env.reset(seed=40 + i)
        b_obs, b_info = batch.reset(i, seed=40 + i)
        np.testing.assert_array_equal(obs, b_obs)
        _assert_same_info(info, b_info, f"reset {i}")
        observations.append(b_obs)
    rng = np.random.default_rng(7)
    waypoint = [0] * len(make)
    for t in range(steps):
        actions = _goal_seeker(observations, rng, singles[0].action_space.shape[0])
        if t % 50 == 49:
            actions[0, :2] = [np.nan, 5.0]  # broken and out-of-range actions too
        b_obs, b_rew, b_term, b_trunc, b_info = batch.step(actions)
        for i, env in enumerate(singles):
            where = f"step {t}, env {i}"
            obs, reward, terminated, truncated, info = env.step(actions[i])
            np.testing.assert_array_equal(obs, b_obs[i], err_msg=where)
            assert (reward, terminated, truncated) == (b_rew[i], b_term[i], b_trunc[i]), where
            _assert_same_info(info, b_info[i], where)
            events["waypoints"] += info.get("waypoint", 0) > waypoint[i]
            waypoint[i] = info.get("waypoint", 0)
            if terminated or truncated:
                events["resets"] += 1
                events["collisions"] += info["collision"]
                events["truncations"] += truncated
                events["successes"] += bool(info.get("success"))
                obs, _ = env.reset()
                b_obs[i], _ = batch.reset(i)
                np.testing.assert_array_equal(obs, b_obs[i], err_msg=f"{where}, reset")
                waypoint[i] = 0
        observations = b_obs
    batch.close()
    for env in singles:
        env.close()
    return events


@pytest.fixture(scope="module")
def nav_config():
    return load_train_config("training/configs/nav.toml").env_config()


def test_lidar_nav_batched_equals_single_envs(nav_config) -> None:
    """nav.toml's env (random response, noise, dropout, mount error, mass, wind), plus slots with a
    short time limit, the ideal autopilot, and the shield with scan latency and PX4's response."""
    configs = [
        nav_config,
        replace(nav_config, max_steps=40),
        replace(nav_config, autopilot_response="ideal", acceptance_radius=2.0),
        replace(nav_config, shield=True, latency_scans=1, autopilot_response="px4", unshielded_fraction=0.3),
    ]
    events = _run_side_by_side([lambda c=c: LidarNavEnv(c) for c in configs], steps=400)
    assert events["collisions"] >= 1 and events["truncations"] >= 1 and events["resets"] >= 4, events


def test_lidar_nav_waypoint_switching_is_the_same(nav_config) -> None:
    """Open worlds and a wide acceptance radius: waypoints are reached and switched in the batch too."""
    config = replace(
        nav_config, families=("rooms", "pillars"), acceptance_radius=2.5, difficulty_range=(0.0, 0.2)
    )
    singles = [LidarNavEnv(config) for _ in range(3)]
    batch = BatchedEnvs([LidarNavEnv(config) for _ in range(3)])
    observations = [batch.reset(i, seed=5 + i)[0] for i in range(3)]
    for i, env in enumerate(singles):
        env.reset(seed=5 + i)
    rng = np.random.default_rng(1)
    switches = 0
    waypoint = [0, 0, 0]
    for t in range(300):
        actions = _goal_seeker(observations, rng, singles[0].action_space.shape[0])
        b_obs, b_rew, b_term, b_trunc, b_info = batch.step(actions)
        for i, env in enumerate(singles):
            obs, reward, terminated, truncated, info = env.step(actions[i])
            np.testing.assert_array_equal(obs, b_obs[i], err_msg=f"step {t}, env {i}")
            assert (reward, terminated, truncated) == (b_rew[i], b_term[i], b_trunc[i])
            _assert_same_info(info, b_info[i], f"step {t}, env {i}")
            switches += info["waypoint"] > waypoint[i]
            waypoint[i] = info["waypoint"]
            if terminated or truncated:
                env.reset()
                b_obs[i], _ = batch.reset(i)
                waypoint[i] = 0
        observations = b_obs
    assert switches >= 2


def test_lidar_avoid_batched_equals_single_envs() -> None:
    """shipped.toml's env through training's TrainingWorlds (narrow rooms, difficulty spread), and
    slots with the shield, ArduPilot's and random responses."""
    train = load_train_config("training/configs/shipped.toml")
    base = train.env_config(max_steps=120)

    def make(config: EnvConfig) -> Callable[[], gym.Env]:
        return lambda: TrainingWorlds(LidarAvoidEnv(config), 0.65, 0.35, 0.4, (6.0, 9.0))

    configs = [
        base,
        replace(base, shield=True, autopilot_response="ardupilot"),
        replace(base, autopilot_response="random", reward="tutorial"),
    ]
    events = _run_side_by_side([make(c) for c in configs], steps=400)
    assert events["collisions"] >= 1 and events["truncations"] >= 1, events


def test_a_wrapper_that_changes_step_is_refused() -> None:
    with pytest.raises(ValueError, match="reset-only"):
        BatchedEnvs([gym.wrappers.ClipAction(LidarAvoidEnv())])


def test_different_sensors_cannot_share_a_batch() -> None:
    from flightsim.envs.raycast import LidarConfig

    with pytest.raises(ValueError, match="lidar"):
        BatchedEnvs([LidarAvoidEnv(), LidarAvoidEnv(EnvConfig(lidar=LidarConfig(noise_std=0.1)))])
