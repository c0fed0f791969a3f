"""Training worlds: held-out seeds stay out, narrow rooms come at the configured rate."""

from __future__ import annotations

from flightsim.envs.env import TRAIN_SEED_OFFSET, EnvConfig, LidarAvoidEnv
from training.vec_env import TrainingWorlds


def test_narrow_rooms_are_drawn_in_range_and_seeds_stay_out_of_evaluation() -> None:
    env = TrainingWorlds(LidarAvoidEnv(EnvConfig(max_steps=5)), 0.5, 0.2, narrow_room_prob=0.5)
    env.reset(seed=3)
    widths = []
    for _ in range(12):
        env.reset()
        world = env.unwrapped.world
        assert int(world.name.split("-")[1]) >= TRAIN_SEED_OFFSET
        widths.append(world.room_size[1])
    narrow = [w for w in widths if w <= 9.0]
    assert 2 <= len(narrow) <= 10  # about half, out of 12 draws
    assert all(6.0 <= w <= 9.0 for w in narrow)
    assert all(w >= 10.0 for w in widths if w > 9.0)  # the generator's own sizes otherwise
