"""The goal task's evaluation: figures from known episodes, held-out worlds, the CLI end to end."""

from __future__ import annotations

import json

import pytest

from companion.common.errors import UserError
from flightsim.envs import seeds
from flightsim.worlds.families import FAMILIES
from training.__main__ import main
from training.episodes import EpisodeResult, goal_worlds
from training.report import format_table, goal_summary, report


def _episode(controller, world, family, *, success=False, collision=False, timeout=False, steps=100, flown=12.0):  # noqa: E501
    return EpisodeResult(
        controller=controller, world=world, episode=0, steps=steps, max_steps=3000, collision=collision,
        distance=flown, mean_speed=flown / (steps * 0.1), min_clearance=0.4, near_misses=1, success=success,
        family=family, waypoints=2, waypoints_reached=2 if success else 1, timeout=timeout,
        time_s=steps * 0.1, shortest_path_m=10.0,
    )  # fmt: skip


def test_goal_summary_rates_time_and_spl_over_successes_only():
    results = [
        _episode("a", "w1", "forest", success=True, steps=100, flown=12.5),  # SPL 0.8, 10 s
        _episode("a", "w2", "forest", success=True, steps=200, flown=10.0),  # SPL 1.0, 20 s
        _episode("a", "w3", "gaps", collision=True, steps=50, flown=3.0),
        _episode("a", "w4", "gaps", timeout=True, steps=400, flown=30.0),
    ]
    s = goal_summary(results)
    assert (s["success_rate"], s["collision_rate"], s["timeout_rate"]) == (0.5, 0.25, 0.25)
    assert s["mean_time_s"] == pytest.approx(15.0) and s["spl"] == pytest.approx(0.9)
    assert s["spl_all"] == pytest.approx(1.8 / 4) and s["waypoints_reached"] == pytest.approx(6 / 8)
    assert goal_summary(results[2:])["spl"] is None and goal_summary(results[2:])["mean_time_s"] is None

    out = report([*results, _episode("b", "w1", "forest")], [])
    a = out["controllers"]["a"]
    assert set(a) == {"overall", "per_world", "per_family"}
    assert a["per_family"]["forest"]["success_rate"] == 1.0 and a["per_family"]["gaps"]["success_rate"] == 0.0
    assert out["controllers"]["b"]["overall"]["success_rate"] == 0.0
    assert "every waypoint reached in order" in out["success_definition"]
    table = format_table(out, per_world=False)
    assert "forest" in table and "gaps" in table and "ALL" in table


def test_collisions_with_movers_are_counted_against_the_shields_speed_bound():
    """A collision with a walker (1.2 m/s) counts within the 1.5 m/s the shield's promise assumes, one
    with a drone (2.5 m/s) outside it, one with a wall not at all; of the walkers within it, the one
    that kept its velocity for the 2 s before counts within the model too, not the one that turned
    at a corner of its path 0.5 s before; the table says so."""
    results = [_episode("a", f"w{k}", "rooms-dynamic", collision=True) for k in range(4)]
    for r, speed, steady in zip(results, (1.2, 2.5, 1.4), (2.0, 2.0, 0.5), strict=False):
        r.collision_mover_speed, r.collision_mover_steady_s = speed, steady
    s = goal_summary(results)
    assert (s["collisions"], s["mover_collisions"]) == (4, 3)
    assert (s["mover_collisions_within_bound"], s["mover_collisions_within_model"]) == (2, 1)
    table = format_table(report(results, []), per_world=False)
    assert (
        "hit a mover                 3 (2 at most 1.5 m/s, the shield's mover_speed; 1 of them also kept "
        "their velocity for the 2 s before)"
    ) in table
    assert "hit a mover" not in format_table(report(results[3:], []), per_world=False)


def test_the_report_breaks_the_figures_down_by_the_response_structure_drawn():
    px4, ardupilot = {"name": "random-px4"}, {"name": "random-ardupilot"}
    results = [
        _episode("a", "w1", "forest", success=True),
        _episode("a", "w2", "forest", collision=True),
        _episode("a", "w3", "gaps", timeout=True),
        _episode("a", "w4", "gaps", success=True),
    ]
    for r, response in zip(results, (px4, ardupilot, ardupilot, px4), strict=True):
        r.response = response
    a = report(results, [])["controllers"]["a"]
    assert list(a["per_response"]) == ["random-ardupilot", "random-px4"]
    assert a["per_response"]["random-px4"]["success_rate"] == 1.0
    shaped = a["per_response"]["random-ardupilot"]
    assert (shaped["episodes"], shaped["collision_rate"], shaped["timeout_rate"]) == (2, 0.5, 0.5)
    table = format_table(report(results, []), per_world=False)
    assert "resp. random-ardupilot" in table and "resp. random-px4" in table
    for r in results:
        r.response = px4  # one response flown: nothing to break down
    assert "per_response" not in report(results, [])["controllers"]["a"]


