"""The shield giving way behind the backup gate (``[shield] give_way``): where a mover's tracked
course runs through the vehicle's stop, a sidestep whose own stop keeps clear of the returns."""

from __future__ import annotations

import math

import numpy as np

from companion.perception.scan import N_BINS
from companion.perception.tracking import Mover
from companion.safety.give_way import GiveWay, GiveWayConfig
from companion.safety.shield import Command, SafetyShield, ShieldConfig

MAX_RANGE = 10.0
WALKER = 0.25
OPEN = np.ones(N_BINS)
#: 1 m/s leftwards from 3 m to the right: its course runs through the vehicle's position
CROSSING = Mover((0.0, -3.0), (0.0, 1.0), WALKER)


def _shield(give_way: bool = True) -> SafetyShield:
    return SafetyShield(ShieldConfig(backup_gate=True, give_way=give_way), MAX_RANGE, "ardupilot")


def _send(shield: SafetyShield, scan: np.ndarray, movers: list[Mover], velocity=(0.0, 0.0), yaw_rate=0.0):
    return shield.filter(Command(0.0, yaw_rate, 0.0), scan, 0.1, velocity, heading=0.0, movers=movers)


def test_a_walker_whose_course_runs_through_the_vehicle_at_rest_makes_it_step_aside() -> None:
    """At rest, asked to stay (and turn): without ``give_way`` the stop stands in the walker's way
    (the gate's promise is kept: the vehicle does not move); with it, a sidestep along the nose
    clears its course, flown with the heading held (it is judged in the body axes of now)."""
    stays = _send(_shield(give_way=False), OPEN, [CROSSING], yaw_rate=0.5)
    assert (stays.forward, stays.lateral) == (0.0, 0.0) and stays.yaw_rate > 0.0
    shield = _shield()
    out = _send(shield, OPEN, [CROSSING], yaw_rate=0.5)
    assert shield.interventions["gate_give_way"] == 1
    assert abs(out.forward) > 0.4 and abs(out.lateral) < 0.5  # out of its course, not along it
    assert out.yaw_rate == 0.0
    rule = GiveWay(GiveWayConfig(vehicle_radius=shield.config.body_radius))
    assert rule.closest((out.forward, out.lateral), (0.0, 0.0), [CROSSING], 3.0) >= 0.0


def test_a_walker_that_passes_clear_changes_nothing() -> None:
    """Crossing 3 m ahead, its course misses the vehicle's stop: the gate's command stands."""
    shield = _shield()
    assert _send(shield, OPEN, [Mover((3.0, -3.0), (0.0, 1.0), WALKER)]) == Command(0.0, 0.0, 0.0)
    assert shield.interventions["gate_give_way"] == 0


def test_a_sidestep_keeps_clear_of_the_returns() -> None:
    """A wall 0.7 m ahead: the sidestep is backwards (at the reverse limit), never into the wall;
    with walls 0.4 m all round, no sidestep's stop keeps clear and the stop stands."""
    ahead = np.ones(N_BINS)
    ahead[np.r_[0:60, 300:360]] = 0.7 / MAX_RANGE
    shield = _shield()
    out = _send(shield, ahead, [CROSSING])
    assert shield.interventions["gate_give_way"] == 1
    assert -shield.config.max_reverse_speed - 1e-9 <= out.forward < 0.0
    boxed = _shield()
    assert _send(boxed, np.full(N_BINS, 0.4 / MAX_RANGE), [CROSSING]).forward == 0.0
    assert boxed.interventions["gate_give_way"] == 0


def _hover_in_a_walkers_way(give_way: bool, seconds: float = 8.0) -> float:
    """A vehicle asked to hover (its velocity following the setpoint with a 0.3 s lag) while a
    walker crosses its position at 1.2 m/s from 4.8 m away; the shield sees the walker as tracked,
    a scan old. Returns the least gap between the two bodies, m."""
    shield = _shield(give_way)
    position, velocity = np.zeros(2), np.zeros(2)
    walker, walk = np.array([0.2, -4.8]), np.array([0.0, 1.2])
    least = math.inf
    for _ in range(round(seconds / 0.1)):
        seen = Mover(tuple(walker - position), tuple(walk), WALKER)
        out = _send(shield, OPEN, [seen], velocity=tuple(velocity))
        setpoint = np.array([out.forward, out.lateral])
        for _ in range(10):
            velocity += (setpoint - velocity) * (0.01 / 0.3)
            position += velocity * 0.01
            walker += walk * 0.01
            least = min(least, float(np.hypot(*(walker - position))) - WALKER - shield.config.body_radius)
    return least


def test_in_closed_loop_the_walker_misses_a_vehicle_that_gives_way() -> None:
    """Without ``give_way`` the walker runs into the hovering vehicle; with it, it passes clear."""
    assert _hover_in_a_walkers_way(give_way=False) < 0.0
    assert _hover_in_a_walkers_way(give_way=True) > 0.2


def test_a_sidestep_towards_the_walker_is_not_taken() -> None:
    """Walls 1 m off all round but to the right, where the walker comes from: the one sidestep
    with room runs into the walker sooner than the stop would be met, so the stop stands."""
    right = np.full(N_BINS, 1.0 / MAX_RANGE)
    right[225:315] = 1.0
    shield = _shield()
    out = _send(shield, right, [CROSSING])
    assert (out.forward, out.lateral) == (0.0, 0.0)
    assert shield.interventions["gate_give_way"] == 0
