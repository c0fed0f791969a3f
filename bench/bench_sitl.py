"""SITL figures: setpoint rate and latency from lidar revolution end to setpoint at the autopilot.

Flies the real companion process against the simulated ArduCopter and PX4 (real MAVLink and
VLP-16 packets on loopback) in ``flightsim/worlds/two-pillars.json`` and prints, per autopilot:
setpoints per second (compare: one per 10 Hz revolution = 10 Hz; PX4's figure also counts
MAVSDK's own 20 Hz repetition) and the delay from the send time of a revolution's last packet
to the first setpoint the autopilot receives after it, p50/p99 (compare: the 100 ms revolution
period, the time budget of one scan).

Usage: ``python bench/bench_sitl.py [--duration 20] [--policy FILE]`` (default policy: the shipped
``models/policy.onnx``, else the repository's test "steer" policy).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
REVOLUTION_MS = 100.0  # the VLP-16 at 10 Hz: one scan, one setpoint, per 100 ms
sys.path.insert(0, str(ROOT))

from flightsim.sitl.harness import FlightOptions, run_flight  # noqa: E402
from flightsim.worlds.world import load_world  # noqa: E402


def pick_policy(arg: str | None, workdir: Path) -> Path:
    if arg:
        return Path(arg)
    shipped = ROOT / "models" / "policy.onnx"
    if shipped.is_file():
        return shipped
    from tests.onnx_models import write_policy

    return write_policy(workdir / "steer.onnx", kind="steer")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--policy")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    workdir = Path(tempfile.mkdtemp(prefix="bench-sitl-"))
    policy = pick_policy(args.policy, workdir)
    world = load_world(ROOT / "flightsim" / "worlds" / "two-pillars.json")
    print(f"policy {policy}, world {world.name}, {args.duration:g} s of companion flight per autopilot")
    print(
        f"{'autopilot':<14} {'setpoints/s':>11} {'latency p50':>12} {'p99':>8} {'p99/period':>10}   "
        f"(against the {REVOLUTION_MS:.0f} ms revolution period)"
    )
    for autopilot in ("sim-ardupilot", "sim-px4"):
        t0 = time.monotonic()
        report = run_flight(
            FlightOptions(
                autopilot=autopilot,
                world=world,
                policy=policy,
                duration=args.duration,
                workdir=workdir / autopilot,
            )
        )
        note = f"  error: {report.error}" if report.error else ""
        p50, p99 = report.latency_p50_ms, report.latency_p99_ms
        if p50 is None or p99 is None:
            print(f"{autopilot:<14} {report.setpoint_rate_hz:>11.1f}   no latency measured{note}")
            continue
        print(
            f"{autopilot:<14} {report.setpoint_rate_hz:>11.1f} {p50:>9.1f} ms {p99:>5.1f} ms "
            f"{p99 / REVOLUTION_MS:>9.1%}   (flight wall time {time.monotonic() - t0:.0f} s, "
            f"load average {os.getloadavg()[0]:.1f}){note}"
        )


if __name__ == "__main__":
    main()
