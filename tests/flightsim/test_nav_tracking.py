"""LidarNav-v0 tracks what moves, as the companion does in flight: a walker crossing while the vehicle
flies is kept out of the route's map and the drift estimate, the pillars still go on the map, and a
static world flies exactly as it does without tracking."""

from __future__ import annotations

import hashlib
from dataclasses import replace

import numpy as np
import pytest

from flightsim.envs.nav_env import LidarNavEnv, NavEnvConfig
from flightsim.worlds.families import FAMILIES
from flightsim.worlds.moving import MovingObstacle, PathMotion
from flightsim.worlds.world import Box, Cylinder, World
from training.config import load_train_config

#: a walker crossing 5 m ahead of the start at 1.2 m/s, four pillars and a wall behind, in a hall too
#: large for its walls to be seen: the walker is much of what the lidar sees
WALKER = MovingObstacle("cylinder", PathMotion(((3.0, -5.0), (3.0, 5.0)), 1.2), 1.8, radius=0.35)
PILLARS = (
    Cylinder((2.0, 3.5), 0.3, 3.0),
    Cylinder((4.5, -3.0), 0.3, 3.0),
    Cylinder((-1.0, -3.5), 0.3, 3.0),
    Cylinder((6.0, 2.0), 0.3, 3.0),
)
CROSSING = World(
    "crossing", (40.0, 40.0), 3.0, (*PILLARS, Box((-4.0, 0.0, 1.5), (0.3, 4.0, 3.0))), (-2.0, 0.0, 1.5), 0.0,
    ((15.0, 0.0, 1.5),), moving=(WALKER,),
)  # fmt: skip


def _fly_crossing(tracking: bool, steps: int = 40) -> tuple[LidarNavEnv, np.ndarray]:
    """Slowly forward through the crossing (the measured velocity is the truth): the env at the end,
    and every step's drift estimate (forward, left, m/s)."""
    env = LidarNavEnv(NavEnvConfig(autopilot_response="ideal", drift=True, route=True, tracking=tracking))
    env.reset(seed=0, options={"world": CROSSING})
    drift = []
    for _ in range(steps):
        env.step(np.array([0.25, 0.0], np.float32))
        drift.append(env.drift_estimate)
    return env, np.array(drift)


def _occupied_near(env: LidarNavEnv, x: float, y: float, radius: float) -> bool:
    """Whether the route's map has an occupied cell within about ``radius`` of (x, y)."""
    route = env._route
    i, j, _ = route._cells(np.array([x]), np.array([y]))
    n = round(radius / route.config.resolution)
    return bool(route.occupied[i[0] - n : i[0] + n + 1, j[0] - n : j[0] + n + 1].any())


def test_a_walker_crossing_is_kept_out_of_the_route_map_and_the_drift_estimate() -> None:
    tracked, drift = _fly_crossing(tracking=True)
    untracked, drift_untracked = _fly_crossing(tracking=False)
    try:
        walker = WALKER.positions(tracked.sim_time)[0]
        assert np.array_equal(untracked._state.position, tracked._state.position)  # the same flight
        assert tracked.tracked is not None and len(tracked.tracked.moving) == 1
        assert not _occupied_near(tracked, *walker, 0.5) and _occupied_near(untracked, *walker, 0.5)
        for env in (tracked, untracked):  # the pillars are on both maps
            assert all(_occupied_near(env, *pillar.center, 0.4) for pillar in PILLARS)
        # the walker crosses from the right: matched as if it stood, it reads as a slide to the right
        # the reported velocity does not show, 0.1 m/s on average; kept out, the estimate stays near 0
        assert np.abs(drift_untracked[:, 1]).mean() > 0.08
        assert np.abs(drift[:, 1]).max() < 0.04
    finally:
        tracked.close()
        untracked.close()


def _episode_digest(config: NavEnvConfig, family: str) -> str:
    """The pinned static test's episode (validation seed 500123, difficulty 0.6, a fixed action
    sequence) in ``family``: its observations, rewards and positions."""
    env = LidarNavEnv(config)
    obs, _ = env.reset(seed=3, options={"family": family, "world_seed": 500123, "difficulty": 0.6})
    assert not env.world.moving
    h = hashlib.sha256(obs.tobytes())
    for t in range(80):
        action = np.array([0.3, 0.3 * np.sin(t / 7.0), 0.0], dtype=np.float32)
        obs, reward, terminated, truncated, info = env.step(action)
        h.update(obs.tobytes())
        h.update(np.float64(reward).tobytes())
        h.update(np.asarray(info["position"]).tobytes())
        if terminated or truncated:
            break
    env.close()
    return h.hexdigest()


@pytest.mark.parametrize("family", FAMILIES)
def test_a_static_world_flies_the_same_with_tracking_on_and_off(family: str) -> None:
    """Training's env (range noise and dropout, the drift estimate and the route, a random
    autopilot response): nothing taken for moving, nothing kept out, the same episode."""
    config = load_train_config("training/configs/nav.toml").env_config()
    assert config.tracking and config.drift and config.route
    assert _episode_digest(config, family) == _episode_digest(replace(config, tracking=False), family)


def test_the_movers_frame_carries_the_walker_crossing_ahead_and_needs_the_tracker() -> None:
    """With ``movers``, the frame ends with the tracker's movers: the walker crossing 5 m ahead from
    the right, at 1.2 m/s to the left (0.4 of 3 m/s), in the first slot, the two others empty; the
    flight and the rest of the frame are those without it."""
    config = NavEnvConfig(autopilot_response="ideal", movers=True)
    env, plain = LidarNavEnv(config), LidarNavEnv(replace(config, movers=False))
    movers = config.layout.slices()["movers"]
    try:
        obs, _ = env.reset(seed=0, options={"world": CROSSING})
        plain_obs, _ = plain.reset(seed=0, options={"world": CROSSING})
        for _ in range(40):
            obs, *_ = env.step(np.array([0.25, 0.0], np.float32))
            plain_obs, *_ = plain.step(np.array([0.25, 0.0], np.float32))
            np.testing.assert_array_equal(obs[: movers.start], plain_obs)
        slots = obs[movers].reshape(3, 6)
        walker = WALKER.positions(env.sim_time)[0]
        x, y, _ = env._state.position.tolist()
        assert slots[0, 5] == 1.0 and abs(slots[0, 3] - 0.4) < 0.05  # present, moving left
        # heading east: the walker's offset is its body position (forward, left), / 10 m
        np.testing.assert_allclose(slots[0, :2], [(walker[0] - x) / 10.0, (walker[1] - y) / 10.0], atol=0.02)
        np.testing.assert_array_equal(slots[1:], 0.0)
    finally:
        env.close()
        plain.close()
    with pytest.raises(ValueError, match="movers = true needs tracking = true"):
        NavEnvConfig(movers=True, tracking=False)
