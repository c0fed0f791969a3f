"""The goal task through the whole pipeline, tiny: train LidarNav-v0, export (parity, layout metadata),
the companion's OnnxPolicy accepts it only under the goal layout, evaluate the .onnx."""

from __future__ import annotations

import contextlib
import csv
import io
import json
from pathlib import Path

import numpy as np
import onnx
import pytest

from companion.common.errors import UserError
from companion.guidance.policy import OnnxPolicy, PolicySpec
from companion.perception.framestack import FrameStack
from companion.perception.observation import ObservationLayout
from training.__main__ import main

TINY_NAV = """
env_id = "flightsim/LidarNav-v0"
name = "tiny-nav"
seed = 2
total_timesteps = 128
n_envs = 1
checkpoint_every = 128
progress_bar = false

[env]
families = ["gaps"]
difficulty_range = [0.0, 0.2]
max_steps = 60

[ppo]
n_steps = 64
batch_size = 64
n_epochs = 1
net_arch = [16, 16]

[eval]
every_steps = 1000
n_worlds = 1
first_seed = 500000
workers = 1
"""
GOAL = ObservationLayout(goal=True, goal_range=30.0, velocity_scale=2.0)


def _train_and_export(
    tmp: Path, config_text: str, name: str, parity_samples: int
) -> tuple[Path, Path, Path, str]:
    """Train the tiny run ``config_text`` under ``tmp`` and export it to ``tmp/<name>.onnx``.

    :return: the config file, the run directory, the model and what the export printed
    """
    config = tmp / f"tiny-{name}.toml"
    config.write_text(config_text)
    assert main(["train", "--config", str(config), f"run_root={tmp / 'runs'}"]) == 0
    run_dir = tmp / "runs" / "tiny-nav-s2"
    onnx_path = tmp / f"{name}.onnx"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["export", "--model", str(run_dir / "final_model.zip"), "--out", str(onnx_path),
                     "--parity-samples", str(parity_samples)]) == 0  # fmt: skip
    return config, run_dir, onnx_path, printed.getvalue()


@pytest.fixture(scope="module")
def nav_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("nav")
    config, run_dir, onnx_path, printed = _train_and_export(tmp, TINY_NAV, "nav", 100)
    return {"config": config, "run_dir": run_dir, "onnx": onnx_path, "printed": printed}


