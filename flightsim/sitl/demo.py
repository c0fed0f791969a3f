"""``avoid-sim demo``: the whole system on a fresh machine in under three minutes.

A few short SITL mission flights (:mod:`flightsim.sitl.harness`, as ``avoid-sim fly --mission``): three
generated worlds of different families and the example worlds shipped in ``flightsim/worlds/``,
each with its waypoints uploaded as a mission through the ground-station link; the shipped policy,
the simulated ArduCopter (or PX4), the real companion process flying the mission. A flight ends
when the companion announces the mission complete, or at the goal task's time limit (the one
``avoid-train evaluate`` judges success by), so a demo mission succeeds as an evaluation episode
does. Flights run :data:`LANES` at a time, each in its own process, so that even with every flight
timed out the demo ends within three minutes. Prints a line per flight as it ends, then the table
in the worlds' order and where the top-down PNGs are.

Any exported model flies (:func:`~flightsim.sitl.fly_cli.model_overrides`: the companion is set up
as the model's metadata says); a scan-only model flies no missions, each world for its time limit.

``--worlds validation`` flies instead every world family twice, at validation seeds (difficulties
0.35 and 0.75): the SITL check of a policy or shield change before the test worlds are flown.
``--worlds dynamic`` flies each dynamic family (people, forklifts and other drones moving) once, at
a validation seed: the lidar stream shows them moving, and collisions are judged against them.
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing
import signal
import time
from concurrent.futures import CancelledError, Future, ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from importlib import resources
from pathlib import Path
from typing import Any

from companion.cli import LOG_FORMAT
from companion.common.errors import UserError
from flightsim.envs import seeds
from flightsim.sitl.flight_report import INTERRUPTED, FlightReport
from flightsim.sitl.fly_cli import default_policy, model_overrides, time_limit
from flightsim.sitl.harness import FlightOptions, run_flight
from flightsim.worlds.families import DYNAMIC_FAMILIES, FAMILIES, generate_family_world
from flightsim.worlds.world import World, load_world

#: (family, seed, difficulty) of the generated worlds: held-out test seeds, never trained on
GENERATED = (
    ("forest", seeds.TEST.start + 1, 0.3),
    ("office", seeds.TEST.start + 1, 0.3),
    ("pillars", seeds.TEST.start + 1, 0.3),
)
#: the difficulties ``--worlds validation`` flies each family at, one seed each
VALIDATION_DIFFICULTIES = (0.35, 0.75)
#: flights flown at once, each in its own process: a flight takes about a third of one core (the
#: simulated autopilot, the lidar packets and the companion), and this machine class has two
LANES = 2


def demo_worlds() -> list[World]:
    """The generated worlds, then every example world shipped with the package (all with waypoints)."""
    worlds = [generate_family_world(family, seed, difficulty) for family, seed, difficulty in GENERATED]
    shipped = resources.files("flightsim") / "worlds"
    for entry in sorted(shipped.iterdir(), key=lambda p: p.name):
        if entry.name.endswith(".json"):
            with resources.as_file(entry) as path:
                worlds.append(load_world(path))
    return worlds


def validation_worlds() -> list[World]:
    """Every family at each of :data:`VALIDATION_DIFFICULTIES`, each at its own validation seed (the
    family's index modulo 5 from the first, 5 on for the second difficulty): 18 worlds that no
    training run and no test figure flies."""
    first = seeds.VALIDATION.start
    return [
        generate_family_world(family, first + i % 5 + 5 * j, difficulty)
        for j, difficulty in enumerate(VALIDATION_DIFFICULTIES)
        for i, family in enumerate(FAMILIES)
    ]


def dynamic_worlds() -> list[World]:
    """Each of :data:`~flightsim.worlds.families.DYNAMIC_FAMILIES` once, at difficulty 0.5 and its
    own validation seed."""
    first = seeds.VALIDATION.start
    return [generate_family_world(family, first + i, 0.5) for i, family in enumerate(DYNAMIC_FAMILIES)]


def lane_schedule(durations: list[float], lanes: int = LANES) -> float:
    """When the last of ``durations`` ends, each started in order on the first lane free (s): how
    :class:`~concurrent.futures.ProcessPoolExecutor` hands out the flights."""
    free = [0.0] * lanes
    for duration in durations:
        lane = free.index(min(free))
        free[lane] += duration
    return max(free, default=0.0)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--policy", help="ONNX policy (default: the shipped models/policy.onnx)")
    parser.add_argument(
        "--duration", type=float, default=None,
        help="seconds of companion flight per world at most (default: the goal task's time limit, "
        "from the world's shortest safe path)",
    )
    parser.add_argument(
        "--worlds", choices=("demo", "validation", "dynamic"), default="demo",
        help="demo: the generated and example worlds (under 3 minutes); validation: every family at "
        "two validation seeds and difficulties (18 flights, about 8 minutes); dynamic: each family "
        "with moving obstacles once (4 flights)",
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
    verbose = bool(getattr(args, "verbose", False))
    if not verbose:  # the table is the demo's output; -v shows every step
        logging.getLogger("flightsim").setLevel(logging.WARNING)
    overrides = model_overrides(policy)
    missions = overrides["policy"]["observation"] == "goal"
    worlds = {"validation": validation_worlds, "dynamic": dynamic_worlds}.get(args.worlds, demo_worlds)()
    kind = "mission flights" if missions else "flights (a scan-only model: no missions)"
    print(f"avoid-sim demo: {len(worlds)} {kind}, {LANES} at a time, policy {policy}, {args.autopilot}")
    start = time.monotonic()
    flights = [
        FlightOptions(
            autopilot=args.autopilot,
            world=world,
            policy=policy,
            duration=args.duration if args.duration is not None else time_limit(world),
            workdir=out / world.name,
            mission=missions,
            ideal_response=args.ideal_response,
            companion_overrides=overrides,
        )
        for world in worlds
    ]
    reports = _fly_all(flights, out, verbose)
    wall = time.monotonic() - start
    (out / "summary.json").write_text(
        json.dumps({"wall_time_s": round(wall, 1), "flights": [r.__dict__ for r in reports]}, indent=2)
    )
    print(_table(reports))
    print(f"wall time {wall:.0f} s; plots, companion logs and summary.json in {out.resolve()}")
    if any(r.error == INTERRUPTED for r in reports):
        return 130
    return 0 if all(not r.error for r in reports) else 1


def _fly_all(flights: list[FlightOptions], out: Path, verbose: bool) -> list[FlightReport]:
    """Fly ``flights`` :data:`LANES` at a time; their reports in the same order. On Ctrl-C the
    flights in the air end themselves (each process gets the signal and cleans up its flight),
    those not started are cancelled and reported as interrupted."""
    reports: dict[int, FlightReport] = {}
    context = multiprocessing.get_context("spawn")  # no inherited threads; logging set up again
    stop = context.Event()  # set on Ctrl-C: a flight already handed to a process does not start
    with ProcessPoolExecutor(LANES, context, initializer=_start_worker, initargs=(verbose, stop)) as pool:
        futures: dict[Future[FlightReport], int] = {
            pool.submit(_fly, options, out / f"{options.world.name}.png"): i
            for i, options in enumerate(flights)
        }
        try:
            for future in as_completed(futures):
                reports[futures[future]] = report = _result(future, flights[futures[future]])
                print(_progress(len(reports), len(flights), report), flush=True)
        except KeyboardInterrupt:
            stop.set()
            for future in futures:
                future.cancel()
            for future, i in futures.items():
                if i not in reports:
                    reports[i] = _result(future, flights[i])
    return [reports[i] for i in range(len(flights))]


def _result(future: Future[FlightReport], options: FlightOptions) -> FlightReport:
    """A flight's report, or the report of one cancelled by Ctrl-C or whose process died (any
    other error in a flight process is raised here, as it would be flying in this one)."""
    try:
        return future.result()
    except CancelledError:
        return FlightReport.failed(options.world.name, options.autopilot, INTERRUPTED)
    except BrokenProcessPool as exc:
        return FlightReport.failed(options.world.name, options.autopilot, f"its process died ({exc})")


_VEHICLE: Any = None  # a worker process's JSBSim vehicle, loaded once for all its flights
_STOP: Any = None  # the demo's Ctrl-C event, shared by its worker processes


def _start_worker(verbose: bool, stop: Any) -> None:
    """A flight process: the demo's logging, its Ctrl-C event, and Ctrl-C ignored between flights
    (see :func:`_fly`)."""
    global _STOP
    _STOP = stop
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, format=LOG_FORMAT)
    if not verbose:
        logging.getLogger("flightsim").setLevel(logging.WARNING)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _fly(options: FlightOptions, plot: Path) -> FlightReport:
    """One flight in a worker process; Ctrl-C during it ends it as ``avoid-sim fly`` does, and one
    before it (the pool hands a process its next flight early) keeps it on the ground."""
    global _VEHICLE
    interrupted = FlightReport.failed(options.world.name, options.autopilot, INTERRUPTED)
    if _STOP.is_set():
        return interrupted
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        if _VEHICLE is None:
            from flightsim.vehicle.quadrotor import Vehicle

            _VEHICLE = Vehicle()
        report = run_flight(options, plot=plot, vehicle=_VEHICLE)
    except RuntimeError as exc:  # this flight could not start; the others go on
        report = FlightReport.failed(options.world.name, options.autopilot, str(exc))
    except KeyboardInterrupt:  # before the flight's own handling took over
        report = interrupted
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    if report.error == INTERRUPTED:  # before this process takes its next flight, whatever the demo does
        _STOP.set()
    return report


#: the table's columns after the world's: (title, width)
COLUMNS = (("engaged", 7), ("waypoints", 9), ("complete", 8), ("time s", 6), ("collision", 9),
           ("dist m", 6), ("min clr m", 9))  # fmt: skip
#: the world column is at least this wide, and as wide as the longest name
WORLD_WIDTH = 20


def _cell(value: float | None, width: int, fmt: str) -> str:
    """A figure right-aligned in its column, "n/a" where the flight measured none."""
    return f"{'n/a' if value is None else format(value, fmt):>{width}}"


def _header(world_width: int = WORLD_WIDTH) -> str:
    return f"{'world':<{world_width}} " + " ".join(f"{title:>{width}}" for title, width in COLUMNS)


def _outcome(r: FlightReport) -> str:
    """A flight's result in a few words, for the line printed as it ends."""
    if r.error:
        return f"error: {r.error}"
    if r.collision:
        return "collision"
    if r.waypoints_total:
        done = f"complete in {r.mission_time_s:.1f} s" if r.mission_complete else "not complete"
        return f"{len(r.waypoints_reached)}/{r.waypoints_total} waypoints, {done}"
    return f"{r.distance_m:.1f} m flown"


