"""The pure logic test_px4_flight judges the OFFBOARD setpoints with: after engaging, the shield's
ramp from standstill (and nothing else) may precede the policy's command; after it, only the command.

The recorded sequence is the one a failing run of test_px4_flight saw on 2026-11-24 (times relative
to the moment the vehicle's true speed passed 0.4 m/s, where the old test opened its window): PX4's
estimate bias had the hovering vehicle drifting at 0.22 m/s when the companion engaged, so 0.4 m/s
came 0.40 s later, before the ramp's last step (0.7977 m/s) had been repeated for the last time.
"""

from __future__ import annotations

import pytest

from companion.safety.shield import ShieldConfig
from tests.sitl.helpers import engagement_ramp, is_command, ramp_problem

COMMAND = (1.0, -0.6)  # the constant test policy's 0.5, 0.4: m/s forward, rad/s FRD
SHIELD = ShieldConfig(max_accel=2.0)  # the shield that recording ran (4 m/s² since 2026-12-05)
ZEROS = [(-0.5305, 0.0, -0.0), (-0.4809, 0.0, -0.0), (-0.4302, 0.0, -0.0), (-0.3801, 0.0, -0.0)]
RAMP = [
    (-0.3788, 0.2000, -0.4), (-0.3296, 0.2000, -0.4), (-0.2812, 0.3976, -0.6), (-0.2303, 0.3976, -0.6),
    (-0.1791, 0.6017, -0.6), (-0.1778, 0.6017, -0.6), (-0.1290, 0.6017, -0.6), (-0.0807, 0.7977, -0.6),
    (-0.0309, 0.7977, -0.6), (0.0207, 0.7977, -0.6),
]
FLYING = [(0.0213, 1.0, -0.6), (0.0718, 1.0, -0.6), (0.1207, 1.0, -0.6)]
RECORDED = ZEROS + RAMP + FLYING


def problem(setpoints):
    ramp, first = engagement_ramp(setpoints, COMMAND)
    return ramp_problem(ramp, first, COMMAND, SHIELD.max_accel, SHIELD.max_yaw_accel)


def test_the_recorded_failure_is_the_shields_ramp_and_the_window_after_it_is_all_command():
    ramp, first = engagement_ramp(RECORDED, COMMAND)
    assert ramp == RAMP and first == FLYING[0]
    assert problem(RECORDED) is None
    # the old window (from the speed, t = 0) held a ramp step; the one from the ramp's end holds none
    assert [s for s in RECORDED if s[0] >= 0.0 and not is_command(s, COMMAND)] == [RAMP[-1]]
    t0 = max(0.0, first[0])
    assert all(is_command(s, COMMAND) for s in RECORDED if s[0] >= t0)


@pytest.mark.parametrize(
    ("setpoints", "why"),
    [
        (ZEROS + FLYING, "grew faster"),  # straight to the command: no ramp at all
        ([*ZEROS, (-0.37, 0.2, -0.4), (-0.27, 0.6, -0.6), *FLYING], "grew faster"),
        (ZEROS + RAMP[:4] + [(-0.2, 0.2, -0.6)] + FLYING, "not monotonic"),  # a dip
        (ZEROS + RAMP[:4] + [(-0.2, 1.2, -0.6)] + FLYING, "not between"),  # past the command
        (ZEROS + RAMP[:4] + [(-0.2, 0.6, 0.3)] + FLYING, "not between"),  # turning the other way
    ],
)
def test_anything_but_a_ramp_from_standstill_before_the_command_is_named(setpoints, why):
    assert why in problem(setpoints)


def test_a_hold_restarts_the_ramp_which_is_judged_from_the_hold_on():
    held = [(t + 0.5, 0.0, 0.0) for t, *_ in ZEROS[:2]]
    again = [(t + 0.6, vx, yr) for t, vx, yr in RAMP]
    setpoints = ZEROS + RAMP[:5] + held + again + [(s[0] + 0.6, *s[1:]) for s in FLYING]
    assert engagement_ramp(setpoints, COMMAND)[0] == again
    assert problem(setpoints) is None


def test_no_command_at_all_fails():
    with pytest.raises(AssertionError, match="no setpoint is the command"):
        engagement_ramp(ZEROS + RAMP, COMMAND)
