"""N LidarAvoid-v0 / LidarNav-v0 environments stepped together in one process.

Not a gymnasium env and no stable-baselines3 (the SB3 ``VecEnv`` adapter is
``training/batched_vec_env.py``). Each slot is a real :class:`~flightsim.envs.env.LidarAvoidEnv` (or
:class:`~flightsim.envs.nav_env.LidarNavEnv`): its own ``reset`` chooses the world, draws the domain
randomisation and resets the vehicle, and a step runs the env's own three phases
(``_command``: action, shield, wind; ``_arrive``: pose, path, collision; ``_conclude``: reward,
observation, info). Only the two expensive middles are batched: the flight of all N vehicles
(:class:`~flightsim.vehicle.batch_vehicle.VehicleBatch`) and their N lidar scans
(:class:`~flightsim.envs.batch_lidar.BatchLidar`), each the same arithmetic as the single env's, so a
slot's episode is the single env's episode for the same seed and actions, bit for bit
(tests/flightsim/test_batch_env.py).

A slot may be wrapped in reset-only wrappers (training's ``TrainingWorlds`` chooses the next
world in ``reset``): resets go through the wrapper, steps straight to the env underneath.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from flightsim.envs.batch_lidar import BatchLidar
from flightsim.envs.env import LidarAvoidEnv
from flightsim.vehicle.batch_vehicle import VehicleBatch

StepResult = tuple[list[np.ndarray], list[float], list[bool], list[bool], list[dict[str, Any]]]


def _check_reset_only(env: gym.Env) -> None:
    """Refuse wrappers that change ``step``: the batch steps the env underneath them."""
    while isinstance(env, gym.Wrapper):
        if type(env).step is not gym.Wrapper.step:
            raise ValueError(
                f"{type(env).__name__} wraps step(); a batched env only keeps reset-only wrappers"
            )
        env = env.env


class BatchedEnvs:
    """N environments of one class and one sensor config, stepped together.

    :param envs: the environments (each a LidarAvoidEnv or subclass, possibly in reset-only
        wrappers); the batch owns them from now on
    """

    def __init__(self, envs: list[gym.Env]) -> None:
        if not envs:
            raise ValueError("a batched env needs at least one environment")
        for env in envs:
            _check_reset_only(env)
        cores = [env.unwrapped for env in envs]
        first = cores[0]
        for core in cores:
            if not isinstance(core, LidarAvoidEnv):
                raise TypeError(f"{type(core).__name__} is not a LidarAvoidEnv")
            if type(core) is not type(first):
                raise TypeError("a batched env needs one environment class")
            if (core.config.lidar, core.config.scan) != (first.config.lidar, first.config.scan):
                raise ValueError("a batched env needs one lidar and scan configuration")
        self.envs = envs
        self.cores: list[LidarAvoidEnv] = cores
        self.n = len(envs)
        self.vehicles = VehicleBatch([core._vehicle for core in cores])
        self.lidar = BatchLidar(self.n, first.config.lidar, first.config.scan, first._slice_band)
        self.observation_space = envs[0].observation_space
        self.action_space = envs[0].action_space

    def reset(
        self, i: int, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset slot ``i`` through its wrappers, exactly as ``env.reset`` (its return value)."""
        observation, info = self.envs[i].reset(seed=seed, options=options)
        core = self.cores[i]
        self.vehicles.load(i, core._response)
        return observation, info

    def step(self, actions: np.ndarray) -> StepResult:
        """Step every slot with its action (no auto-reset: that is the vector env's).

        :param actions: ``(N, 2)``, or ``(N, 3)`` for goal envs with ``sideways``
        :return: per slot what ``env.step`` returns: observations, rewards, terminated,
            truncated, infos (lists)
        """
        cores = self.cores
        if len(actions) != self.n:
            raise ValueError(f"{len(actions)} actions for {self.n} environments")
        commands = [core._command(action) for core, action in zip(cores, actions, strict=True)]
        self.vehicles.fly(
            np.array([c.forward for c in commands]),
            np.array([c.lateral for c in commands]),
            np.array([c.yaw_rate for c in commands]),
            np.array([core._altitude for core in cores]),
        )
        poses = []
        for core in cores:
            core._arrive(core._vehicle.state)
            poses.append(core._sensor_pose())
        scans = self.lidar.scans(
            [core.world for core in cores],
            np.array([origin for origin, _ in poses]),
            np.array([rotation for _, rotation in poses]),
            [core.np_random for core in cores],
            [core.sim_time for core in cores],
        )
        results = [
            core._conclude(c, scans[i]) for i, (core, c) in enumerate(zip(cores, commands, strict=True))
        ]
        observations, rewards, terminated, truncated, infos = (list(x) for x in zip(*results, strict=True))
        return observations, rewards, terminated, truncated, infos

    def close(self) -> None:
        for env in self.envs:
            env.close()
