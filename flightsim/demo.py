"""``avoid-sim demo``: the whole system on a fresh machine in under three minutes.

A few short SITL flights (:mod:`flightsim.harness`): two generated rooms and the example worlds
shipped in ``flightsim/worlds/``, the shipped policy, the simulated ArduCopter, the real companion
process. Prints one table row per flight and where the top-down PNGs are.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from importlib import resources
from pathlib import Path

from companion.errors import UserError
from flightsim.harness import FlightOptions, FlightReport, default_policy, run_flight
from flightsim.world import World, generate_world, load_world

#: (seed, difficulty) of the generated rooms
GENERATED = ((1, 0.3), (2, 0.6))


def demo_worlds() -> list[World]:
    """The generated rooms, then every example world shipped with the package."""
    worlds = [generate_world(seed, difficulty) for seed, difficulty in GENERATED]
    shipped = resources.files("flightsim") / "worlds"
    for entry in sorted(shipped.iterdir(), key=lambda p: p.name):
        if entry.name.endswith(".json"):
            with resources.as_file(entry) as path:
                worlds.append(load_world(path))
    return worlds


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--policy", help="ONNX policy (default: the shipped models/policy.onnx)")
    parser.add_argument(
        "--duration", type=float, default=20.0, help="seconds of companion flight per world (20)"
    )
    parser.add_argument("--out", default="avoid-sim-demo", help="directory for PNGs, logs and summary.json")
    parser.add_argument(
        "--autopilot",
        choices=("sim-ardupilot", "sim-px4"),
        default="sim-ardupilot",
        help="simulated autopilot personality (sim-ardupilot)",
    )
    parser.add_argument(
        "--ideal-response",
        action="store_true",
        help="fly setpoints as given, not with the firmware's calibrated (slower) response",
    )


def command(args: argparse.Namespace) -> int:
    if args.duration <= 0:
        raise UserError(f"--duration must be positive, got {args.duration}")
    policy = Path(args.policy) if args.policy else default_policy()
    if not policy.is_file():
        raise UserError(f"policy file not found: {policy}")
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--out {out}: {exc.strerror}") from None
    if not getattr(args, "verbose", False):  # the table is the demo's output; -v shows every step
        logging.getLogger("flightsim").setLevel(logging.WARNING)
    from flightsim.vehicle import Vehicle

    vehicle = Vehicle()  # one JSBSim load for all flights
    worlds = demo_worlds()
    print(f"avoid-sim demo: {len(worlds)} flights of {args.duration:g} s, policy {policy}, {args.autopilot}")
    start = time.monotonic()
    reports: list[FlightReport] = []
    for world in worlds:
        options = FlightOptions(
            autopilot=args.autopilot,
            world=world,
            policy=policy,
            duration=args.duration,
            workdir=out / world.name,
            ideal_response=args.ideal_response,
        )
        try:
            report = run_flight(options, plot=out / f"{world.name}.png", vehicle=vehicle)
        except RuntimeError as exc:  # this flight could not start; try the others
            report = FlightReport.failed(world.name, args.autopilot, str(exc))
        reports.append(report)
        print(_row(report), flush=True)
        if report.error == "interrupted":  # Ctrl-C: that flight was cleaned up; skip the rest
            break
    wall = time.monotonic() - start
    (out / "summary.json").write_text(
        json.dumps({"wall_time_s": round(wall, 1), "flights": [r.__dict__ for r in reports]}, indent=2)
    )
    print(_table(reports))
    print(f"wall time {wall:.0f} s; plots, companion logs and summary.json in {out.resolve()}")
    return 0 if all(not r.error for r in reports) else 1


HEADER = (
    f"{'world':<18} {'engaged':>7} {'collision':>9} {'dist m':>7} {'min clr m':>9} {'sp Hz':>6} "
    f"{'lat p50 ms':>10} {'p99 ms':>7}"
)


def _row(r: FlightReport) -> str:
    line = (
        f"{r.world:<18} {'yes' if r.engaged else 'NO':>7} {'YES' if r.collision else 'no':>9} "
        f"{r.distance_m:>7.1f} {r.min_clearance_m:>9.2f} {r.setpoint_rate_hz:>6.1f} "
        f"{r.latency_p50_ms:>10.1f} {r.latency_p99_ms:>7.1f}"
    )
    return line + (f"  ({r.error})" if r.error else "")


def _table(reports: list[FlightReport]) -> str:
    lines = ["", HEADER, "-" * len(HEADER)]
    lines += [_row(r) for r in reports]
    lines += ["", "plots:"] + [f"  {r.plot}" for r in reports]
    return "\n".join(lines)
