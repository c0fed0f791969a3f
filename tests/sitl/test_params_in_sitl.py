"""SITL flies what the drone flies: the companion in ``avoid-sim fly`` runs the example config's
start-up parameter check against the simulated autopilot (which serves its parameters over the
real parameter protocol), and the shield caps the yaw rate at the autopilot's own limit."""

from __future__ import annotations

import math

import pytest

from flightsim.sitl.harness import FlightOptions, SitlFlight
from tests.sitl.helpers import OPEN_ROOM, recorded_setpoints, said, wait_for, write_constant_policy

pytestmark = pytest.mark.sitl


@pytest.mark.parametrize(
    ("personality", "param", "deg_s"),
    [("ardupilot", "ATC_RATE_WPY_MAX", 75.0), ("ardupilot", "ATC_RATE_WPY_MAX", 60.0),
     ("px4", "MC_YAWRATE_MAX", 70.0)],
)  # fmt: skip
def test_the_sitl_companion_reads_the_yaw_limit_from_the_autopilot(tmp_path, personality, param, deg_s):
    """A policy asking for the full 1.5 rad/s yaw rate is flown at the autopilot's limit, read from it
    at start-up (ArduPilot's 60 deg/s default, or what ``params apply`` set), and the pilot is told."""
    options = FlightOptions(
        autopilot=f"sim-{personality}",
        world=OPEN_ROOM,
        policy=write_constant_policy(tmp_path / "spin.onnx", 0.0, 1.0),
        lidar_step_deg=1.0,
        workdir=tmp_path / "flight",
        autopilot_params={param: deg_s},
    )
    cap = math.radians(deg_s)
    with SitlFlight(options) as flight:
        flight.wait_companion_up(timeout=60.0)
        flight.take_off()
        assert flight.wait_engaged(30.0), flight.companion_log()[-2000:]
        engaged = flight.engaged_at
        wait_for(lambda: sum(t > engaged + 1.0 for t, *_ in recorded_setpoints(flight)) > 20, 20.0,
                 "the companion's setpoints")  # past the shield's yaw ramp from standstill
        assert said(flight, f"yaw limit {param} {deg_s:.0f} deg/s"), flight.recorder.texts()
        yaw_rates = [abs(yr) for t, _vx, yr in recorded_setpoints(flight) if t > engaged]
    assert max(yaw_rates) == pytest.approx(cap, abs=1e-3)  # the cap, reached and never passed
