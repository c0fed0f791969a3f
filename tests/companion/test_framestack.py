"""FrameStack must feed the policy exactly what SB3's VecFrameStack fed it in training."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from stable_baselines3.common.vec_env import DummyVecEnv, VecFrameStack

from companion.perception.framestack import FrameStack


class ReplayEnv(gym.Env):
    """Emits a fixed sequence of scans; episode ends where the sequence says."""

    observation_space = gym.spaces.Box(0.0, 1.0, (360,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def __init__(self, scans: np.ndarray, done_at: set[int]) -> None:
        self.scans, self.done_at, self.i = scans, done_at, 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        obs = self.scans[self.i]
        self.i += 1
        return obs, {}

    def step(self, action):
        obs = self.scans[self.i]
        done = self.i in self.done_at
        self.i += 1
        return obs, 0.0, done, False, {}


def test_matches_vec_frame_stack_across_resets() -> None:
    rng = np.random.default_rng(7)
    scans = rng.random((40, 360), dtype=np.float32)
    done_at = {9, 23}  # steps whose episode ends; the next scan is a reset observation
    venv = VecFrameStack(DummyVecEnv([lambda: ReplayEnv(scans, done_at)]), n_stack=4)
    ours = FrameStack(4, 360)

    theirs = venv.reset()[0]
    mine = ours.reset(scans[0])
    np.testing.assert_array_equal(mine, theirs)
    i = 1
    while i < 30:
        obs, _, dones, _ = venv.step(np.zeros((1, 2), np.float32))
        if dones[0]:
            # DummyVecEnv auto-resets: the returned obs comes from the reset scan, i + 1.
            i += 1
            mine = ours.reset(scans[i])
        else:
            mine = ours.push(scans[i])
        np.testing.assert_array_equal(mine, obs[0])
        i += 1


def test_oldest_first_newest_last_and_zeros_after_reset() -> None:
    fs = FrameStack(4, 3)
    first = fs.reset(np.array([1, 1, 1]))
    np.testing.assert_array_equal(first, [0] * 9 + [1, 1, 1])
    fs.push(np.array([2, 2, 2]))
    out = fs.push(np.array([3, 3, 3]))
    np.testing.assert_array_equal(out, [0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3])
    out[:] = -1  # returned arrays are copies
    np.testing.assert_array_equal(fs.push(np.array([4, 4, 4]))[-6:], [3, 3, 3, 4, 4, 4])


def test_rejects_a_scan_of_the_wrong_size() -> None:
    with pytest.raises(ValueError, match="expects 360"):
        FrameStack().push(np.zeros(359))
