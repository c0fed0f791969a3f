"""``avoid-sim fly``: one SITL flight from the command line (world, policy, autopilot), its report printed.

Apart from :mod:`flightsim.sitl.harness` because the command line (arguments, their checks, the shipped
policy, exit codes) is not the flight: the demo, the benchmarks and the SITL tests fly through the
harness without it.

Any exported model flies: the companion's ``[policy]`` table is set from the model's own metadata
(:func:`model_overrides`), so a scan-only model (LidarAvoid-v0) flies as one and a goal model with
the features it was trained on. A world file's waypoints are flown as a mission by a goal model
unless ``--no-mission`` says otherwise, for the goal task's time limit unless ``--duration`` says.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from companion.common.errors import UserError
from companion.config import model_policy_settings
from companion.guidance.policy import read_model_metadata
from flightsim.envs.env import CONTROL_HZ
from flightsim.envs.nav_env import NavEnvConfig, time_limit_steps
from flightsim.sitl.external_sitl import POSITION_TIMEOUT_S
from flightsim.sitl.flight_report import INTERRUPTED, print_report
from flightsim.sitl.harness import AUTOPILOTS, FlightOptions, run_flight
from flightsim.worlds.planner import shortest_safe_path
from flightsim.worlds.world import DEFAULT_VEHICLE_RADIUS, World, generate_world, load_world


def load_flight_world(world_file: str | None, seed: int | None, difficulty: float) -> World:
    """``--world FILE`` or ``--seed N --difficulty D`` (UserError naming the problem)."""
    if world_file and seed is not None:
        raise UserError("give either --world or --seed, not both")
    if world_file:
        return load_world(world_file)
    if not 0.0 <= difficulty <= 1.0:
        raise UserError(f"--difficulty must be within [0, 1], got {difficulty}")
    if seed is not None and seed < 0:
        raise UserError(f"--seed must be a non-negative integer, got {seed}")
    return generate_world(0 if seed is None else seed, difficulty)


def default_policy() -> Path:
    """The shipped policy (``models/policy.onnx`` in the checkout or the package's copy)."""
    here = Path(__file__).resolve().parents[1]  # the flightsim package
    for candidate in (here.parent / "models" / "policy.onnx", here / "models" / "policy.onnx"):
        if candidate.is_file():
            return candidate
    raise UserError(
        "no shipped policy found (models/policy.onnx): train and export one with `avoid-train`, "
        "or pass --policy FILE"
    )


#: seconds of companion flight without a mission (``--duration``'s default then)
FREE_FLIGHT_S = 30.0


def time_limit(world: World) -> float:
    """Seconds of companion flight a world's mission gets: the goal task's time limit
    (:func:`flightsim.envs.nav_env.time_limit_steps`, from the world's shortest safe path), the
    one ``avoid-train evaluate`` judges an episode by."""
    length = world.shortest_path_m
    if length is None:
        path = shortest_safe_path(world, vehicle_radius=DEFAULT_VEHICLE_RADIUS)
        length = path.length if path is not None else 0.0
    return time_limit_steps(float(length), NavEnvConfig()) / CONTROL_HZ


def model_overrides(policy: Path) -> dict[str, dict[str, Any]]:
    """The companion config changes that fly ``policy`` as its metadata says it was trained
    (``[policy]``: observation, features, stack and scales).

    :raises UserError: the model is unreadable or its metadata names no layout the companion feeds
    """
    return {"policy": model_policy_settings(read_model_metadata(policy))}


def flies_mission(world: World, scan_only: bool, asked: bool | None) -> tuple[bool, str]:
    """Whether a flight of ``world`` flies its waypoints as a mission, and the line that says so
    ("" when there is nothing to say).

    :param scan_only: the model has no goal input (it cannot fly to a waypoint)
    :param asked: ``--mission`` (True), ``--no-mission`` (False) or neither (None: a world's
        waypoints are flown when the model can)
    :raises UserError: ``--mission`` with a scan-only model
    """
    n = len(world.waypoints)
    if asked and scan_only:
        raise UserError("--mission: the model is scan-only (LidarAvoid-v0) and flies to no waypoint")
    if asked is not None or not n:
        return bool(asked), ""
    if scan_only:
        return False, f"world {world.name}: its {n} waypoints are not flown: the model is scan-only"
    return True, f"world {world.name}: flying its {n} waypoints as a mission (--no-mission: fly without)"


def configure_parser(parser: Any) -> None:
    """``avoid-sim fly``."""
    parser.add_argument(
        "--autopilot",
        choices=AUTOPILOTS,
        default="sim-ardupilot",
        help="simulated ArduCopter, simulated PX4, or an external SITL (default sim-ardupilot)",
    )
    parser.add_argument(
        "--connect",
        default="",
        help="external SITL's MAVLink address (pymavlink string, e.g. tcp:127.0.0.1:5760)",
    )
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--world", help="world JSON file (e.g. flightsim/worlds/slalom.json)")
    where.add_argument("--seed", type=int, help="generate a room from this seed")
    parser.add_argument("--difficulty", type=float, default=0.5, help="generated room difficulty 0..1 (0.5)")
    parser.add_argument("--policy", help="ONNX policy (default: the shipped models/policy.onnx)")
    parser.add_argument("--duration", type=float,
                        help="seconds the companion flies (default: a mission's time limit, the goal "
                        "task's, from the world's shortest safe path; 30 without a mission)")
    parser.add_argument(
        "--lidar-step",
        type=float,
        default=0.2,
        choices=(0.2, 1.0),
        help="ray-cast azimuth step in degrees: 0.2 like the VLP-16, 1.0 to save CPU",
    )
    parser.add_argument("--signed", action="store_true",
                        help="MAVLink 2 signing on every link: autopilot, GCS, companion (sim autopilots)")
    missions = parser.add_mutually_exclusive_group()
    missions.add_argument("--mission", action="store_true", default=None,
                          help="upload the world's waypoints as a mission (GCS) and fly it "
                          "(goal.source = mission; the default for a world with waypoints and a goal model)")
    missions.add_argument("--no-mission", dest="mission", action="store_false",
                          help="fly without the world's waypoints (the goal model flies 20 m ahead)")
    parser.add_argument(
        "--ideal-response",
        action="store_true",
        help="simulated autopilots: fly setpoints as given, not with the firmware's calibrated response",
    )
    parser.add_argument("--position-timeout", type=float, default=POSITION_TIMEOUT_S, metavar="S",
                        help="external SITL: seconds to wait for its first position, the EKF origin "
                        "(a fresh ArduPilot SITL needs 40-47 s; default 120)")
    parser.add_argument("--json", help="write the flight report as JSON here")
    parser.add_argument("--plot", help="write a top-down PNG of the flight here")
    parser.add_argument("--workdir", help="where the companion's config and log go (default: a temp dir)")


def command(args: Any) -> int:
    """Fly once as the command line says: exit 0, 1 when the flight failed, 130 on Ctrl-C."""
    import tempfile

    if args.duration is not None and args.duration <= 0:
        raise UserError(f"--duration must be positive, got {args.duration}")
    if not args.position_timeout > 0:
        raise UserError(f"--position-timeout must be positive, got {args.position_timeout}")
    world = load_flight_world(args.world, args.seed, args.difficulty)
    policy = Path(args.policy) if args.policy else default_policy()
    overrides = model_overrides(policy)
    mission, note = flies_mission(world, overrides["policy"]["observation"] == "scan", args.mission)
    if note:
        print(note)
    duration = args.duration or (time_limit(world) if mission else FREE_FLIGHT_S)
    workdir = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="avoid-sim-fly-"))
    options = FlightOptions(
        autopilot=args.autopilot,
        world=world,
        policy=policy,
        duration=duration,
        connect=args.connect,
        lidar_step_deg=args.lidar_step,
        workdir=workdir,
        signed=args.signed,
        mission=mission,
        ideal_response=args.ideal_response,
        companion_overrides=overrides,
        position_timeout=args.position_timeout,
    )
    try:
        report = run_flight(options, plot=Path(args.plot) if args.plot else None)
    except KeyboardInterrupt:  # during start-up; run_flight cleaned up on its way out
        print("avoid-sim fly: interrupted", file=sys.stderr)
        return 130
    except RuntimeError as exc:  # start-up failed (no autopilot heartbeat, ...): one line, no traceback
        print(f"avoid-sim fly: error: {exc}", file=sys.stderr)
        return 1
    print_report(report)
    print(f"companion log: {workdir / 'companion.log'}")
    if args.json:
        Path(args.json).write_text(report.to_json())
    if report.error == INTERRUPTED:
        return 130  # as a shell reports a command Ctrl-C stopped
    return 0 if not report.error else 1
