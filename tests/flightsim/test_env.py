"""LidarAvoid environment: API checkers, determinism, options, termination, scan semantics, rewards."""

from __future__ import annotations

import importlib
import math
from importlib.resources import files
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env

import flightsim
from companion.common.errors import UserError
from companion.common.tomlconfig import from_dict
from companion.perception.scan import ScanConfig, scan_from_points
from companion.safety.shield import ShieldConfig
from flightsim.envs.env import TRAIN_SEED_OFFSET, EnvConfig, LidarAvoidEnv, slice_band
from flightsim.envs.raycast import LidarConfig, VLP16Raycaster, grid_to_points
from flightsim.envs.reward import StepOutcome, progress_reward, tutorial_reward
from flightsim.worlds.world import Box, Cylinder, World, generate_world

TWO_PILLARS = Path(str(files("flightsim") / "worlds" / "two-pillars.json"))
# a corridor: start at x = -3 facing +x: end wall (x = +4) 7 m ahead, back wall 1 m, side walls 2 m
CORRIDOR = World("corridor", (8.0, 4.0), 3.0, (), (-3.0, 0.0, 1.5), 0.0)
# a pillar front-left and a box to the right in a 12 m room
PILLAR = World(
    "pillar", (12.0, 12.0), 3.0, (Cylinder((2.0, 2.0), 0.5, 3.0), Box((0, -3.0, 1.5), (1, 1, 3))),
    (0.0, 0.0, 1.5), 0.0,
)  # fmt: skip
ANGLES = (np.arange(360) + 0.5 + 180.0) % 360.0 - 180.0  # bin centres, degrees CCW from the nose


def reactive_policy(scan: np.ndarray) -> np.ndarray:
    """Head for the most open direction (clearance over a ±20° window), slow down near things."""
    r = scan * 10.0
    ext = np.concatenate([r[-20:], r, r[:20]])
    clear = np.lib.stride_tricks.sliding_window_view(ext, 41).min(axis=1)
    best = int(np.argmax(np.minimum(clear, 3.0) - 0.004 * np.abs(ANGLES)))
    a1 = float(np.clip(ANGLES[best] / 40.0, -1.0, 1.0))
    a0 = float(np.clip((clear[0] - 0.7) / 1.5, 0.0, 1.0)) if abs(ANGLES[best]) < 50 else 0.0
    return np.array([a0, a1], np.float32)


@pytest.fixture(scope="module")
def env() -> LidarAvoidEnv:
    e = LidarAvoidEnv(EnvConfig(max_steps=200))
    yield e
    e.close()


# -- API ---------------------------------------------------------------------------------------


def test_gymnasium_env_checker() -> None:
    env = gym.make(flightsim.ENV_ID, config=EnvConfig(max_steps=50), render_mode="rgb_array")
    gym_check_env(env.unwrapped, skip_render_check=False)
    env.close()


def test_stable_baselines3_env_checker() -> None:
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = LidarAvoidEnv(EnvConfig(max_steps=50))
    sb3_check_env(env, warn=True)
    env.close()


def test_registered_on_import_and_reimport_is_harmless() -> None:
    importlib.reload(flightsim)
    assert flightsim.ENV_ID == "flightsim/LidarAvoid-v0"
    env = gym.make(flightsim.ENV_ID, config=EnvConfig(max_steps=3, difficulty=0.0))
    obs, info = env.reset(seed=3)
    assert env.observation_space.shape == (360,) and env.action_space.shape == (2,)
    assert obs.dtype == np.float32 and env.observation_space.contains(obs)
    assert info["world"].endswith("d0.00")
    env.close()


def test_config_is_strict_loadable() -> None:
    cfg = from_dict(EnvConfig, {"difficulty": 0.8, "lidar": {"noise_std": 0.02}, "reward": "tutorial"})
    assert cfg.difficulty == 0.8 and cfg.lidar.noise_std == 0.02 and cfg.reward == "tutorial"
    with pytest.raises(UserError, match="latency_scans: 2 is above the maximum 1"):
        from_dict(EnvConfig, {"latency_scans": 2})
    with pytest.raises(UserError, match="reward: must be one of"):
        from_dict(EnvConfig, {"reward": "speed"})
    with pytest.raises(UserError, match=r"lidar\.dropout"):
        from_dict(EnvConfig, {"lidar": {"dropout": -0.1}})


