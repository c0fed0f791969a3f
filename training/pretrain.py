"""Behaviour cloning warm start: PPO begins from a policy that imitates a classical controller.

PPO from scratch on the goal task learns first not to crash and then, slowly, that goals pay: for
its first half million steps it circles in open space. A warm start skips that phase. The
classical controller (:class:`~training.baselines.GoalFollower` on the goal task,
:class:`~training.baselines.GapFollower` on the avoid task) flies the training environments, its
own (stacked) observations and actions are recorded, and before ``learn`` the PPO actor's mean is
fitted to its actions (mean squared error; the exploration noise ``log_std`` stays as configured)
and the critic to the discounted returns it earned. PPO then improves on the demonstrator, which
collides where it misjudges the autopilot's lag; nothing keeps the policy close to it afterwards.

The demonstrations come from the training worlds (:data:`flightsim.envs.seeds.TRAIN`), so training and
selection seeds stay apart. Read top to bottom: :func:`collect`, :func:`discounted_returns`,
:func:`fit`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from training.mirror import Mirror
from training.progress import Progress

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Demonstrations:
    """What the demonstrator saw and did, one row per env step.

    :param obs: stacked observations, as the policy sees them
    :param actions: the demonstrator's actions, in ``[-1, 1]``
    :param returns: discounted return from each step to its episode's end (or the data's end)
    :param episodes: episodes that ended within the data
    :param successes: of those, how many reached their goal (goal task) or ended without a collision
    """

    obs: np.ndarray
    actions: np.ndarray
    returns: np.ndarray
    episodes: int
    successes: int


def collect(
    venv: Any, n_stack: int, demonstrator: str, env_config: Any, n_steps: int, gamma: float,
    bar: bool = False,
) -> Demonstrations:  # fmt: skip
    """Fly ``demonstrator`` in every env of ``venv`` (frame-stacked) for ``n_steps`` steps in all.

    :param venv: the training VecEnv (monitored, frame-stacked), freshly built
    :param n_stack: frames per observation (the newest is the demonstrator's)
    :param demonstrator: a baseline's name (``goal_follower`` or ``gap_follower``)
    :param env_config: the envs' config (the demonstrator reads the frame with its layout)
    :param n_steps: env steps to record, all envs together
    :param gamma: discount of the recorded returns (PPO's)
    :param bar: show the progress as a bar (False: a log line every 30 s), with the time left
    """
    from training.controllers import ControllerSpec, build_controller

    n_envs = venv.num_envs
    frame = venv.observation_space.shape[0] // n_stack
    controllers = [build_controller(ControllerSpec(demonstrator), env_config, seed=i) for i in range(n_envs)]
    obs = venv.reset()
    actions = np.stack([c.reset(o[-frame:]) for c, o in zip(controllers, obs, strict=True)])
    rows = max(1, n_steps // n_envs)
    all_obs = np.empty((rows, *obs.shape), dtype=np.float32)
    all_actions = np.empty((rows, n_envs, 2), dtype=np.float32)
    rewards = np.empty((rows, n_envs), dtype=np.float32)
    dones = np.empty((rows, n_envs), dtype=bool)
    episodes = successes = 0
    with Progress(rows * n_envs, f"{demonstrator} steps", "step", bar) as progress:
        for t in range(rows):
            all_obs[t], all_actions[t] = obs, actions
            obs, rewards[t], dones[t], infos = venv.step(actions)
            progress.update(n_envs)
            next_actions = []
            for i, (controller, o, info) in enumerate(zip(controllers, obs, infos, strict=True)):
                if dones[t, i]:
                    episodes += 1
                    successes += bool(info.get("success", not info.get("collision", False)))
                    next_actions.append(controller.reset(o[-frame:]))
                else:
                    next_actions.append(controller.act(o[-frame:]))
            actions = np.clip(np.stack(next_actions), -1.0, 1.0).astype(np.float32)
    returns = discounted_returns(rewards, dones, gamma)
    return Demonstrations(
        all_obs.reshape(-1, obs.shape[1]),
        all_actions.reshape(-1, 2),
        returns.reshape(-1),
        episodes,
        successes,
    )


def discounted_returns(rewards: np.ndarray, dones: np.ndarray, gamma: float) -> np.ndarray:
    """Per step, ``sum_k gamma^k r_{t+k}`` up to its episode's end (``dones[t]``: step ``t`` ended it).

    An episode still running when the data ends is cut there (its last returns are short by what
    would have followed; a warm start does not need better).
    """
    returns = np.zeros_like(rewards, dtype=np.float32)
    running = np.zeros(rewards.shape[1], dtype=np.float32)
    for t in range(len(rewards) - 1, -1, -1):
        running = rewards[t] + gamma * running * ~dones[t]
        returns[t] = running
    return returns


def proximity_weights(
    obs: np.ndarray, n_stack: int, n_bins: int, max_range: float, near_weight: float, near_distance: float
) -> np.ndarray:
    """Per observation, ``1 + near_weight × (1 − d / near_distance)`` where the newest scan's nearest
    return ``d`` is within ``near_distance`` metres, else 1.

    The states beside obstacles, where an imitation error costs the episode, are a small share of
    what a teacher flies; the weights make the fit count them more.

    :param obs: stacked observations, ``n_stack`` frames side by side, oldest first, each starting
        with ``n_bins`` scan values normalised by ``max_range``
    """
    frame = obs.shape[1] // n_stack
    newest = obs[:, (n_stack - 1) * frame : (n_stack - 1) * frame + n_bins]
    nearest = newest.min(axis=1) * max_range
    closeness = np.clip(1.0 - nearest / near_distance, 0.0, 1.0)
    return (1.0 + near_weight * closeness).astype(np.float32)


def fit(
    policy: Any, data: Demonstrations, epochs: int, batch_size: int, learning_rate: float, seed: int,
    schedule: str = "constant", weights: np.ndarray | None = None, mirror: Mirror | None = None,
) -> dict[str, float]:  # fmt: skip
    """Fit ``policy``'s action mean to the demonstrations and its value to their returns.

    :param policy: an SB3 ``ActorCriticPolicy`` (the PPO model's ``policy``)
    :param schedule: ``"constant"`` learning rate, or ``"cosine"``: annealed to 0 over the fit
        (Loshchilov & Hutter), so the fit ends in a minimum rather than at the last batches' noise
    :param weights: per demonstration, its weight in the action loss (e.g. :func:`proximity_weights`);
        None: all alike. The reported ``action_mse`` is the weighted one.
    :param mirror: each batch's demonstrations are mirrored across the nose with probability 0.5
        (:mod:`training.mirror`: the task's symmetry, twice the worlds); None: as recorded
    :returns: the last epoch's mean losses (``action_mse``, ``value_mse``)
    """
    import torch

    generator = torch.Generator().manual_seed(seed)
    obs = torch.as_tensor(data.obs)
    actions = torch.as_tensor(data.actions)
    returns = torch.as_tensor(data.returns)
    weight = torch.as_tensor(np.ones(len(obs), np.float32) if weights is None else weights)
    # the same mirror over torch tensors, so each batch is mirrored where it lies
    flipped = None
    if mirror is not None:
        parts = (mirror.index, mirror.signs, mirror.action_signs)
        flipped = Mirror(*(torch.as_tensor(part) for part in parts))
    parameters = [p for name, p in policy.named_parameters() if name != "log_std"]
    optimizer = torch.optim.Adam(parameters, lr=learning_rate)
    annealing = None
    if schedule == "cosine":
        batches = epochs * -(-len(obs) // batch_size)
        annealing = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, batches)
    policy.set_training_mode(True)
    losses: dict[str, float] = {}
    for epoch in range(epochs):
        order = torch.randperm(len(obs), generator=generator)
        totals = np.zeros(2)
        for start in range(0, len(obs), batch_size):
            index = order[start : start + batch_size]
            batch_obs, batch_actions = obs[index], actions[index]
            if flipped is not None:
                flip = (torch.rand(len(index), generator=generator) < 0.5)[:, None]
                batch_obs = torch.where(flip, flipped.observations(batch_obs), batch_obs)
                batch_actions = torch.where(flip, flipped.actions(batch_actions), batch_actions)
            distribution = policy.get_distribution(batch_obs)
            errors = (distribution.distribution.mean - batch_actions).square().mean(dim=-1)
            action_mse = (weight[index] * errors).sum() / weight[index].sum()
            value_mse = torch.nn.functional.mse_loss(
                policy.predict_values(batch_obs).squeeze(-1), returns[index]
            )
            optimizer.zero_grad()
            (action_mse + 0.5 * value_mse).backward()
            torch.nn.utils.clip_grad_norm_(parameters, 0.5)
            optimizer.step()
            if annealing is not None:
                annealing.step()
            totals += (action_mse.item() * len(index), value_mse.item() * len(index))
        losses = {"action_mse": totals[0] / len(obs), "value_mse": totals[1] / len(obs)}
        log.info("pretrain epoch %d/%d: action mse %.4f, value mse %.2f", epoch + 1, epochs, *losses.values())
    policy.set_training_mode(False)
    return losses
