"""``avoid-train trace``: one episode of an evaluation, step by step.

An evaluation says that a world failed; a trace says how. It flies the same episode as
``avoid-train evaluate`` with the same arguments (the same world, response draw and sensor noise:
:func:`~training.episodes.episode_seed`) and records, at every command: where the vehicle truly is,
the nearest return of the scan the controller saw, what the controller asked, what the shield sent
and which of its limits acted, the velocity the autopilot reported and the true one (the difference
is the estimate error that made most shielded collisions). Rows print as a table, or go to a CSV.

    avoid-train trace --config training/configs/nav.toml --first-seed 500020 --seeds 30 \\
        --world forest-500045 --policy models/policy.onnx --shield --last 40
"""

from __future__ import annotations

import argparse
import csv
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from companion.common.errors import UserError
from companion.perception.scan import N_BINS
from companion.safety.shield import command_from_action
from training.config import sideways_scale
from training.controllers import Controller, ControllerSpec, ShieldedController, load_policy
from training.episodes import EpisodeResult, make_tasks, run_task
from training.evaluate import Flight, add_flight_arguments, load_flight, parse_baselines


@dataclass(frozen=True)
class StepTrace:
    """One command of an episode (world frame ENU, body frame FLU; m, m/s, rad/s, degrees).

    :param step: the env step the command follows (0: chosen at reset)
    :param nearest_m: the nearest return of the scan the controller saw
    :param nearest_deg: its bearing, counter-clockwise from the nose
    :param asked_forward: what the controller asked, before the shield
    :param sent_forward: what left for the autopilot: after the shield, with the held drift
        (the env's ``drift_hold``)
    :param sent_lateral: the shield's sideways brake or push and the held drift (the controller
        never asks one)
    :param reported_forward: the body velocity the autopilot reports (its estimate)
    :param true_forward: the body velocity it truly has
    :param shield: the shield's limits that acted on this command, with their counts
    """

    step: int
    x: float
    y: float
    yaw_deg: float
    nearest_m: float
    nearest_deg: float
    asked_forward: float
    asked_yaw_rate: float
    sent_forward: float
    sent_lateral: float
    sent_yaw_rate: float
    reported_forward: float
    reported_left: float
    true_forward: float
    true_left: float
    shield: str


class Tracer:
    """Flies ``inner`` and records a :class:`StepTrace` for each of its commands.

    :param inner: the controller (a :class:`~training.controllers.ShieldedController` shows its shield)
    :param env: the unwrapped env it flies (its true state is read, never changed)
    """

    def __init__(self, inner: Controller, env: Any) -> None:
        self._inner = inner
        self._env = env
        self.steps: list[StepTrace] = []

    def reset(self, scan: np.ndarray) -> np.ndarray:
        self.steps = []
        return self._record(scan, lambda: self._inner.reset(scan))

    def act(self, scan: np.ndarray) -> np.ndarray:
        return self._record(scan, lambda: self._inner.act(scan))

    def _record(self, scan: np.ndarray, choose: Callable[[], np.ndarray]) -> np.ndarray:
        shielded = self._inner if isinstance(self._inner, ShieldedController) else None
        before = dict(shielded.shield.interventions) if shielded else {}
        action = choose()
        config = self._env.config
        if shielded is not None and shielded.last is not None:
            asked, sent = shielded.last
            counts = shielded.shield.interventions
            acted = {k: n - before.get(k, 0) for k, n in sorted(counts.items()) if n > before.get(k, 0)}
        else:
            scales = (config.max_speed, config.max_yaw_rate, sideways_scale(config))
            asked = sent = command_from_action(action, *scales)
            acted = {}
        held_forward, held_left = self._env.drift_held()
        state = self._env.true_state
        reported, true = self._env.measured_body_velocity(), self._env.true_body_velocity()
        ranges = np.asarray(scan[:N_BINS], dtype=np.float64) * float(config.scan.max_range)
        nearest = int(np.argmin(ranges))
        self.steps.append(StepTrace(
            step=len(self.steps), x=float(state.position[0]), y=float(state.position[1]),
            yaw_deg=math.degrees(state.yaw), nearest_m=float(ranges[nearest]), nearest_deg=nearest + 0.5,
            asked_forward=asked.forward, asked_yaw_rate=asked.yaw_rate,
            sent_forward=sent.forward + held_forward, sent_lateral=sent.lateral + held_left,
            sent_yaw_rate=sent.yaw_rate,
            reported_forward=float(reported[0]), reported_left=float(reported[1]),
            true_forward=float(true[0]), true_left=float(true[1]),
            shield=" ".join(f"{k}" if n == 1 else f"{k}x{n}" for k, n in acted.items()),
        ))  # fmt: skip
        return action