# -- determinism and options ---------------------------------------------------------------------


def _rollout(env: LidarAvoidEnv, seed: int, n: int = 15, **reset_kw) -> tuple[np.ndarray, list[float]]:
    obs, _ = env.reset(seed=seed, **reset_kw)
    actions = np.random.default_rng(99).uniform(-1, 1, (n, 2)).astype(np.float32)
    observations, rewards = [obs], []
    for a in actions:
        obs, r, term, trunc, _ = env.step(a)
        observations.append(obs)
        rewards.append(r)
        if term or trunc:
            break
    return np.stack(observations), rewards


def test_reset_and_rollout_are_deterministic_for_a_seed(env: LidarAvoidEnv) -> None:
    obs_a, rew_a = _rollout(env, seed=11)
    world_a = env.world
    obs_b, rew_b = _rollout(env, seed=11)
    assert env.world == world_a
    np.testing.assert_array_equal(obs_a, obs_b)
    assert rew_a == rew_b
    env.reset(seed=12)
    assert env.world != world_a


def _episode_record(env: LidarAvoidEnv, seed: int, n: int = 40) -> tuple[np.ndarray, list]:
    obs, info = env.reset(seed=seed)
    actions = np.random.default_rng(7).uniform(-1, 1, (n, 2)).astype(np.float32)
    actions[:, 0] = 0.3 + 0.6 * np.abs(actions[:, 0])
    observations, rest = [obs], [sorted((k, np.asarray(v).tolist()) for k, v in info.items())]
    for a in actions:
        obs, r, term, trunc, info = env.step(a)
        observations.append(obs)
        rest.append((r, term, trunc, sorted((k, np.asarray(v).tolist()) for k, v in info.items())))
        if term or trunc:
            break
    return np.stack(observations), rest


def test_seeded_episode_replays_bit_exact_in_a_fresh_or_used_env() -> None:
    # The speed work (scan, ray cast glue, vehicle loop, single reset) must not move a single bit:
    # a fresh env and one that has flown (and been reset from) elsewhere give the same episode.
    cfg = EnvConfig(max_steps=60, mount_yaw_error_deg=3.0, mass_jitter=0.2, wind_gust_max=1.0)
    fresh, used = LidarAvoidEnv(cfg), LidarAvoidEnv(cfg)
    try:
        _episode_record(used, seed=1)  # fly somewhere else first
        obs_a, rest_a = _episode_record(fresh, seed=3)
        obs_b, rest_b = _episode_record(used, seed=3)
        np.testing.assert_array_equal(obs_a, obs_b)
        assert rest_a == rest_b
    finally:
        fresh.close()
        used.close()


def test_training_worlds_use_seeds_above_the_held_out_range(env: LidarAvoidEnv) -> None:
    env.reset(seed=0)
    for _ in range(5):
        env.reset()
        seed = int(env.world.name.split("-")[1])
        assert TRAIN_SEED_OFFSET <= seed < 2**31


def test_world_options(env: LidarAvoidEnv) -> None:
    _, info = env.reset(seed=1, options={"world": str(TWO_PILLARS)})
    assert info["world"] == "two-pillars"
    np.testing.assert_allclose(info["position"], (-4.5, 0.0, 1.5), atol=1e-6)
    _, info = env.reset(seed=1, options={"world": CORRIDOR})
    assert env.world is CORRIDOR and info["yaw"] == pytest.approx(0.0)
    env.reset(seed=1, options={"world_seed": 42, "difficulty": 0.9})
    assert env.world == generate_world(42, 0.9)
    env.reset(seed=1, options={"world_seed": 42, "difficulty": 0.9, "room_width": 7.0})
    assert env.world == generate_world(42, 0.9, room_width=7.0) and env.world.room_size[1] == 7.0
    with pytest.raises(ValueError, match="either 'world'"):
        env.reset(options={"world": str(TWO_PILLARS), "room_width": 7.0})
    with pytest.raises(ValueError, match="unknown reset option 'wrld'"):
        env.reset(options={"wrld": "x"})
    with pytest.raises(UserError, match="not found"):
        env.reset(options={"world": "/nonexistent/world.json"})


