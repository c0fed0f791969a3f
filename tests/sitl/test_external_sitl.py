"""``--autopilot external``: a real ArduPilot/PX4 SITL flies its own physics, the harness mirrors its
pose into the world and casts the lidar from it.

Runs only where a SITL is installed: set ``LIDAR_AVOID_EXTERNAL_SITL`` to the command that starts
it (for example ``arducopter --model quad --defaults copter.parm -I0``, or PX4's
``make px4_sitl sih``) and, when it is not ArduPilot's ``tcp:127.0.0.1:5760``,
``LIDAR_AVOID_EXTERNAL_CONNECT`` to the pymavlink address of its GCS port.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import time

import pytest

from flightsim.harness import FlightOptions, SitlFlight
from tests.sitl.helpers import OPEN_ROOM, write_constant_policy

SITL_COMMAND = os.environ.get("LIDAR_AVOID_EXTERNAL_SITL", "")
CONNECT = os.environ.get("LIDAR_AVOID_EXTERNAL_CONNECT", "tcp:127.0.0.1:5760")

pytestmark = [
    pytest.mark.sitl,
    pytest.mark.skipif(not SITL_COMMAND, reason="LIDAR_AVOID_EXTERNAL_SITL does not name a SITL to start"),
]


@pytest.fixture(scope="module")
def sitl(tmp_path_factory):
    log = open(tmp_path_factory.mktemp("external") / "sitl.log", "wb")  # noqa: SIM115
    proc = subprocess.Popen(shlex.split(SITL_COMMAND), stdout=log, stderr=subprocess.STDOUT)
    time.sleep(3.0)
    yield proc
    proc.terminate()
    proc.wait(timeout=20)
    log.close()


def test_companion_flies_an_external_sitl(sitl, tmp_path):
    assert sitl.poll() is None, "the SITL exited at start-up"
    options = FlightOptions(
        autopilot="external",
        connect=CONNECT,
        world=OPEN_ROOM,
        policy=write_constant_policy(tmp_path / "circle.onnx", 0.5, 0.4),
        workdir=tmp_path,
    )
    with SitlFlight(options) as f:
        f.take_off()
        assert f.wait_engaged(60.0), f.companion_log()
        t0 = time.monotonic()
        f.fly(5.0)
        assert f.recorder.setpoints_since(t0) >= 30
        report = f.report()
    assert report.engaged and report.distance_m > 1.0
