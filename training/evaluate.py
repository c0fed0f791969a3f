"""``avoid-train evaluate``: fly a policy and two baselines over the same worlds and compare them.

The task is the training config's ``env_id``: ``--config``'s, or without it the policy's own: the
one an exported (``.onnx``) policy's metadata carries, or its run directory's ``config.toml`` for a
checkpoint (``.zip``), so a model is flown in the task and observation it was trained for.

Avoidance (``flightsim/LidarAvoid-v0``): success is strict: the whole episode (``max_steps``)
without a collision AND a mean speed of at least :data:`~training.config.SUCCESS_MIN_MEAN_SPEED`
(40 m in the default 100 s), because a policy that hovers in place survives every episode. Per
controller the report gives, per world and overall: success rate, collisions, distance flown, mean
speed, minimum clearance and near misses. Baselines: the gap follower and random actions.

Goal (``flightsim/LidarNav-v0``): success is every waypoint reached in order, without a collision,
within the world's time limit. Per controller, per world, per family and overall: success,
collision and timeout rates, mean time to the last waypoint and SPL (shortest safe path / path
flown, both over successes only; ``spl_all`` is Anderson et al.'s, failures counting 0).
Baselines: the goal follower and the straight line; named in ``--baselines``, also the DAgger
teachers (``path_expert`` and ``predictive_expert``, privileged: they read the simulator's truth,
so their rates bound what imitating them can reach). ``--seeds N`` flies N test worlds per family
(:data:`flightsim.envs.seeds.TEST`), difficulties spread evenly over the config's ``difficulty_range``.

Every controller sees one scan per step through the same interface (``reset(scan)`` then
``act(scan)``). The learned policy goes through the companion's own :class:`FrameStack`; an
``.onnx`` file runs through the companion's :class:`OnnxPolicy`, so the figures are those of what
flies, not of the training framework. With ``--shield`` every controller's actions also pass
through the companion's :class:`SafetyShield` (default ``[shield]`` limits, or the ``[shield]`` table
of the companion config given in ``--shield-config``), as they do in flight; the report labels those
rows ``<controller>+shield``.

Episodes are independent tasks run in a process pool (one process per core by default) or, with
``--executor ray``, as Ray tasks on a local Ray or a cluster (``--address``); both feed the same
:func:`run_tasks`, so the report is the same, in the same order.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from collections.abc import Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from companion.common.errors import UserError
from companion.common.tomlconfig import from_dict, load_toml
from companion.config import CompanionShieldConfig
from companion.safety.shield import ShieldConfig
from training.attackers import ATTACKERS
from training.controllers import (
    BASELINES,
    GOAL_BASELINES,
    PRIVILEGED_GOAL_CONTROLLERS,
    TRACK_BASELINES,
    ControllerSpec,
    load_policy,
)
from training.episodes import (
    AVOID_ENV_ID,
    NAV_ENV_ID,
    EpisodeResult,
    EpisodeTask,
    WorldSpec,
    goal_worlds,
    make_tasks,
    run_task,
)
from training.progress import Progress
from training.report import format_table, plot_trajectories, report

#: where ``avoid-train evaluate`` runs its episodes
EXECUTORS = ("local", "ray")


def make_executor(workers: int, kind: str = "local", address: str | None = None) -> Executor:
    """Where episodes run: a process pool of ``workers`` (forkserver: safe with torch's threads in
    the parent), or Ray tasks (:class:`~training.ray_executor.RayExecutor`) on a local Ray of
    ``workers`` CPUs or on the cluster at ``address``."""
    if kind == "ray":
        from training.ray_executor import RayExecutor

        return RayExecutor(address, None if address else workers)
    return ProcessPoolExecutor(max_workers=workers, mp_context=get_context("forkserver"))


def run_tasks(
    tasks: Sequence[EpisodeTask], executor: Executor | None = None, progress: Progress | None = None
) -> list[EpisodeResult]:
    """Run ``tasks`` in ``executor`` (or in this process when ``None``), results in task order.

    :param progress: counts the episodes as they end
    """
    results = []
    for result in map(run_task, tasks) if executor is None else executor.map(run_task, tasks):
        results.append(result)
        if progress is not None:
            progress.update()
    return results


# --- command line ----------------------------------------------------------------------------------


def world_files(directory: Path) -> tuple[list[WorldSpec], list[str]]:
    """The worlds of ``--worlds DIR`` that load, and a line for each file that does not (each
    also warned about on stderr as it is skipped): one bad file does not stop an evaluation.

    :raises UserError: not a directory, no world files, or none of them loads
    """
    if not directory.is_dir():
        raise UserError(f"--worlds {directory}: not a directory")
    files = sorted(directory.glob("*.json"))
    if not files:
        raise UserError(f"--worlds {directory}: no *.json world files")
    from flightsim.worlds.world import load_world

    worlds, bad = [], []
    for f in files:
        try:
            load_world(f)  # checked before any worker starts
        except UserError as exc:
            bad.append(str(exc))
            print(f"avoid-train: warning: skipping {exc}", file=sys.stderr)
            continue
        worlds.append(WorldSpec(name=f.stem, path=str(f.resolve())))
    if not worlds:
        raise UserError(f"--worlds {directory}: none of its {len(files)} world files loads")
    return worlds, bad


def worlds_from_args(args: argparse.Namespace, env_config: Any = None) -> list[WorldSpec]:
    """The generated worlds ``--seeds`` names; the goal task's when ``env_config`` is one."""
    if hasattr(env_config, "families"):
        return _goal_worlds_from_args(args, env_config)
    from flightsim.envs.env import TRAIN_SEED_OFFSET

    args.first_seed = 0 if args.first_seed is None else args.first_seed
    if args.difficulty is None:
        args.difficulty = 0.5
    first, last = args.first_seed, args.first_seed + args.seeds - 1
    if args.seeds < 1 or first < 0 or last >= TRAIN_SEED_OFFSET:
        raise UserError(
            f"--first-seed {first} --seeds {args.seeds}: world seeds must lie in 0..{TRAIN_SEED_OFFSET - 1} "
            "(seeds from there up are training worlds)"
        )
    if not 0.0 <= args.difficulty <= 1.0:
        raise UserError(f"--difficulty must be in [0, 1], got {args.difficulty}")
    return [WorldSpec(name=f"seed-{s}", seed=s, difficulty=args.difficulty) for s in range(first, last + 1)]


