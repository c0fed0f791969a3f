"""The companion process feeding a goal-layout model (real ONNX Runtime, real MAVLink over loopback).

Echo models answer with the features the companion built (``tests/onnx_models.py``), so each
setpoint shows what reached the model: the goal's bearing from LOCAL_POSITION_NED and ATTITUDE, the
measured velocity turned into the body frame, the goal 20 m ahead when there is no goal source, and
the climb toward a waypoint's height beside the policy's horizontal command.
"""

from __future__ import annotations

import itertools
import math
import time
from pathlib import Path

import numpy as np
import pytest

from companion.app import policy_spec
from companion.autopilot.mavlink_adapter import mavlink
from companion.config import CompanionConfig, PolicyConfig
from companion.perception.drift import DriftHoldConfig
from companion.safety.shield import AUTOPILOT_LIMITS, stopping_speed
from tests.companion.companion_process import (
    WEST_AND_UP,
    Flight,
    free_udp_port,
    run_to_exit,
    write_config,
)
from tests.companion.companion_process import wait_until as _wait
from tests.companion.mavlink_peer import SETPOINT
from tests.onnx_models import SCAN_SPEC, write_policy


def test_without_a_goal_source_the_goal_is_ahead_and_the_altitude_held(tmp_path):
    f = Flight.with_model(tmp_path, "echo_goal")
    try:
        # goal 20 m ahead on the heading: bearing (cos, sin) = (1, 0), whatever the heading
        f.vehicle.yaw_ned = 2.0
        last = f.settled(lambda m: m.vx > 1.0 and abs(m.yaw_rate) < 1e-3, "forward flight, goal ahead")
        assert last.vz == 0.0  # altitude held
    finally:
        f.close()


def test_fixed_goal_bearing_from_position_and_heading_and_climb_to_its_height(tmp_path):
    f = Flight.with_model(tmp_path, "echo_goal", WEST_AND_UP)
    try:
        # heading north, the goal due west: on the left (sin = 1), a left turn = negative FRD yaw rate;
        # 2 m below the waypoint: climb at max_vertical_speed (down-positive vz = -0.5)
        last = f.settled(lambda m: m.yaw_rate < -1.0 and m.vz < -0.4, "turning left and climbing")
        assert abs(last.vx) < 0.05 and last.vz >= -0.5 - 1e-6
        # heading west: the goal ahead, fly forward without turning
        f.vehicle.yaw_ned = -math.pi / 2
        f.settled(lambda m: m.vx > 1.0 and abs(m.yaw_rate) < 0.05, "flying toward the goal ahead")
        # at the waypoint's height, west of the origin by 4.5 m: reached (1 m), complete, zero setpoints
        f.vehicle.local_position = (0.0, -4.5, -3.5)
        f.settled(lambda m: m.vx == 0.0 and m.vz == 0.0 and m.yaw_rate == 0.0, "holding at completion")
        texts = [m.text for m in f.vehicle.messages("STATUSTEXT")]
        assert any("reached fixed 1 (1/1)" in t for t in texts)
        # a fixed waypoint is no mission item: no MISSION_ITEM_REACHED
        assert not f.vehicle.messages("MISSION_ITEM_REACHED")
    finally:
        f.close()


def test_measured_velocity_reaches_the_model_in_the_body_frame(tmp_path):
    f = Flight.with_model(tmp_path, "echo_velocity")
    try:
        # heading north, moving west at 1 m/s: body left +1 m/s, feature 0.5, a1 = 0.5: yaw rate
        # 0.75 rad/s counter-clockwise, sent as FRD -0.75
        f.vehicle.velocity_ned = (0.0, -1.0)
        f.settled(lambda m: abs(m.yaw_rate + 0.75) < 0.02, "yaw rate from the measured left velocity")
        # heading east, the same motion is backwards: left 0, no turn
        f.vehicle.yaw_ned = math.pi / 2
        f.settled(lambda m: abs(m.yaw_rate) < 0.02, "no yaw rate with the motion along the body axis")
    finally:
        f.close()