def _progress(done: int, total: int, r: FlightReport) -> str:
    """The line printed as a flight ends (the table follows once all have)."""
    return f"[{done}/{total}] {r.world}: {_outcome(r)}"


def _row(r: FlightReport, world_width: int = WORLD_WIDTH) -> str:
    waypoints = f"{len(r.waypoints_reached)}/{r.waypoints_total}"
    widths = [width for _, width in COLUMNS]
    line = (
        f"{r.world:<{world_width}} {'yes' if r.engaged else 'NO':>{widths[0]}} {waypoints:>{widths[1]}} "
        f"{'yes' if r.mission_complete else 'no':>{widths[2]}} "
        f"{_cell(r.mission_time_s if r.mission_complete else None, widths[3], '.1f')} "
        f"{'YES' if r.collision else 'no':>{widths[4]}} {r.distance_m:>{widths[5]}.1f} "
        f"{_cell(r.min_clearance_m, widths[6], '.2f')}"
    )
    return line + (f"  ({r.error})" if r.error else "")


def _table(reports: list[FlightReport]) -> str:
    """Every flight's row in the worlds' order, the world column as wide as the longest name."""
    width = max([WORLD_WIDTH, *(len(r.world) for r in reports)])
    header = _header(width)
    lines = ["", header, "-" * len(header)]
    lines += [_row(r, width) for r in reports]
    if any(r.waypoints_total for r in reports):
        complete = sum(r.mission_complete and not r.collision for r in reports)
        lines += ["", f"{complete}/{len(reports)} missions complete without collision"]
    else:  # a scan-only model flies no missions
        safe = sum(r.engaged and not r.collision and not r.error for r in reports)
        lines += ["", f"{safe}/{len(reports)} flights without collision"]
    lines += ["", "plots:"] + [f"  {r.plot}" for r in reports]
    return "\n".join(lines)
