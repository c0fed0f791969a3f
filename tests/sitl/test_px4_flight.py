"""SITL on the simulated PX4: the real companion (MAVSDK inside) flies in OFFBOARD; killing it makes
PX4's offboard-loss failsafe (COM_OF_LOSS_T, then COM_OBL_RC_ACT = 5: Hold) stop the vehicle."""

from __future__ import annotations

import signal
import time

import numpy as np
import pytest

from companion.config import load_config
from flightsim.sitl.harness import FlightOptions, SitlFlight
from tests.sitl.helpers import (
    OPEN_ROOM,
    engagement_ramp,
    is_command,
    ramp_problem,
    recorded_setpoints,
    speed,
    stopped_at,
    wait_for,
    write_constant_policy,
)

pytestmark = pytest.mark.sitl


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("sitl-px4")
    options = FlightOptions(
        autopilot="sim-px4",
        world=OPEN_ROOM,
        policy=write_constant_policy(workdir / "circle.onnx", 0.5, 0.4),
        workdir=workdir,
        autopilot_params={"COM_OBL_RC_ACT": 5},
    )
    with SitlFlight(options) as f:
        f.take_off()
        assert f.wait_engaged(25.0), f.companion_log()
        yield f


def test_companion_flies_px4_in_offboard(flight):
    f = flight
    assert f.server.autopilot.mode_name() == "OFFBOARD"
    wait_for(lambda: speed(f) > 0.4, 10.0, "the vehicle to fly")  # PX4's calibrated circle: 0.4-0.7 m/s
    # The speed alone does not say the ramp is over: hovering on zero setpoints, PX4's true velocity
    # wanders with its estimate's bias (0.1-0.42 m/s seen here), so 0.4 m/s can come before the
    # shield's ramp from standstill (0 -> 1 m/s at max_accel, ~0.25 s) has reached the command.
    # The window starts once both hold; before it, only that ramp is allowed.
    command = (1.0, -0.6)  # the policy's 0.5, 0.4 as sent: m/s forward, rad/s FRD (a CCW turn is negative)
    t_speed = time.monotonic()
    wait_for(lambda: any(is_command(s, command) for s in recorded_setpoints(f)), 2.0,
             "the shield's ramp to reach the command")
    ramp, first = engagement_ramp(recorded_setpoints(f), command)
    shield = load_config(f.config_path).shield
    problem = ramp_problem(ramp, first, command, shield.max_accel, shield.max_yaw_accel)
    assert problem is None, (problem, ramp)
    t0 = max(t_speed, first[0])
    revs0 = f.cosim.stats.revolutions
    time.sleep(max(0.0, t0 + 3.0 - time.monotonic()))
    assert f.recorder.setpoints_since(t0) >= f.cosim.stats.revolutions - revs0 - 2  # (MAVSDK also repeats)
    with f.recorder.lock:
        recent = [s for s in f.recorder.setpoints if s[0] >= t0]
    # every setpoint after the ramp is the policy's command (the open room never makes the shield act)
    wrong = [s for s in recent if not is_command(s, command)]
    assert not wrong, (wrong, [line for line in f.companion_log().splitlines() if "supervisor" in line])
    # PX4's calibrated response is slow (0.75 m/s of 1 m/s after 4 s): give it the time to cover 2 m
    wait_for(lambda: f.report().distance_m > 2.0, 5.0, "the vehicle to cover 2 m")
    report = f.report()
    assert report.engaged and not report.collision and report.distance_m > 2.0


def test_companion_sigkill_offboard_loss_holds_after_com_of_loss_t(flight):
    f = flight
    ap = f.server.autopilot
    t_kill = time.monotonic()
    f.kill_companion(signal.SIGKILL)
    time.sleep(0.6)
    # within COM_OF_LOSS_T: still in OFFBOARD, flying the companion's last setpoint at the speed PX4
    # sees (its velocity estimate, which its loop closes on). Not the true speed: the calibrated
    # response's estimate bias (sigma 0.25 m/s per axis, tau 3 s) takes this circle's true speed below
    # 0.3 m/s now and then (2 of 80 runs on 2026-11-24: 0.23 and 0.10 m/s 0.6 s after the kill; the
    # response model alone: 40 of 1500 seeds below 0.3, the estimate's speed never below 0.25)
    with f.recorder.lock:
        last_setpoint = f.recorder.setpoint_times[-1]
    target, reported = f.server.call(lambda a: (a.target, a.reported_velocity()))
    assert ap.mode_name() == "OFFBOARD" and target is not None
    assert f.server.t0 + target.time == pytest.approx(last_setpoint, abs=1e-6)
    assert np.linalg.norm(reported[:2]) > 0.2  # PX4 sees 0.4-1.0 m/s in this circle; stopped is < 0.1
    wait_for(lambda: ap.mode_name() == "AUTO.LOITER", 3.0, "the offboard-loss failsafe", poll=0.005)
    assert last_setpoint < t_kill + 0.05
    assert 1.0 <= time.monotonic() - last_setpoint < 1.5  # COM_OF_LOSS_T = 1 s after the last setpoint
    assert ap.counters["offboard_lost"] == 1
    wait_for(lambda: stopped_at(f, t_kill) is not None, 4.0, "the vehicle to stop")
    assert stopped_at(f, t_kill) - t_kill < 1.0 + 1.5
    assert any("no offboard signal" in t for t in f.pilot(lambda g: g.statustexts))  # to the GCS link only