def test_the_drift_the_reported_velocity_hides_reaches_a_drift_model(tmp_path):
    # the lidar shows a still room (a circle of 8 m) while the autopilot reports motion: the velocity
    # estimate is wrong by all of it, and the drift features say so
    f = Flight.with_model(tmp_path, "echo_drift")  # the default config: goal frames with drift
    try:
        # heading north, reported 0.6 m/s north: drift forward 0.6 m/s, feature 0.3, a0 0.3 = 0.6 m/s
        f.vehicle.velocity_ned = (0.6, 0.0)
        f.settled(lambda m: abs(m.vx - 0.6) < 0.05 and abs(m.yaw_rate) < 0.05, "the drift forward")
        # reported 0.4 m/s west: drift to the left, a1 0.2 = 0.3 rad/s CCW, sent as FRD -0.3
        f.vehicle.velocity_ned = (0.0, -0.4)
        f.settled(lambda m: abs(m.vx) < 0.05 and abs(m.yaw_rate + 0.3) < 0.05, "the drift to the left")
    finally:
        f.close()


def _wall_east(azimuth_deg: np.ndarray) -> np.ndarray:
    """A wall 0.4 m east of a vehicle facing north, in a round room of 8 m."""
    east = np.sin(np.radians(azimuth_deg))
    return np.where(east > 0.05, np.minimum(0.4 / np.maximum(east, 0.05), 8.0), 8.0)


def _close_wall_west(azimuth_deg: np.ndarray) -> np.ndarray:
    """A wall 0.4 m west of a vehicle facing north (on its left), in a round room of 8 m."""
    return _wall_east(-azimuth_deg)


def test_a_sideways_model_flies_its_third_value_to_the_left_and_the_shield_stops_it_at_a_wall(tmp_path):
    """A model trained with ``env.sideways`` (a = (0, 0, 1): 1 m/s to the left), as the default config
    expects: the setpoint carries it as body vy (FRD: right positive, so -1); with a wall 0.4 m to
    the left, the shield judges the move along its course and lets none of it through."""
    f = Flight.with_model(tmp_path, "slide_left")
    try:
        f.settled(lambda m: abs(m.vy + 1.0) < 0.05 and abs(m.vx) < 0.05 and abs(m.yaw_rate) < 0.05,
                  "1 m/s to the left")
        f.lidar.scene = _close_wall_west
        f.settled(lambda m: m.vy > -0.05, "no move towards the wall on the left")
    finally:
        f.close()


def test_a_two_part_model_under_the_default_config_is_refused_naming_the_fix(tmp_path):
    """A model trained before ``env.sideways`` (two action values, no ``max_sideways_speed`` key) needs
    ``policy.max_sideways_speed = 0``: the default config expects the shipped model's three."""
    spec = policy_spec(CompanionConfig(policy=PolicyConfig(max_sideways_speed=0.0)))
    model = write_policy(tmp_path / "two.onnx", spec=spec,
                         metadata_overrides={"lidar_avoid.max_sideways_speed": None})
    path = write_config(tmp_path, model, free_udp_port(), free_udp_port())
    result = run_to_exit(["run", "--config", str(path)])
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1
    assert result.stderr.strip().endswith(
        "model output (N, 2) does not match config (1, 3) float32 "
        "(policy.max_sideways_speed 1; set policy.max_sideways_speed = 0, as the model's metadata says)"
    )


#: a config table that holds none of the drift estimate
NO_HOLD = "[drift_hold]\nlateral = 0.0\n"
#: what the default ``[drift_hold]`` holds of a 0.4 m/s drift estimate: all but its deadband, m/s
HELD = 0.4 - DriftHoldConfig().deadband