def _goal_worlds_from_args(args: argparse.Namespace, env_config: Any) -> list[WorldSpec]:
    from flightsim.envs import seeds

    first = seeds.TEST.start if args.first_seed is None else args.first_seed
    held_out = [r for r in (seeds.VALIDATION, seeds.TEST) if first in r and first + args.seeds - 1 in r]
    if args.seeds < 1 or not held_out:
        raise UserError(
            f"--first-seed {first} --seeds {args.seeds}: goal-task world seeds must lie within the test "
            f"seeds {seeds.TEST.start}..{seeds.TEST.stop - 1} or the validation seeds "
            f"{seeds.VALIDATION.start}..{seeds.VALIDATION.stop - 1}"
        )
    span = env_config.difficulty_range
    if args.difficulty is not None:
        if not 0.0 <= args.difficulty <= 1.0:
            raise UserError(f"--difficulty must be in [0, 1], got {args.difficulty}")
        span = (args.difficulty, args.difficulty)
    return goal_worlds(env_config.families, first, args.seeds, span)


def evaluate(
    policy: Path | None,
    worlds: Sequence[WorldSpec],
    episodes: int,
    env: dict[str, Any],
    workers: int,
    baselines: Sequence[str] | None = None,
    shield: bool = False,
    env_id: str = AVOID_ENV_ID,
    executor: str = "local",
    address: str | None = None,
    shield_config: ShieldConfig | None = None,
    bar: bool = False,
) -> tuple[dict[str, Any], list[EpisodeResult]]:
    """Evaluate ``policy`` (optional) and ``baselines`` on ``worlds``: (report dict, episode results).

    :param baselines: default: the task's (:data:`BASELINES` or :data:`GOAL_BASELINES`)
    :param shield: every controller behind the companion's safety shield
    :param env_id: the task
    :param shield_config: the shield's limits (None: the defaults)
    :param executor: one of :data:`EXECUTORS` (see :func:`make_executor`; ``local`` with one worker
        runs in this process)
    :param address: the Ray cluster to join (``ray`` only; default: start a local Ray)
    :param bar: show a progress bar of the episodes on stderr, with the time left
    """
    if baselines is None:
        baselines = GOAL_BASELINES if env_id == NAV_ENV_ID else BASELINES
    controllers = (
        [ControllerSpec("policy", str(policy), "policy", shield, shield_config)] if policy else []
    ) + [ControllerSpec(b, shield=shield, shield_config=shield_config) for b in baselines]
    tasks = make_tasks(controllers, worlds, episodes, env, env_id)
    with contextlib.ExitStack() as stack:
        local = workers <= 1 and executor == "local"
        pool = None if local else stack.enter_context(make_executor(workers, executor, address))
        # the bar once the executor stands: a Ray that cannot start is one line, no bar before it
        progress = stack.enter_context(Progress(len(tasks), "episodes", "episode")) if bar else None
        results = run_tasks(tasks, pool, progress)
    return report(results, worlds), results


