"""``avoid-train evaluate``: fly a policy and two baselines over the same worlds and compare them.

The task is the training config's ``env_id``.

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
(:data:`flightsim.seeds.TEST`), difficulties spread evenly over the config's ``difficulty_range``.

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
import json
import logging
import math
import os
import zlib
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from companion.errors import UserError
from companion.framestack import FrameStack
from companion.scan import N_BINS
from companion.shield import Command, SafetyShield, ShieldConfig, command_from_action
from companion.tomlconfig import from_dict, load_toml
from training.config import NEAR_MISS_DISTANCE, STEP_SECONDS, SUCCESS_MIN_MEAN_SPEED

log = logging.getLogger(__name__)

BASELINES = ("gap_follower", "random")
GOAL_BASELINES = ("goal_follower", "straight_line")
#: flown only when named: not a baseline a drone could fly, it reads the simulator's truth (the
#: DAgger teachers, :mod:`training.path_expert`, :mod:`training.predictive_expert`): what
#: imitation can reach
PRIVILEGED_GOAL_CONTROLLERS = ("path_expert", "predictive_expert", "robust_expert")
AVOID_ENV_ID = "flightsim/LidarAvoid-v0"
NAV_ENV_ID = "flightsim/LidarNav-v0"


class Controller(Protocol):
    """Anything that turns one scan per step into an action in ``[-1, 1]²``."""

    def reset(self, scan: np.ndarray) -> np.ndarray: ...

    def act(self, scan: np.ndarray) -> np.ndarray: ...


class StackedPolicyController:
    """A stacked-scan policy behind the companion's :class:`FrameStack` (as on the drone).

    :param act_stacked: maps one ``(n_stack * frame_size,)`` observation to a ``(2,)`` action
    :param n_stack: stack depth
    :param frame_size: floats per frame (360 scan bins, 365 with the goal features)
    """

    def __init__(
        self, act_stacked: Callable[[np.ndarray], np.ndarray], n_stack: int, frame_size: int = N_BINS
    ) -> None:
        self._act = act_stacked
        self._stack = FrameStack(n_stack, frame_size)

    def reset(self, scan: np.ndarray) -> np.ndarray:
        return np.asarray(self._act(self._stack.reset(scan)), dtype=np.float32)

    def act(self, scan: np.ndarray) -> np.ndarray:
        return np.asarray(self._act(self._stack.push(scan)), dtype=np.float32)


class ShieldedController:
    """Another controller's actions filtered by the companion's safety shield, as in flight.

    :param inner: the controller whose actions are filtered
    :param shield: the companion's shield (its limits are the flight configuration's)
    :param max_speed: m/s that an action of 1 stands for (the env's action scaling)
    :param max_yaw_rate: rad/s that an action of 1 stands for
    :param velocity: the measured body velocity (forward, left) now, as the companion reads it from
        the autopilot (the env's :meth:`~flightsim.env.LidarAvoidEnv.measured_body_velocity`)
    :param lateral: where the shield's sideways brake goes (the env's
        :meth:`~flightsim.env.LidarAvoidEnv.command_lateral`), since an action carries none
    """

    def __init__(
        self,
        inner: Controller,
        shield: SafetyShield,
        max_speed: float,
        max_yaw_rate: float,
        velocity: Callable[[], np.ndarray] | None = None,
        lateral: Callable[[float], None] | None = None,
    ) -> None:
        self._inner = inner
        self.shield = shield
        self._scale = (max_speed, max_yaw_rate)
        self._velocity = velocity
        self._lateral = lateral
        #: the last (requested, sent) commands, for a trace (``avoid-train trace``)
        self.last: tuple[Command, Command] | None = None

    def reset(self, scan: np.ndarray) -> np.ndarray:
        self.shield.reset()
        return self._filter(self._inner.reset(scan), scan)

    def act(self, scan: np.ndarray) -> np.ndarray:
        return self._filter(self._inner.act(scan), scan)

    def _filter(self, action: np.ndarray, scan: np.ndarray) -> np.ndarray:
        max_speed, max_yaw_rate = self._scale
        scan = scan[:N_BINS]  # a goal frame's scan part
        measured = None
        if self._velocity is not None:
            v = self._velocity()
            measured = (float(v[0]), float(v[1]))
        requested = command_from_action(action, max_speed, max_yaw_rate)
        safe = self.shield.filter(requested, scan, STEP_SECONDS, measured)
        self.last = (requested, safe)
        if self._lateral is not None:
            self._lateral(safe.lateral)
        return np.array([safe.forward / max_speed, safe.yaw_rate / max_yaw_rate], dtype=np.float32)


def sb3_controller(model: Any, n_stack: int, frame_size: int = N_BINS) -> StackedPolicyController:
    """An SB3 model acting deterministically (what ``model.predict(..., deterministic=True)`` gives)."""

    def act(obs: np.ndarray) -> np.ndarray:
        action, _ = model.predict(obs[None, :], deterministic=True)
        return action[0]

    return StackedPolicyController(act, n_stack, frame_size)


# --- what is evaluated, as picklable descriptions (tasks cross process boundaries) ------------------


@dataclass(frozen=True)
class ControllerSpec:
    """What to build in a worker: ``kind`` is ``policy`` (``path``) or one of :data:`BASELINES` /
    :data:`GOAL_BASELINES` / :data:`PRIVILEGED_GOAL_CONTROLLERS`; ``shield``: behind the
    companion's safety shield, with ``shield_config``'s limits (None: the defaults)."""

    kind: str
    path: str = ""
    name: str = ""
    shield: bool = False
    shield_config: ShieldConfig | None = None

    @property
    def label(self) -> str:
        return (self.name or self.kind) + ("+shield" if self.shield else "")


@dataclass(frozen=True)
class WorldSpec:
    """A world: a JSON file (``path``) or a generated one (``seed``, ``difficulty``; of ``family``
    for the goal task)."""

    name: str
    path: str = ""
    seed: int = -1
    difficulty: float = 0.5
    family: str = ""

    def reset_options(self) -> dict[str, Any]:
        if self.path:
            return {"world": self.path}
        family = {"family": self.family} if self.family else {}
        return {**family, "world_seed": self.seed, "difficulty": self.difficulty}

    def world(self, vehicle_radius: float) -> Any:
        """The :class:`~flightsim.world.World` itself (for pictures)."""
        from flightsim.families import generate_family_world
        from flightsim.world import generate_world, load_world

        if self.path:
            return load_world(self.path, vehicle_radius=vehicle_radius)
        if self.family:
            return generate_family_world(
                self.family, self.seed, self.difficulty, vehicle_radius=vehicle_radius
            )
        return generate_world(self.seed, self.difficulty, vehicle_radius)


@dataclass(frozen=True)
class EpisodeTask:
    controller: ControllerSpec
    world: WorldSpec
    episode: int
    env: dict[str, Any]
    seed: int
    env_id: str = AVOID_ENV_ID


@dataclass
class EpisodeResult:
    """One episode's figures (distances in metres, speed in m/s)."""

    controller: str
    world: str
    episode: int
    steps: int
    max_steps: int
    collision: bool
    distance: float
    mean_speed: float
    min_clearance: float
    near_misses: int
    success: bool
    trajectory: list[tuple[float, float]] = field(default_factory=list, repr=False)
    #: the goal task's (0 waypoints: the avoidance task)
    family: str = ""
    waypoints: int = 0
    waypoints_reached: int = 0
    timeout: bool = False
    time_s: float = 0.0
    shortest_path_m: float = 0.0
    #: the autopilot response flown (:class:`~flightsim.autopilot_response.ResponseParams`'s fields)
    response: dict[str, Any] = field(default_factory=lambda: {"name": "ideal"})


def is_success(collision: bool, steps: int, max_steps: int, distance: float, dt: float) -> bool:
    """The evaluation's definition of success (see the module docstring)."""
    return (not collision) and steps >= max_steps and distance >= SUCCESS_MIN_MEAN_SPEED * max_steps * dt


def run_episode(
    env: Any, controller: Controller, reset_options: dict[str, Any], seed: int | None = None
) -> EpisodeResult:
    """Fly one episode of ``env`` (a ``LidarAvoidEnv`` or a ``LidarNavEnv``) with ``controller``.

    :param env: the simulator environment (unwrapped observation: one scan)
    :param controller: turns scans into actions
    :param reset_options: ``{"world": ...}`` or ``{"world_seed": ..., "difficulty": ...}``
    :param seed: reset seed (sensor noise, randomisation); ``None`` leaves the env's generator as is
    """
    obs, info = env.reset(seed=seed, options=reset_options)
    params = env.unwrapped.response_params
    action = controller.reset(obs)
    trajectory = [_xy(info)]
    clearance = float(info["min_distance"])
    min_clearance, near_misses, inside = clearance, 0, clearance < NEAR_MISS_DISTANCE
    steps, collision = 0, False
    while True:
        obs, _, terminated, truncated, info = env.step(action)
        steps += 1
        trajectory.append(_xy(info))
        clearance = float(info["min_distance"])
        min_clearance = min(min_clearance, clearance)
        if clearance < NEAR_MISS_DISTANCE and not inside:
            near_misses += 1
        inside = clearance < NEAR_MISS_DISTANCE
        collision = collision or bool(info["collision"])
        if terminated or truncated:
            break
        action = controller.act(obs)
    max_steps = int(env.unwrapped.config.max_steps)
    dt = STEP_SECONDS
    distance = float(info["distance"])
    goal: dict[str, Any] = {"success": is_success(collision, steps, max_steps, distance, dt)}
    if "waypoints" in info:  # the goal task: success is the env's (every waypoint, in time)
        goal = {
            "success": bool(info["success"]),
            "family": str(info["family"]),
            "waypoints": int(info["waypoints"]),
            "waypoints_reached": int(info["waypoint"]),
            "timeout": bool(truncated and not info["success"]),
            "time_s": steps * dt,
            "shortest_path_m": float(info["shortest_path_m"]),
        }
    return EpisodeResult(
        controller="",
        world="",
        episode=0,
        steps=steps,
        max_steps=max_steps,
        collision=collision,
        distance=distance,
        mean_speed=distance / max(steps * dt, 1e-9),
        min_clearance=max(min_clearance, 0.0),
        near_misses=near_misses,
        trajectory=trajectory,
        response=asdict(params) if params is not None else {"name": "ideal"},
        **goal,
    )


def _xy(info: dict[str, Any]) -> tuple[float, float]:
    p = info["position"]
    return (round(float(p[0]), 3), round(float(p[1]), 3))


# --- workers ---------------------------------------------------------------------------------------

_WORKER_CACHE: dict[Any, Any] = {}


def build_controller(
    spec: ControllerSpec,
    env_config: Any,
    seed: int,
    n_stack: int = 4,
    velocity: Callable[[], np.ndarray] | None = None,
    lateral: Callable[[float], None] | None = None,
    env: Any = None,
) -> Controller:
    """Build the controller ``spec`` describes, behind the shield if it says so (the shield braking
    and capping yaw as the env's autopilot response does, watching ``velocity`` as in flight).

    :param env: the unwrapped env the controller flies, for a privileged one
        (:data:`PRIVILEGED_GOAL_CONTROLLERS`)
    """
    controller = _bare_controller(spec, env_config, seed, n_stack, env)
    if not spec.shield:
        return controller
    limits = spec.shield_config or ShieldConfig()
    shield = SafetyShield(limits, float(env_config.scan.max_range), env_config.autopilot_response)
    return ShieldedController(
        controller, shield, float(env_config.max_speed), float(env_config.max_yaw_rate), velocity, lateral
    )


def _teacher_controller(kind: str, env: Any) -> Controller:
    """A privileged teacher flying ``env`` (imported here: evaluation needs them only when named)."""
    from training.dagger import TEACHERS
    from training.path_expert import ExpertController

    return ExpertController(TEACHERS[kind](env))


def _bare_controller(
    spec: ControllerSpec, env_config: Any, seed: int, n_stack: int, env: Any = None
) -> Controller:
    """The controller itself (policies are loaded once per process)."""
    from training.baselines import (
        GapFollower,
        GapFollowerConfig,
        GoalFollower,
        GoalFollowerConfig,
        RandomController,
        StraightLine,
    )

    if spec.kind == "random":
        return RandomController(seed)
    if spec.kind == "gap_follower":
        return GapFollower(GapFollowerConfig(max_range=float(env_config.scan.max_range)))
    if spec.kind == "goal_follower":
        return GoalFollower(env_config.layout, GoalFollowerConfig(max_range=float(env_config.scan.max_range)))
    if spec.kind == "straight_line":
        return StraightLine(env_config.layout)
    if spec.kind in PRIVILEGED_GOAL_CONTROLLERS:
        if env is None:
            raise ValueError(f"{spec.kind} reads the env it flies: pass env")
        return _teacher_controller(spec.kind, env)
    if spec.kind != "policy":
        raise ValueError(f"unknown controller kind {spec.kind!r}")
    # keyed by modification time too: training re-saves its evaluation model under one name
    key = ("policy", spec.path, os.stat(spec.path).st_mtime_ns, env_config.scan.max_range)
    if key not in _WORKER_CACHE:
        for old in [k for k in _WORKER_CACHE if k[0] == "policy"]:
            del _WORKER_CACHE[old]
        _WORKER_CACHE[key] = load_policy(Path(spec.path), env_config, n_stack)
    act, stack = _WORKER_CACHE[key]
    return StackedPolicyController(act, stack, _layout(env_config).frame_size)


def _layout(env_config: Any) -> Any:
    """The observation layout an env config produces (goal configs carry theirs)."""
    from companion.observation import ObservationLayout

    return getattr(env_config, "layout", None) or ObservationLayout(n_bins=N_BINS)


def load_policy(
    path: Path, env_config: Any, n_stack: int = 4
) -> tuple[Callable[[np.ndarray], np.ndarray], int]:
    """``(act_stacked, n_stack)`` for an ``.onnx`` file (companion OnnxPolicy) or an SB3 ``.zip``."""
    if not path.is_file():
        raise UserError(f"policy file not found: {path}")
    if path.suffix == ".onnx":
        from companion.policy import OnnxPolicy, PolicySpec
        from companion.scan import BIN_CONVENTION

        spec = PolicySpec(
            stack=n_stack,
            n_bins=N_BINS,
            max_range=float(env_config.scan.max_range),
            bin_convention=BIN_CONVENTION,
            max_speed=float(env_config.max_speed),
            max_yaw_rate=float(env_config.max_yaw_rate),
            layout=_layout(env_config),
        )
        try:
            policy = OnnxPolicy(path, spec)
        except UserError:
            raise
        except Exception as exc:
            raise UserError(f"{path}: cannot load the ONNX policy: {exc}") from None
        return policy.act, n_stack
    if path.suffix == ".zip":
        import torch

        from training.export import load_model

        torch.set_num_threads(1)  # one episode per process: more threads only contend for the cores
        model = load_model(path)
        frame = _layout(env_config).frame_size
        size = int(model.observation_space.shape[0])
        if size % frame:
            raise UserError(f"{path}: observation of {size} floats is not a stack of {frame}-float frames")
        return sb3_controller(model, size // frame, frame)._act, size // frame
    raise UserError(f"{path}: a policy is an .onnx or a stable-baselines3 .zip file")


def _worker_env(env_dict: dict[str, Any], env_id: str = AVOID_ENV_ID) -> Any:
    key = ("env", env_id, json.dumps(env_dict, sort_keys=True))
    if key not in _WORKER_CACHE:
        _WORKER_CACHE[key] = make_eval_env(env_dict, env_id)
    return _WORKER_CACHE[key]


def make_eval_env(env_dict: dict[str, Any], env_id: str = AVOID_ENV_ID) -> Any:
    """A single simulator environment of ``env_id`` from an ``[env]`` table (strictly checked)."""
    if env_id == NAV_ENV_ID:
        from flightsim.nav_env import LidarNavEnv, NavEnvConfig

        return LidarNavEnv(from_dict(NavEnvConfig, env_dict, prefix="env."))
    from flightsim.env import EnvConfig, LidarAvoidEnv

    return LidarAvoidEnv(from_dict(EnvConfig, env_dict, prefix="env."))


def run_task(task: EpisodeTask, wrap: Callable[[Controller, Any], Controller] | None = None) -> EpisodeResult:
    """Run one :class:`EpisodeTask` (in a worker process or in-line).

    :param wrap: given the controller and the unwrapped env, the controller to fly instead (one that
        watches it: :class:`training.trace.Tracer`)
    """
    env = _worker_env(task.env, task.env_id)
    unwrapped = env.unwrapped
    controller: Controller = build_controller(
        task.controller, unwrapped.config, task.seed,
        velocity=unwrapped.measured_body_velocity, lateral=unwrapped.command_lateral, env=unwrapped,
    )  # fmt: skip
    if wrap is not None:
        controller = wrap(controller, unwrapped)
    result = run_episode(env, controller, task.world.reset_options(), seed=task.seed)
    result.controller, result.world, result.episode = task.controller.label, task.world.name, task.episode
    return result


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


def run_tasks(tasks: Sequence[EpisodeTask], executor: Executor | None = None) -> list[EpisodeResult]:
    """Run ``tasks`` in ``executor`` (or in this process when ``None``), results in task order."""
    if executor is None:
        return [run_task(t) for t in tasks]
    return list(executor.map(run_task, tasks))


def make_tasks(
    controllers: Iterable[ControllerSpec],
    worlds: Sequence[WorldSpec],
    episodes: int,
    env: dict[str, Any],
    env_id: str = AVOID_ENV_ID,
) -> list[EpisodeTask]:
    """Every controller × world × episode; every controller flies the same reset seed there
    (:func:`episode_seed`)."""
    return [
        EpisodeTask(controller=c, world=w, episode=k, env=env, seed=episode_seed(w, k, env_id), env_id=env_id)
        for c in controllers
        for w in worlds
        for k in range(episodes)
    ]


def episode_seed(world: WorldSpec, episode: int, env_id: str) -> int:
    """The reset seed of ``episode`` on ``world``: what the env draws from it (the autopilot
    response, sensor noise, mass, wind) differs from world to world.

    Goal task: ``crc32("<world name>/<episode>")``, so each world flies its own random response
    draw (with the episode index alone, every world flew the same one). Avoidance task: the
    episode index, as every avoidance figure so far was measured (its responses are fixed ones).
    """
    if env_id != NAV_ENV_ID:
        return episode
    return zlib.crc32(f"{world.name}/{episode}".encode())


# --- summaries -------------------------------------------------------------------------------------


def summarise(results: Sequence[EpisodeResult]) -> dict[str, Any]:
    """Success rate, collisions, mean distance and speed, worst clearance and near misses of ``results``
    (and for the goal task :func:`goal_summary`'s figures too)."""
    n = len(results)
    if n == 0:
        return {"episodes": 0}
    if any(r.waypoints for r in results):
        return goal_summary(results)
    return {
        "episodes": n,
        "success_rate": sum(r.success for r in results) / n,
        "collisions": sum(r.collision for r in results),
        "mean_distance_m": float(np.mean([r.distance for r in results])),
        "mean_speed_mps": float(np.mean([r.mean_speed for r in results])),
        "min_clearance_m": float(min(r.min_clearance for r in results)),
        "near_misses": sum(r.near_misses for r in results),
    }


def goal_summary(results: Sequence[EpisodeResult]) -> dict[str, Any]:
    """The goal task's figures: success, collision and timeout rates, mean time to goal and SPL (the
    last two over successes only; ``spl_all`` counts a failure as 0, as Anderson et al. define it)."""
    n = len(results)
    won = [r for r in results if r.success]
    spl = [r.shortest_path_m / max(r.distance, r.shortest_path_m, 1e-9) for r in won]
    return {
        "episodes": n,
        "success_rate": len(won) / n,
        "collision_rate": sum(r.collision for r in results) / n,
        "timeout_rate": sum(r.timeout for r in results) / n,
        "mean_time_s": float(np.mean([r.time_s for r in won])) if won else None,
        "spl": float(np.mean(spl)) if won else None,
        "spl_all": float(np.sum(spl)) / n,
        "waypoints_reached": sum(r.waypoints_reached for r in results)
        / max(sum(r.waypoints for r in results), 1),
        "collisions": sum(r.collision for r in results),
        "mean_distance_m": float(np.mean([r.distance for r in results])),
        "min_clearance_m": float(min(r.min_clearance for r in results)),
        "near_misses": sum(r.near_misses for r in results),
    }


def report(results: Sequence[EpisodeResult], worlds: Sequence[WorldSpec]) -> dict[str, Any]:
    """The evaluation as a JSON-able dict: per controller, overall and per world, plus every episode."""
    controllers = list(dict.fromkeys(r.controller for r in results))
    goal = any(r.waypoints for r in results)
    out: dict[str, Any] = {
        "success_definition": (
            "every waypoint reached in order, no collision, within the world's time limit; "
            "mean_time_s and spl over successes only"
            if goal
            else f"no collision for max_steps and mean speed >= {SUCCESS_MIN_MEAN_SPEED} m/s "
            f"(40 m over the default 100 s)"
        )
        + f"; near miss: clearance < {NEAR_MISS_DISTANCE} m",
        "worlds": [asdict(w) for w in worlds],
        "controllers": {},
    }
    for c in controllers:
        mine = [r for r in results if r.controller == c]
        out["controllers"][c] = {
            "overall": summarise(mine),
            "per_world": {w.name: summarise([r for r in mine if r.world == w.name]) for w in worlds},
        }
        if goal:
            out["controllers"][c]["per_family"] = {
                f: summarise([r for r in mine if r.family == f])
                for f in dict.fromkeys(r.family for r in mine)
            }
    out["episodes"] = [{k: v for k, v in asdict(r).items() if k != "trajectory"} for r in results]
    return out


def format_table(summary: dict[str, Any], per_world: bool) -> str:
    """A readable text table of :func:`report`'s output."""
    if any("per_family" in data for data in summary["controllers"].values()):
        return format_goal_table(summary, per_world)
    header = f"{'controller':<19} {'world':<16} {'eps':>4} {'success':>8} {'coll':>5} {'dist m':>8} "
    header += f"{'speed':>6} {'min clr':>8} {'near':>5}"
    lines = [header, "-" * len(header)]

    def row(name: str, world: str, s: dict[str, Any]) -> str:
        return (
            f"{name:<19} {world:<16} {s['episodes']:>4} {100 * s['success_rate']:>7.1f}% "
            f"{s['collisions']:>5} {s['mean_distance_m']:>8.1f} {s['mean_speed_mps']:>6.2f} "
            f"{s['min_clearance_m']:>8.2f} {s['near_misses']:>5}"
        )

    for name, data in summary["controllers"].items():
        if per_world:
            for world, s in data["per_world"].items():
                lines.append(row(name, world, s))
        lines.append(row(name, "ALL", data["overall"]))
    return "\n".join(lines)


#: the usual colour of each controller; a "+shield" variant keeps it unless its unshielded self is
#: in the same picture, and any other controller takes the next free colour of the palette
CONTROLLER_COLOURS = {"policy": "tab:blue", "gap_follower": "tab:orange", "random": "tab:gray"}
PALETTE = ("tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan", "navy", "black")


def controller_colours(names: Iterable[str]) -> dict[str, str]:
    """A distinct colour for every controller label (``policy``, ``policy+shield``, custom names)."""
    labels = sorted(set(names), key=lambda n: (n.endswith("+shield"), n))  # unshielded ones choose first
    colours: dict[str, str] = {}
    for label in labels:
        preferred = CONTROLLER_COLOURS.get(label.removesuffix("+shield"))
        free = [c for c in (preferred, *PALETTE) if c is not None and c not in colours.values()]
        colours[label] = free[0] if free else f"C{len(colours) % 10}"
    return colours


def format_goal_table(summary: dict[str, Any], per_world: bool) -> str:
    """The goal task's table: a row per family (and per world with ``per_world``), then overall."""
    header = f"{'controller':<22} {'family/world':<24} {'eps':>4} {'success':>8} {'coll':>6} {'timeout':>8} "
    header += f"{'time s':>7} {'SPL':>5} {'min clr':>8}"
    lines = [header, "-" * len(header)]

    def row(name: str, where: str, s: dict[str, Any]) -> str:
        time_s = "-" if s["mean_time_s"] is None else f"{s['mean_time_s']:.1f}"
        spl = "-" if s["spl"] is None else f"{s['spl']:.2f}"
        return (
            f"{name:<22} {where:<24} {s['episodes']:>4} {100 * s['success_rate']:>7.1f}% "
            f"{100 * s['collision_rate']:>5.1f}% {100 * s['timeout_rate']:>7.1f}% {time_s:>7} {spl:>5} "
            f"{s['min_clearance_m']:>8.2f}"
        )

    for name, data in summary["controllers"].items():
        if per_world:
            lines += [row(name, world, s) for world, s in data["per_world"].items()]
        lines += [row(name, family, s) for family, s in data["per_family"].items()]
        lines.append(row(name, "ALL", data["overall"]))
    return "\n".join(lines)


def plot_trajectories(
    results: Sequence[EpisodeResult], worlds: Sequence[WorldSpec], out: Path, env_config: Any
) -> None:
    """Write :func:`trajectory_figure` as a PNG."""
    fig = trajectory_figure(results, worlds, env_config)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(str(out), dpi=100 if len(worlds) <= 16 else 50)  # a 100-world grid stays ~1 MB


def trajectory_figure(results: Sequence[EpisodeResult], worlds: Sequence[WorldSpec], env_config: Any) -> Any:
    """One panel per world (drawn by :func:`flightsim.render.draw_top_down`), each controller's first
    episode over it in its own colour (:func:`controller_colours`), one legend for all; a red cross
    marks a collision."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from flightsim.render import draw_top_down

    colours = controller_colours(r.controller for r in results)
    cols = min(len(worlds), 10 if len(worlds) > 16 else 4)
    rows = math.ceil(len(worlds) / cols)
    fig = Figure(figsize=(2.8 * cols, 2.4 * rows + 0.6))
    FigureCanvasAgg(fig)  # attaches itself to the figure: no pyplot state in worker processes
    legend: dict[str, Any] = {}
    for i, w in enumerate(worlds):
        ax = fig.add_subplot(rows, cols, i + 1)
        radius = env_config.vehicle_radius
        draw_top_down(w.world(radius), ax=ax, vehicle_radius=radius)
        for r in results:
            if r.world != w.name or r.episode != 0:
                continue
            xy = np.asarray(r.trajectory)
            (line,) = ax.plot(xy[:, 0], xy[:, 1], lw=0.9, color=colours[r.controller], zorder=5)
            legend.setdefault(r.controller, line)
            if r.collision:
                ax.plot(xy[-1, 0], xy[-1, 1], "x", color="red", ms=7, mew=2, zorder=6)
        ax.set_title(w.name, fontsize=8)
        ax.set_xlabel("")
        ax.set_ylabel("")
        ax.tick_params(labelsize=5)
    from matplotlib.lines import Line2D

    labels = sorted(legend)
    handles = [legend[n] for n in labels]
    handles.append(Line2D([], [], color="red", marker="x", ls="none", mew=2))
    labels = [*labels, "collision"]
    fig.legend(handles, labels, loc="lower center", ncol=len(handles), fontsize=9)
    fig.tight_layout(rect=(0, 0.6 / fig.get_figheight(), 1, 1))
    return fig


# --- command line ----------------------------------------------------------------------------------


def goal_worlds(
    families: Sequence[str], first_seed: int, n: int, difficulty_range: tuple[float, float]
) -> list[WorldSpec]:
    """``n`` generated goal-task worlds per family, seeds ``first_seed…``, difficulties spread evenly
    over ``difficulty_range`` (world ``k`` at the middle of the ``k``-th of ``n`` equal slices)."""
    low, high = difficulty_range
    return [
        WorldSpec(
            f"{f}-{first_seed + k}",
            seed=first_seed + k,
            difficulty=round(low + (high - low) * (k + 0.5) / n, 3),
            family=f,
        )
        for f in families
        for k in range(n)
    ]


def worlds_from_args(args: argparse.Namespace, env_config: Any = None) -> list[WorldSpec]:
    """The worlds the command line names; ``--seeds`` of the goal task when ``env_config`` is one."""
    if args.worlds is not None:
        directory = Path(args.worlds)
        if not directory.is_dir():
            raise UserError(f"--worlds {directory}: not a directory")
        files = sorted(directory.glob("*.json"))
        if not files:
            raise UserError(f"--worlds {directory}: no *.json world files")
        from flightsim.world import load_world

        for f in files:
            load_world(f)  # a bad world file is the user's error, before any worker starts
        return [WorldSpec(name=f.stem, path=str(f.resolve())) for f in files]
    if hasattr(env_config, "families"):
        return _goal_worlds_from_args(args, env_config)
    from flightsim.env import TRAIN_SEED_OFFSET

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
    from flightsim import seeds

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
) -> tuple[dict[str, Any], list[EpisodeResult]]:
    """Evaluate ``policy`` (optional) and ``baselines`` on ``worlds``: (report dict, episode results).

    :param baselines: default: the task's (:data:`BASELINES` or :data:`GOAL_BASELINES`)
    :param shield: every controller behind the companion's safety shield
    :param env_id: the task
    :param shield_config: the shield's limits (None: the defaults)
    :param executor: one of :data:`EXECUTORS` (see :func:`make_executor`; ``local`` with one worker
        runs in this process)
    :param address: the Ray cluster to join (``ray`` only; default: start a local Ray)
    """
    if baselines is None:
        baselines = GOAL_BASELINES if env_id == NAV_ENV_ID else BASELINES
    controllers = (
        [ControllerSpec("policy", str(policy), "policy", shield, shield_config)] if policy else []
    ) + [ControllerSpec(b, shield=shield, shield_config=shield_config) for b in baselines]
    tasks = make_tasks(controllers, worlds, episodes, env, env_id)
    if workers <= 1 and executor == "local":
        results = run_tasks(tasks)
    else:
        with make_executor(workers, executor, address) as pool:
            results = run_tasks(tasks, pool)
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
        "--config", type=Path, help="training config whose [env] table to fly in (default: env defaults)"
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
        help="fly every controller behind the companion's safety shield (default limits), as in flight",
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
    known = GOAL_BASELINES + PRIVILEGED_GOAL_CONTROLLERS if env_id == NAV_ENV_ID else BASELINES
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
    return from_dict(ShieldConfig, table, "shield.")


@dataclass(frozen=True)
class Flight:
    """What :func:`add_flight_arguments` said, loaded and checked.

    :param config: the training config (its ``env`` table, with the overrides)
    :param env_config: its env's config object
    :param worlds: the worlds named
    :param shield_config: the shield's limits
    :param shield: whether controllers fly behind the shield
    """

    config: Any
    env_config: Any
    worlds: list[WorldSpec]
    shield_config: ShieldConfig
    shield: bool


def load_flight(args: argparse.Namespace) -> Flight:
    """The :class:`Flight` of :func:`add_flight_arguments`' arguments.

    :raises UserError: a bad config, override, world or shield table, in one line
    """
    from training.config import load_train_config

    overrides = list(args.overrides)
    if args.autopilot_response:
        overrides.append(f"env.autopilot_response={args.autopilot_response}")
    config = load_train_config(args.config, overrides)
    env_config = config.env_config()
    worlds = worlds_from_args(args, env_config)
    limits = read_shield_table(args.shield_config) if args.shield_config else ShieldConfig()
    return Flight(config, env_config, worlds, limits, args.shield or args.shield_config is not None)


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
        env_id=config.env_id, executor=args.executor, address=args.address, shield_config=limits,
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
    return 0
