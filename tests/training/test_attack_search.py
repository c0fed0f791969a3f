"""The search-based attacker (:mod:`training.attack_search`): it cannot crash through the gated
shield, it does crash without one (the search is real), it keeps and replays what it found, and
its cross-entropy step on a toy objective.

Through the real evaluation machinery as ``test_shield_attacks.py``: LidarNav-v0, the world's
random firmware response, a narrow-gaps world at validation seed 599,900 (no shield rule was tuned
on it). Budgets are tiny (a few generations of 6): ``bench/bench_shield_attack.py --search`` flies more.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from companion.safety.shield import ShieldConfig
from training.attack_search import SearchConfig, cem, cem_update, fly, search_attack, sequence
from training.attackers import ReplayAttacker
from training.config import load_train_config
from training.episodes import goal_worlds

#: 15 s of flight: long enough to reach the gaps
MAX_STEPS = 150
WORLD = goal_worlds(("gaps",), 599_900, 1, (0.9, 0.9))[0]
VEHICLE_RADIUS = 0.25
FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "shield-attacks"


@pytest.fixture(scope="module")
def env() -> dict:
    return load_train_config("training/configs/nav.toml", [f"env.max_steps={MAX_STEPS}"]).env


def test_cem_update_refits_to_the_elite() -> None:
    samples = np.array([[0.0, 1.0], [1.0, 1.0], [-1.0, 0.0], [0.5, 0.5]])
    mean, std = cem_update(samples, np.array([3.0, 0.0, 2.0, 1.0]), 0.5, 0.1)
    np.testing.assert_allclose(mean, [0.75, 0.75])  # the two best: rows 1 and 3
    np.testing.assert_allclose(std, [0.25, 0.25])
    _, floored = cem_update(samples[[1, 1]], np.array([0.0, 0.0]), 0.5, 0.1)
    np.testing.assert_allclose(floored, [0.1, 0.1])  # no collapse


def test_cem_finds_the_bottom_of_a_bowl() -> None:
    target = np.linspace(-0.8, 0.8, 8)
    found = cem(lambda x: ((x - target) ** 2).sum(axis=1), 8, SearchConfig(generations=20, population=30))
    assert found.evaluations == 600
    assert found.history[-1] < found.history[0] / 20  # it improves, not only keeps its first best
    np.testing.assert_allclose(found.best, target, atol=0.1)


def test_a_candidate_is_segments_of_held_actions() -> None:
    z = np.array([1.0, -0.5, -1.0, 0.2, 0.3, 1.0])  # (1, -0.5) for 5 steps, then (0.2, 0.3) for 10
    actions = sequence(z, 2, (5, 10))
    assert actions == ((1.0, -0.5),) * 5 + ((0.2, 0.3),) * 10
    replay = ReplayAttacker(actions, 2)
    flown = [replay.reset(np.zeros(360))] + [replay.act(np.zeros(360)) for _ in range(16)]
    np.testing.assert_allclose(flown[4], [1.0, -0.5])
    np.testing.assert_allclose(flown[5], [0.2, 0.3])
    np.testing.assert_allclose(flown[-1], [0.2, 0.3])  # past the end: the last held


def test_the_search_does_not_crash_through_the_gated_shield(env: dict) -> None:
    gate = ShieldConfig(backup_gate=True)
    found = search_attack(WORLD, env, True, gate, SearchConfig(generations=2, population=6))
    assert found.episodes == 12
    assert not found.collision, f"crashed through at {found.min_clearance:.3f} m: {found.history}"
    assert found.min_clearance > VEHICLE_RADIUS


def test_without_a_shield_the_search_crashes(env: dict) -> None:
    """The search is real: the same budget and world, no shield, and it hits something."""
    found = search_attack(WORLD, env, False, None, SearchConfig(generations=2, population=6))
    assert found.collision or found.min_clearance < VEHICLE_RADIUS


def test_the_search_keeps_its_best_and_flies_it_again_alike(env: dict) -> None:
    """Behind the rules alone: the best is the least of every generation's, no worse than the first
    generation's, and flying its sequence again (same world, same seed) gives the same clearance."""
    found = search_attack(WORLD, env, True, None, SearchConfig(generations=3, population=6))
    assert found.episodes == 18 and len(found.history) == 3
    assert found.min_clearance == min(found.history) <= found.history[0]
    again = fly([found.actions, found.actions], WORLD, env, True, None)
    assert [r.min_clearance for r in again] == [found.min_clearance] * 2
    assert [r.collision for r in again] == [found.collision] * 2


@pytest.mark.xfail(
    strict=True,
    reason="issue 66, open: the vehicle starts 0.98 m from a pole, inside the 1.08 m the random "
    "envelope needs to stop clear, so the gate is out of its promise from the first step",
)
def test_the_sequence_the_search_found_does_not_crash_through_the_gate() -> None:
    """A known hole, kept in sight: ``bench_shield_attack.py --search`` found this sequence on a
    forest (tests/fixtures/shield-attacks). No command passes from the first step; the gate sends
    the variant with the most room while the autopilot's own estimate error (about 1 m/s at the end)
    drifts the vehicle into the pole. Strict: once it stops this, the mark comes off."""
    from training.attack_search import replay_spec
    from training.episodes import NAV_ENV_ID, make_tasks, run_task

    found = json.loads((FIXTURES / "forest-599000-gate.json").read_text())
    env = load_train_config("training/configs/nav.toml", [f"env.max_steps={found['max_steps']}"]).env
    world = goal_worlds(("forest",), 599_000, 1, (found["difficulty"],) * 2)[0]
    spec = replay_spec(tuple(tuple(a) for a in found["actions"]), True, ShieldConfig(backup_gate=True))
    result = run_task(make_tasks([spec], [world], 1, env, NAV_ENV_ID)[0])
    assert not result.collision, f"collided, least clearance {result.min_clearance:.3f} m"
