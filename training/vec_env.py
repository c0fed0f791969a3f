"""The training environments: a fresh generated world every episode, at the curriculum's difficulty,
vectorised and frame-stacked as SB3 trains on them.

Apart from :mod:`training.train` so that export (its parity rollout), benchmarks and tests build the
same vector env without importing the training loop.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
from typing import Any

import gymnasium as gym
import numpy as np

from training.config import TrainConfig


class TrainingWorlds(gym.Wrapper):
    """A fresh generated training world every episode, at a difficulty the curriculum can raise.

    Each episode's difficulty is drawn uniformly within ``spread`` of the current difficulty, so
    one run sees big sparse rooms and small crowded ones. World seeds are drawn at or above
    ``flightsim.envs.env.TRAIN_SEED_OFFSET``, so evaluation's held-out worlds (lower seeds) are never
    trained on.
    """

    def __init__(
        self,
        env: gym.Env,
        difficulty: float,
        spread: float = 0.0,
        narrow_room_prob: float = 0.0,
        narrow_room_widths: tuple[float, float] = (6.0, 9.0),
    ) -> None:
        super().__init__(env)
        self.difficulty = difficulty
        self.spread = spread
        self.narrow_room_prob = narrow_room_prob
        self.narrow_room_widths = narrow_room_widths
        self._rng = np.random.default_rng()

    def set_difficulty(self, difficulty: float) -> None:
        """Used by the curriculum through ``VecEnv.env_method``."""
        self.difficulty = float(difficulty)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        from flightsim.envs.env import TRAIN_SEED_OFFSET

        if seed is not None:
            self._rng = np.random.default_rng(seed)
        if options is None:
            world_seed = TRAIN_SEED_OFFSET + int(self._rng.integers(0, 2**31 - 1 - TRAIN_SEED_OFFSET))
            low, high = max(0.0, self.difficulty - self.spread), min(1.0, self.difficulty + self.spread)
            options = {"world_seed": world_seed, "difficulty": float(self._rng.uniform(low, high))}
            if self._rng.uniform() < self.narrow_room_prob:
                options["room_width"] = float(self._rng.uniform(*self.narrow_room_widths))
        return self.env.reset(seed=seed, options=options)


def make_env(config: TrainConfig, difficulty: float):
    """A thunk building one training environment (called inside each subprocess).

    The goal task's env draws its own training worlds (families, difficulties, training seeds).
    """
    env_config = config.env_config()

    def thunk() -> gym.Env:
        from flightsim.envs.env import LidarAvoidEnv

        ignore_sigint_in_worker()
        if config.is_goal_task:
            from flightsim.envs.nav_env import LidarNavEnv

            return LidarNavEnv(env_config)

        return TrainingWorlds(
            LidarAvoidEnv(env_config),
            difficulty,
            config.difficulty_spread,
            config.narrow_room_prob,
            config.narrow_room_widths,
        )

    return thunk


def make_vec_env(
    config: TrainConfig, n_envs: int, seed: int, subprocess: bool = True, difficulty: float | None = None
):
    """``n_envs`` simulators → VecMonitor → VecFrameStack(``config.n_stack``), seeded with ``seed``.

    ``config.vec_env`` "batched": all in this process, stepped together (:class:`BatchedVecEnv`);
    "sharded": batched shards in one worker per CPU core (:class:`ShardedVecEnv`, in this process
    as "batched" when ``subprocess`` is false); "subproc": one ``SubprocVecEnv`` worker each, or a
    ``DummyVecEnv`` in this process when ``subprocess`` is false or there is one env.
    """
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecFrameStack, VecMonitor

    from training.batched_vec_env import BatchedVecEnv

    d = config.env_config().difficulty if difficulty is None else difficulty
    thunks = [make_env(config, d) for _ in range(n_envs)]
    if config.vec_env == "sharded" and subprocess:
        from training.sharded_vec_env import ShardedVecEnv

        venv = ShardedVecEnv(thunks, os.cpu_count() or 1)
    elif config.vec_env in ("batched", "sharded"):
        venv = BatchedVecEnv(thunks)
    elif subprocess and n_envs > 1:
        venv = SubprocVecEnv(thunks, start_method="forkserver")
    else:
        venv = DummyVecEnv(thunks)
    venv.seed(seed)
    return VecFrameStack(VecMonitor(venv), n_stack=config.n_stack)


def ignore_sigint_in_worker() -> None:
    """In a worker process, leave Ctrl-C to the main process.

    A terminal's Ctrl-C reaches every process of the foreground group: without this each
    simulator and evaluation worker would print its own KeyboardInterrupt traceback while the main
    process saves ``interrupted.zip`` and closes them in order. In the main process (one env runs
    there with ``n_envs = 1``) Ctrl-C stays as it is.
    """
    if multiprocessing.parent_process() is not None:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