def test_goal_worlds_spread_difficulty_per_family_and_are_deterministic():
    worlds = goal_worlds(("forest", "traps"), 900_000, 4, (0.2, 1.0))
    assert [w.family for w in worlds] == ["forest"] * 4 + ["traps"] * 4
    assert [w.difficulty for w in worlds[:4]] == [0.3, 0.5, 0.7, 0.9]
    assert worlds[0].reset_options() == {"family": "forest", "world_seed": 900_000, "difficulty": 0.3}
    assert worlds == goal_worlds(("forest", "traps"), 900_000, 4, (0.2, 1.0))
    # a family named twice weighs training's draws; the held-out set still flies it once
    assert goal_worlds(("forest", "traps", "forest"), 900_000, 4, (0.2, 1.0)) == worlds


def test_the_default_test_set_is_20_held_out_worlds_per_family():
    worlds = goal_worlds(FAMILIES, seeds.TEST.start, 20, (0.0, 1.0))
    assert len(worlds) == 20 * len(FAMILIES)
    assert all(w.seed in seeds.TEST for w in worlds)
    assert not any(w.seed in seeds.TRAIN or w.seed in seeds.VALIDATION for w in worlds)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--seeds", "2", "--first-seed", "1000000"], "goal-task world seeds must lie within the test seeds"),
        (["--seeds", "2", "--first-seed", "999999"], "goal-task world seeds must lie within the test seeds"),
        (["--seeds", "1", "--difficulty", "2"], "--difficulty must be in [0, 1]"),
        (["--seeds", "1", "--baselines", "gap_follower"], "'gap_follower' is not a baseline of this task"),
        (["--seeds", "1", "--baselines", ""], "nothing to evaluate"),
    ],
)
def test_goal_evaluation_refuses_training_seeds(tmp_path, capsys, argv, message):
    config = tmp_path / "nav.toml"
    config.write_text('env_id = "flightsim/LidarNav-v0"\n[eval]\nfirst_seed = 500000\n')
    assert main(["evaluate", "--config", str(config), *argv]) == 2
    assert message in capsys.readouterr().err


def test_goal_evaluation_end_to_end_writes_json_and_png(tmp_path, capsys):
    config = tmp_path / "nav.toml"
    config.write_text(
        'env_id = "flightsim/LidarNav-v0"\n[eval]\nfirst_seed = 500000\n'
        '[env]\nfamilies = ["gaps"]\ndifficulty_range = [0.0, 0.3]\n'
    )
    out_json, out_png = tmp_path / "eval.json", tmp_path / "eval.png"
    argv = ["evaluate", "--config", str(config), "--seeds", "1", "--shield", "--workers", "1"]
    assert main([*argv, "--json", str(out_json), "--png", str(out_png)]) == 0
    data = json.loads(out_json.read_text())
    assert data["env_id"] == "flightsim/LidarNav-v0" and data["policy"] is None
    assert set(data["controllers"]) == {"goal_follower+shield", "straight_line+shield"}
    only = tmp_path / "only.json"
    assert main([*argv, "--baselines", "straight_line", "--json", str(only)]) == 0
    assert set(json.loads(only.read_text())["controllers"]) == {"straight_line+shield"}
    overall = data["controllers"]["goal_follower+shield"]["overall"]
    assert {"success_rate", "collision_rate", "timeout_rate", "mean_time_s", "spl"} <= set(overall)
    assert overall["success_rate"] == 1.0 and 0.5 < overall["spl"] <= 1.0  # gaps-900000, an easy one
    assert list(data["controllers"]["goal_follower+shield"]["per_family"]) == ["gaps"]
    assert data["worlds"][0]["family"] == "gaps" and out_png.stat().st_size > 10_000
    assert "goal_follower+shield" in capsys.readouterr().out
    response = data["episodes"][0]["response"]  # the env's default: a random draw, reported
    assert response["name"].startswith("random-") and response["est_vel_sigma"] >= 0.0



