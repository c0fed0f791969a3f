"""Height figures: the true altitude error of mission flights whose autopilot's altitude estimate
drifts, with the companion's lidar height hold (``goal.height_hold``) and without it.

Flies the shipped policy (the real companion process, real MAVLink and VLP-16 packets on loopback)
through the example worlds and validation missions (seeds 500,000 on) as uploaded missions, on the
simulated ArduCopter and PX4, whose altitude estimate ends up ``--drift`` metres off the truth 20 s
after arming (they fly their estimate). The drifts default to the range the real PX4 SIH flights
were measured to have, -1.08 to +0.82 m; ArduPilot's real flights carry no true altitude (SIMSTATE
has none), so the same drifts are flown for it. Prints, per flight and per (autopilot, drift, hold),
the true height's mean and largest error from the waypoints' altitude while engaged, its range, and
the outcome (compare: with the hold, the error stays near the tolerance, 0.3 m, whatever the drift;
without it, it grows to the drift).

Usage: ``python bench/bench_height_hold.py [--drift 0.82 --drift -1.08] [--validation 2]``
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from flightsim.sitl.harness import FlightOptions, SitlFlight  # noqa: E402
from flightsim.worlds.families import generate_family_world  # noqa: E402
from flightsim.worlds.world import World, load_world  # noqa: E402

#: the validation missions flown: (family, seed), seeds from flightsim.envs.seeds.VALIDATION
VALIDATION_MISSIONS = (("pillars", 500_000), ("office", 500_001), ("forest", 500_002), ("rooms", 500_003))


def fly(autopilot: str, world: World, drift: float, hold: bool, workdir: Path) -> dict:
    """One mission flight; the true height's error from the current waypoint's altitude."""
    options = FlightOptions(autopilot=autopilot, world=world, policy=ROOT / "models" / "policy.onnx",
                            duration=60.0, lidar_step_deg=1.0, workdir=workdir, mission=True,
                            altitude_drift=drift, companion_overrides={"goal": {"height_hold": hold}})
    with SitlFlight(options) as flight:
        error = ""
        try:
            flight.wait_companion_up(60.0)
            flight.upload_mission()
            flight.take_off()
            error = flight.fly(options.duration) if flight.wait_engaged(30.0) else "never engaged"
        except RuntimeError as exc:
            error = str(exc)
        report = flight.report(error=error)
        with flight.recorder.lock:
            traj = np.array([r for r in flight.recorder.trajectory
                             if flight.engaged_at is not None and r[0] >= flight.engaged_at])
    target = np.array([w[2] for w in world.waypoints])
    heights = traj[:, 3] if len(traj) else np.zeros(0)
    err = np.abs(heights - target.mean()) if len(heights) else np.zeros(1)
    return {"mean": float(err.mean()), "max": float(err.max()), "min_h": report.altitude_min_m,
            "max_h": report.altitude_max_m, "complete": report.mission_complete,
            "collision": report.collision, "floor": report.floor_contact, "error": report.error}


def cost_ratio() -> float:
    """The floor estimate's cost per revolution over the scan's (both on one 0.2° VLP-16 revolution)."""
    import time

    from companion.perception.floor import floor_height
    from companion.perception.scan import ScanConfig, scan_from_points
    from flightsim.envs.raycast import LidarConfig, VLP16Raycaster
    from flightsim.vehicle.quadrotor import VehicleState

    scan = ScanConfig()
    world = load_world(ROOT / "flightsim" / "worlds" / "two-pillars.json")
    state = VehicleState(time=0.0, position=np.array([-4.5, 0.0, 1.5]), velocity=np.zeros(3), roll=0.03,
                         pitch=0.08, yaw=0.2, angular_rate=np.zeros(3), on_ground=False, armed=True)
    points = VLP16Raycaster(LidarConfig(azimuth_step_deg=0.2)).cast_points(world, state.position,
                                                                           state.rotation())
    seconds = []
    for run in (lambda: floor_height(points, scan, 0.03, -0.08), lambda: scan_from_points(points, scan)):
        run()
        t0 = time.perf_counter()
        for _ in range(100):
            run()
        seconds.append(time.perf_counter() - t0)
    return seconds[0] / seconds[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drift", type=float, action="append", help="estimate minus truth, m (repeatable)")
    parser.add_argument("--validation", type=int, default=2, help="validation missions flown (of 4)")
    parser.add_argument("--autopilot", action="append", choices=("sim-ardupilot", "sim-px4"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    drifts = args.drift or [0.82, -1.08]
    autopilots = args.autopilot or ["sim-ardupilot", "sim-px4"]
    examples = ("two-pillars.json", "slalom.json")
    worlds = [load_world(ROOT / "flightsim" / "worlds" / name) for name in examples]
    worlds += [generate_family_world(f, s, 0.5) for f, s in VALIDATION_MISSIONS[: args.validation]]
    base = Path(tempfile.mkdtemp(prefix="bench-height-"))
    print(f"floor estimate per revolution: {cost_ratio():.0f}x the scan's cost (one 0.2° VLP-16 revolution)")
    print(f"{'autopilot':<14} {'drift':>6} {'hold':>5} {'world':<28} {'mean err':>8} {'max err':>8} "
          f"{'true height':>12}  outcome")
    summary: dict[tuple[str, float, bool], list[dict]] = {}
    for autopilot in autopilots:
        for drift in drifts:
            for hold in (False, True):
                for i, world in enumerate(worlds):
                    r = fly(autopilot, world, drift, hold, base / f"{autopilot}-{drift}-{hold}-{i}")
                    summary.setdefault((autopilot, drift, hold), []).append(r)
                    outcome = ("COLLISION " if r["collision"] else "") + ("FLOOR " if r["floor"] else "") + (
                        "complete" if r["complete"] else f"incomplete {r['error'][:40]}")
                    heights = f"{r['min_h']!s:>5}-{r['max_h']!s:<6}"
                    print(f"{autopilot:<14} {drift:>+6.2f} {'on' if hold else 'off':>5} {world.name:<28} "
                          f"{r['mean']:>8.2f} {r['max']:>8.2f} {heights}  {outcome}", flush=True)
    print("\nper autopilot, drift and hold, over the worlds: mean of the mean error, largest error")
    for (autopilot, drift, hold), rows in summary.items():
        print(f"{autopilot:<14} {drift:>+6.2f} {'on' if hold else 'off':>5}  "
              f"{np.mean([r['mean'] for r in rows]):.2f} m  {max(r['max'] for r in rows):.2f} m  "
              f"complete {sum(r['complete'] for r in rows)}/{len(rows)}")


if __name__ == "__main__":
    main()
