"""The companion process with a goal: progress announced, HOLD without position and at the end.

No goal-conditioned policy exists yet (issue 12), so the forward policy flies; what is tested is
the goal plumbing around it: the setpoints become zero exactly when the goal says hold.
"""

from __future__ import annotations

import time

from tests.companion.companion_process import Flight
from tests.companion.companion_process import wait_until as _wait

GOAL = """
[goal]
source = "fixed"
acceptance_radius = 1.0
[[goal.waypoints]]
north = 5.0
east = 0.0
down = -1.5
"""


def test_fixed_goal_position_loss_and_completion_hold(tmp_path):
    f = Flight.with_model(tmp_path, "forward", GOAL)
    vehicle = f.vehicle
    try:
        _wait(lambda: any(m.vx > 0 for m in f.setpoints()), 20.0, "the policy flying")
        _wait(lambda: any("goal: tracking" in t for t in f.texts()), 5.0, "goal: tracking")

        # position lost: after 1 s the goal says hold, the setpoints are zero, the pilot is told why
        vehicle.velocity_ned = None  # no LOCAL_POSITION_NED: neither position nor velocity
        t_lost = time.monotonic()
        _wait(lambda: any("hold (no position)" in t for t in f.texts(t_lost)), what="position hold")
        t_held = time.monotonic() + 0.2
        time.sleep(0.8)
        held = f.setpoints(since=t_held)
        assert len(held) >= 3 and all(m.vx == 0.0 for m in held)

        # position back: tracking again, the policy's setpoints resume
        vehicle.local_position, vehicle.velocity_ned = (1.0, 0.0, -1.5), (0.0, 0.0)
        t_back = time.monotonic()
        _wait(lambda: any(m.vx > 0 for m in f.setpoints(since=t_back)), what="tracking again")

        # at the waypoint: reached, complete, hold (the mode is never changed: on_complete = hold)
        vehicle.local_position = (4.6, 0.2, -1.5)
        t_end = time.monotonic()
        _wait(lambda: any("complete, holding" in t for t in f.texts(t_end)), what="completion")
        assert any("reached fixed 1 (1/1)" in t for t in f.texts(t_end))
        t_done = time.monotonic() + 0.2
        time.sleep(0.8)
        done = f.setpoints(since=t_done)
        assert len(done) >= 3 and all(m.vx == 0.0 for m in done)
        assert not [m for m in vehicle.messages("COMMAND_LONG", since=t_end) if m.command == 176]  # no mode
    finally:
        f.close()


def test_on_complete_rtl_requested_once(tmp_path):
    f = Flight.with_model(tmp_path, "forward",
                          GOAL.replace('source = "fixed"', 'source = "fixed"\non_complete = "rtl"'))
    try:
        _wait(lambda: any(m.vx > 0 for m in f.setpoints()), 20.0, "the policy flying")
        f.vehicle.local_position = (5.0, 0.0, -1.5)
        _wait(lambda: any("requesting RTL" in t for t in f.texts()), what="the RTL request")
        time.sleep(1.0)
        modes = [m for m in f.vehicle.messages("COMMAND_LONG") if m.command == 176]  # MAV_CMD_DO_SET_MODE
        assert len(modes) == 1 and modes[0].param2 == 6  # ArduCopter RTL
        assert (modes[0].target_system, modes[0].target_component) == (1, 1)
    finally:
        f.close()
