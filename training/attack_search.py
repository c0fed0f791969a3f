"""A search-based attacker: the command sequence that brings the vehicle closest to an obstacle
behind the shield, found by flying candidates.

The scripted attackers (:mod:`training.attackers`) each try one idea (ram, dash, random); a shield
can hold against all three and still have a hole none of them happens to fly into. This one looks
for the hole: on one world and one reset seed (so the autopilot response, sensor noise and wind are
those of every candidate), it optimises an open-loop sequence of held actions by the cross-entropy
method (:func:`cem`), scoring each candidate by flying one real episode (the real env, the real
shield, through :func:`~training.episodes.run_task`) and keeping its least clearance.

A sequence is ``K`` segments, each an action in ``[-1, 1]`` of the env's action size held for
``hold_steps`` (0.5-1 s by default, the duration searched too), enough segments to fill the
episode. The flown candidate is a :data:`~training.attackers.REPLAY` controller carrying the
sequence one action per step, so an attack found here can be flown again anywhere a
:class:`~training.controllers.ControllerSpec` goes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.safety.shield import ShieldConfig
from training.attackers import REPLAY
from training.config import sideways_scale
from training.controllers import ControllerSpec
from training.episodes import NAV_ENV_ID, EpisodeResult, WorldSpec, make_eval_env, make_tasks, run_task


@dataclass(frozen=True)
class SearchConfig:
    """How hard to search.

    :param generations: CEM generations (each flies ``population`` episodes)
    :param population: candidates per generation
    :param elite_fraction: the share of each generation the next is refitted to (at least 2 kept,
        so the spread has something to measure)
    :param init_std: the first generation's spread about 0 (actions are clipped to ``[-1, 1]``, so a
        wide spread puts much of each generation at full command, which is what an attacker wants)
    :param min_std: the least spread after a refit: a handful of elites must not collapse it
    :param smoothing: the share of the refit taken (1: plain CEM; less keeps some of the old
        mean and spread, steadier with a small population)
    :param hold_steps: the least and most steps a segment holds its action (10 a second)
    :param seed: the sampler's seed (the episodes' seed is the world's, fixed)
    """

    generations: int = 3
    population: int = 8
    elite_fraction: float = 0.25
    init_std: float = 1.0
    min_std: float = 0.05
    smoothing: float = 0.8
    hold_steps: tuple[int, int] = (5, 10)
    seed: int = 0


@dataclass
class CemResult:
    """What :func:`cem` found: the best candidate flown, its score, the best score of each
    generation and how many candidates were scored."""

    best: np.ndarray
    best_score: float
    history: list[float] = field(default_factory=list)
    evaluations: int = 0


def cem_update(
    samples: np.ndarray, scores: np.ndarray, elite_fraction: float, min_std: float
) -> tuple[np.ndarray, np.ndarray]:
    """The cross-entropy refit: mean and spread of the lowest-scoring ``elite_fraction`` of ``samples``.

    :param samples: ``(population, dim)`` candidates
    :param scores: one per candidate, lower is better
    :param elite_fraction: share kept (at least 2 candidates)
    :param min_std: floor on each dimension's spread
    """
    n_elite = min(len(samples), max(2, round(elite_fraction * len(samples))))
    elite = samples[np.argsort(scores, kind="stable")[:n_elite]]
    return elite.mean(axis=0), np.maximum(elite.std(axis=0), min_std)


def cem(objective: Callable[[np.ndarray], Sequence[float]], dim: int, config: SearchConfig) -> CemResult:
    """Minimise ``objective`` over ``[-1, 1]^dim`` by the cross-entropy method.

    :param objective: scores a ``(population, dim)`` batch at once (so the episodes can run in
        parallel), lower is better
    :param dim: the search space's dimension
    :param config: budget and sampler (:class:`SearchConfig`)
    """
    rng = np.random.default_rng(config.seed)
    mean, std = np.zeros(dim), np.full(dim, config.init_std)
    result = CemResult(best=np.zeros(dim), best_score=math.inf)
    for _ in range(config.generations):
        samples = np.clip(mean + std * rng.standard_normal((config.population, dim)), -1.0, 1.0)
        scores = np.asarray(objective(samples), dtype=np.float64)
        result.evaluations += len(samples)
        k = int(np.argmin(scores))
        result.history.append(float(scores[k]))
        if scores[k] < result.best_score:
            result.best, result.best_score = samples[k].copy(), float(scores[k])
        new_mean, new_std = cem_update(samples, scores, config.elite_fraction, config.min_std)
        a = config.smoothing
        mean = a * new_mean + (1 - a) * mean
        std = np.maximum(a * new_std + (1 - a) * std, config.min_std)
    return result


def n_segments(max_steps: int, hold_steps: tuple[int, int]) -> int:
    """Segments enough to fill ``max_steps`` even when each holds the least."""
    return math.ceil(max_steps / hold_steps[0])


def sequence(z: np.ndarray, action_size: int, hold_steps: tuple[int, int]) -> tuple[tuple[float, ...], ...]:
    """The per-step actions a candidate stands for.

    :param z: ``K * (action_size + 1)`` values in ``[-1, 1]``: per segment its action, then its hold
        (-1: ``hold_steps[0]`` steps, 1: ``hold_steps[1]``)
    :param action_size: 2 or 3
    :param hold_steps: the least and most steps a segment holds
    """
    low, high = hold_steps
    steps: list[tuple[float, ...]] = []
    for segment in np.asarray(z, dtype=np.float64).reshape(-1, action_size + 1):
        hold = low + round((high - low) * (float(segment[-1]) + 1.0) / 2.0)
        action = tuple(round(float(v), 6) for v in segment[:action_size])
        steps.extend([action] * hold)
    return tuple(steps)


@dataclass
class AttackResult:
    """The worst the search found on one world.

    :param world: the world's name
    :param actions: the best sequence, one action per step (replay it with a
        :data:`~training.attackers.REPLAY` ``ControllerSpec``)
    :param min_clearance: its least clearance (m from the vehicle centre; a collision is below the
        vehicle radius, 0.25)
    :param collision: whether it collided
    :param episodes: episodes flown
    :param history: the least clearance of each generation's best
    """

    world: str
    actions: tuple[tuple[float, ...], ...]
    min_clearance: float
    collision: bool
    episodes: int
    history: list[float]


def replay_spec(
    actions: tuple[tuple[float, ...], ...], shield: bool, shield_config: ShieldConfig | None = None
) -> ControllerSpec:
    """The spec that flies ``actions``, behind the shield (``shield_config``'s) if ``shield``."""
    return ControllerSpec(REPLAY, name="search", shield=shield, shield_config=shield_config, actions=actions)


def fly(
    actions: Sequence[tuple[tuple[float, ...], ...]],
    world: WorldSpec,
    env: dict[str, Any],
    shield: bool,
    shield_config: ShieldConfig | None = None,
    executor: Executor | None = None,
    env_id: str = NAV_ENV_ID,
) -> list[EpisodeResult]:
    """Fly each sequence once on ``world`` with its episode 0 seed (the same for all).

    :param executor: where to run the episodes (None: in this process, one after another)
    """
    tasks = [make_tasks([replay_spec(a, shield, shield_config)], [world], 1, env, env_id)[0] for a in actions]
    return list(executor.map(run_task, tasks) if executor is not None else map(run_task, tasks))


def score(result: EpisodeResult) -> float:
    """Lower is worse for the shield: the least clearance, less 1 for a collision (so a collision
    ranks below every near miss, whatever clearance the collision check reported)."""
    return result.min_clearance - (1.0 if result.collision else 0.0)


def search_attack(
    world: WorldSpec,
    env: dict[str, Any],
    shield: bool = True,
    shield_config: ShieldConfig | None = None,
    config: SearchConfig | None = None,
    executor: Executor | None = None,
    env_id: str = NAV_ENV_ID,
) -> AttackResult:
    """Search for the sequence that flies closest to an obstacle on ``world``.

    :param world: the world attacked (with its episode 0 reset seed: one firmware response)
    :param env: the ``[env]`` table (its ``max_steps`` sets the sequence's length)
    :param shield: behind the companion's shield (False: bare, to show the search finds a crash)
    :param shield_config: the shield's limits (None: the defaults; ``backup_gate=True`` the gate)
    :param config: the search's budget (:class:`SearchConfig`)
    :param executor: where the episodes run (None: in this process)
    :param env_id: the task (the goal task by default, as the other attack tests)
    """
    config = config or SearchConfig()
    env_config = make_eval_env(env, env_id).unwrapped.config
    action_size = 3 if sideways_scale(env_config) else 2
    dim = n_segments(int(env_config.max_steps), config.hold_steps) * (action_size + 1)
    flown: dict[bytes, EpisodeResult] = {}
    history: list[float] = []  # each generation's best's least clearance

    def objective(samples: np.ndarray) -> list[float]:
        results = fly(
            [sequence(z, action_size, config.hold_steps) for z in samples],
            world, env, shield, shield_config, executor, env_id,
        )  # fmt: skip
        for z, result in zip(samples, results, strict=True):
            flown[z.tobytes()] = result
        scores = [score(r) for r in results]
        history.append(results[int(np.argmin(scores))].min_clearance)
        return scores

    found = cem(objective, dim, config)
    best = flown[found.best.tobytes()]
    return AttackResult(
        world=world.name,
        actions=sequence(found.best, action_size, config.hold_steps),
        min_clearance=best.min_clearance,
        collision=best.collision,
        episodes=found.evaluations,
        history=history,
    )
