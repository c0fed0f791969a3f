"""The mover-aware teacher (``mover_expert``): it gives way to a walker crossing its path where the
robust teacher flies into it, it flies a dynamic validation world the robust teacher collides in
and one where a walker turns back at it, and in a world without movers it is the robust teacher,
command for command."""

from __future__ import annotations

import numpy as np
import pytest

from flightsim.envs.nav_env import LidarNavEnv, NavEnvConfig
from flightsim.worlds.moving import MovingObstacle, PathMotion
from flightsim.worlds.world import World
from tests.training.test_path_expert import RADIUS
from training.config import load_train_config
from training.controllers import TEACHERS, ControllerSpec
from training.episodes import NAV_ENV_ID, goal_worlds, make_tasks, run_task
from training.predictive_expert import PredictiveExpert, mover_expert, robust_expert

WALKER_RADIUS = 0.25


def crossing(walker_start_y: float) -> World:
    """An empty room; the waypoint 12 m ahead of the start; a walker crossing the straight line
    halfway at 1.5 m/s (out along x = 0 from ``walker_start_y`` and back)."""
    walker = MovingObstacle(
        "cylinder", PathMotion(((0.0, walker_start_y), (0.0, walker_start_y + 10.0)), 1.5),
        height=1.8, radius=WALKER_RADIUS, kind="pedestrian",
    )  # fmt: skip
    return World(
        name="crossing", room_size=(20.0, 12.0), room_height=3.0, obstacles=(),
        start_position=(-6.0, 0.0, 1.5), start_yaw_deg=0.0, waypoints=((6.0, 0.0, 1.5),), moving=(walker,),
    )  # fmt: skip


def fly_past_walker(teacher, world: World) -> tuple[dict, float, float]:
    """Fly ``teacher`` in ``world`` (PX4's response, the sideways action): the end's info, the least
    gap between the vehicle and the walker (surface to surface, metres), and the largest sideways
    offset from the straight line, metres."""
    env = LidarNavEnv(NavEnvConfig(autopilot_response="px4", vehicle_radius=RADIUS, sideways=True))
    env.reset(seed=0, options={"world": world})
    expert: PredictiveExpert = teacher(env)
    action, gap, offset = expert.reset(), np.inf, 0.0
    while True:
        _, _, terminated, truncated, info = env.step(action)
        walker = env.world.moving[0].positions(env.sim_time)[0]
        position = env.true_state.position
        gap = min(gap, float(np.hypot(*(position[:2] - walker))) - RADIUS - WALKER_RADIUS)
        offset = max(offset, abs(float(position[1])))
        if terminated or truncated:
            return info, gap, offset
        action = expert.act()


@pytest.mark.parametrize("walker_start_y", [-8.0, -7.5])
def test_it_gives_way_to_a_crossing_walker_the_robust_teacher_flies_into(walker_start_y):
    """The walker reaches the line as the vehicle does: the robust teacher, blind to it, collides;
    the mover-aware one waits or steps aside, keeps more than its margin from the walker
    and still reaches the waypoint."""
    world = crossing(walker_start_y)
    blind, _, _ = fly_past_walker(robust_expert, world)
    assert blind["collision"]
    info, gap, _ = fly_past_walker(mover_expert, world)
    assert info["success"] and not info["collision"], info
    assert gap > 0.3, gap


def test_in_a_world_without_movers_it_is_the_robust_teacher():
    """Two static validation worlds (warehouse 500,400-1, the training env, the random response):
    every action the same, bit for bit, and the space-time teacher's too."""
    config = load_train_config("training/configs/nav.toml", ['env.families=["warehouse"]'])
    worlds = goal_worlds(["warehouse"], 500_400, 5, tuple(config.env_config().difficulty_range))[:2]
    actions: dict[str, list[np.ndarray]] = {"robust_expert": [], "mover_expert": [], "space_time_expert": []}
    for kind, recorded in actions.items():
        for task in make_tasks([ControllerSpec(kind)], worlds, 1, config.env, NAV_ENV_ID):
            run_task(task, lambda controller, env, out=recorded: Recording(controller, out))
    assert len(actions["mover_expert"]) > 300
    np.testing.assert_array_equal(np.array(actions["mover_expert"]), np.array(actions["robust_expert"]))
    np.testing.assert_array_equal(np.array(actions["space_time_expert"]), np.array(actions["robust_expert"]))


class Recording:
    """A controller that flies ``controller`` and keeps every action in ``out``."""

    def __init__(self, controller, out: list[np.ndarray]) -> None:
        self.controller, self.out = controller, out

    def reset(self, scan: np.ndarray) -> np.ndarray:
        self.out.append(action := self.controller.reset(scan))
        return action

    def act(self, scan: np.ndarray) -> np.ndarray:
        self.out.append(action := self.controller.act(scan))
        return action


def _validation_world(family: str, index: int) -> tuple:
    """nav.toml flying only ``family``, and its world ``index`` of the five from 500,400 that
    ``avoid-train evaluate --first-seed 500400 --seeds 5`` flies, as a one-world list."""
    config = load_train_config("training/configs/nav.toml", [f'env.families=["{family}"]'])
    worlds = goal_worlds([family], 500_400, 5, tuple(config.env_config().difficulty_range))
    return config, worlds[index : index + 1]


def test_it_flies_a_dynamic_validation_world_the_robust_teacher_collides_in():
    """office-dynamic-500403 (validation; the fourth of five as ``avoid-train evaluate --first-seed
    500400 --seeds 5`` flies them, the random response): the robust teacher flies into a walker
    after 2.3 s, the mover-aware teacher reaches every waypoint."""
    config, world = _validation_world("office-dynamic", 3)
    assert world[0].name == "office-dynamic-500403"
    blind, aware = (
        run_task(task)
        for task in make_tasks(
            [ControllerSpec("robust_expert"), ControllerSpec("mover_expert")],
            world,
            1,
            config.env,
            NAV_ENV_ID,
        )
    )
    assert blind.collision
    assert aware.success and not aware.collision


def test_it_arrives_where_a_walker_turns_back_at_it():
    """warehouse-dynamic-500402 (validation, the third of five, the random response): a walker
    turns back at its track's end and walks at the vehicle, 1.4 m/s; carried on at its velocity
    before the turn, the mover-aware teacher flew into it after 11.2 s. It arrives if the walker
    may turn back, and when it does the vehicle keeps on out of its way rather than stopping in it."""
    config, world = _validation_world("warehouse-dynamic", 2)
    assert world[0].name == "warehouse-dynamic-500402"
    (task,) = make_tasks([ControllerSpec("mover_expert")], world, 1, config.env, NAV_ENV_ID)
    result = run_task(task)
    assert result.success and not result.collision, result


def test_it_is_a_teacher():
    assert TEACHERS["mover_expert"] is mover_expert
