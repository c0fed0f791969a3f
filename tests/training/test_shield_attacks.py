"""Controllers that want to crash, flown behind the shield with its backup gate: no collision.

Through the real evaluation machinery: LidarNav-v0, a random firmware response per episode, the
thin-pole forest, narrow gaps and a warehouse. The worlds are validation seeds 599,900 on, which
no shield rule was tuned on. ``bench/bench_shield_attack.py`` flies many more.
"""

from __future__ import annotations

import pytest

from companion.safety.shield import ShieldConfig
from training.attackers import ATTACKERS
from training.config import load_train_config
from training.controllers import ControllerSpec
from training.episodes import NAV_ENV_ID, goal_worlds, make_tasks, run_task

FAMILIES = ("forest", "gaps", "warehouse")
#: 20 s of flight each: long enough for every attacker to reach what it rams
MAX_STEPS = 200


@pytest.fixture(scope="module")
def env() -> dict:
    config = load_train_config("training/configs/nav.toml", [f"env.max_steps={MAX_STEPS}"])
    return config.env


@pytest.mark.parametrize("attacker", ATTACKERS)
def test_no_attacker_crashes_through_the_gated_shield(env: dict, attacker: str) -> None:
    worlds = goal_worlds(FAMILIES, 599_900, 1, (0.9, 0.9))
    spec = ControllerSpec(attacker, shield=True, shield_config=ShieldConfig(backup_gate=True))
    results = [run_task(task) for task in make_tasks([spec], worlds, 1, env, NAV_ENV_ID)]
    crashed = [(r.world, round(r.min_clearance, 3)) for r in results if r.collision]
    assert not crashed, f"{attacker} crashed through: {crashed}"
    assert min(r.min_clearance for r in results) < 1.0  # it did go for the obstacles


def test_the_ram_attacker_crashes_without_the_shield(env: dict) -> None:
    """The attack is real: without a shield the same attacker hits something."""
    worlds = goal_worlds(FAMILIES, 599_900, 1, (0.9, 0.9))
    results = [run_task(task) for task in make_tasks([ControllerSpec("ram")], worlds, 1, env, NAV_ENV_ID)]
    assert any(r.collision for r in results)
