"""The robust teacher predicts the hardest response for as few candidates as its pick needs, and
picks exactly what predicting it for every candidate picks: in a real LidarNav-v0 env with the
sideways action and the random response, where the teacher's pick is safe and where, at a wall,
nothing is (its recovery)."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from flightsim.envs.nav_env import LidarNavEnv, NavEnvConfig
from flightsim.vehicle.autopilot_response import AutopilotResponse, ResponseParams
from flightsim.worlds.world import World
from tests.training.test_path_expert import RADIUS, corridor
from tests.training.test_predictive_expert import wall_ahead
from training.predictive_expert import PredictiveExpert, pick, robust_expert

PREDICT = AutopilotResponse.predict


def full_pick(
    expert: PredictiveExpert, commands: np.ndarray, steps: tuple[int, int, float], held: tuple[float, float],
    spare: np.ndarray, near: np.ndarray, score: np.ndarray,
) -> int:  # fmt: skip
    """The pick as the teacher made it before: the hardest response predicted for every candidate."""
    env = expert.env
    state = env.true_state
    slow = PREDICT(env.response, float(state.yaw), commands, *steps, expert._hardest, held)
    excess = expert._excess(slow, state.position)[0]
    spare, near = np.minimum(spare, excess.min(axis=1)), np.minimum(near, excess[:, : steps[0]].min(axis=1))
    return pick(spare, near, score, expert.config.recovery_tolerance)


def fly_checked(
    env: LidarNavEnv, world: World, seed: int, reckless: bool, steps: int, monkeypatch: pytest.MonkeyPatch,
    counts: Counter,
) -> None:  # fmt: skip
    """Fly one episode of ``world`` (the teacher's labels with noise, or straight ahead at full
    speed when ``reckless``, as a student that has not learnt to brake), checking every label the
    robust teacher makes against :func:`full_pick`; ``counts`` gains the picks made in the
    teacher's first chunk, in a later one, and in recovery."""
    env.reset(seed=seed, options={"world": world})
    expert = robust_expert(env)
    fast = expert._pick_through_hardest
    calls: list[tuple[int, int]] = []  # (candidates, periods) of each hardest prediction this step

    def spy(
        self: AutopilotResponse, yaw: float, commands: np.ndarray, command_steps: int, total_steps: int,
        period: float = 0.1, params: ResponseParams | None = None, held: tuple[float, float] = (0.0, 0.0),
    ) -> np.ndarray:  # fmt: skip
        if params is not None:
            calls.append((len(commands), total_steps))
        return PREDICT(self, yaw, commands, command_steps, total_steps, period, params, held)

    def checked(
        commands: np.ndarray, steps: tuple[int, int, float], held: tuple[float, float], spare: np.ndarray,
        near: np.ndarray, score: np.ndarray,
    ) -> int:  # fmt: skip
        calls.clear()
        best = fast(commands, steps, held, spare, near, score)
        assert best == full_pick(expert, commands, steps, held, spare, near, score)
        if any(periods == steps[0] for _, periods in calls):  # the rest, while the command is sent
            counts["recovery"] += 1
        else:
            counts["first chunk" if len(calls) == 1 else "later chunk"] += 1
            counts["rows"] += sum(rows for rows, _ in calls)
            counts["candidates"] += len(commands)
        return best

    monkeypatch.setattr(AutopilotResponse, "predict", spy)
    monkeypatch.setattr(expert, "_pick_through_hardest", checked)
    rng = np.random.default_rng(seed)
    label = expert.reset()
    for _ in range(steps):
        action = np.array([1.0, 0.0, 0.0]) if reckless else label + rng.normal(0.0, 0.4, label.shape)
        _, _, terminated, truncated, _ = env.step(np.clip(action, -1.0, 1.0).astype(np.float32))
        if terminated or truncated:
            return
        label = expert.act()


def test_it_picks_as_if_it_predicted_every_candidate_through_the_hardest_response(monkeypatch):
    env = LidarNavEnv(NavEnvConfig(autopilot_response="random", vehicle_radius=RADIUS, sideways=True))
    counts: Counter = Counter()
    for seed in range(3):  # three draws of the response, at the wall
        fly_checked(env, wall_ahead(), seed, True, 40, monkeypatch, counts)
    fly_checked(env, corridor(width=1.4), 0, False, 150, monkeypatch, counts)
    assert counts["first chunk"] and counts["later chunk"] and counts["recovery"], counts
    assert counts["rows"] < counts["candidates"] / 10, counts  # outside recovery, a few candidates a step
