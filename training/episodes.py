"""One evaluation episode: the world (:class:`WorldSpec`), the task that names a controller, a
world, an episode index and its reset seed (:class:`EpisodeTask`, picklable: tasks cross process
boundaries), flying it (:func:`run_task`, :func:`run_episode`) and its figures
(:class:`EpisodeResult`).
"""

from __future__ import annotations

import json
import math
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from companion.common.tomlconfig import from_dict
from training.config import NEAR_MISS_DISTANCE, STEP_SECONDS, SUCCESS_MIN_MEAN_SPEED
from training.controllers import ENV_OVERRIDES, Controller, ControllerSpec, build_controller

AVOID_ENV_ID = "flightsim/LidarAvoid-v0"
NAV_ENV_ID = "flightsim/LidarNav-v0"


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
        """The :class:`~flightsim.worlds.world.World` itself (for pictures)."""
        from flightsim.worlds.families import generate_family_world
        from flightsim.worlds.world import generate_world, load_world

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
    #: the autopilot response flown (:class:`~flightsim.vehicle.autopilot_response.ResponseParams`'s fields)
    response: dict[str, Any] = field(default_factory=lambda: {"name": "ideal"})
    #: the speed of the moving obstacle the episode collided with, m/s (None: no collision with one)
    collision_mover_speed: float | None = None
    #: how long that obstacle had kept its velocity before the contact, up to
    #: :data:`~flightsim.envs.env.MOVER_STEADY_WINDOW_S`, s (None: no collision with one)
    collision_mover_steady_s: float | None = None
    #: the largest difference between the velocity a shield judges by (the env's ``shield_velocity``)
    #: and the true one, m/s: the firmware envelope's ``estimate_error`` bounds it, the simulator's
    #: random walk does not
    max_velocity_error: float = 0.0
    #: the shield's interventions by reason over the episode (empty: flown without a shield)
    shield_counts: dict[str, int] = field(default_factory=dict)


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
    steps, collision, mover_speed, mover_steady = 0, False, None, None
    # what a shield judges the motion by, against the truth (an env without them records 0)
    judged = getattr(env.unwrapped, "shield_velocity", None)
    truth = getattr(env.unwrapped, "true_body_velocity", None)
    velocity_error = 0.0
    while True:
        obs, _, terminated, truncated, info = env.step(action)
        steps += 1
        if judged is not None and truth is not None:
            error = judged() - truth()
            velocity_error = max(velocity_error, math.hypot(float(error[0]), float(error[1])))
        trajectory.append(_xy(info))
        clearance = float(info["min_distance"])
        min_clearance = min(min_clearance, clearance)
        if clearance < NEAR_MISS_DISTANCE and not inside:
            near_misses += 1
        inside = clearance < NEAR_MISS_DISTANCE
        collision = collision or bool(info["collision"])
        if info.get("collision_mover_speed") is not None:
            mover_speed = float(info["collision_mover_speed"])
            mover_steady = float(info["collision_mover_steady_s"])
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
        collision_mover_speed=mover_speed,
        collision_mover_steady_s=mover_steady,
        max_velocity_error=velocity_error,
        **goal,
    )


def _xy(info: dict[str, Any]) -> tuple[float, float]:
    p = info["position"]
    return (round(float(p[0]), 3), round(float(p[1]), 3))


#: the simulator of each env table, built once per worker process
_ENVS: dict[Any, Any] = {}


def _worker_env(env_dict: dict[str, Any], env_id: str = AVOID_ENV_ID) -> Any:
    key = ("env", env_id, json.dumps(env_dict, sort_keys=True))
    if key not in _ENVS:
        _ENVS[key] = make_eval_env(env_dict, env_id)
    return _ENVS[key]


def make_eval_env(env_dict: dict[str, Any], env_id: str = AVOID_ENV_ID) -> Any:
    """A single simulator environment of ``env_id`` from an ``[env]`` table (strictly checked)."""
    if env_id == NAV_ENV_ID:
        from flightsim.envs.nav_env import LidarNavEnv, NavEnvConfig

        return LidarNavEnv(from_dict(NavEnvConfig, env_dict, prefix="env."))
    from flightsim.envs.env import EnvConfig, LidarAvoidEnv

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
        velocity=unwrapped.shield_velocity, lateral=unwrapped.command_lateral, env=unwrapped,
        drift=unwrapped.shield_drift, heading=unwrapped.shield_heading, movers=unwrapped.shield_movers,
    )  # fmt: skip
    if wrap is not None:
        controller = wrap(controller, unwrapped)
    result = run_episode(env, controller, task.world.reset_options(), seed=task.seed)
    result.controller, result.world, result.episode = task.controller.label, task.world.name, task.episode
    shield = getattr(controller, "shield", None)
    if shield is not None:
        result.shield_counts = dict(shield.interventions)
    return result


def make_tasks(
    controllers: Iterable[ControllerSpec],
    worlds: Sequence[WorldSpec],
    episodes: int,
    env: dict[str, Any],
    env_id: str = AVOID_ENV_ID,
) -> list[EpisodeTask]:
    """Every controller × world × episode; every controller flies the same reset seed there
    (:func:`episode_seed`), in ``env`` with its own :data:`~training.controllers.ENV_OVERRIDES`."""
    return [
        EpisodeTask(
            controller=c,
            world=w,
            episode=k,
            env={**env, **ENV_OVERRIDES.get(c.kind, {})},
            seed=episode_seed(w, k, env_id),
            env_id=env_id,
        )
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


def goal_worlds(
    families: Sequence[str], first_seed: int, n: int, difficulty_range: tuple[float, float]
) -> list[WorldSpec]:
    """``n`` generated goal-task worlds per family, seeds ``first_seed…``, difficulties spread evenly
    over ``difficulty_range`` (world ``k`` at the middle of the ``k``-th of ``n`` equal slices).

    A family named twice is flown once: naming it twice weighs training's draws, not the held-out set.
    """
    low, high = difficulty_range
    return [
        WorldSpec(
            f"{f}-{first_seed + k}",
            seed=first_seed + k,
            difficulty=round(low + (high - low) * (k + 0.5) / n, 3),
            family=f,
        )
        for f in dict.fromkeys(families)
        for k in range(n)
    ]
