"""The mirror of a demonstration is the demonstration of the mirrored world (training.mirror)."""

from __future__ import annotations

import numpy as np
import pytest

from companion.perception.observation import ObservationLayout
from flightsim.envs.nav_env import LidarNavEnv, NavEnvConfig
from flightsim.worlds.world import Box, World
from training.mirror import mirror_for


def clutter(side: float) -> World:
    """A 20 × 8 m hall with an uneven clutter of boxes; ``side`` -1 reflects it across the start's
    nose (y → -y), the start facing +x on y = 0."""
    boxes = ((-5.0, 1.2, 0.4), (-3.0, -2.0, 0.6), (0.0, 0.5, 0.3), (2.5, 2.5, 0.5))
    return World(
        "clutter", (20.0, 8.0), 3.0,
        tuple(Box((x, side * y, 1.5), (size, 2 * size, 3.0)) for x, y, size in boxes),
        (-8.0, 0.0, 1.5), 0.0, ((-1.0, side * -2.5, 1.5), (6.0, side * 1.5, 1.5)),
    )  # fmt: skip


@pytest.mark.parametrize("sideways", [False, True])
def test_the_mirrored_frames_are_the_frames_of_the_mirrored_world(sideways: bool) -> None:
    """Flown through a cluttered hall and through its reflection with mirrored commands, the two
    envs' stacked frames (scan, route-bent goal, velocity, drift) are each other's mirror; with a
    sideways action too, whose sideways part the mirror reverses."""
    config = NavEnvConfig(autopilot_response="ideal", drift=True, route=True, max_steps=60, sideways=sideways)
    envs = LidarNavEnv(config), LidarNavEnv(config)
    mirror = mirror_for(config.layout, n_stack=1, sideways=sideways)
    rng = np.random.default_rng(0)
    try:
        obs, _ = envs[0].reset(seed=0, options={"world": clutter(1.0)})
        mirrored, _ = envs[1].reset(seed=0, options={"world": clutter(-1.0)})
        for _ in range(30):
            np.testing.assert_allclose(mirror.observations(obs), mirrored, atol=1e-4)
            action = np.array([rng.uniform(0.2, 1.0), rng.uniform(-1.0, 1.0)], np.float32)
            if sideways:
                action = np.append(action, np.float32(rng.uniform(-1.0, 1.0)))
            obs, *_ = envs[0].step(action)
            mirrored, *_ = envs[1].step(mirror.actions(action))
        assert obs[config.layout.slices()["velocity"]].any()  # it flew: not 30 frames of a hover
    finally:
        for env in envs:
            env.close()


def test_every_frame_of_a_stack_is_mirrored_and_mirroring_twice_is_none() -> None:
    layout = ObservationLayout(n_bins=8, goal=True, drift=True, command=True, firmware=True)
    mirror = mirror_for(layout, n_stack=3)
    frame = np.arange(1, layout.frame_size + 1, dtype=np.float32)
    stacked = np.concatenate([frame, frame + 100, frame + 200])[None]
    flipped = mirror.observations(stacked)
    # bins reversed; goal cos, distance, forward velocity and drift, forward command, firmware kept;
    # goal sin, left velocity, left drift and the yaw-rate command negated
    expected = [8, 7, 6, 5, 4, 3, 2, 1, 9, -10, 11, 12, -13, 14, -15, 16, -17, 18]
    np.testing.assert_array_equal(flipped[0, :18], expected)
    np.testing.assert_array_equal(flipped[0, 36:54], np.array(expected) + np.sign(expected) * 200)
    np.testing.assert_array_equal(mirror.observations(flipped), stacked)
    np.testing.assert_array_equal(mirror.actions(np.array([[0.5, 0.3]])), [[0.5, -0.3]])
    with pytest.raises(ValueError, match="n_stack"):
        mirror_for(layout, n_stack=0)


def test_each_movers_left_position_and_left_velocity_are_mirrored() -> None:
    layout = ObservationLayout(n_bins=4, goal=True, movers=True)
    frame = np.arange(1, layout.frame_size + 1, dtype=np.float32)
    flipped = mirror_for(layout, n_stack=1).observations(frame[None])[0]
    movers = layout.slices()["movers"]
    # per slot: forward kept, left negated, forward velocity kept, left velocity negated, radius, presence
    slots = frame[movers].reshape(3, 6) * np.array([1, -1, 1, -1, 1, 1], np.float32)
    np.testing.assert_array_equal(flipped[movers], slots.ravel())
    np.testing.assert_array_equal(flipped[:4], [4, 3, 2, 1])
