"""SITL with MAVLink 2 signing on every link: the real companion flies the simulated ArduPilot, and
unsigned frames carrying the autopilot's ids (a LOITER heartbeat at 20 Hz to the companion, a mode
change to the autopilot) change nothing: both ends drop and count them."""

from __future__ import annotations

import re
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from flightsim.sitl.harness import FlightOptions, SitlFlight
from tests.companion.mavlink_peer import COPTER_LOITER, AutopilotPeer
from tests.sitl.helpers import (
    OPEN_ROOM,
    companion_counters,
    estimated_speed,
    speed,
    wait_for,
    write_constant_policy,
)

pytestmark = pytest.mark.sitl
LOITER_MODE = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED


def _counter(line: str, name: str) -> int:
    match = re.search(rf"\b{re.escape(name)}=(\d+)", line)
    return int(match.group(1)) if match else 0


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("sitl-signed")
    options = FlightOptions(
        autopilot="sim-ardupilot",
        world=OPEN_ROOM,
        policy=write_constant_policy(workdir / "circle.onnx", 0.5, 0.4),
        workdir=workdir,
        companion_overrides={"runtime": {"log_interval": 1.0}},
        signed=True,
    )
    with SitlFlight(options) as f:
        f.take_off()
        assert f.wait_engaged(25.0), f.companion_log()
        yield f


def test_signed_flight_engages_and_flies(flight):
    f = flight
    wait_for(lambda: speed(f) > 0.6, 5.0, "the vehicle to fly")
    assert (f.key_path.stat().st_mode & 0o777) == 0o600
    assert f.server.endpoint.counters.get("signature_rejected", 0) == 0
    t0 = time.monotonic()
    time.sleep(2.0)
    assert f.recorder.setpoints_since(t0) >= 15


def test_unsigned_frames_with_the_autopilots_ids_change_nothing(flight):
    f = flight
    # to the companion: an unsigned "autopilot" in LOITER, 20 Hz for 2 s
    spoof = AutopilotPeer(f"udpout:127.0.0.1:{f.companion_port}", sysid=1, compid=1)
    # to the autopilot: an unsigned ground station asking for LOITER
    gcs_port = f.server.endpoint.address(0)[1]
    rogue = AutopilotPeer(f"udpout:127.0.0.1:{gcs_port}", sysid=255, compid=190)
    rejected_before = f.server.endpoint.counters.get("signature_rejected", 0)
    t0 = time.monotonic()
    try:
        for _ in range(40):
            spoof.heartbeat(armed=True, custom_mode=COPTER_LOITER)
            rogue.mav.command_long_send(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, LOITER_MODE, COPTER_LOITER,
                                        0, 0, 0, 0, 0)
            time.sleep(0.05)
        assert f.server.autopilot.mode_name() == "GUIDED"
        assert f.server.endpoint.counters["signature_rejected"] >= rejected_before + 40
        assert not [t for t in f.recorder.texts(t0) if "PILOT_OVERRIDE" in t]
        assert f.recorder.setpoints_since(t0) >= 15  # still commanding all along
        assert spoof.drain(0.2) == []  # the companion answers only the signed autopilot's address
        wait_for(lambda: _counter(companion_counters(f), "link.signature_rejected") >= 40, 5.0,
                 "the companion's count of rejected frames")
    finally:
        spoof.close()
        rogue.close()


def test_signed_px4_flight_engages_through_mavsdk(tmp_path):
    """MAVSDK cannot sign: the PX4 link signs its frames, and PX4 (simulated) takes them."""
    options = FlightOptions(
        autopilot="sim-px4",
        world=OPEN_ROOM,
        policy=write_constant_policy(tmp_path / "circle.onnx", 0.5, 0.4),
        workdir=tmp_path,
        autopilot_params={"COM_OBL_RC_ACT": 5},
        signed=True,
        # the setpoint exactly the policy's command: the drift hold would add PX4's estimate error
        # sideways (0.08 m/s seen), which is not what this test is about
        companion_overrides={"drift_hold": {"lateral": 0.0}},
    )
    with SitlFlight(options) as f:
        f.take_off()
        assert f.wait_engaged(25.0), f.companion_log()
        # what PX4 took and flies: the signed command, at the speed its estimator sees. Not the true
        # speed: PX4's estimate error keeps this circle's true speed under 0.6 m/s for 5 s now and
        # then (3 of 38 runs on 2026-11-24), while its estimate was past 0.6 within 3.2 s in all 12
        wait_for(lambda: estimated_speed(f) > 0.6, 5.0, "PX4 to fly the setpoints")
        target = f.server.call(lambda a: a.target)
        assert target is not None and np.linalg.norm(target.velocity[:2]) == pytest.approx(1.0, abs=0.01)
        assert f.server.autopilot.mode_name() == "OFFBOARD"
        assert f.server.endpoint.counters.get("signature_rejected", 0) == 0