def test_training_validates_on_goal_worlds(nav_run):
    with (nav_run["run_dir"] / "eval.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 1 and rows[0]["episodes"] == "2"  # one gaps world, with and without the shield
    assert rows[0]["moving_success_rate"] == ""  # no world with movers


def test_training_reports_the_worlds_with_movers_apart(tmp_path):
    """eval.csv's moving_success_rate is the worse of alone and behind the shield on the dynamic
    worlds only: here the one rooms-dynamic world, flown again by ``evaluate`` both ways."""
    config_text = TINY_NAV.replace('families = ["gaps"]', 'families = ["gaps", "rooms-dynamic"]')
    config_text = config_text.replace("max_steps = 60", "max_steps = 150")
    config, run_dir, _, _ = _train_and_export(tmp_path, config_text, "movers", 10)
    with (run_dir / "eval.csv").open() as f:
        (row,) = csv.DictReader(f)
    assert row["episodes"] == "4"
    again = []
    for shield in ([], ["--shield"]):
        out = tmp_path / f"again{len(shield)}.json"
        model = str(run_dir / "eval_model.zip")
        argv = ["evaluate", "--config", str(config), "--policy", model, "--seeds", "1", "--baselines", "",
                "--set", 'env.families=["rooms-dynamic"]', "--workers", "1", "--json", str(out),
                *shield]  # fmt: skip
        assert main(argv) == 0
        (flown,) = json.loads(out.read_text())["controllers"].values()  # policy, or policy+shield
        again.append(flown["overall"]["success_rate"])
    assert float(row["moving_success_rate"]) == min(again)


def test_export_writes_the_goal_layout_and_the_companion_checks_it(nav_run):
    meta = {p.key: p.value for p in onnx.load(str(nav_run["onnx"])).metadata_props}
    assert meta["lidar_avoid.obs_layout"] == GOAL.name
    assert meta["lidar_avoid.obs_size"] == "1460"
    assert "max abs diff" in nav_run["printed"]
    policy = OnnxPolicy(nav_run["onnx"], PolicySpec(layout=GOAL))
    stack = FrameStack(4, GOAL.frame_size)
    action = policy.act(stack.reset(np.concatenate([np.ones(360), [1.0, 0.0, 0.3, 0.0, 0.0]])))
    assert action.shape == (2,) and np.all(np.abs(action) <= 1.0)
    with pytest.raises(UserError, match=r"model obs_layout scan360\+goal.* does not match config observation layout scan360"):  # noqa: E501
        OnnxPolicy(nav_run["onnx"], PolicySpec())


def test_evaluate_flies_the_exported_goal_policy(nav_run, tmp_path, capsys):
    out = tmp_path / "eval.json"
    argv = ["evaluate", "--config", str(nav_run["config"]), "--policy", str(nav_run["onnx"]), "--seeds", "1",
            "--workers", "1", "--json", str(out)]  # fmt: skip
    assert main(argv) == 0
    data = json.loads(out.read_text())
    assert set(data["controllers"]) == {"policy", "goal_follower", "straight_line"}
    assert data["controllers"]["policy"]["per_family"]["gaps"]["episodes"] == 1


def test_two_checkpoints_export_as_one_model_flying_their_mean_action(nav_run, tmp_path):
    """Two members (the run's final model, and a copy whose action bias is moved so they differ)
    export as one file the companion loads; its action is the mean of theirs, within parity."""
    import onnxruntime as ort
    import torch
    from stable_baselines3 import PPO

    run_dir = nav_run["run_dir"]
    other = tmp_path / "other.zip"
    model = PPO.load(str(run_dir / "final_model.zip"), device="cpu")
    with torch.no_grad():
        model.policy.action_net.bias.add_(torch.tensor([0.3, -0.2]))
    model.save(str(other))
    (tmp_path / "config.toml").write_text((run_dir / "config.toml").read_text())
    out = tmp_path / "mean.onnx"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        argv = ["export", "--model", str(run_dir / "final_model.zip"), "--model", str(other),
                "--out", str(out), "--parity-samples", "50"]  # fmt: skip
        assert main(argv) == 0
    obs = np.random.default_rng(0).uniform(size=(20, 1460)).astype(np.float32)
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    got = session.run(None, {"observation": obs})[0]
    members = [PPO.load(str(path), device="cpu") for path in (run_dir / "final_model.zip", other)]
    predictions = [member.predict(obs, deterministic=True)[0] for member in members]
    assert np.abs(predictions[0] - predictions[1]).max() > 0.1  # the members differ
    np.testing.assert_allclose(got, np.mean(predictions, axis=0), atol=1e-5)
    assert "members" in onnx.load(str(out)).doc_string
    OnnxPolicy(out, PolicySpec(layout=GOAL))  # the companion takes it as any model


def test_an_ensemble_member_for_another_action_scaling_is_refused_in_one_line(nav_run, tmp_path, capsys):
    """A member whose run flew another top speed would be averaged in the wrong units: refused."""
    import shutil

    run_dir = nav_run["run_dir"]
    member = tmp_path / "faster" / "final_model.zip"
    member.parent.mkdir()
    shutil.copy(run_dir / "final_model.zip", member)
    config = (run_dir / "config.toml").read_text().replace("[env]\n", "[env]\nmax_speed = 3.0\n", 1)
    (member.parent / "config.toml").write_text(config)
    argv = ["export", "--model", str(run_dir / "final_model.zip"), "--model", str(member),
            "--out", str(tmp_path / "mean.onnx"), "--parity-samples", "10"]  # fmt: skip
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert f"{member}: trained for another observation or action scaling than" in err
    assert not (tmp_path / "mean.onnx").exists()


def _fine_tune(nav_run, tmp_path, *overrides: str, trained: Path | None = None) -> int:
    trained = trained or nav_run["run_dir"] / "final_model.zip"
    argv = ["train", "--config", str(nav_run["config"]), f"run_root={tmp_path / 'runs'}", "name=tiny-ft",
            f"ppo.init_from={trained}", "total_timesteps=64", *overrides]  # fmt: skip
    return main(argv)


def test_a_fine_tune_starts_from_the_trained_weights_with_fresh_action_noise(nav_run, tmp_path):
    """PPO from a trained model: its actor and critic carry over, the noise restarts at log_std_init
    (one update at the smallest learning rate moves the weights by far less than the tolerance)."""
    import torch
    from stable_baselines3 import PPO

    assert _fine_tune(nav_run, tmp_path, "ppo.log_std_init=-2.0", "ppo.learning_rate=1e-7") == 0
    trained = PPO.load(str(nav_run["run_dir"] / "final_model.zip"), device="cpu").policy.state_dict()
    tuned_path = tmp_path / "runs" / "tiny-ft-s2" / "final_model.zip"
    tuned = PPO.load(str(tuned_path), device="cpu").policy.state_dict()
    assert set(tuned) == set(trained)
    for name, weights in tuned.items():
        if name == "log_std":
            torch.testing.assert_close(weights, torch.full_like(weights, -2.0), atol=1e-4, rtol=0)
        else:
            torch.testing.assert_close(weights, trained[name], atol=1e-4, rtol=0)


def test_a_fine_tune_from_another_network_is_refused_in_one_line(nav_run, tmp_path, capsys):
    assert _fine_tune(nav_run, tmp_path, "ppo.net_arch=[32, 32]") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "ppo.init_from" in err and "its network is not this config's" in err and "size mismatch" in err


def test_a_missing_fine_tune_start_is_refused_in_one_line_before_the_run_directory(tmp_path, nav_run, capsys):
    assert _fine_tune(nav_run, tmp_path, trained=tmp_path / "nowhere.zip") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert err.endswith(f"ppo.init_from: model file not found: {tmp_path / 'nowhere.zip'}")
    assert not (tmp_path / "runs" / "tiny-ft-s2").exists()  # nothing to --overwrite after the fix


@pytest.fixture(scope="module")
def side_run(tmp_path_factory):
    """The tiny run with ``env.sideways``: a three-part action, exported."""
    side = TINY_NAV.replace("[env]\n", "[env]\nsideways = true\n")
    config, _, onnx_path, _ = _train_and_export(tmp_path_factory.mktemp("side"), side, "side", 50)
    return {"config": config, "onnx": onnx_path}


def test_a_sideways_export_says_so_and_the_companion_takes_it_only_when_told(side_run):
    proto = onnx.load(str(side_run["onnx"]))
    meta = {p.key: p.value for p in proto.metadata_props}
    assert meta["lidar_avoid.max_sideways_speed"] == "1.0"
    assert "[forward, yaw rate, sideways]" in proto.doc_string
    policy = OnnxPolicy(side_run["onnx"], PolicySpec(layout=GOAL, max_sideways_speed=1.0))
    action = policy.act(np.zeros(4 * GOAL.frame_size, np.float32))
    assert action.shape == (3,) and np.all(np.abs(action) <= 1.0)
    with pytest.raises(UserError, match=r"set policy.max_sideways_speed = 1, as the model's metadata says"):
        OnnxPolicy(side_run["onnx"], PolicySpec(layout=GOAL))


def test_evaluate_flies_the_exported_sideways_policy(side_run, tmp_path):
    out = tmp_path / "eval.json"
    argv = ["evaluate", "--config", str(side_run["config"]), "--policy", str(side_run["onnx"]),
            "--seeds", "1", "--workers", "1", "--baselines", "", "--json", str(out)]  # fmt: skip
    assert main(argv) == 0
    assert json.loads(out.read_text())["controllers"]["policy"]["per_family"]["gaps"]["episodes"] == 1


def test_a_movers_run_exports_its_layout_and_the_companion_flies_it_under_policy_movers(tmp_path):
    """``env.movers`` in a tiny run on a dynamic family: the export names the movers part, and the
    companion, configured as the metadata says (``policy.movers``), loads it and runs it on a frame
    carrying a mover."""
    from companion.app import policy_spec
    from companion.config import CompanionConfig, GoalConfig, PolicyConfig, model_policy_settings
    from companion.guidance.policy import read_model_metadata
    from companion.perception.observation import build_frame, goal_features, mover_features
    from companion.perception.tracking import Mover

    movers = TINY_NAV.replace('families = ["gaps"]', 'families = ["rooms-dynamic"]\nmovers = true')
    _, _, onnx_path, _ = _train_and_export(tmp_path, movers, "movers", 50)
    layout = ObservationLayout(goal=True, goal_range=30.0, velocity_scale=2.0, movers=True)
    meta = read_model_metadata(onnx_path)
    assert meta["lidar_avoid.obs_layout"] == layout.name
    assert meta["lidar_avoid.obs_layout"].endswith(
        "+movers(3x(forward,left/10m,velocity/3m/s,radius/1m,present))"
    )
    assert meta["lidar_avoid.obs_size"] == str(4 * 383)
    settings = model_policy_settings(meta)
    assert settings["movers"] and not settings["drift"]
    companion = CompanionConfig(policy=PolicyConfig(**settings), goal=GoalConfig(source="mission"))
    policy = OnnxPolicy(onnx_path, policy_spec(companion))
    features = np.concatenate([goal_features(5.0, 0.0, 0.5, 0.0, layout),
                               mover_features([Mover((3.0, -1.0), (0.0, 1.2), 0.25)], layout)])  # fmt: skip
    stack = FrameStack(4, layout.frame_size)
    action = policy.act(stack.reset(build_frame(np.ones(360), features, layout)))
    assert action.shape == (2,) and np.all(np.abs(action) <= 1.0)
    with pytest.raises(UserError, match=r"\(movers features: set policy.movers = true\)$"):
        OnnxPolicy(onnx_path, PolicySpec(layout=GOAL))
