"""``avoid-train trace``: the evaluation's own episode, every command of it, with the shield's part."""

from __future__ import annotations

import csv
import math

import pytest

from companion.config import CompanionShieldConfig
from companion.safety.shield import ShieldConfig
from training.__main__ import main
from training.controllers import ControllerSpec
from training.episodes import make_tasks, run_task
from training.trace import trace

CONFIG = (
    'env_id = "flightsim/LidarNav-v0"\n[eval]\nfirst_seed = 500000\n'
    '[env]\nfamilies = ["gaps"]\ndifficulty_range = [0.0, 0.3]\n'
)
WORLDS = ["--seeds", "2", "--first-seed", "500000"]
WORLD = [*WORLDS, "--world", "gaps-500001"]


@pytest.fixture()
def config(tmp_path):
    path = tmp_path / "nav.toml"
    path.write_text(CONFIG)
    return path


def _flight(config, *extra):
    """The :class:`~training.evaluate.Flight` the trace command loads for ``extra``."""
    import argparse

    from training.evaluate import add_flight_arguments, load_flight

    parser = argparse.ArgumentParser()
    add_flight_arguments(parser)
    return load_flight(parser.parse_args(["--config", str(config), *WORLDS, *extra]))


def test_the_trace_is_the_evaluations_episode_and_shows_the_estimate_error_and_the_shield(config):
    flight = _flight(config, "--shield")
    spec = ControllerSpec("goal_follower", shield=True)
    result, steps = trace(flight, "gaps-500001", spec, episode=1)
    world = next(w for w in flight.worlds if w.name == "gaps-500001")
    task = make_tasks([spec], [world], 2, flight.config.env, flight.config.env_id)[1]
    evaluated = run_task(task)  # the same episode, not traced
    assert (result.steps, result.success, result.trajectory) == (
        evaluated.steps, evaluated.success, evaluated.trajectory)  # fmt: skip
    assert len(steps) == result.steps  # a command at reset, one after every step but the last
    assert [s.step for s in steps] == list(range(result.steps))
    # the response is a random draw with an estimate error: reported and true velocity differ
    errors = [math.hypot(s.reported_forward - s.true_forward, s.reported_left - s.true_left) for s in steps]
    assert max(errors) > 0.01
    # the shield acted somewhere (at least the acceleration limit from standstill), and what it
    # sent differs from what was asked exactly where it says it acted
    assert steps[0].shield and steps[0].sent_forward < steps[0].asked_forward
    for s in steps:
        if not s.shield:
            assert (s.sent_forward, s.sent_yaw_rate, s.sent_lateral) == pytest.approx(
                (s.asked_forward, s.asked_yaw_rate, 0.0)
            )
    assert all(0.0 <= s.nearest_m <= 10.0 and 0.0 < s.nearest_deg < 360.0 for s in steps)


def test_the_shield_flies_the_configs_limits_unless_a_flight_config_is_named(config, tmp_path):
    assert _flight(config, "--shield").shield_config == ShieldConfig()
    config.write_text(CONFIG + "[env.shield_limits]\nmax_speed = 1.0\n")
    assert _flight(config, "--shield").shield_config == ShieldConfig(max_speed=1.0)
    flown = tmp_path / "companion.toml"
    flown.write_text("[shield]\nmax_speed = 1.5\n")
    # the drone's [shield], with the companion's defaults for what it does not set (the drift carried)
    flown_limits = _flight(config, "--shield-config", str(flown)).shield_config
    assert flown_limits == CompanionShieldConfig(max_speed=1.5) and flown_limits.drift_compensation == 0.6


def test_alone_what_is_sent_is_what_was_asked(config):
    result, steps = trace(_flight(config), "gaps-500000", ControllerSpec("goal_follower"))
    assert len(steps) == result.steps
    assert all(s.shield == "" and s.sent_forward == s.asked_forward and s.sent_lateral == 0.0 for s in steps)


def test_alone_what_is_sent_is_what_was_asked_and_the_held_drift(config):
    """With ``drift_hold`` the setpoint also carries the drift estimate sideways: the trace shows
    what left for the autopilot, so its lateral is the held drift, beyond the deadband."""
    config.write_text(CONFIG + "drift = true\ndrift_hold = true\n")
    _, steps = trace(_flight(config), "gaps-500000", ControllerSpec("goal_follower"))
    assert all(s.sent_forward == s.asked_forward for s in steps)
    lateral = [abs(s.sent_lateral) for s in steps]
    assert 0.0 < max(lateral) <= 0.6  # at most the hold's bound


def test_the_command_prints_the_last_rows_and_writes_every_row_to_csv(config, tmp_path, capsys):
    out = tmp_path / "trace.csv"
    argv = ["trace", "--config", str(config), *WORLD, "--baseline", "goal_follower", "--shield"]
    assert main([*argv, "--last", "3", "--csv", str(out)]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[0].startswith("gaps-500001 episode 0, goal_follower+shield: ")
    assert printed[1].split()[:3] == ["step", "x", "y"] and len(printed) == 2 + 3 + 1  # + "wrote"
    rows = list(csv.DictReader(out.open()))
    assert int(rows[-1]["step"]) == int(printed[-2].split()[0]) == len(rows) - 1
    assert {"asked_forward", "sent_lateral", "reported_forward", "true_forward", "shield"} <= set(rows[0])


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--world", "gaps-500007"], "--world gaps-500007: not among the 2 worlds named (gaps-500000, "),
        (["--world", "gaps-500001", "--episode", "-1"], "--episode must be 0 or more"),
        (["--world", "gaps-500001", "--last", "0"], "--last must be at least 1"),
    ],
)
def test_bad_arguments_are_one_line_and_exit_2(config, capsys, argv, message):
    base = ["trace", "--config", str(config), *WORLDS, "--baseline", "goal_follower"]
    assert main([*base, *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def test_a_baseline_of_another_task_is_refused_naming_the_option(config, capsys):
    assert main(["trace", "--config", str(config), *WORLD, "--baseline", "gap_follower"]) == 2
    assert "--baseline: 'gap_follower' is not a baseline of this task" in capsys.readouterr().err
