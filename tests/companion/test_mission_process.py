"""The companion process with a goal: progress announced, HOLD without position and at the end.

No goal-conditioned policy exists yet (issue 12), so the forward policy flies; what is tested is
the goal plumbing around it: the setpoints become zero exactly when the goal says hold.
"""

from __future__ import annotations

import time

from tests.companion.companion_process import LidarSender, free_udp_port, start_companion, stop, write_config
from tests.companion.companion_process import wait_until as _wait
from tests.companion.mavlink_peer import SimulatedAutopilot
from tests.onnx_models import write_policy

SETPOINT = "SET_POSITION_TARGET_LOCAL_NED"
GOAL = """
[goal]
source = "fixed"
acceptance_radius = 1.0
[[goal.waypoints]]
north = 5.0
east = 0.0
down = -1.5
"""



def _texts(vehicle, since):
    return [m.text for m in vehicle.messages("STATUSTEXT", since=since)]


def test_fixed_goal_position_loss_and_completion_hold(tmp_path):
    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    model = write_policy(tmp_path / "forward.onnx", kind="forward")
    config = write_config(tmp_path, model, lidar_port, mavlink_port, extra=GOAL)
    vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{mavlink_port}")
    vehicle.local_position = (0.0, 0.0, -1.5)
    proc = start_companion(config)
    lidar = LidarSender(lidar_port)
    try:
        lidar.on = True
        _wait(lambda: any(m.vx > 0 for m in vehicle.messages(SETPOINT)), 20.0, "the policy flying")
        _wait(lambda: any("goal: tracking" in t for t in _texts(vehicle, 0.0)), 5.0, "goal: tracking")

        # position lost: after 1 s the goal says hold, the setpoints are zero, the pilot is told why
        vehicle.velocity_ned = None  # no LOCAL_POSITION_NED: neither position nor velocity
        t_lost = time.monotonic()
        _wait(lambda: any("hold (no position)" in t for t in _texts(vehicle, t_lost)), what="position hold")
        t_held = time.monotonic() + 0.2
        time.sleep(0.8)
        held = vehicle.messages(SETPOINT, since=t_held)
        assert len(held) >= 3 and all(m.vx == 0.0 for m in held)

        # position back: tracking again, the policy's setpoints resume
        vehicle.local_position, vehicle.velocity_ned = (1.0, 0.0, -1.5), (0.0, 0.0)
        t_back = time.monotonic()
        _wait(lambda: any(m.vx > 0 for m in vehicle.messages(SETPOINT, since=t_back)), what="tracking again")

        # at the waypoint: reached, complete, hold (the mode is never changed: on_complete = hold)
        vehicle.local_position = (4.6, 0.2, -1.5)
        t_end = time.monotonic()
        _wait(lambda: any("complete, holding" in t for t in _texts(vehicle, t_end)), what="completion")
        assert any("reached fixed 1 (1/1)" in t for t in _texts(vehicle, t_end))
        t_done = time.monotonic() + 0.2
        time.sleep(0.8)
        done = vehicle.messages(SETPOINT, since=t_done)
        assert len(done) >= 3 and all(m.vx == 0.0 for m in done)
        assert not [m for m in vehicle.messages("COMMAND_LONG", since=t_end) if m.command == 176]  # no mode
    finally:
        lidar.close()
        if proc.poll() is None:
            print(stop(proc)[2][-5000:])
        vehicle.close()


def test_on_complete_rtl_requested_once(tmp_path):
    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    model = write_policy(tmp_path / "forward.onnx", kind="forward")
    config = write_config(tmp_path, model, lidar_port, mavlink_port,
                          extra=GOAL.replace('source = "fixed"', 'source = "fixed"\non_complete = "rtl"'))
    vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{mavlink_port}")
    vehicle.local_position = (0.0, 0.0, -1.5)
    proc = start_companion(config)
    lidar = LidarSender(lidar_port)
    try:
        lidar.on = True
        _wait(lambda: any(m.vx > 0 for m in vehicle.messages(SETPOINT)), 20.0, "the policy flying")
        vehicle.local_position = (5.0, 0.0, -1.5)
        _wait(lambda: any("requesting RTL" in t for t in _texts(vehicle, 0.0)), what="the RTL request")
        time.sleep(1.0)
        modes = [m for m in vehicle.messages("COMMAND_LONG") if m.command == 176]  # MAV_CMD_DO_SET_MODE
        assert len(modes) == 1 and modes[0].param2 == 6  # ArduCopter RTL
        assert (modes[0].target_system, modes[0].target_component) == (1, 1)
    finally:
        lidar.close()
        if proc.poll() is None:
            print(stop(proc)[2][-5000:])
        vehicle.close()