@pytest.mark.parametrize(("extra", "right"), [("", -HELD), (NO_HOLD, 0.0)])
def test_the_setpoint_holds_the_sideways_drift_the_estimate_hides(tmp_path, extra, right):
    """A hovering model in a still room, heading north, while the autopilot reports 0.4 m/s west:
    its estimate is 0.4 m/s to the left of the truth, so it would fly any setpoint 0.4 m/s to the
    right of what it is told. The setpoint holds the drift estimate less the deadband (0.15 m/s):
    0.25 m/s to the left (FRD: negative); with ``[drift_hold] lateral = 0``, nothing."""
    f = Flight.with_model(tmp_path, "stop", extra)
    f.vehicle.velocity_ned = (0.0, -0.4)
    try:
        f.settled(lambda m: abs(m.vy - right) < 0.03 and abs(m.vx) < 0.03, f"{right} m/s to the right")
    finally:
        f.close()


#: a keep-out reaching 0.6 m: the wall 0.4 m away is 0.2 m inside it, a push of 0.4 m/s (gain 2)
KEEPOUT = "[shield]\nkeepout_distance = 0.6\n"
#: the rest of the ``[shield]`` table above: a shield that carries none of the drift estimate
NO_CARRY = "drift_compensation = 0.0\n"


@pytest.mark.parametrize(
    ("extra", "push_west"),
    [(KEEPOUT, 0.8), (KEEPOUT + NO_CARRY, 0.4 + HELD), (KEEPOUT + NO_CARRY + NO_HOLD, 0.4)],
)
def test_the_keepout_push_carries_the_drift_the_estimate_hides(tmp_path, extra, push_west):
    """A hovering model, a wall 0.4 m east, and an autopilot that reports 0.4 m/s west while the
    scans stand still: it would fly its setpoint 0.4 m/s east of what it is told. The keep-out
    (reaching 0.6 m here) pushes 0.4 m/s west and the setpoint holds 0.25 m/s of the drift on top
    (0.65); the shield's ``drift_compensation`` (0.6 by default) carries the rest of the estimate,
    0.15 (0.8); carrying none, 0.65; holding none either, 0.4."""
    f = Flight.with_model(tmp_path, "stop", extra)
    f.lidar.scene = _wall_east
    f.vehicle.velocity_ned = (0.0, -0.4)
    try:
        # a body-frame setpoint: vy is to the right, so west (left, facing north) is negative
        f.settled(lambda m: abs(m.vy + push_west) < 0.05 and abs(m.vx) < 0.05, f"{push_west} m/s west")
    finally:
        f.close()


def _wall_ahead(azimuth_deg: np.ndarray) -> np.ndarray:
    """A wall 0.7 m north of a vehicle facing north, in a round room of 8 m."""
    north = np.cos(np.radians(azimuth_deg))
    return np.where(north > 0.05, np.minimum(0.7 / np.maximum(north, 0.05), 8.0), 8.0)


def test_the_shield_judges_the_motion_the_scans_show_not_the_estimate(tmp_path):
    """A model asking full speed ahead, a wall 0.7 m ahead, and an autopilot that reports 0.6 m/s
    north while the scans stand still: the drift estimate takes up the 0.6, so the shield judges a
    hovering vehicle and lets through the true speed that stops before the wall (0.35 m/s for
    ArduPilot's braking, the firmware envelope's 3 m/s² after 1.1 s; 0.5 m/s with the 2.5 m/s² after
    0.7 s it assumed before issue 66), as a setpoint 0.6 faster, since the autopilot flies it on an
    estimate that reads 0.6 fast: 0.95 m/s. Judged by the estimate alone, that 0.6 m/s could not stop
    in 0.4 m: the shield braked against a motion the scans did not show (0.1 m/s once the brake
    carried the drift); capping the setpoint rather than the true motion, it sent the true speed
    alone, which with the 0.6 truly hovers."""
    ap = AUTOPILOT_LIMITS["ardupilot"]
    true_speed = stopping_speed(0.7 - 0.3, ap.decel, ap.reaction_time)  # the wall less estop_distance
    assert true_speed == pytest.approx(0.35, abs=0.01)
    f = Flight.with_model(tmp_path, "forward")
    f.lidar.scene = _wall_ahead
    f.vehicle.velocity_ned = (0.6, 0.0)
    try:
        ahead = 0.6 + true_speed
        f.settled(lambda m: abs(m.vx - ahead) < 0.1 and abs(m.vy) < 0.05, f"{ahead:.2f} m/s ahead")
    finally:
        f.close()