def add_flight_arguments(parser: argparse.ArgumentParser) -> None:
    """The arguments that say where and how an episode is flown (``evaluate`` and ``trace``): the
    worlds, the config and its overrides, the shield and the autopilot response."""
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--worlds", type=Path, help="directory of world JSON files")
    where.add_argument(
        "--seeds",
        type=int,
        help="evaluate on N held-out generated worlds (seeds from --first-seed; goal task: N per family)",
    )
    parser.add_argument(
        "--first-seed",
        type=int,
        help="first world seed for --seeds (default 0; goal task: the first test seed)",
    )
    parser.add_argument(
        "--difficulty",
        type=float,
        help="generator difficulty for --seeds (default 0.5; goal task: spread over env.difficulty_range)",
    )
    parser.add_argument(
        "--config",
        type=Path,
        help="training config whose task and [env] table to fly in (default: the policy's own, from an "
        ".onnx file's metadata or a checkpoint's run directory; else the avoidance task's env defaults)",
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override an [env] key of the config, e.g. --set env.max_steps=300",
    )
    parser.add_argument(
        "--shield",
        action="store_true",
        help="fly every controller behind the companion's safety shield, as in flight (the config's "
        "[env.shield_limits]: the default limits unless it sets some)",
    )
    parser.add_argument(
        "--shield-config",
        type=Path,
        metavar="TOML",
        help="a companion config whose [shield] table gives the shield's limits (implies --shield)",
    )
    parser.add_argument(
        "--autopilot-response",
        metavar="NAME",
        help="how the autopilot answers the setpoints (sets env.autopilot_response): ideal, the calibrated "
        "px4 or ardupilot firmware response, or random per episode (default: the config's, else ideal)",
    )


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--policy", type=Path, help="policy to evaluate (.onnx or SB3 .zip); without one, the baselines alone"
    )
    parser.add_argument(
        "--baselines",
        metavar="NAMES",
        help="comma-separated baselines to fly beside the policy (default: the task's; empty: none)",
    )
    add_flight_arguments(parser)
    parser.add_argument("--episodes", type=int, default=1, help="episodes per world")
    parser.add_argument(
        "--workers",
        type=int,
        default=0,
        help="episodes at once: processes or a local Ray's CPUs (0: one per core)",
    )
    parser.add_argument(
        "--executor",
        choices=EXECUTORS,
        default="local",
        help="run episodes in a local process pool, or as Ray tasks (the [ray] extra)",
    )
    parser.add_argument(
        "--address",
        metavar="ADDR",
        help="with --executor ray: the cluster to join (auto, HOST:PORT or ray://HOST:10001; "
        "default: start a local Ray)",
    )
    parser.add_argument("--per-world", action="store_true", help="print a row per world, not only the totals")
    parser.add_argument("--json", type=Path, help="write the full report here")
    parser.add_argument("--png", type=Path, help="draw the trajectories over each world here")


def parse_baselines(value: str | None, env_id: str, flag: str = "--baselines") -> list[str] | None:
    """``--baselines``: None (not given: the task's), or the names, each checked against the task's
    (``flag``: the option named in the error)."""
    if value is None:
        return None
    known = (
        GOAL_BASELINES + TRACK_BASELINES + PRIVILEGED_GOAL_CONTROLLERS if env_id == NAV_ENV_ID else BASELINES
    ) + ATTACKERS
    names = [name.strip() for name in value.split(",") if name.strip()]
    unknown = [name for name in names if name not in known]
    if unknown:
        raise UserError(
            f"{flag}: {unknown[0]!r} is not a baseline of this task; known: {', '.join(known)}"
        )
    return names


