"""LidarNav-v0: API checkers, observation layout, waypoints in order, reward, termination, options."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env

import flightsim
from companion.common.tomlconfig import from_dict
from companion.perception.drift import DriftHoldConfig, held_drift
from companion.perception.observation import ObservationLayout
from companion.safety.shield import ShieldConfig
from flightsim.envs import seeds
from flightsim.envs.nav_env import LidarNavEnv, NavEnvConfig, time_limit_steps
from flightsim.envs.reward import GoalRewardConfig, GoalStep, StepOutcome, goal_reward
from flightsim.worlds.families import FAMILIES, generate_family_world
from flightsim.worlds.world import Box, World

# an empty 20 × 6 m hall: start at x = -8 facing +x, waypoint 1 at x = -2, waypoint 2 at x = +5
HALL = World("hall", (20.0, 6.0), 3.0, (), (-8.0, 0.0, 1.5), 0.0, ((-2.0, 0.0, 1.5), (5.0, 0.0, 1.5)))
# the same hall with a wall across it 2 m ahead of the start (the first waypoint behind it)
BLOCKED = World(
    "blocked", (20.0, 6.0), 3.0, (Box((-6.0, -1.0, 1.5), (0.3, 4.0, 3.0)),), (-8.0, 0.0, 1.5), 0.0,
    ((-2.0, 0.0, 1.5),),
)  # fmt: skip
FORWARD = np.array([1.0, 0.0], np.float32)
HOVER = np.array([0.0, 0.0], np.float32)


@pytest.fixture(scope="module")
def env() -> LidarNavEnv:
    # the ideal response: exact expectations (the default random response adds estimate error)
    e = LidarNavEnv(NavEnvConfig(autopilot_response="ideal"), render_mode="rgb_array")
    yield e
    e.close()


def test_gymnasium_env_checker() -> None:
    env = gym.make(flightsim.NAV_ENV_ID, config=NavEnvConfig(max_steps=50), render_mode="rgb_array")
    gym_check_env(env.unwrapped, skip_render_check=False)
    env.close()


def test_stable_baselines3_env_checker() -> None:
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = LidarNavEnv(NavEnvConfig(max_steps=50))
    sb3_check_env(env, warn=True)
    env.close()


def test_config_is_strict_loadable_and_checked() -> None:
    cfg = from_dict(
        NavEnvConfig,
        {"families": ["forest", "gaps"], "difficulty_range": [0.2, 0.6], "goal_reward": {"progress": 2.0}},
        prefix="env.",
    )
    assert cfg.families == ("forest", "gaps") and cfg.goal_reward.progress == 2.0
    with pytest.raises(ValueError, match="families"):
        NavEnvConfig(families=("moon",))
    with pytest.raises(ValueError, match="difficulty_range"):
        NavEnvConfig(difficulty_range=(0.8, 0.2))
    with pytest.raises(TypeError, match="NavEnvConfig"):
        LidarNavEnv(flightsim.envs.env.EnvConfig())


def test_observation_is_the_documented_layout(env: LidarNavEnv) -> None:
    obs, _ = env.reset(seed=3, options={"world": HALL})
    layout = ObservationLayout(goal=True, goal_range=30.0, velocity_scale=2.0)
    assert env.layout == layout and env.observation_space.shape == (365,)
    assert env.observation_space.contains(obs)
    # waypoint 1 is 6 m straight ahead; at rest
    np.testing.assert_allclose(obs[360:], [1.0, 0.0, 0.2, 0.0, 0.0], atol=1e-5)
    assert obs[180] == pytest.approx(0.2, abs=0.01) and obs[90] == pytest.approx(0.3, abs=0.01)  # walls
    for _ in range(15):
        obs, *_ = env.step(np.array([1.0, 1.0], np.float32))  # forward while turning left
    p, yaw = env.unwrapped._state.position, env.unwrapped._state.yaw
    bearing = math.atan2(0.0 - p[1], -2.0 - p[0]) - yaw
    np.testing.assert_allclose(obs[360:362], [math.cos(bearing), math.sin(bearing)], atol=1e-5)
    assert obs[361] < -0.3  # turned left of the goal: it is now on the right
    assert obs[363] > 0.2  # flying forward, measured


def test_the_velocity_features_are_what_the_autopilot_reports_randomised_by_default() -> None:
    env = LidarNavEnv(NavEnvConfig(max_steps=50))
    assert env.config.autopilot_response == "random"
    obs, _ = env.reset(seed=4, options={"world": HALL})
    for _ in range(10):
        obs, *_ = env.step(FORWARD)
    measured = np.clip(np.asarray(env.measured_body_velocity()) / 2.0, -1.0, 1.0)
    np.testing.assert_allclose(obs[363:365], measured, atol=1e-6)
    assert obs[363] > 0.2
    env.close()


def test_waypoints_are_reached_in_order_paid_and_the_last_terminates(env: LidarNavEnv) -> None:
    _, info = env.reset(seed=0, options={"world": HALL})
    assert info["waypoint"] == 0 and info["waypoints"] == 2
    assert info["shortest_path_m"] == pytest.approx(13.0, abs=0.15)
    assert info["time_limit_steps"] == math.ceil((10.0 + 2.0 * info["shortest_path_m"]) * 10)
    rewards, waypoints = [], []
    terminated = truncated = False
    while not (terminated or truncated):
        _, reward, terminated, truncated, info = env.step(FORWARD)
        rewards.append(reward)
        waypoints.append(info["waypoint"])
    assert terminated and not truncated and info["success"] and not info["collision"]
    first, second = waypoints.index(1), waypoints.index(2)
    assert 0 < first < second == len(waypoints) - 1
    assert env.unwrapped._state.position[0] == pytest.approx(5.0 - 1.0, abs=0.25)  # 1 m acceptance
    assert rewards[first] > 10.0 and rewards[second] > 20.0  # the bonuses
    # progress pays about a point per metre: 12 m to the second acceptance circle
    assert sum(rewards) - 30.0 + 0.02 * len(rewards) == pytest.approx(12.0, abs=0.5)


def test_collision_terminates_with_the_collision_cost(env: LidarNavEnv) -> None:
    env.reset(seed=0, options={"world": BLOCKED})
    for _ in range(100):
        _, reward, terminated, truncated, info = env.step(FORWARD)
        if terminated or truncated:
            break
    assert terminated and info["collision"] and not info["success"] and reward == -50.0


def test_truncated_at_the_path_proportional_time_limit() -> None:
    cfg = NavEnvConfig(time_limit_per_m=0.5, time_limit_slack_s=1.0, autopilot_response="ideal")
    env = LidarNavEnv(cfg)
    _, info = env.reset(seed=0, options={"world": HALL})
    limit = info["time_limit_steps"]
    assert limit == math.ceil((1.0 + 0.5 * info["shortest_path_m"]) * 10)
    rewards = []
    for step in range(1, limit + 1):
        _, reward, terminated, truncated, info = env.step(HOVER)
        rewards.append(reward)
        assert not terminated and truncated == (step == limit)
    assert sum(rewards) == pytest.approx(-0.02 * limit, abs=0.05)  # hovering only costs time
    assert time_limit_steps(20.0, cfg) == 110 and time_limit_steps(1e6, cfg) == cfg.max_steps
    env.close()


def test_goal_reward_pure() -> None:
    w = GoalRewardConfig()
    clear = StepOutcome(np.zeros(2, np.float32), 1.0, 1.0, 2.0, False)
    near = StepOutcome(np.zeros(2, np.float32), 0.05, 1.0, 2.0, False)
    crash = StepOutcome(np.zeros(2, np.float32), 0.0, 1.0, 2.0, True)
    assert goal_reward(clear, GoalStep(0.2, False, False), w) == pytest.approx(0.18)
    assert goal_reward(clear, GoalStep(-0.2, False, False), w) == pytest.approx(-0.22)
    assert goal_reward(near, GoalStep(0.0, False, False), w) == pytest.approx(-0.02 - 0.25 * 0.5)
    assert goal_reward(clear, GoalStep(0.0, True, False), w) == pytest.approx(10.0 - 0.02)
    assert goal_reward(clear, GoalStep(0.0, True, True), w) == pytest.approx(20.0 - 0.02)
    assert goal_reward(crash, GoalStep(5.0, True, True), w) == -50.0


def test_generated_worlds_from_options_and_from_the_training_range(env: LidarNavEnv) -> None:
    _, info = env.reset(seed=1, options={"family": "traps", "world_seed": 5, "difficulty": 0.7})
    assert info["family"] == "traps" and info["world"] == generate_family_world("traps", 5, 0.7).name
    assert info["shortest_path_m"] == generate_family_world("traps", 5, 0.7).shortest_path_m
    seen = set()
    for k in range(12):
        _, info = env.reset(seed=100 + k)
        family, seed = info["world"].split("-")[:2]
        assert family in FAMILIES and int(seed) in seeds.TRAIN and 0 < info["waypoints"] <= 4
        seen.add(family)
    assert len(seen) >= 4
    few = LidarNavEnv(NavEnvConfig(families=("pillars",), difficulty_range=(0.9, 0.9)))
    _, info = few.reset(seed=2)
    assert info["world"].startswith("pillars-") and info["world"].endswith("-d0.90")
    few.close()
    with pytest.raises(ValueError, match="unknown reset option 'room_width'"):
        env.reset(options={"room_width": 7.0})
    with pytest.raises(ValueError, match="no waypoints"):
        env.reset(options={"world": World("empty", (8.0, 8.0), 3.0, (), (0.0, 0.0, 1.5), 0.0)})


def test_reset_and_rollout_are_deterministic_for_a_seed(env: LidarNavEnv) -> None:
    def roll() -> list[np.ndarray]:
        obs, _ = env.reset(seed=42)
        out = [obs]
        for k in range(20):
            obs, *_ = env.step(np.array([0.8, math.sin(k / 3)], np.float32))
            out.append(obs)
        return out

    for a, b in zip(roll(), roll(), strict=True):
        np.testing.assert_array_equal(a, b)


def test_render_shows_the_waypoint_being_flown_to(env: LidarNavEnv) -> None:
    env.reset(seed=0, options={"world": HALL})
    active = np.array([0xE0, 0x8A, 0x00])  # flightsim.worlds.render's active-waypoint colour

    def active_pixels() -> int:
        img = env.render()
        return int(np.sum(np.all(np.abs(img.astype(int) - active) < 8, axis=-1)))

    assert active_pixels() > 30
    first_centre = active_pixels()
    for _ in range(60):
        _, _, terminated, _, info = env.step(FORWARD)
        if info["waypoint"] == 1:
            break
    assert info["waypoint"] == 1 and not terminated
    assert active_pixels() == pytest.approx(first_centre, rel=0.3)  # still one active waypoint, now #2


def test_the_drift_layout_passes_both_checkers_and_documents_its_frame() -> None:
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = LidarNavEnv(NavEnvConfig(max_steps=50, drift=True), render_mode="rgb_array")
    assert env.observation_space.shape == (367,)
    assert env.layout.name.endswith("+drift(forward,left/2m/s)")
    gym_check_env(env, skip_render_check=False)
    sb3_check_env(env, warn=True)
    env.close()


def test_the_command_features_carry_the_command_flown_after_the_shield() -> None:
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    free = LidarNavEnv(NavEnvConfig(max_steps=50, drift=True, command=True))
    assert free.observation_space.shape == (369,)
    assert free.layout.name.endswith("+command(forward/2m/s,yaw/1.5rad/s)")
    gym_check_env(free)
    sb3_check_env(free, warn=True)
    obs, _ = free.reset(seed=2, options={"world": HALL})
    assert obs[367:].tolist() == [0.0, 0.0]  # nothing commanded yet
    obs, *_ = free.step(np.array([0.6, -0.4], np.float32))
    np.testing.assert_allclose(obs[367:], [0.6, -0.4], atol=1e-6)
    obs, *_ = free.step(np.array([3.0, 0.2], np.float32))  # clipped to the action space
    np.testing.assert_allclose(obs[367:], [1.0, 0.2], atol=1e-6)
    free.close()
    # behind the shield, the frame carries what the shield let through: a wall 1.7 m ahead
    shielded = LidarNavEnv(NavEnvConfig(shield=True, command=True, autopilot_response="ideal"))
    obs, _ = shielded.reset(seed=2, options={"world": BLOCKED})
    for _ in range(5):
        obs, *_ = shielded.step(FORWARD)
    assert 0.0 < obs[365] < 0.9  # full speed (1.0) was asked, less was flown
    shielded.close()


def test_the_env_shield_is_given_the_drift_estimate_the_frame_carries() -> None:
    """With ``drift``, the env's shield gets the newest frame's drift estimate, as the companion
    gives its shield its own, so ``shield_limits.drift_compensation`` acts in training too."""
    limits = ShieldConfig(drift_compensation=0.6)
    env = LidarNavEnv(NavEnvConfig(shield=True, drift=True, shield_limits=limits, autopilot_response="px4"))
    shield = env.unwrapped._shield
    given: list[tuple[float, float] | None] = []
    carried: list[np.ndarray] = []
    filter_ = shield.filter

    def spy(*args, **kwargs):
        given.append(kwargs.get("drift"))
        return filter_(*args, **kwargs)

    shield.filter = spy
    env.reset(seed=3, options={"world": HALL})
    for _ in range(40):
        carried.append(env.drift_estimate)
        env.step(FORWARD)
    env.close()
    np.testing.assert_allclose(np.array(given), np.array(carried))
    assert max(abs(f) + abs(left) for f, left in given) > 0.0  # px4's estimate error: a drift to carry
    with pytest.raises(ValueError, match="drift_compensation needs a drift estimate"):
        NavEnvConfig(shield_limits=limits)


def _sideways_drift(config: NavEnvConfig, steps: int = 150) -> tuple[float, LidarNavEnv]:
    """RMS of the true sideways velocity of a vehicle told to hover in HALL, m/s (from 3 s on)."""
    env = LidarNavEnv(config)
    env.reset(seed=3, options={"world": HALL})  # a draw whose error sideways is 0.34 m/s RMS
    left = []
    for step in range(steps):
        env.step(HOVER)
        if step >= 30:
            left.append(env.true_body_velocity()[1])
    return float(np.sqrt(np.mean(np.square(left)))), env


def test_the_held_drift_stops_the_sideways_slide_the_estimate_hides() -> None:
    """PX4's response (an estimate error of 0.25 m/s, one sigma, per axis): told to
    hover, the vehicle slides sideways at the error; with ``drift_hold`` the setpoint carries the
    drift estimate beyond its deadband and the slide shrinks. The shield judges the measured velocity
    less the whole drift estimate and carries the estimate less the held part, as the companion's."""
    base = dict(autopilot_response="px4", drift=True, shield=True)
    unheld, env = _sideways_drift(NavEnvConfig(**base))
    env.close()
    held, env = _sideways_drift(NavEnvConfig(**base, drift_hold=True))
    assert unheld > 0.15  # there was a slide to stop
    assert held < 0.5 * unheld
    limits = DriftHoldConfig()
    for _ in range(100):  # on to a step where the estimate is beyond the deadband
        if abs(env.drift_estimate[1]) > limits.deadband + 0.05:
            break
        env.step(HOVER)
    hold = held_drift(env.drift_estimate, limits)
    assert env.drift_held() == hold and abs(hold[1]) > 0.04
    np.testing.assert_allclose(env.shield_velocity(), env.measured_body_velocity() - env.drift_estimate)
    np.testing.assert_allclose(env.shield_drift(), env.drift_estimate - np.array(hold))
    env.close()
    with pytest.raises(ValueError, match="drift_hold needs the drift estimate: set drift = true"):
        NavEnvConfig(drift_hold=True)


