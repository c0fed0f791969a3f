"""Controllers that want to crash, in offices where people walk, behind the gate that sees them move.

LidarNav-v0 runs unshielded and :func:`training.mover_attack.fly` applies the shield in the loop,
the movers taken from the simulator's truth, or from the env's scan tracker as in flight. The firmware is
ArduPilot's response, so the gate's envelope is the one it flies; the walkers (0.5-1.5 m/s) keep
within the speed bound. Passive safety is asserted: no contact while the vehicle moves faster than
the creep a stop leaves (a walker reaching a vehicle at rest is reported apart). The worlds are
validation seeds (500,100 on); ``bench/bench_shield_movers.py`` flies more.
"""

from __future__ import annotations

import pytest

from training.config import load_train_config
from training.episodes import NAV_ENV_ID, goal_worlds, make_eval_env
from training.mover_attack import MOVER_ATTACKERS, fly

#: 20 s of flight each
MAX_STEPS = 200


def _dynamic_env(tracking: bool, family: str = "office-dynamic"):
    overrides = [
        f"env.max_steps={MAX_STEPS}",
        f'env.families=["{family}"]',
        'env.autopilot_response="ardupilot"',
        f"env.tracking={str(tracking).lower()}",
    ]
    return make_eval_env(load_train_config("training/configs/nav.toml", overrides).env, NAV_ENV_ID)


@pytest.fixture(scope="module")
def env():
    made = _dynamic_env(tracking=True)
    yield made
    made.close()


@pytest.fixture(scope="module")
def rooms_envs():
    """Rooms with walkers and other drones, tracked, and as before movers were tracked (their
    returns bias the drift estimate and fill the map)."""
    made = (
        _dynamic_env(tracking=True, family="rooms-dynamic"),
        _dynamic_env(tracking=False, family="rooms-dynamic"),
    )
    yield made
    for env in made:
        env.close()


@pytest.mark.parametrize("source", ["truth", "tracker"])
@pytest.mark.parametrize("attacker", MOVER_ATTACKERS)
def test_no_attacker_closes_on_a_walker_while_moving(env, attacker: str, source: str) -> None:
    """Offices with 2-4 walkers (0.5-1.5 m/s, within the bound), three worlds per attacker; the
    movers from the truth, and from the env's tracker as the companion gives them in flight."""
    worlds = goal_worlds(["office-dynamic"], 500_100, 3, (0.9, 0.9))
    flights = {w.name: fly(env, w, attacker, movers=source) for w in worlds}
    moving = {name: f.while_moving for name, f in flights.items() if f.while_moving}
    at_rest = {name: f.contacts for name, f in flights.items() if f.contacts and not f.while_moving}
    assert not moving, f"{attacker} met a walker while moving: {moving} (at rest: {at_rest})"
    assert min(f.moving_gap for f in flights.values()) >= 0.0


def test_the_gate_that_takes_movers_for_standing_returns_meets_one_while_moving(rooms_envs) -> None:
    """The tests above can fail: as before movers were tracked (nothing tracked, the movers' returns
    remembered as standing ones), the mover ram meets a mover while the vehicle still moves in
    rooms-dynamic-500104; with the tracker and the gate that sees them move, not in that same room.
    (Of rooms 500,100-500,111 it is the one where it does: elsewhere, and in the offices above, the
    memory's inflation and the stop kept while it grows keep it off the movers.)"""
    tracked, untracked = rooms_envs
    worlds = goal_worlds(["rooms-dynamic"], 500_104, 1, (0.9, 0.9))
    met = [w for w in worlds if fly(untracked, w, "mover_ram", movers="none").while_moving]
    assert met, "the gate that takes movers for standing returns met none while moving"
    assert not [w.name for w in met if fly(tracked, w, "mover_ram", movers="tracker").while_moving]