def trace(
    flight: Flight, world: str, spec: ControllerSpec, episode: int = 0
) -> tuple[EpisodeResult, list[StepTrace]]:
    """Fly ``spec`` on the ``world`` of ``flight`` (:func:`~training.evaluate.load_flight`) as
    ``avoid-train evaluate`` flies its episode ``episode``, recording every command.

    :raises UserError: no such world among the flight's
    """
    names = [w.name for w in flight.worlds]
    if world not in names:
        shown = ", ".join(names[:5]) + (", ..." if len(names) > 5 else "")
        raise UserError(f"--world {world}: not among the {len(names)} worlds named ({shown})")
    chosen = flight.worlds[names.index(world)]
    task = make_tasks([spec], [chosen], episode + 1, flight.config.env, flight.config.env_id)[episode]
    tracers: list[Tracer] = []

    def wrap(controller: Controller, env: Any) -> Controller:
        tracers.append(Tracer(controller, env))
        return tracers[-1]

    result = run_task(task, wrap)
    return result, tracers[0].steps


def format_rows(steps: list[StepTrace]) -> str:
    """The table ``avoid-train trace`` prints."""
    lines = [
        f"{'step':>5} {'x':>7} {'y':>7} {'yaw':>5} {'nearest':>11} {'asked fwd,yaw':>13} "
        f"{'sent fwd,lat,yaw':>17} {'reported':>11} {'true':>11}  shield"
    ]
    for s in steps:
        lines.append(
            f"{s.step:5d} {s.x:7.2f} {s.y:7.2f} {s.yaw_deg:5.0f} {s.nearest_m:5.2f}@{s.nearest_deg:5.1f} "
            f"{s.asked_forward:+6.2f},{s.asked_yaw_rate:+6.2f} "
            f"{s.sent_forward:+5.2f},{s.sent_lateral:+5.2f},{s.sent_yaw_rate:+5.2f} "
            f"{s.reported_forward:+5.2f},{s.reported_left:+5.2f} "
            f"{s.true_forward:+5.2f},{s.true_left:+5.2f}  {s.shield}"
        )
    return "\n".join(lines)


def write_csv(steps: list[StepTrace], path: Path) -> None:
    """Every row, one column per :class:`StepTrace` field."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=[field.name for field in fields(StepTrace)])
        writer.writeheader()
        writer.writerows(asdict(s) for s in steps)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--policy", type=Path, help="the policy to fly (.onnx or SB3 .zip)")
    what.add_argument("--baseline", metavar="NAME", help="a baseline to fly instead")
    parser.add_argument("--world", required=True, help="the world, as evaluate names it (e.g. forest-500045)")
    parser.add_argument(
        "--episode", type=int, default=0, help="which episode of that world (evaluate's index)"
    )
    add_flight_arguments(parser)
    parser.add_argument("--last", type=int, metavar="N", help="print only the last N commands")
    parser.add_argument("--csv", type=Path, help="write every command here")


def command(args: argparse.Namespace) -> int:
    if args.episode < 0:
        raise UserError("--episode must be 0 or more")
    if args.last is not None and args.last < 1:
        raise UserError("--last must be at least 1")
    flight = load_flight(args)
    if args.policy is not None:
        load_policy(args.policy, flight.env_config, flight.config.n_stack)  # a one-line error
        spec = ControllerSpec("policy", str(args.policy), "policy", flight.shield, flight.shield_config)
    else:
        names = parse_baselines(args.baseline, flight.config.env_id, "--baseline") or []
        if len(names) != 1:
            raise UserError(f"--baseline {args.baseline!r}: name one baseline")
        spec = ControllerSpec(names[0], shield=flight.shield, shield_config=flight.shield_config)
    result, steps = trace(flight, args.world, spec, args.episode)
    outcomes = (("success", result.success), ("collision", result.collision), ("timeout", result.timeout))
    outcome = next((name for name, happened in outcomes if happened), "failure")
    response = result.response.get("name", "ideal") if result.response else "ideal"
    print(
        f"{result.world} episode {args.episode}, {spec.label}: {outcome} after {result.steps} steps "
        f"({result.time_s:.1f} s), min clearance {result.min_clearance:.2f} m, response {response}"
    )
    print(format_rows(steps[-args.last :] if args.last else steps))
    if args.csv:
        write_csv(steps, args.csv)
        print(f"wrote {args.csv}")
    return 0