def test_the_firmware_feature_says_which_structure_the_drawn_response_has() -> None:
    env = LidarNavEnv(NavEnvConfig(max_steps=50, drift=True, firmware=True))
    assert env.observation_space.shape == (368,)
    assert env.layout.name.endswith("+firmware(ardupilot=1,px4=0)")
    gym_check_env(env)
    seen = {}
    for seed in range(8):  # "random": each structure about half of the episodes
        obs, _ = env.reset(seed=seed, options={"world": HALL})
        params = env.response_params
        seen[params.name] = obs[367]
        obs, *_ = env.step(FORWARD)
        assert obs[367] == seen[params.name]  # the whole episode
    assert seen == {"random-ardupilot": 1.0, "random-px4": 0.0}
    env.close()
    for response, flag in (("ardupilot", 1.0), ("px4", 0.0), ("ideal", 0.0)):
        fixed = LidarNavEnv(NavEnvConfig(firmware=True, autopilot_response=response))
        obs, _ = fixed.reset(seed=0, options={"world": HALL})
        assert obs[-1] == flag, response
        fixed.close()


@pytest.mark.parametrize("action", [HOVER, np.array([0.3, 0.4], np.float32)])
def test_the_drift_features_find_the_error_the_reported_velocity_hides(action) -> None:
    # PX4's calibrated response: a velocity estimate that wanders by 0.25 m/s (one sigma)
    env = LidarNavEnv(NavEnvConfig(autopilot_response="px4", drift=True))
    obs, _ = env.reset(seed=11, options={"world": HALL})
    assert np.all(obs[365:367] == 0.0)  # nothing matched yet
    errors = []
    for _ in range(60):
        obs, *_ = env.step(action)
        yaw = float(env.true_state.yaw)
        ex, ey = env.estimate_error
        truth = np.array([math.cos(yaw) * ex + math.sin(yaw) * ey, -math.sin(yaw) * ex + math.cos(yaw) * ey])
        errors.append((obs[365:367] * 2.0, truth))
    np.testing.assert_allclose(obs[365:367] * 2.0, env.drift_estimate, atol=1e-6)
    seen, truth = map(np.array, zip(*errors[20:], strict=True))
    assert np.abs(truth).max() > 0.1  # there was an error to find
    rms = lambda x: float(np.sqrt(np.mean(x**2)))  # noqa: E731
    # most of the error is found; the rest is the filter's lag (0.5 s) behind an error that wanders
    # within a second (0.59 of it measured; none found would be 1.0, a sign error 2.0)
    assert rms(seen - truth) < 0.7 * rms(truth)
    env.close()


