"""``avoid-sim fly`` flies any exported model, scan-only or goal, as its metadata says it was trained,
and flies a world's waypoints as a mission when the model can (or says that it does not)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from companion.common.errors import UserError
from companion.config import PolicyConfig, model_policy_settings
from companion.guidance.policy import PolicySpec, read_model_metadata
from companion.perception.observation import ObservationLayout
from flightsim.sitl.fly_cli import flies_mission, model_overrides
from flightsim.worlds.world import load_world
from tests.onnx_models import SCAN_SPEC, write_policy

REPO = Path(__file__).resolve().parents[2]
SLALOM = REPO / "flightsim" / "worlds" / "slalom.json"


@pytest.mark.parametrize(
    ("drift", "command", "firmware", "movers"),
    [(False, False, False, False), (True, False, False, False), (True, True, False, False),
     (False, False, True, False), (True, True, True, False), (True, False, False, True),
     (True, True, True, True)],
)
def test_the_policy_settings_rebuild_the_layout_the_metadata_names(tmp_path, drift, command, firmware,
                                                                   movers):  # fmt: skip
    layout = ObservationLayout(goal=True, drift=drift, command=command, firmware=firmware, movers=movers)
    spec = PolicySpec(layout=layout, max_sideways_speed=1.0)
    settings = model_policy_settings(read_model_metadata(write_policy(tmp_path / "m.onnx", spec=spec)))
    assert settings["observation"] == "goal"
    assert PolicyConfig(**settings).layout.name == layout.name
    assert settings["max_sideways_speed"] == 1.0


def test_a_scan_only_model_is_configured_as_one(tmp_path):
    settings = model_overrides(write_policy(tmp_path / "scan.onnx", spec=SCAN_SPEC))["policy"]
    assert settings["observation"] == "scan"
    assert PolicyConfig(**settings).layout.name == SCAN_SPEC.layout.name


def test_a_layout_the_companion_cannot_feed_is_one_line(tmp_path):
    model = write_policy(tmp_path / "m.onnx", metadata_overrides={"lidar_avoid.obs_layout": "scan720"})
    with pytest.raises(UserError, match="model observation layout scan720 is not one the companion can feed"):
        model_overrides(model)


def test_a_world_s_waypoints_are_a_mission_for_a_goal_model_unless_told_otherwise():
    world = load_world(SLALOM)
    n = len(world.waypoints)
    assert n > 0
    note = f"world {world.name}: flying its {n} waypoints as a mission (--no-mission: fly without)"
    assert flies_mission(world, scan_only=False, asked=None) == (True, note)
    assert flies_mission(world, scan_only=False, asked=False) == (False, "")
    mission, note = flies_mission(world, scan_only=True, asked=None)
    assert not mission and "not flown: the model is scan-only" in note
    with pytest.raises(UserError, match="--mission: the model is scan-only"):
        flies_mission(world, scan_only=True, asked=True)


def test_fly_flies_a_scan_only_model(tmp_path):
    """Before, the companion refused it (the default config is the goal layout) and fly exited 1."""
    model = write_policy(tmp_path / "scan.onnx", kind="steer", spec=SCAN_SPEC)
    argv = ["fly", "--policy", str(model), "--seed", "3", "--duration", "3", "--lidar-step", "1.0",
            "--workdir", str(tmp_path / "fly")]  # fmt: skip
    result = subprocess.run([sys.executable, "-m", "flightsim", *argv], cwd=REPO, capture_output=True,
                            text=True, timeout=240)  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr
    assert "engaged: True" in result.stdout
    assert 'observation = "scan"' in (tmp_path / "fly" / "companion.toml").read_text()


def test_a_mission_flies_for_the_goal_tasks_time_limit_unless_told(monkeypatch, capsys):
    """Before, a mission had 30 s like any flight: too short for slalom's two waypoints."""
    import argparse

    from flightsim.sitl import fly_cli
    from flightsim.sitl.flight_report import FlightReport

    flown: list[fly_cli.FlightOptions] = []

    def record(options, plot=None):
        flown.append(options)
        return FlightReport.failed(options.world.name, options.autopilot, "")

    monkeypatch.setattr(fly_cli, "run_flight", record)
    parser = argparse.ArgumentParser()
    fly_cli.configure_parser(parser)
    for extra, mission in (([], True), (["--no-mission"], False), (["--duration", "12"], True)):
        fly_cli.command(parser.parse_args(["--world", str(SLALOM), *extra]))
        assert flown[-1].mission is mission
    limit = fly_cli.time_limit(load_world(SLALOM))
    assert limit > 30.0
    assert [o.duration for o in flown] == [limit, fly_cli.FREE_FLIGHT_S, 12.0]
