"""``--autopilot external`` end to end, in CI: the project's own simulated autopilot runs as a SEPARATE
process (``avoid-sim autopilot``, the way an external SITL runs: its own physics, MAVLink sockets,
ground truth as SIMSTATE / HIL_STATE_QUATERNION), and ``avoid-sim fly --autopilot external`` flies the
real companion against it through the harness's ground-station relay.

A real ArduPilot/PX4 SITL plugs in the same way: set ``LIDAR_AVOID_EXTERNAL_SITL`` to the command
that starts it and ``LIDAR_AVOID_EXTERNAL_CONNECT`` to its GCS port to fly the last test against it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest

from flightsim.sitl.harness import FlightOptions, SitlFlight
from flightsim.worlds.world import save_world
from tests.companion.mavlink_peer import free_tcp_port, free_udp_port
from tests.onnx_models import write_policy
from tests.sitl.helpers import OPEN_ROOM, write_constant_policy

pytestmark = pytest.mark.sitl

SITL_COMMAND = os.environ.get("LIDAR_AVOID_EXTERNAL_SITL", "")
CONNECT = os.environ.get("LIDAR_AVOID_EXTERNAL_CONNECT", "tcp:127.0.0.1:5760")
#: the world starts facing 30° right of East; the separate autopilot boots facing North
ROOM = dataclasses.replace(OPEN_ROOM, start_yaw_deg=-30.0)
#: two waypoints, the first 0.5 m above the take-off height
MISSION_ROOM = dataclasses.replace(ROOM, name="open-mission", waypoints=((2.5, 0.5, 2.0), (-1.0, 2.5, 1.5)))


def start_autopilot(tmp_path: Path, personality: str, link: str, *extra: str) -> subprocess.Popen[bytes]:
    """``avoid-sim autopilot`` as its own process, logging to a file; waits until it listens."""
    log = open(tmp_path / f"autopilot-{personality}.log", "wb")  # noqa: SIM115 - closed by the test
    proc = subprocess.Popen(
        [sys.executable, "-m", "flightsim", "autopilot", "--personality", personality, "--link", link,
         "--start-yaw", "90", *extra],
        stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    proc.log = log  # type: ignore[attr-defined]
    end = time.monotonic() + 30.0
    while b"running on" not in (tmp_path / f"autopilot-{personality}.log").read_bytes():
        assert proc.poll() is None, (tmp_path / f"autopilot-{personality}.log").read_text()
        assert time.monotonic() < end, "the simulated autopilot did not start"
        time.sleep(0.1)
    return proc


def stop_autopilot(proc: subprocess.Popen[bytes]) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=5)
    proc.log.close()  # type: ignore[attr-defined]


def fly_process(tmp_path: Path, name: str, connect: str, policy: Path, world: Path,
                *extra: str) -> subprocess.CompletedProcess[str]:
    """``avoid-sim fly --autopilot external`` as the user runs it (report in ``<name>.json``)."""
    return subprocess.run(
        [sys.executable, "-m", "flightsim", "fly", "--autopilot", "external", "--connect", connect,
         "--world", str(world), "--policy", str(policy), "--duration", "6", "--lidar-step", "1.0",
         "--json", str(tmp_path / f"{name}.json"), "--workdir", str(tmp_path / name), *extra],
        capture_output=True, text=True, timeout=240,
    )  # fmt: skip


def fly_cli(tmp_path: Path, name: str, connect: str, policy: Path, world: Path, *extra: str) -> dict:
    """``avoid-sim fly --autopilot external`` as the user runs it; returns its JSON report."""
    result = fly_process(tmp_path, name, connect, policy, world, *extra)
    report = tmp_path / f"{name}.json"
    assert report.exists(), result.stdout + result.stderr
    data = json.loads(report.read_text())
    assert result.returncode == 0, result.stdout + result.stderr
    return data


@pytest.fixture
def world_file(tmp_path: Path) -> Path:
    path = tmp_path / "room.json"
    save_world(ROOM, path)
    return path


@pytest.fixture
def mission_file(tmp_path: Path) -> Path:
    path = tmp_path / "mission.json"
    save_world(MISSION_ROOM, path)
    return path


def test_fly_external_px4_switches_to_hold_and_judges_on_hil_state_quaternion(tmp_path, world_file):
    port = free_udp_port()
    policy = write_constant_policy(tmp_path / "circle.onnx", 0.5, 0.4)
    sitl = start_autopilot(tmp_path, "px4", f"udpin:127.0.0.1:{port}")
    try:
        report = fly_cli(tmp_path, "px4", f"udpout:127.0.0.1:{port}", policy, world_file)
    finally:
        stop_autopilot(sitl)
    assert report["error"] == "", report
    assert report["engaged"] and not report["collision"], report
    assert report["ground_truth"] == "HIL_STATE_QUATERNION"
    assert report["distance_m"] > 2.0


@pytest.mark.parametrize(("personality", "flights"), [("ardupilot", 2), ("px4", 1)])
def test_fly_external_mission_through_the_turned_sitl(tmp_path, mission_file, personality, flights):
    """``fly --autopilot external --mission``: the world's waypoints go up as a mission through the
    ground-station link, turned into the SITL's frame (it boots facing North, the world starts at
    −30°), and the companion flies them in GUIDED / OFFBOARD: the report (judged on the SITL's
    truth, in the world) has each waypoint reached, in order. On ArduPilot a second flight on the same
    running SITL finds the vehicle still flying from the first, lands and disarms it, and flies the
    mission again from where the first ended, away from the SITL's home: its waypoints are placed
    from there; both are judged on SIMSTATE ground truth."""
    policy = write_policy(tmp_path / "goal.onnx", kind="echo_goal")
    udp = personality == "px4"
    port = free_udp_port() if udp else free_tcp_port()
    sitl = start_autopilot(tmp_path, personality, f"{'udpin' if udp else 'tcpin'}:127.0.0.1:{port}")
    try:
        for flight in range(flights):
            connect = f"{'udpout' if udp else 'tcp'}:127.0.0.1:{port}"
            result = fly_process(tmp_path, f"mission-{flight}", connect, policy, mission_file, "--mission",
                                 "--duration", "60")  # fmt: skip
            assert result.returncode == 0, result.stdout + result.stderr
            report = json.loads((tmp_path / f"mission-{flight}.json").read_text())
            assert report["error"] == "" and not report["collision"], report
            assert report["setpoint_rate_hz"] > 5.0, report  # (loaded CI)
            assert ("the external SITL is armed" in result.stderr) == (flight > 0), result.stderr
            if personality == "ardupilot":
                assert report["ground_truth"] == "SIMSTATE" and report["warnings"] == [], report
            assert [i for i, _t in report["waypoints_reached"]] == [0, 1], report
            assert report["mission_complete"] and 0 < report["mission_time_s"] < 60, report
            first = 1 if personality == "ardupilot" else 0  # ArduPilot's item 0 is home
            assert report["items_reached"] == [first, first + 1], report
            assert any("complete" in t for t in report["goal_events"]), report
    finally:
        stop_autopilot(sitl)


def test_world_rotated_into_the_sitls_heading_and_estimate_fallback_warns(tmp_path):
    """The SITL boots facing North (90°), the world starts at −30°: the mirrored pose starts at the
    world's start, facing its start yaw. Without truth messages the report says it judged on the
    estimate."""
    port = free_tcp_port()
    sitl = start_autopilot(tmp_path, "ardupilot", f"tcpin:127.0.0.1:{port}", "--no-ground-truth")
    try:
        options = FlightOptions(
            autopilot="external",
            connect=f"tcp:127.0.0.1:{port}",
            world=ROOM,
            policy=write_constant_policy(tmp_path / "stop.onnx", 0.0, 0.0),
            workdir=tmp_path / "flight",
            lidar_step_deg=1.0,
        )
        with SitlFlight(options) as flight:
            state = flight.external.state()
            assert state.yaw == pytest.approx(math.radians(-30.0), abs=math.radians(1.0))
            assert state.position[:2] == pytest.approx(ROOM.start_position[:2], abs=0.05)
            flight.wait_companion_up()  # the companion hears the autopilot before any take-off
            report = flight.report()
    finally:
        stop_autopilot(sitl)
    assert report.ground_truth == "estimate"
    assert report.warnings and "estimate" in report.warnings[0]


@pytest.mark.skipif(not SITL_COMMAND, reason="LIDAR_AVOID_EXTERNAL_SITL does not name a real SITL to start")
@pytest.mark.parametrize("mission", [False, True])
def test_companion_flies_a_real_external_sitl(tmp_path, world_file, mission_file, mission):
    """A constant policy flies a circle; or (``--mission``) a goal-steering one flies two waypoints."""
    log = open(tmp_path / "sitl.log", "wb")  # noqa: SIM115
    proc = subprocess.Popen(shlex.split(SITL_COMMAND), stdout=log, stderr=subprocess.STDOUT)
    try:
        time.sleep(3.0)
        assert proc.poll() is None, "the SITL exited at start-up"
        if not mission:
            report = fly_cli(tmp_path, "real", CONNECT, write_constant_policy(tmp_path / "c.onnx", 0.5, 0.4),
                             world_file)
            assert report["engaged"] and report["distance_m"] > 1.0, report
            return
        policy = write_policy(tmp_path / "goal.onnx", kind="echo_goal")
        report = fly_cli(tmp_path, "real-mission", CONNECT, policy, mission_file, "--mission",
                         "--duration", "90")
        assert [i for i, _t in report["waypoints_reached"]] == [0, 1] and report["mission_complete"], report
    finally:
        proc.terminate()
        proc.wait(timeout=20)
        log.close()


def test_fly_external_waits_for_an_autopilot_whose_position_starts_late(tmp_path, world_file):
    """A fresh ArduPilot SITL reports no position for 40-47 s: ``fly`` waits for it (saying so every
    5 s), then flies; a position that never comes within ``--position-timeout`` is one line naming
    what never arrived, exit 1."""
    port = free_tcp_port()
    policy = write_constant_policy(tmp_path / "circle.onnx", 0.5, 0.4)
    sitl = start_autopilot(tmp_path, "ardupilot", f"tcpin:127.0.0.1:{port}", "--position-delay", "14")
    try:
        result = fly_process(tmp_path, "late", f"tcp:127.0.0.1:{port}", policy, world_file)
    finally:
        stop_autopilot(sitl)
    assert result.returncode == 0, result.stdout + result.stderr
    report = json.loads((tmp_path / "late.json").read_text())
    assert report["error"] == "" and report["engaged"] and not report["collision"], report
    assert 8.0 < report["position_wait_s"] < 14.5, report  # the autopilot's boot came first
    # a note every 5 s of the wait, however long the start-up under load left it
    notes = [int(n) for n in re.findall(r"waiting for EKF origin: (\d+) s", result.stderr)]
    assert notes == [5 * (k + 1) for k in range(len(notes))], result.stderr
    assert 5 * len(notes) <= report["position_wait_s"] + 0.5 < 5 * len(notes) + 6.0, (notes, report)

    port = free_udp_port()
    sitl = start_autopilot(tmp_path, "px4", f"udpin:127.0.0.1:{port}", "--position-delay", "600")
    try:
        result = fly_process(tmp_path, "never", f"udpout:127.0.0.1:{port}", policy, world_file,
                             "--position-timeout", "6")
    finally:
        stop_autopilot(sitl)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "waiting for EKF origin: 5 s" in result.stderr
    errors = [line for line in result.stderr.splitlines() if "error" in line]
    assert errors == ["avoid-sim fly: error: external SITL: no LOCAL_POSITION_NED / GLOBAL_POSITION_INT "
                      "within 6 s: the autopilot never reported a position (no GPS fix or EKF origin?); "
                      "raise --position-timeout or check the SITL"], result.stderr
    assert "Traceback" not in result.stderr
