"""The whole training pipeline through its command line, tiny: train, resume, export (parity), evaluate.

One module-scoped run keeps the suite fast; each test checks one promise of it. Everything is real:
the JSBSim simulator in subprocesses, SB3 PPO, torch's ONNX export, ONNX Runtime through the
companion's own OnnxPolicy and FrameStack.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import re
from pathlib import Path

import numpy as np
import onnx
import pytest

from companion.common.errors import UserError
from companion.guidance.policy import OnnxPolicy, PolicySpec
from companion.perception.framestack import FrameStack
from training.__main__ import main

WORLDS = Path(__file__).parents[2] / "flightsim" / "worlds"

TINY = """
name = "tiny"
seed = 1
total_timesteps = 256
n_envs = 2
checkpoint_every = 128
progress_bar = false

[env]
max_steps = 40
shield = true
unshielded_fraction = 0.5

[ppo]
n_steps = 64
batch_size = 64
n_epochs = 1
net_arch = [16, 16]

[eval]
every_steps = 128
n_worlds = 1
workers = 1
"""


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory):
    """Train 256 steps, resume to 384, export with parity, evaluate against the baselines."""
    tmp = tmp_path_factory.mktemp("pipeline")
    config = tmp / "tiny.toml"
    config.write_text(TINY)
    run_dir = tmp / "runs" / "tiny-s1"
    out: dict = {"tmp": tmp, "run_dir": run_dir, "config": config}
    assert main(["train", "--config", str(config), f"run_root={tmp / 'runs'}"]) == 0
    out["checkpoints_first"] = sorted(p.name for p in (run_dir / "checkpoints").glob("*.zip"))
    out["eval_rows_first"] = (run_dir / "eval.csv").read_text().splitlines()
    resume_from = run_dir / "checkpoints" / "ppo_256_steps.zip"
    assert main(["train", "--config", str(config), "--resume", str(resume_from), f"run_root={tmp / 'runs'}",
                 "total_timesteps=384"]) == 0  # fmt: skip
    onnx_path = tmp / "policy.onnx"
    out["onnx"] = onnx_path
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["export", "--model", str(run_dir / "final_model.zip"), "--out", str(onnx_path),
                     "--parity-samples", "300"]) == 0  # fmt: skip
    out["export_printed"] = printed.getvalue()
    return out


def test_training_writes_checkpoints_eval_log_and_tensorboard(pipeline):
    run_dir = pipeline["run_dir"]
    assert pipeline["checkpoints_first"] == ["ppo_128_steps.zip", "ppo_256_steps.zip"]
    header, *rows = pipeline["eval_rows_first"]
    assert header.startswith("timesteps,wall_s,difficulty,success_rate")
    assert [int(r.split(",")[0]) for r in rows] == [128, 256]
    # each held-out world is flown behind the companion's shield and without it
    assert [r["episodes"] for r in csv.DictReader(pipeline["eval_rows_first"])] == ["2", "2"]
    assert any((run_dir / "tb").rglob("events.out.tfevents.*"))
    assert (run_dir / "config.toml").is_file() and (run_dir / "best_model.zip").is_file()


def test_resume_continues_the_step_count(pipeline):
    from stable_baselines3 import PPO

    run_dir = pipeline["run_dir"]
    final = PPO.load(run_dir / "final_model.zip", device="cpu")
    assert final.num_timesteps == 384
    assert (run_dir / "checkpoints" / "ppo_384_steps.zip").is_file()
    rows = (run_dir / "eval.csv").read_text().splitlines()[1:]
    steps = [int(r.split(",")[0]) for r in rows]
    assert steps[:2] == [128, 256] and steps[-1] == 384
    walls = [float(r.split(",")[1]) for r in rows]
    assert walls == sorted(walls), "wall-clock time continues across the resume"


def test_export_checks_parity_and_writes_what_the_companion_checks(pipeline):
    onnx_path, printed = pipeline["onnx"], pipeline["export_printed"]
    diff = float(re.search(r"rollout observations ([0-9.e+-]+)", printed).group(1))
    assert diff <= 1e-5
    proto = onnx.load(str(onnx_path))
    onnx.checker.check_model(proto, full_check=True)
    ops = {n.op_type for n in proto.graph.node}
    assert ("Clip" in ops or {"Min", "Max"} <= ops) and not any("Random" in op for op in ops)
    assert len(proto.graph.output) == 1  # the action; no value head
    meta = {p.key: p.value for p in proto.metadata_props}
    assert meta["lidar_avoid.stack"] == "4" and meta["lidar_avoid.max_range"] == "10.0"
    assert json.loads(meta["lidar_avoid.config"])["env"]["max_steps"] == 40
    # the hash it prints is the file's, and what the companion's policy.sha256 checks
    digest = re.search(r"^sha256 ([0-9a-f]{64})  ", printed, re.MULTILINE).group(1)
    assert digest == hashlib.sha256(onnx_path.read_bytes()).hexdigest()
    OnnxPolicy(onnx_path, PolicySpec(), sha256=digest)  # the companion accepts it...
    with pytest.raises(UserError, match="max_speed"):
        OnnxPolicy(onnx_path, PolicySpec(max_speed=3.0))  # ...and refuses it under another config


def test_vecframestack_sb3_and_companion_framestack_onnx_act_the_same(pipeline):
    """The same scans through training's VecFrameStack + SB3 and flight's FrameStack + ONNX."""
    from stable_baselines3 import PPO

    from training.config import load_train_config
    from training.vec_env import make_vec_env

    onnx_path = pipeline["onnx"]
    model = PPO.load(pipeline["run_dir"] / "final_model.zip", device="cpu")
    config = load_train_config(pipeline["config"], ["env.max_steps=15"])
    venv = make_vec_env(config, n_envs=1, seed=5, subprocess=False)
    policy, stack = OnnxPolicy(onnx_path, PolicySpec()), FrameStack(4, 360)
    obs, new_episode, episodes = venv.reset(), True, 0
    try:
        for _ in range(40):
            scan = obs[0, -360:]
            flight_obs = stack.reset(scan) if new_episode else stack.push(scan)
            np.testing.assert_array_equal(flight_obs, obs[0])
            sb3_action, _ = model.predict(obs, deterministic=True)
            np.testing.assert_allclose(policy.act(flight_obs), sb3_action[0], atol=1e-5, rtol=0)
            obs, _, dones, _ = venv.step(sb3_action)
            new_episode = bool(dones[0])
            episodes += new_episode
    finally:
        venv.close()
    assert episodes >= 2, "the sequence must cross episode resets"


def test_evaluate_reports_policy_and_baselines_with_json_and_png(pipeline, capsys):
    tmp, onnx_path = pipeline["tmp"], pipeline["onnx"]
    report, png = tmp / "eval.json", tmp / "eval.png"
    assert main(["evaluate", "--policy", str(onnx_path), "--seeds", "2", "--set", "env.max_steps=40",
                 "--workers", "1", "--json", str(report), "--png", str(png)]) == 0  # fmt: skip
    table = capsys.readouterr().out
    assert re.search(r"^policy\s+ALL\s+2\s", table, re.M)
    data = json.loads(report.read_text())
    assert set(data["controllers"]) == {"policy", "gap_follower", "random"}
    for c in data["controllers"].values():
        assert set(c["per_world"]) == {"seed-0", "seed-1"}
        overall = c["overall"]
        assert overall["episodes"] == 2 and 0.0 <= overall["success_rate"] <= 1.0
        assert overall["min_clearance_m"] >= 0.0
    assert len(data["episodes"]) == 6
    assert png.stat().st_size > 10_000


def test_evaluate_behind_the_shield_flies_every_controller_through_it(pipeline, capsys, tmp_path):
    report = tmp_path / "shield.json"
    assert main(["evaluate", "--policy", str(pipeline["onnx"]), "--seeds", "1", "--set", "env.max_steps=20",
                 "--workers", "1", "--shield", "--json", str(report)]) == 0  # fmt: skip
    assert re.search(r"^policy\+shield\s+ALL\s+1\s", capsys.readouterr().out, re.M)
    data = json.loads(report.read_text())
    assert set(data["controllers"]) == {"policy+shield", "gap_follower+shield", "random+shield"}
    assert data["shield"]["estop_distance"] == 0.3


def test_evaluate_flies_the_shield_limits_of_a_companion_config(capsys, tmp_path):
    """``--shield-config``: the [shield] table of the file the drone flies sets the limits (and implies
    ``--shield``); the same episode flies slower under a lower speed limit."""
    companion = tmp_path / "companion.toml"
    companion.write_text('[policy]\nmodel = "policy.onnx"\n\n[shield]\nmax_speed = 0.3\n')
    flown = {}
    for name, extra in (("default", ["--shield"]), ("slow", ["--shield-config", str(companion)])):
        report = tmp_path / f"{name}.json"
        argv = ["evaluate", "--baselines", "gap_follower", "--seeds", "1", "--workers", "1",
                "--set", "env.max_steps=40", *extra, "--json", str(report)]  # fmt: skip
        assert main(argv) == 0
        data = json.loads(report.read_text())
        assert set(data["controllers"]) == {"gap_follower+shield"}
        flown[name] = data["episodes"][0]["distance"]
        if name == "slow":
            assert data["shield"]["max_speed"] == 0.3 and data["shield"]["estop_distance"] == 0.3
    assert 0.0 < flown["slow"] <= 0.3 * 40 * 0.1 * 1.2  # 40 steps of 0.1 s at 0.3 m/s, and some lag
    assert flown["slow"] < flown["default"] / 2


@pytest.mark.parametrize(
    ("text", "named"),
    [
        ("[policy]\nmodel = 'p.onnx'\n", "no [shield] table"),
        ("[shield]\nmax_speed = -1.0\n", "shield.max_speed"),
        ("[shield]\nmax_sped = 1.0\n", "shield.max_sped"),
        ("[shield\n", "companion.toml"),
    ],
)
def test_a_bad_shield_config_is_one_line_naming_what_is_wrong(capsys, tmp_path, text, named):
    companion = tmp_path / "companion.toml"
    companion.write_text(text)
    argv = ["evaluate", "--baselines", "gap_follower", "--seeds", "1", "--shield-config", str(companion)]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("avoid-train: error: ") and "\n" not in err and named in err


def test_evaluate_through_a_firmware_response_flies_differently(pipeline, capsys, tmp_path):
    """``--autopilot-response px4`` reaches the env: the same episodes fly less far than ideal."""
    flown = {}
    for name in ("ideal", "px4"):
        report = tmp_path / f"{name}.json"
        argv = ["evaluate", "--policy", str(pipeline["onnx"]), "--seeds", "1", "--workers", "1",
                "--set", "env.max_steps=30", "--autopilot-response", name, "--json", str(report)]  # fmt: skip
        assert main(argv) == 0
        episodes = json.loads(report.read_text())["episodes"]
        flown[name] = sorted((e["controller"], e["distance"]) for e in episodes)
    assert flown["px4"] != flown["ideal"]


def test_evaluate_on_the_example_worlds(pipeline, capsys):
    model = pipeline["run_dir"] / "final_model.zip"
    assert main(["evaluate", "--policy", str(model), "--worlds", str(WORLDS), "--set", "env.max_steps=30",
                 "--workers", "1"]) == 0  # fmt: skip
    table = capsys.readouterr().out
    for name in ("two-pillars", "slalom"):
        assert re.search(rf"^gap_follower\s+{name}\s+1\s", table, re.M)


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "--config", "{tmp}/tiny.toml", "ppo.n_stepz=3"],
        ["train", "--config", "{tmp}/missing.toml"],
        ["export", "--model", "{tmp}/tiny.toml", "--out", "{tmp}/x.onnx"],
        ["evaluate", "--policy", "{tmp}/nope.onnx", "--seeds", "1"],
        ["evaluate", "--policy", "{tmp}/tiny.toml", "--seeds", "1"],
        ["evaluate", "--policy", "{tmp}/policy.onnx", "--seeds", "1", "--set", "env.max_speed=3.0"],
        ["evaluate", "--policy", "{tmp}/policy.onnx", "--seeds", "2", "--first-seed", "999999"],
        ["evaluate", "--policy", "{tmp}/policy.onnx", "--seeds", "1", "--autopilot-response", "fast"],
    ],
)
def test_user_mistakes_are_one_line_errors(pipeline, capsys, argv):
    tmp = pipeline["tmp"]
    assert main([a.format(tmp=tmp) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("avoid-train: error: ") and "\n" not in err