def test_world_file_config() -> None:
    env = LidarAvoidEnv(EnvConfig(world_file=str(TWO_PILLARS), max_steps=5))
    for seed in (1, 2):
        _, info = env.reset(seed=seed)
        assert info["world"] == "two-pillars"
    env.close()
    with pytest.raises(UserError, match="not found"):
        LidarAvoidEnv(EnvConfig(world_file="/nonexistent.json"))


# -- episode end and info ------------------------------------------------------------------------


def test_collision_terminates_with_the_collision_reward(env: LidarAvoidEnv) -> None:
    _, info = env.reset(seed=0, options={"world": CORRIDOR})
    assert info["min_distance"] == pytest.approx(1.0, abs=1e-3) and not info["collision"]
    for steps in range(1, 100):  # noqa: B007 (used after the loop)
        _, reward, terminated, truncated, info = env.step(np.array([1.0, 0.0], np.float32))
        if terminated:
            break
    assert info["collision"] and not truncated
    assert info["min_distance"] < 0.25
    assert reward == -100.0
    assert 4.0 - info["position"][0] < 0.25  # the end wall at x = +4
    assert info["distance"] == pytest.approx(info["position"][0] + 3.0, abs=0.1)
    assert steps * 0.1 < 7.0 / 1.5  # it really flew at close to 2 m/s


def test_shield_option_flies_the_same_actions_to_a_stop_short_of_the_wall() -> None:
    env = LidarAvoidEnv(EnvConfig(shield=True))
    _, info = env.reset(seed=0, options={"world": CORRIDOR})
    for _ in range(100):  # full speed at the end wall, as in the collision test above
        _, _, terminated, _, info = env.step(np.array([1.0, 0.0], np.float32))
        assert not terminated
    # it flew the corridor and stopped at the shield's estop_distance (0.3 m), short of the 0.25 m radius
    assert not info["collision"] and info["min_distance"] > 0.28
    assert info["distance"] > 6.0
    assert env.unwrapped._shield.interventions["stopping_distance"] > 0
    env.close()


def test_env_shield_watches_the_measured_velocity_and_the_responses_limits() -> None:
    env = LidarAvoidEnv(EnvConfig(shield=True, autopilot_response="ardupilot"))
    shield = env.unwrapped._shield
    assert shield.max_yaw_rate == pytest.approx(math.radians(60.0))  # ATC_RATE_WPY_MAX default
    env.reset(seed=0, options={"world": CORRIDOR})
    for _ in range(10):
        env.step(np.array([1.0, 0.0], np.float32))
    assert shield.interventions["velocity_nan"] == 0
    env.unwrapped.measured_body_velocity = lambda: np.array([math.nan, 0.0])  # the shield reads it
    env.step(np.array([1.0, 0.0], np.float32))
    assert shield.interventions["velocity_nan"] == 1
    env.close()


def test_env_shield_flies_the_limits_of_its_config() -> None:
    """``shield_limits`` is the ``[shield]`` table the drone flies: the env's shield and the
    overspeed cap use it, not the defaults."""

    def top_speed(limits: ShieldConfig) -> float:
        env = LidarAvoidEnv(EnvConfig(shield=True, shield_limits=limits))
        env.reset(seed=0, options={"world": CORRIDOR})
        forward = np.array([1.0, 0.0], np.float32)
        speeds = [env.step(forward)[4]["measured_velocity_body"][0] for _ in range(25)]
        env.close()
        return max(speeds)

    assert top_speed(ShieldConfig()) > 1.5
    assert 0.3 < top_speed(ShieldConfig(max_speed=0.5)) < 0.6
    config = from_dict(EnvConfig, {"shield": True, "shield_limits": {"max_speed": 0.5}})
    assert config.shield_limits == ShieldConfig(max_speed=0.5)
    with pytest.raises(UserError, match=r"shield_limits\.max_accel: .*maximum"):
        from_dict(EnvConfig, {"shield_limits": {"max_accel": 100.0}})
    # the base env keeps no drift estimate for drift_compensation to carry: refused, not ignored
    with pytest.raises(UserError, match="drift_compensation needs a drift estimate"):
        from_dict(EnvConfig, {"shield_limits": {"drift_compensation": 0.6}})


