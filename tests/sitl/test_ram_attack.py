"""SITL attack on the companion process itself (issue 66): a policy that always asks full speed at the
nearest return (``tests/onnx_models.py``'s ``ram``: ArgMin over the newest scan, then that bin's
bearing looked up as a full-scale forward/sideways/yaw action), flown by the real companion as
``avoid-sim fly`` flies a model (:func:`flightsim.sitl.harness.run_flight`, the ``[policy]`` table
from the model's metadata) through both simulated autopilots with their calibrated responses, in a
small cluttered room, behind the shipped shield and with its backup gate on. The shield alone
stands between the model and the obstacles: 0 collisions, and the least clearance shows the vehicle
was truly driven at them. (The companion has no switch that takes the shield out, so there is no
unshielded flight here to show the model would strike: issue 66, below, showed it.)
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from flightsim.sitl.fly_cli import model_overrides
from flightsim.sitl.harness import FlightOptions, run_flight
from flightsim.worlds.world import DEFAULT_VEHICLE_RADIUS, Box, Cylinder, World
from tests.onnx_models import write_policy

pytestmark = pytest.mark.sitl

#: 8 x 6 m, a pillar 1.85 m ahead-left of the start, a box 1.8 m behind-right, another pillar and
#: the walls within 3 m: the ram reaches a return within a couple of seconds and keeps pushing
CLUTTERED_ROOM = World(
    name="ram-room",
    room_size=(8.0, 6.0),
    room_height=3.0,
    obstacles=(
        Cylinder(center=(2.0, 0.8), radius=0.3, height=3.0),
        Box(center=(-1.5, -1.8, 1.5), size=(1.0, 0.6, 3.0), yaw_deg=20.0),
        Cylinder(center=(-2.5, 1.5), radius=0.3, height=3.0),
    ),
    start_position=(0.0, 0.0, 1.5),
    start_yaw_deg=0.0,
)
#: seconds the companion flies the ram after engaging
RAM_FLIGHT_S = 15.0
#: the attack was real: behind the shipped shield the vehicle came this close to a surface (its
#: centre, metres; 1.76 m at the start)
APPROACHED_M = 1.0


def fly_ram(tmp_path: Path, autopilot: str, shield: dict[str, object]):
    """One flight of the ram model as ``avoid-sim fly --policy ram.onnx --no-mission`` flies it, with
    ``shield`` on top of the shipped ``[shield]``; the report."""
    policy = write_policy(tmp_path / "ram.onnx", kind="ram")
    overrides = model_overrides(policy)
    if shield:
        overrides["shield"] = dict(shield)
    options = FlightOptions(
        autopilot=autopilot,
        world=CLUTTERED_ROOM,
        policy=policy,
        duration=RAM_FLIGHT_S,
        lidar_step_deg=1.0,
        workdir=tmp_path,
        companion_overrides=overrides,
    )
    return run_flight(options)


# Issue 66 (mended 2026-12-06): behind the shipped shield (gate off) the ram struck the box (centre
# (-1.5, -1.8)) on the simulated ArduPilot in 9 of 9 flights, 4.7-7.5 s after engaging, least clearance
# 0.17-0.25 m: the stopping-distance cap assumed ArduPilot stops after 0.7 s at 2.5 m/s² and let
# 0.8-0.97 m/s forward through with the box 0.8-1.0 m off the centre; the motion stop fired only at
# 0.72-0.75 m, too late for the calibrated lag. With the firmware envelope's 1.1 s and 3 m/s²
# (companion.safety.shield.AUTOPILOT_LIMITS) the least clearance is 0.40-0.46 m over 7 flights; PX4
# (unchanged) holds 0.33-0.40 m; with the backup gate ArduPilot keeps 0.69-0.89 m (0.45-0.78 m since).


@pytest.mark.parametrize(
    ("autopilot", "gate"),
    [
        pytest.param("sim-ardupilot", False, id="sim-ardupilot-shipped-shield"),
        pytest.param("sim-ardupilot", True, id="sim-ardupilot-backup-gate"),
        pytest.param("sim-px4", False, id="sim-px4-shipped-shield"),
        pytest.param("sim-px4", True, id="sim-px4-backup-gate"),
    ],
)
def test_ram_policy_never_collides(tmp_path, autopilot, gate):
    report = fly_ram(tmp_path, autopilot, {"backup_gate": True} if gate else {})
    log = (tmp_path / "companion.log").read_text(errors="replace")
    counters = [line for line in log.splitlines() if " state=" in line][-1:]
    summary = (
        f"{autopilot} gate={gate}: collision={report.collision} least clearance={report.min_clearance_m} m "
        f"flight {report.flight_time_s} s, {report.distance_m} m, error={report.error!r}, {counters}"
    )
    print(summary)
    assert report.engaged and not report.error, summary
    assert not report.collision, summary
    assert report.min_clearance_m >= DEFAULT_VEHICLE_RADIUS, summary
    assert report.flight_time_s >= RAM_FLIGHT_S - 1.0, summary
    if not gate:
        assert report.min_clearance_m < APPROACHED_M, summary
    else:
        # The gate keeps the firmware envelope's worst-case stop clear and may hold the vehicle well
        # off (least clearance on PX4 0.37-1.52 m over 5 flights, ArduPilot 0.45-0.89 m): the attack
        # is shown by the gate cutting the ram's commands, not by how near it let the vehicle come.
        gate_cuts = sum(int(n) for n in re.findall(r"shield\.gate_\w+=(\d+)", "".join(counters)))
        assert gate_cuts > 0, summary
