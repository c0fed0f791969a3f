"""The give-way rule of ``goal_follower_tracks`` on hand-made movers (companion/safety/give_way.py)."""

import numpy as np

from companion.perception.tracking import Mover
from companion.safety.give_way import GiveWay, GiveWayConfig

OPEN = np.full(360, np.inf)  # nothing static anywhere
CRUISE = (1.4, 0.0)  # the goal follower's intended velocity: straight ahead, m/s
WALKER = 0.25


def _decide(movers, velocity=CRUISE, clear=OPEN, max_left=1.0, rule=None):
    return (rule or GiveWay()).decide(CRUISE, velocity, movers, clear, max_left)


def test_no_movers_go():
    assert _decide([]).mode == "go"


def test_a_walker_crossing_the_course_makes_it_wait():
    # 2 m ahead, 1.5 m to the right, walking left across the course at 1 m/s
    decision = _decide([Mover((2.0, -1.5), (0.0, 1.0), WALKER)])
    assert decision.mode == "wait"
    assert decision.velocity == (0.0, 0.0)


def test_a_walker_walking_away_does_not():
    assert _decide([Mover((2.0, 0.0), (1.0, 0.0), WALKER)]).mode == "go"
    assert _decide([Mover((2.0, -1.5), (0.0, -1.0), WALKER)]).mode == "go"


def test_a_walker_that_has_passed_close_does_not():
    """Already inside the keep-apart distance but drawing apart: passed, no conflict."""
    assert _decide([Mover((-0.2, 0.5), (0.0, 1.0), WALKER)]).mode == "go"  # just crossed behind


def test_a_head_on_drone_makes_it_step_aside_away_from_its_path():
    # a drone 5 m ahead, a little to the left of the nose, coming straight back at 2.5 m/s
    decision = _decide([Mover((5.0, 0.2), (-2.5, 0.0), 0.4)], velocity=(0.0, 0.0))
    assert decision.mode == "step"
    left = decision.velocity[1]
    assert left < -0.5  # to the right, away from the side the drone is on
    assert GiveWay().closest(decision.velocity, (0.0, 0.0), [Mover((5.0, 0.2), (-2.5, 0.0), 0.4)], 3.0) >= 0.0


def test_a_sidestep_needs_room():
    """Walls close on both sides: no sidestep has room, so it waits rather than steps into one."""
    angles = np.deg2rad(np.arange(360) + 0.5)
    walled = np.where(np.abs(np.sin(angles)) > 0.3, 0.8, np.inf)  # only along the nose is open
    decision = _decide([Mover((5.0, 0.2), (-2.5, 0.0), 0.4)], velocity=(0.0, 0.0), clear=walled, max_left=1.0)
    assert decision.mode in ("step", "wait")
    assert abs(decision.velocity[1]) < 1e-9  # along the nose (back away), never into a wall


def test_without_a_sideways_part_a_sidestep_is_along_the_nose():
    decision = _decide([Mover((5.0, 0.2), (-2.5, 0.0), 0.4)], velocity=(0.0, 0.0), max_left=0.0)
    assert decision.mode == "step"
    assert decision.velocity[0] < 0.0 and abs(decision.velocity[1]) < 1e-9  # back: met latest


def test_it_goes_again_only_after_the_course_stays_clear():
    rule = GiveWay(GiveWayConfig(resume_steps=3))
    crossing = [Mover((2.0, -1.5), (0.0, 1.0), WALKER)]
    assert _decide(crossing, rule=rule).mode == "wait"
    gone = [Mover((2.0, 2.5), (0.0, 1.0), WALKER)]  # it has crossed and walks on
    assert [_decide(gone, rule=rule).mode for _ in range(3)] == ["wait", "wait", "go"]