def test_unshielded_fraction_flies_some_episodes_without_the_shield() -> None:
    env = LidarAvoidEnv(EnvConfig(shield=True, unshielded_fraction=0.5))

    def hits_the_wall(seed: int) -> bool:
        env.reset(seed=seed, options={"world": CORRIDOR})
        for _ in range(60):  # full speed at the end wall: only an unshielded episode reaches it
            _, _, terminated, _, _ = env.step(np.array([1.0, 0.0], np.float32))
            if terminated:
                return True
        return False

    outcomes = [hits_the_wall(seed) for seed in range(12)]
    assert 0 < sum(outcomes) < 12
    assert [hits_the_wall(seed) for seed in range(4)] == outcomes[:4]  # drawn from the episode's seed
    env.close()


def test_overspeed_penalty_charges_asking_for_more_than_the_shield_allows() -> None:
    def rewards(penalty: float, a0: float) -> list[float]:
        env = LidarAvoidEnv(EnvConfig(shield=True, overspeed_penalty=penalty))
        env.reset(seed=0, options={"world": CORRIDOR})
        out = [env.step(np.array([a0, 0.0], np.float32))[1] for _ in range(100)]
        env.close()
        return out

    free, charged = rewards(0.0, 1.0), rewards(2.0, 1.0)
    assert all(c <= f for c, f in zip(charged, free, strict=True))
    # held off the wall by the shield's keep-out push, asking 2 m/s where it lets under 0.5 m/s through
    assert 1.5 < free[-1] - charged[-1] <= 2.0
    assert rewards(2.0, 0.0) == rewards(0.0, 0.0)  # asking for nothing costs nothing


def test_overspeed_along_the_travel_charges_where_the_motion_is_capped_too() -> None:
    """``overspeed_travel``: the cap also watches the measured velocity, as the shield in flight
    does, so it charges at least as much as the nose alone, more when the course runs closer to a
    wall than the nose, and flies the very same episode."""

    def flight(travel: bool, a0_turning: float) -> tuple[list[float], list[np.ndarray]]:
        config = EnvConfig(overspeed_penalty=2.0, overspeed_travel=travel, autopilot_response="px4")
        env = LidarAvoidEnv(config)
        env.reset(seed=0, options={"world": CORRIDOR})
        rewards, positions = [], []
        for k in range(40):  # along the corridor, then a hard turn towards its wall
            action = [1.0, 0.0] if k < 15 else [a0_turning, 1.0]
            _, reward, terminated, truncated, info = env.step(np.array(action, np.float32))
            rewards.append(reward)
            positions.append(info["position"])
            if terminated or truncated:
                break
        env.close()
        return rewards, positions

    (nose, nose_path), (travel, travel_path) = flight(False, 1.0), flight(True, 1.0)
    np.testing.assert_array_equal(np.array(nose_path), np.array(travel_path))  # a reward term only
    assert all(t <= n + 1e-9 for t, n in zip(travel, nose, strict=True))
    assert sum(nose) - sum(travel) > 0.5
    assert flight(True, 0.0)[0][15:] == flight(False, 0.0)[0][15:]  # asking for nothing costs nothing


def test_truncated_at_max_steps() -> None:
    env = LidarAvoidEnv(EnvConfig(max_steps=5))
    env.reset(seed=0, options={"world": CORRIDOR})
    for _ in range(4):
        assert env.step(np.zeros(2, np.float32))[3] is False
    _, _, terminated, truncated, info = env.step(np.zeros(2, np.float32))
    assert truncated and not terminated and info["steps"] == 5
    env.close()


def test_holds_altitude_and_turns_counter_clockwise(env: LidarAvoidEnv) -> None:
    env.reset(seed=0, options={"world": CORRIDOR})
    for _ in range(10):
        _, _, _, _, info = env.step(np.array([0.0, 1.0], np.float32))  # 1.5 rad/s left for 1 s
    assert 0.8 < info["yaw"] < 1.6
    assert info["position"][2] == pytest.approx(1.5, abs=0.1)