def test_the_route_sends_the_goal_features_through_the_gap_and_passes_both_checkers() -> None:
    """BLOCKED's wall leaves a gap at y 1..3: with ``route`` the goal features point at it (left of
    the waypoint straight ahead) and read the longer way round; without, straight ahead."""
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    routed = LidarNavEnv(NavEnvConfig(autopilot_response="ideal", route=True, max_steps=50))
    straight = LidarNavEnv(NavEnvConfig(autopilot_response="ideal", max_steps=50))
    try:
        obs, _ = routed.reset(seed=0, options={"world": BLOCKED})
        direct, _ = straight.reset(seed=0, options={"world": BLOCKED})
        assert direct[360:363] == pytest.approx([1.0, 0.0, 6.0 / 30.0], abs=1e-3)
        cos, sin, distance = obs[360:363]
        assert sin > 0.4 and cos > 0.3  # ahead-left, toward the gap's near side
        assert distance * 30.0 > 6.5  # around the wall's end, not the straight 6 m
        np.testing.assert_array_equal(obs[:360], direct[:360])  # the scan is untouched
        gym_check_env(routed)
        sb3_check_env(routed, warn=True)
    finally:
        routed.close()
        straight.close()


def test_a_sideways_action_flies_left_and_passes_both_checkers() -> None:
    """With ``sideways`` the action's third component is a speed to the left: from a hover in HALL
    (facing +x, the ideal response) one of 0.5 for 2 s carries the vehicle about 1 m to the left
    (+y) and hardly forward; (a0, a1, 0) flies what the two-component env flies for (a0, a1)."""
    config = NavEnvConfig(autopilot_response="ideal", sideways=True)
    env = LidarNavEnv(config)
    assert env.action_space.shape == (3,)
    env.reset(seed=0, options={"world": HALL})
    for _ in range(20):
        env.step(np.array([0.0, 0.0, 0.5], np.float32))
    moved = env.true_state.position[:2] - np.array(HALL.start_position[:2])
    assert 0.6 < moved[1] < 1.1 and abs(moved[0]) < 0.1, moved
    plain = LidarNavEnv(NavEnvConfig(autopilot_response="ideal"))
    observations = []
    pairs = ((env, np.array([0.6, 0.3, 0.0], np.float32)), (plain, np.array([0.6, 0.3], np.float32)))
    for e, action in pairs:
        e.reset(seed=1, options={"world": HALL})
        observations.append([e.step(action)[0] for _ in range(10)])
    np.testing.assert_array_equal(observations[0], observations[1])
    gym_check_env(env)
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    sb3_check_env(env, warn=True)
    env.close()
    plain.close()


@pytest.mark.parametrize("shield", [False, True])
def test_a_sideways_action_towards_a_wall_is_stopped_by_the_shield(shield: bool) -> None:
    """Full speed to the left in HALL (the wall 3 m to the left): alone the vehicle strikes the
    wall; behind the env's shield, which judges the command along its course, it stops short."""
    env = LidarNavEnv(NavEnvConfig(autopilot_response="ideal", sideways=True, shield=shield))
    env.reset(seed=0, options={"world": HALL})
    terminated = False
    for _ in range(80):
        _, _, terminated, _, info = env.step(np.array([0.0, 0.0, 1.0], np.float32))
        if terminated:
            break
    assert terminated == (not shield) and info["collision"] == (not shield)
    if shield:
        assert 1.0 < env.true_state.position[1] < 3.0 - env.config.vehicle_radius
    env.close()
