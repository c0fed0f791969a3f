"""stable-baselines3's ``VecEnv`` over :class:`~training.batched_vec_env.BatchedVecEnv` shards, one
worker process each, with a DAgger teacher beside each env in its worker.

DAgger's privileged teacher reads each simulator's state, so in one process it labels the steps
of all N envs one after another: the teachers among movers plan for about 37 ms a step, and a run's
collection sat on one core while the other idled. Here the envs are split into shards, each a
batched vector env in its own process, and :meth:`ShardedVecEnv.teach` builds a teacher beside
each env there. Its label for the observation a step (or reset) returns rides back in that env's
info as ``"teacher_label"`` (in ``reset_infos`` after a reset), so the labels of all shards are
computed at once. The episodes are those of the batched env for the same seeds: a shard seeds its
envs with the same ``seed + index`` it would have had.
"""

from __future__ import annotations

import itertools
import multiprocessing
import signal
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import (
    CloudpickleWrapper,
    VecEnv,
    VecEnvIndices,
    VecEnvStepReturn,
)

#: the info key of the teacher's label for the observation returned beside it
LABEL = "teacher_label"


def _shard(remote: Connection, parent: Connection, env_fns: CloudpickleWrapper) -> None:
    """A worker: one batched vector env, its teachers once asked for, commands from ``remote``."""
    from training.batched_vec_env import BatchedVecEnv

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the training process's to handle
    parent.close()
    venv = BatchedVecEnv(env_fns.var)
    teachers: list[Any] = []
    try:
        while True:
            command, data = remote.recv()
            if command == "step":
                obs, rewards, dones, infos = venv.step(data)
                for i, teacher in enumerate(teachers):
                    label = teacher.reset() if dones[i] else teacher.act()
                    infos[i][LABEL] = label
                    if dones[i]:
                        venv.reset_infos[i][LABEL] = label
                remote.send((obs, rewards, dones, infos, venv.reset_infos))
            elif command == "reset":
                seed, options = data
                if seed is not None:
                    venv.seed(seed)
                venv.set_options(options)
                obs = venv.reset()
                for i, teacher in enumerate(teachers):
                    venv.reset_infos[i][LABEL] = teacher.reset()
                remote.send((obs, venv.reset_infos))
            elif command == "teach":  # labels from the next reset on
                teachers = [data(env.unwrapped) for env in venv.envs] if data is not None else []
                remote.send(None)
            elif command == "call":
                method, args, kwargs = data
                remote.send(getattr(venv, method)(*args, **kwargs))
            elif command == "spaces":
                remote.send((venv.observation_space, venv.action_space))
            elif command == "close":
                break
    except (EOFError, KeyboardInterrupt):
        pass
    finally:
        venv.close()
        remote.close()


class ShardedVecEnv(VecEnv):
    """N LidarAvoid-v0 / LidarNav-v0 envs in ``shards`` worker processes, each shard a
    :class:`~training.batched_vec_env.BatchedVecEnv` of its contiguous share of the envs.

    :param env_fns: one thunk per env, as for ``SubprocVecEnv``
    :param shards: worker processes (at most one per env)
    """

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]], shards: int) -> None:
        n = len(env_fns)
        shards = max(1, min(shards, n))
        bounds = np.linspace(0, n, shards + 1).round().astype(int)
        self._slices = [slice(int(a), int(b)) for a, b in itertools.pairwise(bounds)]
        context = multiprocessing.get_context("forkserver")
        self._remotes: list[Connection] = []
        self._processes = []
        for part in self._slices:
            remote, work_remote = context.Pipe()
            fns = CloudpickleWrapper(list(env_fns[part]))
            process = context.Process(target=_shard, args=(work_remote, remote, fns), daemon=True)
            process.start()
            work_remote.close()
            self._remotes.append(remote)
            self._processes.append(process)
        self._remotes[0].send(("spaces", None))
        observation_space, action_space = self._remotes[0].recv()
        super().__init__(n, observation_space, action_space)
        self.teacher: Callable[[Any], Any] | None = None
        self._closed = False

    def teach(self, teacher: Callable[[Any], Any] | None) -> None:
        """Build ``teacher(env)`` (a module-level function, e.g. of
        :data:`~training.controllers.TEACHERS`) beside every env, whose labels come from the next
        :meth:`reset` on; None: no teachers."""
        for remote in self._remotes:
            remote.send(("teach", teacher))
        for remote in self._remotes:
            remote.recv()
        self.teacher = teacher

    def reset(self) -> np.ndarray:
        for remote, part in zip(self._remotes, self._slices, strict=True):
            remote.send(("reset", (self._seeds[part.start], self._options[part])))
        observations = []
        for remote, part in zip(self._remotes, self._slices, strict=True):
            obs, self.reset_infos[part] = remote.recv()
            observations.append(obs)
        self._reset_seeds()
        self._reset_options()
        return np.concatenate(observations)

    def step_async(self, actions: np.ndarray) -> None:
        for remote, part in zip(self._remotes, self._slices, strict=True):
            remote.send(("step", np.asarray(actions)[part]))

    def step_wait(self) -> VecEnvStepReturn:
        observations, rewards, dones, infos = [], [], [], []
        for remote, part in zip(self._remotes, self._slices, strict=True):
            obs, reward, done, info, self.reset_infos[part] = remote.recv()
            observations.append(obs)
            rewards.append(reward)
            dones.append(done)
            infos.extend(info)
        return np.concatenate(observations), np.concatenate(rewards), np.concatenate(dones), infos

    def close(self) -> None:
        if self._closed:
            return
        for remote in self._remotes:
            remote.send(("close", None))
        for process in self._processes:
            process.join()
        self._closed = True

    def get_images(self) -> Sequence[np.ndarray | None]:
        return self._gather("get_images", (), {}, None)

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return self._gather("get_attr", (attr_name,), {}, indices)

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        self._gather("set_attr", (attr_name, value), {}, indices)

    def env_method(
        self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs
    ) -> list[Any]:
        return self._gather("env_method", (method_name, *method_args), method_kwargs, indices)

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return self._gather("env_is_wrapped", (wrapper_class,), {}, indices)

    def _gather(self, method: str, args: tuple, kwargs: dict[str, Any], indices: VecEnvIndices) -> list[Any]:
        """``method`` of each shard's batched env on its share of ``indices``, results in env order."""
        wanted = set(self._get_indices(indices))
        asked = []
        for remote, part in zip(self._remotes, self._slices, strict=True):
            local = [i - part.start for i in range(part.start, part.stop) if i in wanted]
            if local or method == "get_images":
                call_kwargs = kwargs if method == "get_images" else {**kwargs, "indices": local}
                remote.send(("call", (method, args, call_kwargs)))
                asked.append(remote)
        results: list[Any] = []
        for remote in asked:
            results.extend(remote.recv() or [])
        return results
