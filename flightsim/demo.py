"""``avoid-sim demo``: the whole system on a fresh machine in under three minutes.

A few short SITL mission flights (:mod:`flightsim.harness`, as ``avoid-sim fly --mission``): three
generated worlds of different families and the example worlds shipped in ``flightsim/worlds/``,
each with its waypoints uploaded as a mission through the ground-station link; the shipped policy,
the simulated ArduCopter (or PX4), the real companion process flying the mission. A flight ends
when the companion announces the mission complete, or at its time limit. Prints one table row per
flight and where the top-down PNGs are.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from importlib import resources
from pathlib import Path

from companion.errors import UserError
from flightsim import seeds
from flightsim.families import generate_family_world
from flightsim.flight_report import INTERRUPTED, FlightReport
from flightsim.fly_cli import default_policy
from flightsim.harness import FlightOptions, run_flight
from flightsim.planner import shortest_safe_path
from flightsim.world import DEFAULT_VEHICLE_RADIUS, World, load_world

#: (family, seed, difficulty) of the generated worlds: held-out test seeds, never trained on
GENERATED = (
    ("forest", seeds.TEST.start + 1, 0.3),
    ("office", seeds.TEST.start + 1, 0.3),
    ("pillars", seeds.TEST.start + 1, 0.3),
)
#: a flight's time limit without ``--duration``: this much, plus TIME_PER_M per metre of the
#: world's shortest safe path (the slowest mission the 3-minute budget allows)
TIME_SLACK_S = 6.0
TIME_PER_M = 0.9


def demo_worlds() -> list[World]:
    """The generated worlds, then every example world shipped with the package (all with waypoints)."""
    worlds = [generate_family_world(family, seed, difficulty) for family, seed, difficulty in GENERATED]
    shipped = resources.files("flightsim") / "worlds"
    for entry in sorted(shipped.iterdir(), key=lambda p: p.name):
        if entry.name.endswith(".json"):
            with resources.as_file(entry) as path:
                worlds.append(load_world(path))
    return worlds


def time_limit(world: World) -> float:
    """Seconds of companion flight a world's mission gets (from its shortest safe path)."""
    length = world.shortest_path_m
    if length is None:
        path = shortest_safe_path(world, vehicle_radius=DEFAULT_VEHICLE_RADIUS)
        length = path.length if path is not None else 0.0
    return TIME_SLACK_S + TIME_PER_M * float(length)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--policy", help="ONNX policy (default: the shipped models/policy.onnx)")
    parser.add_argument(
        "--duration", type=float, default=None,
        help=f"seconds of companion flight per world at most (default: {TIME_SLACK_S:g} s + "
        f"{TIME_PER_M:g} s per metre of the world's shortest safe path)",
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
    if args.duration is not None and args.duration <= 0:
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
    print(f"avoid-sim demo: {len(worlds)} mission flights, policy {policy}, {args.autopilot}")
    start = time.monotonic()
    reports: list[FlightReport] = []
    for world in worlds:
        options = FlightOptions(
            autopilot=args.autopilot,
            world=world,
            policy=policy,
            duration=args.duration if args.duration is not None else time_limit(world),
            workdir=out / world.name,
            mission=True,
            ideal_response=args.ideal_response,
        )
        try:
            report = run_flight(options, plot=out / f"{world.name}.png", vehicle=vehicle)
        except RuntimeError as exc:  # this flight could not start; try the others
            report = FlightReport.failed(world.name, args.autopilot, str(exc))
        reports.append(report)
        print(_row(report), flush=True)
        if report.error == INTERRUPTED:  # Ctrl-C: that flight was cleaned up; skip the rest
            break
    wall = time.monotonic() - start
    (out / "summary.json").write_text(
        json.dumps({"wall_time_s": round(wall, 1), "flights": [r.__dict__ for r in reports]}, indent=2)
    )
    print(_table(reports))
    print(f"wall time {wall:.0f} s; plots, companion logs and summary.json in {out.resolve()}")
    if reports and reports[-1].error == INTERRUPTED:
        return 130
    return 0 if all(not r.error for r in reports) else 1


HEADER = (
    f"{'world':<20} {'engaged':>7} {'waypoints':>9} {'complete':>8} {'time s':>6} {'collision':>9} "
    f"{'dist m':>6} {'min clr m':>9}"
)


def _cell(value: float | None, width: int, fmt: str) -> str:
    """A figure right-aligned in its column, "n/a" where the flight measured none."""
    return f"{'n/a' if value is None else format(value, fmt):>{width}}"


def _row(r: FlightReport) -> str:
    waypoints = f"{len(r.waypoints_reached)}/{r.waypoints_total}"
    line = (
        f"{r.world:<20} {'yes' if r.engaged else 'NO':>7} {waypoints:>9} "
        f"{'yes' if r.mission_complete else 'no':>8} "
        f"{_cell(r.mission_time_s if r.mission_complete else None, 6, '.1f')} "
        f"{'YES' if r.collision else 'no':>9} {r.distance_m:>6.1f} {_cell(r.min_clearance_m, 9, '.2f')}"
    )
    return line + (f"  ({r.error})" if r.error else "")


def _table(reports: list[FlightReport]) -> str:
    lines = ["", HEADER, "-" * len(HEADER)]
    lines += [_row(r) for r in reports]
    complete = sum(r.mission_complete and not r.collision for r in reports)
    lines += ["", f"{complete}/{len(reports)} missions complete without collision"]
    lines += ["", "plots:"] + [f"  {r.plot}" for r in reports]
    return "\n".join(lines)