def read_shield_table(path: Path) -> ShieldConfig:
    """The ``[shield]`` table of a companion config (the file the drone flies; its other tables are
    not read), checked as the companion checks it.

    :raises UserError: naming the file when it has no ``[shield]`` table, or the key that is wrong
    """
    table = load_toml(path).get("shield")
    if not isinstance(table, dict):
        raise UserError(f"--shield-config {path}: no [shield] table")
    return from_dict(CompanionShieldConfig, table, "shield.")


def run_config(policy: Path | None) -> Path | None:
    """The ``config.toml`` of the run an SB3 checkpoint (``.zip``) comes from, when there is one."""
    if policy is None or Path(policy).suffix != ".zip":
        return None
    from training.export import find_run_config

    try:
        return find_run_config(Path(policy))
    except UserError:
        return None


@dataclass(frozen=True)
class Flight:
    """What :func:`add_flight_arguments` said, loaded and checked.

    :param config: the training config (its ``env`` table, with the overrides)
    :param env_config: its env's config object
    :param worlds: the worlds named
    :param shield_config: the shield's limits
    :param shield: whether controllers fly behind the shield
    :param bad_worlds: the world files of ``--worlds`` skipped, each with what is wrong with it
    """

    config: Any
    env_config: Any
    worlds: list[WorldSpec]
    shield_config: ShieldConfig
    shield: bool
    bad_worlds: tuple[str, ...] = ()


def load_flight(args: argparse.Namespace) -> Flight:
    """The :class:`Flight` of :func:`add_flight_arguments`' arguments.

    :raises UserError: a bad config, override, world or shield table, in one line
    """
    from training.config import check_model_task, load_train_config, model_train_config

    overrides = list(args.overrides)
    if args.autopilot_response:
        overrides.append(f"env.autopilot_response={args.autopilot_response}")
    policy = getattr(args, "policy", None)
    exported = policy is not None and Path(policy).suffix == ".onnx"
    if exported and args.config is None:
        config = model_train_config(Path(policy), overrides)
    else:
        config = load_train_config(args.config or run_config(policy), overrides)
        if exported and args.config is not None:
            check_model_task(Path(policy), config, args.config)
    env_config = config.env_config()
    bad: list[str] = []
    if args.worlds is not None:
        worlds, bad = world_files(Path(args.worlds))
    else:
        worlds = worlds_from_args(args, env_config)
    # the limits the config trained behind (the defaults unless it says), unless a flight config is named
    limits = read_shield_table(args.shield_config) if args.shield_config else env_config.shield_limits
    shield = args.shield or args.shield_config is not None
    return Flight(config, env_config, worlds, limits, shield, tuple(bad))


def command(args: argparse.Namespace) -> int:
    if args.episodes < 1:
        raise UserError("--episodes must be at least 1")
    if args.address is not None and args.executor != "ray":
        raise UserError("--address names a Ray cluster: it needs --executor ray")
    if args.address is not None and args.workers:
        raise UserError("--workers sizes a local pool or Ray; with --address the cluster's CPUs decide")
    flight = load_flight(args)
    config, env_config, worlds = flight.config, flight.env_config, flight.worlds
    limits, shield = flight.shield_config, flight.shield
    workers = args.workers or (os.cpu_count() or 1)
    if args.policy is not None:
        load_policy(args.policy, env_config, config.n_stack)  # fail fast, with a one-line error
    baselines = parse_baselines(args.baselines, config.env_id)
    if args.policy is None and baselines == []:
        raise UserError("--baselines '' and no --policy: nothing to evaluate")
    summary, results = evaluate(
        args.policy, worlds, args.episodes, config.env, workers, baselines=baselines, shield=shield,
        env_id=config.env_id, executor=args.executor, address=args.address, shield_config=limits, bar=True,
    )  # fmt: skip
    summary["env_id"] = config.env_id
    summary["policy"] = None if args.policy is None else str(args.policy)
    summary["shield"] = asdict(limits) if shield else None
    print(format_table(summary, per_world=args.per_world or args.worlds is not None))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(summary, indent=1) + "\n")
        print(f"wrote {args.json}")
    if args.png:
        plot_trajectories(results, worlds, args.png, env_config)
        print(f"wrote {args.png}")
    if flight.bad_worlds:  # the user's error, said at the end where it is not scrolled away
        print(f"avoid-train: error: {len(flight.bad_worlds)} world file(s) skipped: "
              + "; ".join(flight.bad_worlds), file=sys.stderr)
        return 2
    return 0