def test_a_drift_model_under_a_config_without_drift_is_refused_naming_both_layouts(tmp_path):
    model = write_policy(tmp_path / "drift.onnx", kind="echo_drift")
    path = write_config(tmp_path, model, free_udp_port(), free_udp_port())
    path.write_text(path.read_text().replace("[policy]\n", "[policy]\ndrift = false\n"))
    result = run_to_exit(["run", "--config", str(path)])
    assert result.returncode == 2
    assert "+drift(forward,left/2m/s)" in result.stderr and len(result.stderr.strip().splitlines()) == 1
    assert result.stderr.strip().endswith("(drift features: set policy.drift = true)")


def _command_model(tmp_path: Path) -> Path:
    config = CompanionConfig(policy=PolicyConfig(command=True))
    return write_policy(tmp_path / "command.onnx", kind="echo_command", spec=policy_spec(config))


def test_the_last_setpoint_sent_reaches_a_command_model(tmp_path):
    # a1 = 0.4 - the last yaw-rate command / 1.5: each setpoint's yaw rate and the one before sum to
    # 0.6 rad/s, and they alternate (the shield's yaw acceleration limit set where it started). A
    # frame without the last command would give 0.6 rad/s throughout. Sent as FRD: negative.
    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    config = write_config(tmp_path, _command_model(tmp_path), lidar_port, mavlink_port)
    config.write_text(config.read_text().replace("[policy]\n", "[policy]\ncommand = true\n"))
    f = Flight(config, lidar_port, mavlink_port)
    try:
        def alternating():
            rates = [m.yaw_rate for m in f.setpoints(since=time.monotonic() - 1.0)]
            pairs = list(itertools.pairwise(rates))
            settled = len(pairs) >= 5 and all(abs(a + b + 0.6) < 0.02 for a, b in pairs)
            return settled and all(abs(a - b) > 0.1 for a, b in pairs)

        _wait(alternating, 20.0, "yaw rates alternating, each pair summing to 0.6 rad/s")
    finally:
        f.close()


@pytest.mark.parametrize(("autopilot", "speed"), [("ardupilot", 1.5), ("px4", 0.5)])
def test_the_autopilot_type_reaches_a_firmware_model(tmp_path, autopilot, speed):
    # a0 = 0.25 + 0.5 x the firmware feature: 1.5 m/s when it reads ArduPilot (1.0), 0.5 m/s for PX4
    config = CompanionConfig(policy=PolicyConfig(firmware=True))
    model = write_policy(tmp_path / "firmware.onnx", kind="echo_firmware", spec=policy_spec(config))
    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    path = write_config(tmp_path, model, lidar_port, mavlink_port, autopilot=autopilot)
    path.write_text(path.read_text().replace("[policy]\n", "[policy]\nfirmware = true\n"))
    peer = mavlink.MAV_AUTOPILOT_PX4 if autopilot == "px4" else mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    f = Flight(path, lidar_port, mavlink_port, autopilot=peer)
    try:
        f.settled(lambda m: abs(m.vx - speed) < 0.05, f"{speed} m/s forward for {autopilot}")
    finally:
        f.close()


def test_a_command_model_under_a_config_without_command_is_refused_naming_the_fix(tmp_path):
    path = write_config(tmp_path, _command_model(tmp_path), free_udp_port(), free_udp_port())
    result = run_to_exit(["run", "--config", str(path)])
    assert result.returncode == 2 and len(result.stderr.strip().splitlines()) == 1
    assert "+command(forward/2m/s,yaw/1.5rad/s)" in result.stderr
    assert result.stderr.strip().endswith("(command features: set policy.command = true)")


