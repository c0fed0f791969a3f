"""``avoid-train evaluate`` and ``trace`` without ``--config``: the model's own training config, from
its ONNX metadata; and one line naming ``--config`` when a given config flies another task."""

from __future__ import annotations

import json
from pathlib import Path

from companion.common.tomlconfig import to_dict
from tests.onnx_models import SCAN_SPEC, write_policy
from training.__main__ import main
from training.config import config_to_toml, load_train_config, model_train_config

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / "models" / "policy.onnx"
#: one short goal-task world of the validation seeds (gaps, the smallest family)
GOAL_WORLD = ["--seeds", "1", "--first-seed", "500000", "--set", 'env.families=["gaps"]',
              "--set", "env.difficulty_range=[0.0, 0.0]"]  # fmt: skip


def test_the_shipped_model_carries_the_goal_task_and_its_layout() -> None:
    config = model_train_config(SHIPPED)
    assert config.env_id == "flightsim/LidarNav-v0"
    assert config.env_config().drift and config.env_config().sideways


def test_evaluate_flies_the_shipped_model_without_a_config(capsys) -> None:
    argv = ["evaluate", "--policy", str(SHIPPED), *GOAL_WORLD, "--baselines", "", "--workers", "1"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "gaps" in out and "ALL" in out and "SPL" in out  # the goal task's table


def test_trace_flies_the_shipped_model_without_a_config(capsys) -> None:
    argv = ["trace", "--policy", str(SHIPPED), *GOAL_WORLD, "--world", "gaps-500000", "--last", "2"]
    assert main(argv) == 0
    assert capsys.readouterr().out.startswith("gaps-500000 episode 0, policy: ")


def test_a_config_of_the_other_task_is_one_line_naming_the_flag(capsys) -> None:
    shipped = REPO / "training" / "configs" / "shipped.toml"
    argv = ["evaluate", "--policy", str(SHIPPED), "--config", str(shipped), *GOAL_WORLD[:4]]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "goal task" in err and "drop --config" in err and "--config training/configs/nav.toml" in err


def test_a_scan_only_model_is_evaluated_in_the_avoidance_task_of_its_metadata(tmp_path, capsys) -> None:
    avoid = load_train_config(None, ["env.max_steps=20"])
    model = write_policy(tmp_path / "scan.onnx", kind="forward", spec=SCAN_SPEC,
                         metadata_overrides={"lidar_avoid.config": json.dumps(to_dict(avoid))})  # fmt: skip
    argv = ["evaluate", "--policy", str(model), "--seeds", "1", "--baselines", "", "--workers", "1"]
    assert main(argv) == 0
    assert "ALL" in capsys.readouterr().out
    nav = REPO / "training" / "configs" / "nav.toml"
    assert main([*argv, "--config", str(nav)]) == 2
    err = capsys.readouterr().err.strip()
    assert "avoidance task" in err and "--config training/configs/shipped.toml" in err


def test_a_model_without_a_training_config_asks_for_one(tmp_path, capsys) -> None:
    model = write_policy(tmp_path / "bare.onnx", kind="forward")  # metadata config: {"test_policy": ...}
    assert main(["evaluate", "--policy", str(model), "--seeds", "1", "--first-seed", "500000"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "carries no training config" in err and "--config FILE" in err


def test_a_model_whose_training_config_does_not_load_names_the_key(tmp_path, capsys) -> None:
    bad = {"lidar_avoid.config": '{"env_id": "flightsim/LidarNav-v0", "bogus": 1}'}
    model = write_policy(tmp_path / "odd.onnx", kind="forward", metadata_overrides=bad)
    assert main(["evaluate", "--policy", str(model), "--seeds", "1", "--first-seed", "500000"]) == 2
    err = capsys.readouterr().err.strip()
    assert "bogus: unknown config key" in err and "--config FILE" in err


def test_a_checkpoint_is_evaluated_in_its_run_directorys_config(tmp_path, capsys) -> None:
    """A goal-task checkpoint without --config: before, flown in the avoidance task and refused."""
    from tests.training.test_dagger import dagger_run

    with dagger_run(tmp_path, "env.max_steps=30") as (config, _venv, model):
        run = tmp_path / "run"
        run.mkdir()
        (run / "config.toml").write_text(config_to_toml(config))
        model.save(run / "final_model.zip")
    argv = ["evaluate", "--policy", str(run / "final_model.zip"), "--seeds", "1", "--first-seed", "500000",
            "--set", 'env.families=["gaps"]', "--baselines", "", "--workers", "1"]  # fmt: skip
    assert main(argv) == 0
    assert "gaps" in capsys.readouterr().out
