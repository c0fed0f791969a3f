"""The real ``avoid-companion run`` process: VLP-16 UDP packets in, MAVLink setpoints out.

A pymavlink peer poses as ArduPilot Copter (armed, GUIDED, in the air at 1.5 m); a test thread
streams VLP-16 revolutions; an AF_UNIX socket stands in for systemd.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import signal
import socket
import time

import pytest

from companion.autopilot.mavlink_adapter import mavlink
from companion.common.errors import UserError
from tests.companion.companion_process import (
    LidarSender,
    NotifySocket,
    free_udp_port,
    run_to_exit,
    start_companion,
    stop,
    write_config,
)
from tests.companion.companion_process import (
    wait_until as _wait,
)
from tests.companion.mavlink_peer import COPTER_GUIDED, COPTER_LOITER, SETPOINT, SimulatedAutopilot
from tests.onnx_models import COMPANION_SPEC, write_policy


@pytest.fixture
def rig(tmp_path):
    """The companion process with its peers; yields a namespace, tears everything down."""
    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    model = write_policy(tmp_path / "forward.onnx", kind="forward")
    config = write_config(tmp_path, model, lidar_port, mavlink_port)
    notify = NotifySocket(tmp_path / "notify.sock")
    vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{mavlink_port}")
    proc = start_companion(config, notify=notify.path)
    lidar = LidarSender(lidar_port)

    class Rig:
        pass

    rig = Rig()
    rig.proc, rig.vehicle, rig.lidar, rig.notify, rig.config = proc, vehicle, lidar, notify, config
    rig.mavlink_port = mavlink_port
    yield rig
    lidar.close()
    if proc.poll() is None:
        print(stop(proc)[2][-5000:])  # the companion's log, shown when a test fails
    vehicle.close()
    notify.close()


def test_flight_engage_hold_recover_override_and_sigterm(rig):
    proc, vehicle, lidar, notify = rig.proc, rig.vehicle, rig.lidar, rig.notify
    assert notify.wait_for("READY=1"), "no READY=1 from the companion"
    # The autopilot hears the companion: HEARTBEAT as an onboard controller, component 191.
    hb = _wait(lambda: vehicle.wait_for("HEARTBEAT", timeout=0.1), what="companion heartbeat")
    assert hb.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER and hb.get_srcComponent() == 191
    time.sleep(0.5)
    assert vehicle.messages(SETPOINT) == [], "setpoints before any lidar data"

    # Engage: setpoints only after recover_scans (5) good scans; the first revolution only starts one.
    lidar.on = True
    first = _wait(lambda: vehicle.wait_for(SETPOINT, timeout=0.1), what="first setpoint")
    first_time = vehicle.times(SETPOINT)[0]
    revolutions_before = sum(t < first_time for t in lidar.sent)
    assert revolutions_before - 1 >= 5, f"engaged after {revolutions_before - 1} scans"
    assert first.type_mask == 0x05C7 and first.coordinate_frame == mavlink.MAV_FRAME_BODY_OFFSET_NED
    assert first.vy == 0.0 and first.vz == 0.0 and first.yaw_rate == 0.0
    lidar.garbage()  # malformed packets in flight: counted and dropped
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as junk:  # and garbage on the MAVLink port
        junk.sendto(b"\xfd\x09\x00\x00" + bytes(range(200)), ("127.0.0.1", rig.mavlink_port))
    time.sleep(1.0)
    active = vehicle.messages(SETPOINT)
    assert len(active) >= 5
    assert active[-1].vx > 0.0, "the forward policy should be flying forward"
    assert max(m.vx for m in active) <= 2.0 + 1e-6  # shield max_speed
    assert any("ACTIVE" in m.text for m in vehicle.messages("STATUSTEXT"))
    distances = vehicle.messages("OBSTACLE_DISTANCE")
    assert len(distances) >= len(active) - 1
    assert distances[-1].increment == 5 and distances[-1].frame == mavlink.MAV_FRAME_BODY_FRD

    # Lidar stops: HOLD, zero setpoints keep coming (~10 Hz).
    lidar.on = False
    t_stop = time.monotonic()
    _wait(lambda: any("HOLD" in m.text for m in vehicle.messages("STATUSTEXT", since=t_stop)), what="HOLD")
    time.sleep(0.6)
    t_hold = time.monotonic() - 0.5
    held = vehicle.messages(SETPOINT, since=t_hold)
    assert len(held) >= 3 and all(m.vx == 0.0 and m.yaw_rate == 0.0 for m in held)

    # Lidar back: ACTIVE again after recover_scans good scans, ramping up from standstill.
    lidar.on = True
    t_back = time.monotonic()
    _wait(lambda: any(m.vx > 0 for m in vehicle.messages(SETPOINT, since=t_back)), what="recovery")
    assert sum(t > t_back for t in lidar.sent) >= 5

    # The pilot switches to LOITER: the companion stops commanding and never switches back.
    vehicle.custom_mode = COPTER_LOITER
    t_override = time.monotonic()
    _wait(lambda: any("PILOT_OVERRIDE" in m.text for m in vehicle.messages("STATUSTEXT", since=t_override)),
          what="PILOT_OVERRIDE")
    time.sleep(0.5)
    late = vehicle.messages(SETPOINT, since=time.monotonic() - 0.3)
    assert late == []
    assert not [m for m in vehicle.messages(since=t_override)
                if m.get_type() in ("SET_MODE", "COMMAND_LONG") and getattr(m, "command", None) != 511]
    vehicle.custom_mode = COPTER_GUIDED
    t_guided = time.monotonic()
    _wait(lambda: vehicle.messages(SETPOINT, since=t_guided), what="re-engage")

    # systemd watchdog pings while healthy.
    assert notify.wait_for("WATCHDOG=1")

    # SIGTERM while commanding: a zero setpoint goes out, exit 0.
    proc.send_signal(signal.SIGTERM)
    t_term = time.monotonic()
    code, _out, err = stop(proc)
    lidar.on = False
    assert code == 0, err
    time.sleep(0.2)
    after = vehicle.messages(SETPOINT, since=t_term)
    assert after and after[-1].vx == 0.0 and after[-1].yaw_rate == 0.0
    assert "Traceback" not in err
    assert "lidar.malformed={" in err and "link.bad_data=" in err  # garbage counted (summary at exit)


def test_bad_config_key_is_one_line_exit_2(tmp_path):
    model = write_policy(tmp_path / "m.onnx")
    extra = "[shield]\nmax_sped = 1.0\n"
    config = write_config(tmp_path, model, free_udp_port(), free_udp_port(), extra=extra)
    result = run_to_exit(["run", "--config", str(config)])
    assert result.returncode == 2
    assert result.stderr.strip() == "avoid-companion: error: shield.max_sped: unknown config key"


def test_bad_override_is_one_line_exit_2(tmp_path):
    model = write_policy(tmp_path / "m.onnx")
    config = write_config(tmp_path, model, free_udp_port(), free_udp_port())
    result = run_to_exit(["run", "--config", str(config), "supervisor.recover_scans=0"])
    assert result.returncode == 2
    expected = "avoid-companion: error: supervisor.recover_scans: 0 is below the minimum 1"
    assert result.stderr.strip() == expected


def test_model_trained_for_another_range_is_refused(tmp_path):
    model = write_policy(tmp_path / "m.onnx", spec=dataclasses.replace(COMPANION_SPEC, max_range=8.0))
    config = write_config(tmp_path, model, free_udp_port(), free_udp_port())
    result = run_to_exit(["run", "--config", str(config)])
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "max_range 8.0" in lines[0] and "scan.max_range 10.0" in lines[0]


def test_start_up_logs_the_models_sha256_and_an_unset_sensor_ip(tmp_path):
    model = write_policy(tmp_path / "m.onnx")
    digest = hashlib.sha256(model.read_bytes()).hexdigest()
    config = write_config(tmp_path, model, free_udp_port(), free_udp_port())
    notify = NotifySocket(tmp_path / "notify.sock")
    proc = start_companion(config, notify=notify.path)
    try:
        assert notify.wait_for("READY=1")
    finally:
        code, _, log = stop(proc)
        notify.close()
    assert code == 0
    assert f"(sha256 {digest}) loaded" in log
    assert "lidar.velodyne.sensor_ip is not set" in log


def test_missing_model_and_busy_lidar_port(tmp_path):
    config = write_config(tmp_path, tmp_path / "nope.onnx", free_udp_port(), free_udp_port())
    result = run_to_exit(["run", "--config", str(config)])
    assert result.returncode == 2 and "policy model" in result.stderr and "file not found" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1

    busy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    busy.bind(("127.0.0.1", 0))
    try:
        model = write_policy(tmp_path / "m.onnx")
        config = write_config(tmp_path, model, busy.getsockname()[1], free_udp_port())
        result = run_to_exit(["run", "--config", str(config)])
        assert result.returncode == 2
        assert "cannot listen for VLP-16 packets" in result.stderr.strip().splitlines()[-1]
    finally:
        busy.close()


def test_can_ring_in_process(tmp_path):
    """The CAN rangefinder path, in-process (python-can's virtual bus does not cross processes)."""
    import can

    from companion.app import Companion
    from companion.config import load_config
    from companion.lidar.can_ring import benewake_frame
    from companion.notify import SystemdNotifier

    mavlink_port = free_udp_port()
    channel = f"ring-{mavlink_port}"
    model = write_policy(tmp_path / "forward.onnx", kind="forward")
    config_path = write_config(tmp_path, model, free_udp_port(), mavlink_port, extra=f"""
[lidar]
source = "can"
[lidar.can]
interface = "virtual"
channel = "{channel}"
[[lidar.can.sensors]]
can_id = 0x10
yaw_deg = 0.0
[[lidar.can.sensors]]
can_id = 0x11
yaw_deg = 90.0
""")
    companion = Companion(load_config(config_path), notifier=SystemdNotifier({}))
    vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{mavlink_port}")
    sensors = can.Bus(interface="virtual", channel=channel)
    try:
        companion.supervisor.start()
        deadline = time.monotonic() + 10
        next_frames = 0.0
        while time.monotonic() < deadline and not vehicle.messages(SETPOINT):
            if time.monotonic() >= next_frames:
                next_frames = time.monotonic() + 0.1
                sensors.send(benewake_frame(0x10, 6.0))  # 6 m ahead
                sensors.send(benewake_frame(0x11, 1.0))  # 1 m to the left
            companion.step(0.01)
        first = vehicle.wait_for(SETPOINT, timeout=1.0)
        assert first is not None, companion.summary()
        assert first.vx > 0
        distances = vehicle.wait_for("OBSTACLE_DISTANCE")
        assert distances.distances[0] == 600 and distances.distances[54] == 100  # ahead; left = 270° cw
        assert companion.counters["scans"] >= 5
    finally:
        sensors.shutdown()
        companion.close()
        vehicle.close()


def _params_rig(tmp_path, mode):
    mavlink_port = free_udp_port()
    model = write_policy(tmp_path / "m.onnx")
    parm = tmp_path / "copter.parm"
    parm.write_text("# wanted\nPRX1_TYPE 2\nFENCE_ENABLE 1\n")
    config = write_config(tmp_path, model, free_udp_port(), mavlink_port,
                          extra=f'[params_check]\nmode = "{mode}"\nfile = "{parm.name}"\ntimeout = 5.0\n')
    vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{mavlink_port}")
    vehicle.params = {"PRX1_TYPE": 0.0, "FENCE_ENABLE": 1.0}  # proximity from MAVLink not enabled
    return config, vehicle


def test_parameter_check_refuse_exits_naming_the_parameter(tmp_path):
    config, vehicle = _params_rig(tmp_path, "refuse")
    try:
        result = run_to_exit(["run", "--config", str(config)])
    finally:
        vehicle.close()
    assert result.returncode == 2
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("avoid-companion: error: params_check: 1 autopilot parameter(s) differ")
    assert "PRX1_TYPE: wanted 2, autopilot 0" in last


@pytest.mark.parametrize("allow", [False, True])
def test_parameter_check_at_start_accepts_only_the_allowed_missing_names(tmp_path, allow):
    """``[params_check] allow_missing``: what ``params --allow-missing`` does, for the start-up check."""
    from companion.app import check_parameters
    from companion.config import load_config

    config_path, vehicle = _params_rig(tmp_path, "refuse")
    (tmp_path / "copter.parm").write_text("PRX1_TYPE 0\nSERIAL2_PROTOCOL 2\n")  # a SITL lacks SERIAL2
    allowed = ['params_check.allow_missing=["SERIAL2_PROTOCOL"]'] if allow else []
    try:
        config = load_config(config_path, allowed)
        if allow:
            assert check_parameters(config)[0] == []
        else:
            with pytest.raises(UserError, match=r"SERIAL2_PROTOCOL: wanted 2, autopilot - \(unknown to the"):
                check_parameters(config)
    finally:
        vehicle.close()


def test_parameter_check_warn_tells_the_pilot_and_flies_on(tmp_path):
    config, vehicle = _params_rig(tmp_path, "warn")
    proc = start_companion(config)
    try:
        text = vehicle.wait_for("STATUSTEXT", timeout=20, condition=lambda m: "PRX1_TYPE" in m.text)
        assert text is not None and text.severity == mavlink.MAV_SEVERITY_WARNING
        assert proc.poll() is None
    finally:
        code, _out, err = stop(proc)
        vehicle.close()
    assert code == 0, err
    assert "param PRX1_TYPE: wanted 2, autopilot 0" in err


def test_stale_velocity_holds_and_fresh_velocity_flies_again(rig):
    vehicle, lidar = rig.vehicle, rig.lidar
    lidar.on = True
    _wait(lambda: any(m.vx > 0 for m in vehicle.messages(SETPOINT)), timeout=20, what="engaged")
    vehicle.velocity_ned = None  # LOCAL_POSITION_NED and ATTITUDE stop
    t_stale = time.monotonic()
    _wait(lambda: any("velocity stale" in m.text for m in vehicle.messages("STATUSTEXT", since=t_stale)),
          what="HOLD on stale velocity")
    t_hold = time.monotonic()
    time.sleep(0.5)
    held = vehicle.messages(SETPOINT, since=t_hold)
    assert len(held) >= 3 and all(m.vx == 0.0 and m.yaw_rate == 0.0 for m in held)
    vehicle.velocity_ned = (0.0, 0.0)
    t_back = time.monotonic()
    _wait(lambda: any(m.vx > 0 for m in vehicle.messages(SETPOINT, since=t_back)), what="recovery")


def test_no_obstacle_distance_before_the_vehicle_is_airborne(rig):
    """On the ground and during take-off the slice cuts the floor: no OBSTACLE_DISTANCE then."""
    vehicle, lidar = rig.vehicle, rig.lidar
    vehicle.landed, vehicle.altitude = mavlink.MAV_LANDED_STATE_ON_GROUND, 0.0
    lidar.on = True
    time.sleep(1.5)
    assert vehicle.messages("OBSTACLE_DISTANCE") == []
    vehicle.landed, vehicle.altitude = mavlink.MAV_LANDED_STATE_TAKEOFF, 1.2
    time.sleep(0.8)
    assert vehicle.messages("OBSTACLE_DISTANCE") == []
    vehicle.landed, vehicle.altitude = mavlink.MAV_LANDED_STATE_IN_AIR, 1.5
    t_air = time.monotonic()
    assert _wait(lambda: vehicle.messages("OBSTACLE_DISTANCE", since=t_air), what="OBSTACLE_DISTANCE")


def test_yaw_rate_capped_at_the_autopilots_limit_read_at_start_up(tmp_path):
    """ArduPilot flies at most ATC_RATE_WPY_MAX; the start-up check reads it, warns, and the shield
    never asks more (75 deg/s here: neither the firmware default 60 nor the policy's 86)."""
    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    model = write_policy(tmp_path / "left.onnx", kind="turn_left")
    parm = tmp_path / "copter.parm"
    parm.write_text("ATC_RATE_WPY_MAX 86\n")
    config = write_config(tmp_path, model, lidar_port, mavlink_port,
                          extra=f'[params_check]\nmode = "warn"\nfile = "{parm.name}"\ntimeout = 5.0\n')
    vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{mavlink_port}")
    vehicle.params = {"ATC_RATE_WPY_MAX": 75.0}
    proc = start_companion(config)
    lidar = LidarSender(lidar_port)
    try:
        lidar.on = True
        text = vehicle.wait_for("STATUSTEXT", timeout=20, condition=lambda m: "yaw limit" in m.text)
        assert text is not None and "ATC_RATE_WPY_MAX 75 deg/s" in text.text
        _wait(lambda: vehicle.messages(SETPOINT), timeout=20, what="setpoints")
        time.sleep(1.5)  # the yaw rate ramps up at max_yaw_accel
        turning = vehicle.messages(SETPOINT)[-3:]
        assert all(m.yaw_rate == pytest.approx(-math.radians(75.0), abs=1e-4) for m in turning)
    finally:
        lidar.close()
        code, _out, err = stop(proc)
        vehicle.close()
    assert code == 0, err


def test_px4_streams_before_offboard_then_flies(tmp_path):
    """PX4 takes OFFBOARD only while setpoints flow: zeros stream in POSCTL, the policy's in OFFBOARD."""
    from tests.companion.mavlink_peer import PX4_MAIN_OFFBOARD, PX4_MAIN_POSCTL, px4_custom_mode

    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    model = write_policy(tmp_path / "forward.onnx", kind="forward")
    config = write_config(tmp_path, model, lidar_port, mavlink_port, autopilot="px4")
    vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{mavlink_port}", autopilot=mavlink.MAV_AUTOPILOT_PX4)
    vehicle.custom_mode = px4_custom_mode(PX4_MAIN_POSCTL)
    proc = start_companion(config)
    lidar = LidarSender(lidar_port)
    try:
        lidar.on = True
        hb = _wait(lambda: vehicle.wait_for("HEARTBEAT", timeout=0.1), timeout=20, what="heartbeat")
        assert hb.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER and hb.get_srcComponent() == 191
        time.sleep(1.5)
        before = vehicle.messages(SETPOINT)
        assert len(before) >= 5 and all(m.vx == 0.0 and m.yaw_rate == 0.0 for m in before)
        assert all(m.coordinate_frame == mavlink.MAV_FRAME_BODY_NED for m in before)
        vehicle.custom_mode = px4_custom_mode(PX4_MAIN_OFFBOARD)  # the pilot switches
        t_switch = time.monotonic()
        _wait(lambda: any(m.vx > 0 for m in vehicle.messages(SETPOINT, since=t_switch)),
              what="policy setpoints")
        assert vehicle.wait_for("OBSTACLE_DISTANCE", since=t_switch) is not None
    finally:
        lidar.close()
        t_term = time.monotonic()
        code, _out, err = stop(proc)
        vehicle.close()
    assert code == 0, err
    after = vehicle.messages(SETPOINT, since=t_term)
    assert after and after[-1].vx == 0.0


def _in_process(tmp_path, kind):
    from companion.app import Companion
    from companion.config import load_config
    from companion.notify import SystemdNotifier

    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    model = write_policy(tmp_path / f"{kind}.onnx", kind=kind)
    companion = Companion(load_config(write_config(tmp_path, model, lidar_port, mavlink_port)),
                          notifier=SystemdNotifier({}))
    vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{mavlink_port}")
    lidar = LidarSender(lidar_port)
    companion.supervisor.start()
    return companion, vehicle, lidar


def _run_for(companion, lidar, seconds):
    deadline = time.monotonic() + seconds
    next_revolution = 0.0
    while time.monotonic() < deadline:
        if time.monotonic() >= next_revolution:
            next_revolution = time.monotonic() + 0.1
            lidar.send_one()
        companion.step(0.01)


def test_inference_faults_never_engage_and_never_crash(tmp_path):
    companion, vehicle, lidar = _in_process(tmp_path, "nan")
    try:
        _run_for(companion, lidar, 1.5)
        assert companion.counters["inference_faults"] >= 8
        assert companion.supervisor.state.value == "STANDBY"
        assert vehicle.messages(SETPOINT) == []
        assert vehicle.messages("OBSTACLE_DISTANCE")  # the autopilot's own layer still gets the scans
    finally:
        lidar.close()
        companion.close()
        vehicle.close()


def test_a_fault_in_one_iteration_is_counted_and_the_loop_goes_on(tmp_path, monkeypatch):
    import os

    companion, vehicle, lidar = _in_process(tmp_path, "forward")
    read, write = os.pipe()
    try:
        real_read = companion.lidar.read_available
        calls = {"n": 0}

        def flaky():
            calls["n"] += 1
            if calls["n"] == 3:
                raise RuntimeError("injected")
            return real_read()

        monkeypatch.setattr(companion.lidar, "read_available", flaky)
        results = [companion._guarded_step(read) for _ in range(5)]
        assert results == [True, True, False, True, True]
        assert companion.counters["loop_faults"] == 1
        _run_for(companion, lidar, 1.5)
        assert vehicle.messages(SETPOINT), companion.summary()
    finally:
        os.close(read)
        os.close(write)
        lidar.close()
        companion.close()
        vehicle.close()


def test_a_late_scan_repeat_keeps_the_brakes_sideways_part(tmp_path):
    """While a scan is late the last setpoint is repeated; the shield's active brake against a
    sideways slide is part of it (it once went out without, letting the slide creep on)."""
    from companion.safety.shield import Command
    from companion.safety.supervisor import CommandKind

    companion, vehicle, lidar = _in_process(tmp_path, "forward")
    try:
        _run_for(companion, lidar, 1.0)  # engaged, flying the policy
        before = len(vehicle.messages(SETPOINT))
        companion._last_command = Command(0.2, 0.1, lateral=-0.3)  # braking a slide to the left
        companion._last_setpoint = companion._clock() - 1.0  # the last one went out long ago
        companion._send(CommandKind.POLICY, new_scan=False)
        assert companion.counters["setpoints_late_scan"] == 1
        deadline = time.monotonic() + 5.0
        while len(vehicle.messages(SETPOINT)) == before and time.monotonic() < deadline:
            time.sleep(0.02)
        repeat = vehicle.messages(SETPOINT)[-1]
        assert (repeat.vx, repeat.vy, repeat.yaw_rate) == pytest.approx((0.2, 0.3, -0.1))  # FRD
    finally:
        lidar.close()
        companion.close()
        vehicle.close()
