"""DAgger from a privileged teacher: the goal policy learns to fly like the path-following expert.

Plain behaviour cloning (:mod:`training.pretrain`) imitates the teacher in the states the
teacher visits; the student, flying on its own, soon leaves them and has never seen how to
recover. DAgger (Ross et al., 2011) lets the student fly and asks the teacher what it would have
done in every state the student reaches, and fits the student to the aggregate of all such
labels. The teacher (:data:`~training.controllers.TEACHERS`) reads the simulator's truth (map, pose,
velocity, the autopilot's estimate error and, for the predictive one, the drawn autopilot response) that the
student never sees; the student sees only its stacked observations, as in flight.

Read top to bottom: :func:`run` (iterations: collect with a mixture, fit, evaluate), then
:func:`collect` (who flies each episode, what is recorded), then :func:`save_iteration` and
:func:`load_iterations` (each iteration's labels on disk, so a run resumes where it stopped).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.common.errors import UserError
from training.controllers import TEACHERS
from training.mirror import Mirror
from training.pretrain import Demonstrations, discounted_returns, fit
from training.progress import Progress
from training.sharded_vec_env import LABEL, ShardedVecEnv

log = logging.getLogger(__name__)


#: the teachers by ``[pretrain] teacher`` name: each is built on one unwrapped env, ``reset()`` at
#: an episode's start and ``act()`` every step after, returning its action in ``[-1, 1]``


@dataclass(frozen=True)
class Rollouts:
    """One iteration's data: the student's observations and the teacher's labels.

    :param obs: stacked observations, as the policy sees them
    :param actions: the teacher's action in each, in ``[-1, 1]``
    :param returns: discounted return from each step, of whoever flew (the critic's target)
    :param episodes: episodes that ended within the data
    :param successes: of those, how many reached every waypoint
    :param student_episodes: of the ended episodes, how many the student flew
    :param student_successes: of those, how many reached every waypoint
    """

    obs: np.ndarray
    actions: np.ndarray
    returns: np.ndarray
    episodes: int
    successes: int
    student_episodes: int
    student_successes: int


def nav_envs(venv: Any) -> list[Any]:
    """The LidarNav-v0 envs under a (wrapped) in-process vector env, for the teacher to read.

    :raises UserError: the envs live in other processes without their teachers (``vec_env = "subproc"``)
    """
    inner = venv.unwrapped
    if not hasattr(inner, "envs"):
        raise UserError(
            "DAgger reads the simulators' state: it needs vec_env = \"batched\" or \"sharded\", "
            f"not {type(inner).__name__}"
        )
    return [env.unwrapped for env in inner.envs]


def collect(
    venv: Any, policy: Any, n_steps: int, beta: float, gamma: float, rng: np.random.Generator,
    teacher: str = "path_expert", teacher_noise: float = 0.0, progress: Progress | None = None,
) -> Rollouts:  # fmt: skip
    """Fly ``n_steps`` env steps (all envs together), each episode by the teacher with probability
    ``beta`` and otherwise by the student (deterministic), recording the teacher's action at every step.

    With ``teacher_noise``, the teacher flies its label plus Gaussian noise (DART, Laskey et al.,
    2017) and the label stays the clean one. A frame carrying the last command (``env.command``)
    otherwise shows, in the teacher's episodes, almost the next label: fitted to those, a student
    learnt to repeat its last command (the "copycat" of imitation from histories) and flew into
    what it should have turned from.

    :param venv: the training vector env (frame-stacked, in-process)
    :param policy: the student, an SB3 ``ActorCriticPolicy``
    :param beta: probability that the teacher flies an episode
    :param gamma: discount of the recorded returns
    :param rng: draws who flies each episode
    :param teacher: a :data:`TEACHERS` name
    :param teacher_noise: the noise's standard deviation, action units (0: none drawn)
    :param progress: counts the env steps flown
    """
    n_envs = venv.num_envs
    inner = venv.unwrapped
    sharded = isinstance(inner, ShardedVecEnv)  # the teachers label in the envs' own processes
    teachers = [] if sharded else [TEACHERS[teacher](env) for env in nav_envs(venv)]
    if sharded:
        inner.teach(TEACHERS[teacher])
    obs = venv.reset()
    first = [info[LABEL] for info in inner.reset_infos] if sharded else [t.reset() for t in teachers]
    labels = np.stack(first)
    teacher_flies = rng.uniform(size=n_envs) < beta
    rows = max(1, n_steps // n_envs)
    all_obs = np.empty((rows, *obs.shape), dtype=np.float32)
    width = venv.action_space.shape[0]  # 2, or 3 with a sideways action
    all_actions = np.empty((rows, n_envs, width), dtype=np.float32)
    rewards = np.empty((rows, n_envs), dtype=np.float32)
    dones = np.empty((rows, n_envs), dtype=bool)
    counts = np.zeros(4, dtype=int)  # episodes, successes, student episodes, student successes
    for t in range(rows):
        all_obs[t], all_actions[t] = obs, labels
        student, _ = policy.predict(obs, deterministic=True)
        flown = labels
        if teacher_noise > 0.0:
            flown = np.clip(labels + rng.normal(0.0, teacher_noise, labels.shape), -1.0, 1.0)
        actions = np.where(teacher_flies[:, None], flown, student).astype(np.float32)
        obs, rewards[t], dones[t], infos = venv.step(actions)
        if progress is not None:
            progress.update(n_envs)
        for i in np.flatnonzero(dones[t]):
            success = bool(infos[i].get("success", False))
            counts += (1, success, not teacher_flies[i], success and not teacher_flies[i])
            teacher_flies[i] = rng.uniform() < beta
        if sharded:
            labels = np.stack([info[LABEL] for info in infos])
        else:
            labels = np.stack(
                [
                    teacher.reset() if done else teacher.act()
                    for teacher, done in zip(teachers, dones[t], strict=True)
                ]
            )
    if sharded:
        inner.teach(None)  # PPO after DAgger steps the envs without labels
    returns = discounted_returns(rewards, dones, gamma)
    return Rollouts(
        all_obs.reshape(-1, obs.shape[1]), all_actions.reshape(-1, width), returns.reshape(-1),
        *counts.tolist(),
    )  # fmt: skip


def run(
    venv: Any,
    model: Any,
    *,
    iterations: int,
    steps: int,
    beta0: float,
    epochs: int,
    batch_size: int,
    learning_rate: float,
    seed: int,
    previous: Sequence[Rollouts] = (),
    after_iteration: Callable[[int, int, Rollouts], None] | None = None,
    teacher: str = "path_expert",
    teacher_noise: float = 0.0,
    schedule: str = "constant",
    weigh: Callable[[np.ndarray], np.ndarray] | None = None,
    mirror: Mirror | None = None,
    bar: bool = False,
) -> Demonstrations:
    """DAgger: iteration 0 is the teacher's alone (plain behaviour cloning), then the student flies
    a growing share (teacher probability ``beta0 ** k``), and the student is refitted on every
    label gathered so far.

    :param venv: the training vector env (frame-stacked, in-process)
    :param model: the PPO model whose policy is the student (fitted in place)
    :param iterations: collect-and-fit rounds, all told
    :param steps: env steps collected per iteration, all envs together
    :param beta0: the teacher's share decays as ``beta0 ** iteration``
    :param epochs: passes over the aggregate per iteration
    :param previous: the first iterations' rollouts when resuming (the model fitted on them);
        the run goes on with iteration ``len(previous)``
    :param after_iteration: called with (iteration, env steps collected so far, its rollouts),
        e.g. to save them and evaluate
    :param teacher: a :data:`TEACHERS` name
    :param teacher_noise: see :func:`collect`
    :param schedule: each fit's learning-rate schedule (:func:`training.pretrain.fit`)
    :param weigh: observations → each label's weight in the fit (``training.pretrain.fit``'s
        ``weights``); None: all alike
    :param mirror: mirror half of each fit's batches across the nose (``training.pretrain.fit``)
    :param bar: show the collection's progress as a bar (False: a log line every 30 s), with
        the time left
    :return: every label gathered (the data of the last fit)
    """
    rows = max(1, steps // venv.num_envs) * venv.num_envs  # what one new iteration gathers
    # the saved iterations keep their own size (a resumed run may collect a different number)
    size = sum(len(r.actions) for r in previous) + max(iterations - len(previous), 0) * rows
    obs = np.empty((size, venv.observation_space.shape[0]), dtype=np.float32)
    actions = np.empty((size, venv.action_space.shape[0]), dtype=np.float32)
    returns = np.empty(size, dtype=np.float32)
    collected = episodes = successes = 0
    data = Demonstrations(obs[:0], actions[:0], returns[:0], 0, 0)
    with Progress(max(iterations - len(previous), 0) * rows, "dagger steps", "step", bar) as progress:
        for k in range(iterations):
            beta = beta0**k
            if k < len(previous):
                rollouts = previous[k]
            else:  # the draws of iteration k are its own: a resumed run draws as an unbroken one would
                rng = np.random.default_rng([seed, k])
                rollouts = collect(
                    venv, model.policy, steps, beta, model.gamma, rng, teacher, teacher_noise, progress
                )
            n = len(rollouts.actions)
            obs[collected : collected + n] = rollouts.obs
            actions[collected : collected + n] = rollouts.actions
            returns[collected : collected + n] = rollouts.returns
            collected += n
            episodes += rollouts.episodes
            successes += rollouts.successes
            data = Demonstrations(
                obs[:collected], actions[:collected], returns[:collected], episodes, successes
            )
            if k < len(previous):
                continue
            student = (
                f", student {rollouts.student_successes}/{rollouts.student_episodes}"
                if rollouts.student_episodes
                else ""
            )
            log.info(
                "dagger iteration %d/%d (teacher share %.2f): %d/%d episodes reached every waypoint%s; %s",
                k + 1, iterations, beta, rollouts.successes, rollouts.episodes, student, progress.line(),
            )  # fmt: skip
            weights = None if weigh is None else weigh(data.obs)
            fit(model.policy, data, epochs, batch_size, learning_rate, seed + k, schedule, weights, mirror)
            if after_iteration is not None:
                after_iteration(k, collected, rollouts)
    return data


def save_iteration(directory: Path, iteration: int, rollouts: Rollouts) -> Path:
    """Write one iteration's rollouts to ``directory/iteration_<k>.npz`` (k from 1), uncompressed
    (float observations barely compress; 60k steps are ~350 MB)."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"iteration_{iteration + 1}.npz"
    counts = [rollouts.episodes, rollouts.successes, rollouts.student_episodes, rollouts.student_successes]
    arrays = {"obs": rollouts.obs, "actions": rollouts.actions, "returns": rollouts.returns}
    np.savez(path, **arrays, counts=np.array(counts))
    return path


def load_iterations(directory: Path, steps: int) -> list[Rollouts]:
    """The saved iterations that make up the first ``steps`` env steps of a run, in order.

    :raises UserError: the files are missing, unreadable, or do not add up to ``steps``
    """
    loaded: list[Rollouts] = []
    total = 0
    while total < steps:
        path = directory / f"iteration_{len(loaded) + 1}.npz"
        try:
            with np.load(path) as f:
                rollouts = Rollouts(f["obs"], f["actions"], f["returns"], *map(int, f["counts"]))
        except (OSError, KeyError, ValueError, TypeError) as exc:
            raise UserError(f"--resume: DAgger iteration data {path} cannot be read ({exc})") from None
        loaded.append(rollouts)
        total += len(rollouts.actions)
    if total != steps:
        raise UserError(
            f"--resume: the DAgger iterations in {directory} hold {total} steps, not the checkpoint's {steps}"
        )
    return loaded