def test_scan_only_model_with_a_goal_source_is_refused_in_one_line(tmp_path):
    model = write_policy(tmp_path / "scan.onnx", spec=SCAN_SPEC)
    config = write_config(tmp_path, model, free_udp_port(), free_udp_port(), extra=WEST_AND_UP)
    config.write_text(config.read_text().replace("[policy]\n", '[policy]\nobservation = "scan"\n'))
    result = run_to_exit(["run", "--config", str(config)])
    assert result.returncode == 2
    assert result.stderr.strip() == (
        "avoid-companion: error: CompanionConfig: goal.source = 'fixed' needs a goal policy "
        '(policy.observation = "goal"); a scan-only policy cannot fly to a goal'
    )


def test_scan_only_model_needs_observation_scan_and_then_flies(tmp_path):
    model = write_policy(tmp_path / "scan.onnx", kind="forward", spec=SCAN_SPEC)
    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    config = write_config(tmp_path, model, lidar_port, mavlink_port)
    refused = run_to_exit(["run", "--config", str(config)])
    assert refused.returncode == 2 and len(refused.stderr.strip().splitlines()) == 1
    assert "does not match config observation layout" in refused.stderr
    assert refused.stderr.strip().endswith('(a scan-only model: set policy.observation = "scan")')
    config.write_text(config.read_text().replace("[policy]\n", '[policy]\nobservation = "scan"\n'))
    f = Flight(config, lidar_port, mavlink_port, position=None)
    try:
        _wait(lambda: any(m.vx > 0 for m in f.vehicle.messages(SETPOINT)), 20.0,
              "the scan-only policy flying")
    finally:
        f.close()


def test_the_shipped_exported_goal_model_flies_toward_a_fixed_goal(tmp_path):
    """``avoid-train export``'s goal model (models/policy.onnx) under the default config: it loads,
    engages and commands (what it asks for is the policy's business, not tested here)."""
    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    shipped = Path(__file__).resolve().parents[2] / "models" / "policy.onnx"
    config = write_config(tmp_path, shipped, lidar_port, mavlink_port, extra=WEST_AND_UP)
    f = Flight(config, lidar_port, mavlink_port)
    try:
        _wait(lambda: any(m.vx != 0.0 or m.yaw_rate != 0.0 for m in f.vehicle.messages(SETPOINT)), 20.0,
              "the shipped policy commanding")
        assert any("goal: tracking" in m.text for m in f.vehicle.messages("STATUSTEXT"))
        assert any(m.vz < -0.1 for m in f.vehicle.messages(SETPOINT))  # climbing toward the waypoint
    finally:
        f.close()


def _wall_west(azimuth_deg: np.ndarray) -> np.ndarray:
    """A wall 2 m west of a vehicle facing north, from 4 m south of it to 1.5 m north, in a round
    room of 8 m: ranges per azimuth (degrees clockwise from the front)."""
    a = np.radians(azimuth_deg)
    west = -np.sin(a)
    t = np.where(west > 1e-6, 2.0 / np.maximum(west, 1e-6), np.inf)
    north = t * np.cos(a)
    return np.where((t < 8.0) & (north >= -4.0) & (north <= 1.5), t, 8.0)


@pytest.mark.parametrize("route", [True, False])
def test_a_goal_behind_a_wall_is_flown_to_around_its_nearer_end(tmp_path, route):
    """The waypoint 5 m west lies behind the wall: with goal.route the goal features point past the
    wall's north end (ahead and left), without it straight at the waypoint (left, nothing ahead)."""
    extra = WEST_AND_UP.replace("[goal]\n", f"[goal]\nroute = {str(route).lower()}\n")
    f = Flight.with_model(tmp_path, "echo_goal", extra)
    f.lidar.scene = _wall_west
    try:
        if route:
            last = f.settled(lambda m: m.vx > 0.6 and m.yaw_rate < -0.3, "ahead and left, around the wall")
            assert last.vx < 1.8  # not straight ahead either: the end is north-west
        else:
            f.settled(lambda m: abs(m.vx) < 0.05 and m.yaw_rate < -1.0, "turning toward the waypoint")
    finally:
        f.close()