def test_the_teachers_are_flown_only_when_named_and_read_the_env_they_fly(tmp_path):
    """``--baselines path_expert,predictive_expert``: the DAgger teachers on the held-out worlds
    (their rates bound the student's); they need the env, so a build without one is refused, and
    the avoidance task has none."""
    from training import controllers
    from training.controllers import TEACHERS, ControllerSpec, build_controller
    from training.episodes import AVOID_ENV_ID, NAV_ENV_ID
    from training.evaluate import parse_baselines

    assert set(controllers.PRIVILEGED_GOAL_CONTROLLERS) == set(TEACHERS)  # every DAgger teacher is flown
    config = tmp_path / "nav.toml"
    config.write_text(
        'env_id = "flightsim/LidarNav-v0"\n[eval]\nfirst_seed = 500000\n'
        '[env]\nfamilies = ["gaps"]\ndifficulty_range = [0.0, 0.3]\n'
    )
    out = tmp_path / "teacher.json"
    argv = ["evaluate", "--config", str(config), "--seeds", "1", "--workers", "1"]
    assert main([*argv, "--baselines", "path_expert,predictive_expert", "--json", str(out)]) == 0
    for name in ("path_expert", "predictive_expert"):
        teacher = json.loads(out.read_text())["controllers"][name]["overall"]
        assert teacher["success_rate"] == 1.0 and teacher["spl"] > 0.8
    assert parse_baselines("goal_follower,path_expert", NAV_ENV_ID) == ["goal_follower", "path_expert"]
    with pytest.raises(UserError, match="'path_expert' is not a baseline of this task"):
        parse_baselines("path_expert", AVOID_ENV_ID)
    for name in ("path_expert", "predictive_expert"):
        with pytest.raises(ValueError, match=f"{name} reads the env it flies"):
            build_controller(ControllerSpec(name), None, seed=0)


def test_each_goal_world_flies_its_own_reset_seed_and_every_controller_the_same():
    """The reset seed decides the random autopilot response: one seed for all worlds was one draw."""
    from training.controllers import ControllerSpec
    from training.episodes import NAV_ENV_ID, make_tasks

    worlds = goal_worlds(FAMILIES[:2], seeds.TEST.start, 5, (0.0, 1.0))
    controllers = [ControllerSpec("goal_follower"), ControllerSpec("straight_line")]
    tasks = make_tasks(controllers, worlds, 2, {}, NAV_ENV_ID)
    by_controller: dict[str, list[int]] = {}
    for t in tasks:
        by_controller.setdefault(t.controller.kind, []).append(t.seed)
    first, second = by_controller.values()
    assert first == second  # the same episodes for every controller
    assert len(set(first)) == len(first) == 2 * len(worlds)  # world × episode: all different


def test_the_straight_line_flies_blind_at_the_waypoint_even_where_the_others_fly_the_route():
    """The straight line gauges how hard a world is. Flown with the route (the goal features
    pointing along a route planned round what the scans showed) it went round this trap and
    reached the goal; flying at the waypoint itself, it flies into the trap on the line."""
    from training.controllers import ControllerSpec
    from training.episodes import NAV_ENV_ID, make_tasks, run_task

    trap = goal_worlds(["traps"], seeds.VALIDATION.start, 4, (0.0, 1.0))[:1]
    controllers = [ControllerSpec("straight_line"), ControllerSpec("goal_follower")]
    line, follower = make_tasks(controllers, trap, 1, {"route": True}, NAV_ENV_ID)
    assert follower.env["route"] is True and line.env["route"] is False
    result = run_task(line)
    assert result.collision and not result.success


@pytest.mark.parametrize("shield", [False, True])
def test_a_baseline_flies_an_env_with_a_sideways_action_exactly_as_the_two_part_one(shield):
    """``nav.toml`` flies ``env.sideways``: the baselines, two-part controllers, ask no sideways speed
    there (a2 = 0), alone and behind the shield, and fly the very episode they fly without it."""
    from training.controllers import ControllerSpec
    from training.episodes import NAV_ENV_ID, make_tasks, run_task

    world = goal_worlds(["pillars"], seeds.VALIDATION.start, 1, (0.5, 0.5))
    spec = ControllerSpec("goal_follower", shield=shield)
    flown = [run_task(make_tasks([spec], world, 1, {"sideways": s}, NAV_ENV_ID)[0]) for s in (False, True)]
    assert flown[0].steps > 20 and flown[0] == flown[1]


@pytest.mark.parametrize("response", ["ideal", "px4"])
def test_an_episode_records_how_far_the_shields_velocity_was_from_the_truth(response):
    """What the gate's envelope bounds (``estimate_error``): with the ideal autopilot the velocity a
    shield judges by is the true one but for the drift estimate's noise; PX4's estimate wanders off
    by tenths of a m/s, which the episode records."""
    from training.config import load_train_config
    from training.controllers import ControllerSpec
    from training.episodes import NAV_ENV_ID, make_tasks, run_task

    overrides = ["env.max_steps=60", f'env.autopilot_response="{response}"']
    config = load_train_config("training/configs/nav.toml", overrides)
    worlds = goal_worlds(["rooms"], 500_000, 1, (0.5, 0.5))
    (task,) = make_tasks([ControllerSpec("goal_follower")], worlds, 1, config.env, NAV_ENV_ID)
    error = run_task(task).max_velocity_error
    assert (error < 0.1) if response == "ideal" else (error > 0.1)
