"""stable-baselines3's ``VecEnv`` over :class:`flightsim.envs.batch_env.BatchedEnvs`: N simulators
in this process.

The semantics are SB3's own vector envs' (``DummyVecEnv`` / ``SubprocVecEnv``): ``seed`` and
``set_options`` apply at the next reset, a finished episode resets at once and its last
observation is ``info["terminal_observation"]``, ``info["TimeLimit.truncated"]`` is set on every
step, and ``get_attr`` / ``set_attr`` / ``env_method`` reach each slot's outermost env (so the
curriculum's ``env_method("set_difficulty", d)`` reaches ``TrainingWorlds``). Rewards come back as
float64, as ``SubprocVecEnv`` returns them. What changes is the cost: no worker processes, no
pipes, and the vehicles and lidars of all N envs stepped in compiled batches.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common import env_util
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn

from flightsim.envs.batch_env import BatchedEnvs


class BatchedVecEnv(VecEnv):
    """N LidarAvoid-v0 / LidarNav-v0 envs as one SB3 vector env, stepped in batches in this process.

    :param env_fns: one thunk per env, as for ``DummyVecEnv`` (each returns a LidarAvoidEnv or
        LidarNavEnv, possibly in reset-only wrappers)
    """

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]]) -> None:
        self.envs = [fn() for fn in env_fns]
        self.batch = BatchedEnvs(self.envs)
        super().__init__(len(self.envs), self.batch.observation_space, self.batch.action_space)
        self._actions: np.ndarray | None = None

    def reset(self) -> np.ndarray:
        observations = []
        for i in range(self.num_envs):
            options = self._options[i] or None
            observation, self.reset_infos[i] = self.batch.reset(i, seed=self._seeds[i], options=options)
            observations.append(observation)
        self._reset_seeds()
        self._reset_options()
        return np.stack(observations)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("step_wait() without step_async()")
        observations, rewards, terminated, truncated, infos = self.batch.step(self._actions)
        self._actions = None
        dones = np.zeros(self.num_envs, dtype=bool)
        for i in range(self.num_envs):
            done = terminated[i] or truncated[i]
            dones[i] = done
            infos[i]["TimeLimit.truncated"] = truncated[i] and not terminated[i]
            if done:
                infos[i]["terminal_observation"] = observations[i]
                observations[i], self.reset_infos[i] = self.batch.reset(i)
        return np.stack(observations), np.array(rewards, dtype=np.float64), dones, infos

    def close(self) -> None:
        self.batch.close()

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [env.render() for env in self.envs]

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [env.get_wrapper_attr(attr_name) for env in self._targets(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        for env in self._targets(indices):
            env.set_wrapper_attr(attr_name, value)

    def env_method(
        self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs
    ) -> list[Any]:
        return [
            env.get_wrapper_attr(method_name)(*method_args, **method_kwargs) for env in self._targets(indices)
        ]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [env_util.is_wrapped(env, wrapper_class) for env in self._targets(indices)]

    def _targets(self, indices: VecEnvIndices) -> list[gym.Env]:
        return [self.envs[i] for i in self._get_indices(indices)]