def test_observation_sees_the_room(env: LidarAvoidEnv) -> None:
    obs, _ = env.reset(seed=0, options={"world": CORRIDOR})
    assert obs[0] == pytest.approx(0.7, abs=0.005)  # end wall 7 m ahead
    assert obs[90] == pytest.approx(0.2, abs=0.005)  # left wall 2 m
    assert obs[270] == pytest.approx(0.2, abs=0.005)
    assert obs[180] == pytest.approx(0.1, abs=0.005)  # back wall 1 m behind


def test_slice_prefilter_leaves_the_scan_unchanged() -> None:
    """The env materialises only points near the scan's slice; the scan must not change."""
    rng = np.random.default_rng(0)
    world = generate_world(5, 1.0)
    caster = VLP16Raycaster(LidarConfig())
    for mount_rpy in ((0.0, 0.0, 0.0), (3.0, -8.0, 20.0)):
        scan_cfg = ScanConfig(mount_xyz=(0.05, 0.0, -0.1), mount_rpy_deg=mount_rpy)
        mount = scan_cfg.rotation()
        band = (mount[2], scan_cfg.mount_xyz[2], scan_cfg.slice_height + 1e-3)
        for _ in range(5):
            c, s = math.cos(rng.uniform(0, 6.3)), math.sin(rng.uniform(0, 6.3))
            rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ mount
            grid = caster.cast(world, np.array([*world.start_position[:2], 1.5]), rot)
            full = scan_from_points(grid_to_points(grid), scan_cfg)
            banded = scan_from_points(grid_to_points(grid, band), scan_cfg)
            np.testing.assert_array_equal(full, banded)


@pytest.mark.parametrize(
    "scan_cfg",
    [
        ScanConfig(),
        ScanConfig(slice_height=0.3),
        ScanConfig(mount_xyz=(0.05, 0.0, -0.1), mount_rpy_deg=(3, -8, 20)),
    ],
)
def test_env_slice_band_keeps_exactly_what_the_scan_keeps(scan_cfg: ScanConfig) -> None:
    # Level mount at the origin: the band is the scan's own slice test, to the bit (the scan then
    # keeps every point it is given); otherwise a superset. Either way the scan is unchanged.
    world = generate_world(5, 1.0)
    caster = VLP16Raycaster(LidarConfig())
    band = slice_band(scan_cfg)
    rng = np.random.default_rng(1)
    for _ in range(5):
        rot = _rz_deg(rng.uniform(0, 360)) @ _rx_deg(rng.uniform(-20, 20)) @ scan_cfg.rotation()
        grid = caster.cast(world, np.array([*world.start_position[:2], rng.uniform(0.5, 2.5)]), rot)
        full, banded = grid_to_points(grid), grid_to_points(grid, band)
        np.testing.assert_array_equal(scan_from_points(full, scan_cfg), scan_from_points(banded, scan_cfg))
        if scan_cfg.mount_xyz == (0.0, 0.0, 0.0) and scan_cfg.mount_rpy_deg == (0.0, 0.0, 0.0):
            in_slice = np.abs(full[:, 2]) < np.float32(scan_cfg.slice_height)
            np.testing.assert_array_equal(banded, full[in_slice])


def _rz_deg(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rx_deg(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


# -- domain randomisation ------------------------------------------------------------------------


def test_latency_delays_the_observation_by_one_scan() -> None:
    fresh = LidarAvoidEnv(EnvConfig(max_steps=20))
    late = LidarAvoidEnv(EnvConfig(max_steps=20, latency_scans=1))
    obs_fresh, _ = _rollout(fresh, seed=4, n=6)
    obs_late, _ = _rollout(late, seed=4, n=6)
    np.testing.assert_array_equal(obs_late[0], obs_fresh[0])
    np.testing.assert_array_equal(obs_late[2:], obs_fresh[1:-1])
    assert not np.array_equal(obs_late[1:], obs_fresh[1:])


def test_mount_yaw_error_rotates_the_scan() -> None:
    env = LidarAvoidEnv(EnvConfig(mount_yaw_error_deg=30.0))
    obs_err, _ = env.reset(seed=8, options={"world": PILLAR})
    error = env.mount_yaw_error_deg
    assert 5.0 < abs(error) <= 30.0
    clean, _ = LidarAvoidEnv(EnvConfig()).reset(seed=8, options={"world": PILLAR})
    # the sensor turned by +e sees a thing at body angle t at its own angle t - e
    shifted = np.roll(clean, -round(error))
    assert np.abs(obs_err - shifted).mean() < 0.2 * np.abs(obs_err - clean).mean()


def test_noise_dropout_mass_and_wind_change_the_flight_deterministically() -> None:
    base = _rollout(LidarAvoidEnv(EnvConfig()), seed=6)[0]
    randomised = EnvConfig(
        lidar=LidarConfig(noise_std=0.03, dropout=0.1), mass_jitter=0.2, wind_gust_max=3.0
    )
    a = _rollout(LidarAvoidEnv(randomised), seed=6)[0]
    b = _rollout(LidarAvoidEnv(randomised), seed=6)[0]
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, base)


# -- flyable worlds --------------------------------------------------------------------------------


def test_generated_hard_worlds_are_flyable() -> None:
    """A simple reactive policy flies >= 40 m in 100 s without a collision at difficulty 1."""
    env = LidarAvoidEnv(EnvConfig(max_steps=1000, difficulty=1.0))
    for seed in (0, 1):
        obs, info = env.reset(seed=seed, options={"world_seed": seed, "difficulty": 1.0})
        for _ in range(1000):
            obs, _, terminated, truncated, info = env.step(reactive_policy(obs))
            if terminated or truncated:
                break
        assert truncated and not info["collision"]
        assert info["distance"] >= 40.0
    env.close()


# -- rewards (pure) ------------------------------------------------------------------------------


def _outcome(a0=0.0, a1=0.0, scan_min=1.0, speed=0.0, collision=False) -> StepOutcome:
    return StepOutcome(np.array([a0, a1], np.float32), scan_min, speed, 2.0, collision)


def test_tutorial_reward_is_the_tutorials() -> None:
    assert tutorial_reward(_outcome(collision=True)) == -200.0
    assert tutorial_reward(_outcome()) == 1.0
    assert tutorial_reward(_outcome(a0=0.4)) == pytest.approx(1.2)
    assert tutorial_reward(_outcome(a0=-0.4)) == pytest.approx(1.0)
    assert tutorial_reward(_outcome(scan_min=0.05)) == pytest.approx(0.5)
    assert tutorial_reward(_outcome(a0=0.6, a1=-0.6)) == pytest.approx(1.0 + 0.3 - 0.2)


def test_progress_reward_pays_for_flying_not_hovering() -> None:
    hover = progress_reward(_outcome(speed=0.0))
    cruise = progress_reward(_outcome(a0=0.5, speed=1.0))
    assert hover == pytest.approx(-0.1)
    assert cruise == pytest.approx(0.5)
    assert progress_reward(_outcome(a0=0.5, speed=1.0, a1=1.0)) == pytest.approx(0.45)
    assert progress_reward(_outcome(a0=0.5, speed=1.0, scan_min=0.05)) == pytest.approx(0.0)
    assert progress_reward(_outcome(speed=-1.0)) == pytest.approx(-0.6)
    assert progress_reward(_outcome(collision=True)) == -100.0


def test_env_uses_the_configured_reward() -> None:
    env = LidarAvoidEnv(EnvConfig(reward="tutorial"))
    env.reset(seed=0, options={"world": CORRIDOR})
    _, reward, *_ = env.step(np.zeros(2, np.float32))
    assert reward == pytest.approx(1.0)
    env = LidarAvoidEnv(EnvConfig())
    env.reset(seed=0, options={"world": CORRIDOR})
    _, reward, *_ = env.step(np.zeros(2, np.float32))
    assert reward == pytest.approx(-0.1, abs=0.01)


def test_obstacle_geometry_reaches_the_observation() -> None:
    obs, _ = LidarAvoidEnv().reset(seed=0, options={"world": PILLAR})
    assert obs[45] == pytest.approx((math.hypot(2, 2) - 0.5) / 10, abs=0.01)  # front-left pillar
    assert obs[270] == pytest.approx(0.25, abs=0.005)  # box face 2.5 m to the right
