"""The training config: strict loading, overrides, the [env] table checked by the simulator's own rules."""

import re
from pathlib import Path

import pytest

from companion.common.errors import UserError
from companion.common.tomlconfig import load_toml
from training.config import TrainConfig, config_from_dict, config_to_toml, load_train_config


def _write(tmp_path, text: str):
    path = tmp_path / "mine.toml"
    path.write_text(text)
    return path


def test_defaults_are_the_tutorial_hyperparameters():
    c = load_train_config(None)
    p = c.ppo
    assert (p.learning_rate, p.n_steps, p.batch_size, p.n_epochs) == (3e-4, 2048, 64, 10)
    assert (p.gamma, p.gae_lambda, p.clip_range, p.ent_coef, p.vf_coef, p.max_grad_norm) == (
        0.99,
        0.95,
        0.2,
        0.01,
        0.5,
        0.5,
    )
    assert c.n_stack == 4 and c.checkpoint_every == 50_000


def test_name_defaults_to_the_file_stem_and_sets_the_run_directory(tmp_path):
    c = load_train_config(_write(tmp_path, "seed = 7\nrun_root = 'out'\n"))
    assert c.name == "mine"
    assert str(c.run_dir) == "out/mine-s7"


def test_autopilot_response_reaches_the_env(tmp_path):
    c = load_train_config(_write(tmp_path, '[env]\nautopilot_response = "random"\n'))
    assert c.env_config().autopilot_response == "random"
    assert load_train_config(None, ["env.autopilot_response=px4"]).env_config().autopilot_response == "px4"


def test_overrides_reach_nested_tables_and_env(tmp_path):
    c = load_train_config(
        _write(tmp_path, "[ppo]\nn_steps = 512\n"), ["ppo.n_steps=128", "env.max_steps=200", "seed=3"]
    )
    assert c.ppo.n_steps == 128 and c.seed == 3
    assert c.env_config().max_steps == 200


@pytest.mark.parametrize(
    ("text", "overrides", "named"),
    [
        ("[ppo]\nn_step = 5\n", [], "ppo.n_step"),
        ("[ppo]\ngamma = 1.5\n", [], "ppo.gamma"),
        ("[env]\nmax_step = 5\n", [], "env.max_step"),
        ("[env]\nmax_steps = 'many'\n", [], "env.max_steps"),
        ("[env]\noverspeed_penalty = -1.0\n", [], "env.overspeed_penalty"),
        ("", ["env.unshielded_fraction=1.5"], "env.unshielded_fraction"),
        ("", ["eval.first_seed=1000000"], "eval.first_seed"),
        ("", ["ppo.batch_size=4096", "ppo.n_steps=16", "n_envs=2"], "ppo.batch_size"),
        ("name = 'a b'\n", [], "name"),
        ("[ppo]\nlearning_rate_schedule = 'cosine'\n", [], "ppo.learning_rate_schedule"),
        ("[env]\nautopilot_response = 'fast'\n", [], "env.autopilot_response"),
        ("[pretrain]\nsteps = 10\n", [], "pretrain.demonstrator"),  # goal_follower on the avoid task
        ("[pretrain]\nsteps = -1\n", [], "pretrain.steps"),
        ("vec_env = 'threads'\n", [], "vec_env"),
        ("total_timesteps = 0\n", [], "total_timesteps"),  # nothing to train
        ("[pretrain]\nsteps = 10\nmethod = 'dagger'\n", [], "dagger"),  # the avoid task
        ("[pretrain]\nmethod = 'imitate'\n", [], "pretrain.method"),
        ("[ppo]\ntarget_kl = -0.1\n", [], "ppo.target_kl"),
        ("[ppo]\ninit_from = 'a.zip'\n[pretrain]\nsteps = 10\n", [], "ppo.init_from"),  # one or the other
        ("", ["ppo.scan_layers=[[8, 4, 2]]"], "ppo.scan_layers[0]"),  # an even kernel
        ("", ["ppo.scan_layers=[[8, 5]]"], "ppo.scan_layers[0]"),
        ("", ["ppo.scan_layers=[[0, 5, 2]]"], "ppo.scan_layers[0][0]"),
    ],
)
def test_mistakes_name_the_key(tmp_path, text, overrides, named):
    with pytest.raises(UserError, match=re.escape(named)):
        load_train_config(_write(tmp_path, text), overrides)


def test_saved_toml_reloads_to_the_same_config(tmp_path):
    c = load_train_config(
        _write(tmp_path, "[env]\nmax_steps = 300\n[curriculum]\nenabled = true\n[ppo]\nnet_arch = [32, 16]\n")
    )
    again = config_from_dict(load_toml(_write(tmp_path, config_to_toml(c))))
    assert again == c
    assert isinstance(again, TrainConfig)


def test_every_committed_config_loads():
    from pathlib import Path

    configs = sorted((Path(__file__).parents[2] / "training" / "configs").glob("*.toml"))
    assert configs, "training/configs/ must hold the shipped policy's config"
    for path in configs:
        assert load_train_config(path).name == path.stem


@pytest.mark.parametrize(("schedule", "at_end"), [("constant", 3e-4), ("linear", 0.0)])
def test_learning_rate_schedule_reaches_the_ppo_model(tmp_path, schedule, at_end):
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv

    from training.train import build_model

    c = load_train_config(None, [f"ppo.learning_rate_schedule={schedule!r}", "ppo.n_steps=64"])
    model = build_model(c, DummyVecEnv([lambda: gym.make("Pendulum-v1")]), tmp_path, None)
    assert model.lr_schedule(1.0) == pytest.approx(3e-4)  # progress_remaining 1: the start
    assert model.lr_schedule(0.5) == pytest.approx((3e-4 + at_end) / 2)
    assert model.lr_schedule(0.0) == pytest.approx(at_end)


@pytest.mark.parametrize(("value", "reaches"), [(0.0, None), (0.02, 0.02)])
def test_target_kl_reaches_the_ppo_model_and_zero_means_none(tmp_path, value, reaches):
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv

    from training.train import build_model

    c = load_train_config(None, [f"ppo.target_kl={value}", "ppo.n_steps=64"])
    model = build_model(c, DummyVecEnv([lambda: gym.make("Pendulum-v1")]), tmp_path, None)
    assert model.target_kl == reaches


def test_the_config_offers_every_dagger_teacher_and_no_other():
    """``[pretrain] teacher`` names a :data:`training.dagger.TEACHERS` entry: the config's list is
    written out (the config must not import the teachers) and kept beside that table by this."""
    from typing import get_args, get_type_hints

    from training.config import PretrainConfig
    from training.controllers import TEACHERS

    assert set(get_args(get_type_hints(PretrainConfig)["teacher"])) == set(TEACHERS)


def test_movers_without_the_tracker_is_one_line_naming_both_keys(tmp_path, capsys):
    from training.__main__ import main

    nav = Path(__file__).parents[2] / "training" / "configs" / "nav.toml"
    assert load_train_config(nav, ["env.movers=true"]).env_config().layout.movers
    argv = ["train", "--config", str(nav), "env.movers=true", "env.tracking=false", f"run_root={tmp_path}"]
    assert main(argv) == 2
    assert capsys.readouterr().err == (
        "avoid-train: error: env: movers are the tracker's: movers = true needs tracking = true\n"
    )
    assert not list(tmp_path.iterdir())  # refused before a run directory


def test_nav_movers_is_the_nav_recipe_with_movers_among_every_family_and_its_env_runs():
    """A smoke check of training/configs/nav-movers.toml (not trained here): nav.toml's recipe but for
    the movers in the frame and drawn as scans, the dynamic families (drawn twice as often as a static
    one) and the teacher that plans round the movers; its env flies a dynamic world (validation seed)
    and its frames stay in their bounds."""
    import dataclasses

    import numpy as np

    from flightsim.envs.nav_env import LidarNavEnv
    from flightsim.worlds.families import ALL_FAMILIES

    configs = Path(__file__).parents[2] / "training" / "configs"
    nav, movers = load_train_config(configs / "nav.toml"), load_train_config(configs / "nav-movers.toml")
    env_config = movers.env_config()
    assert env_config.movers and set(env_config.families) == set(ALL_FAMILIES)
    counts = [env_config.families.count(f) for f in ALL_FAMILIES]
    assert counts == [1 + f.endswith("-dynamic") for f in ALL_FAMILIES]
    assert movers.ppo.mover_ring == [0.0, 0.5, 1.0, 1.5, 2.0]
    ppo = dataclasses.replace(movers.ppo, mover_ring=[])
    assert movers.vec_env == "sharded"
    unlike = {"env": nav.env, "pretrain": nav.pretrain, "ppo": ppo, "vec_env": nav.vec_env}
    assert dataclasses.replace(movers, name="nav", **unlike) == nav
    assert movers.pretrain == dataclasses.replace(nav.pretrain, teacher="space_time_expert")
    static = nav.env_config()
    assert dataclasses.replace(env_config, movers=False, families=static.families) == static
    assert env_config.layout.name == dataclasses.replace(static.layout, movers=True).name  # scan, goal, drift
    env = LidarNavEnv(dataclasses.replace(env_config, max_steps=20))
    try:
        options = {"family": "rooms-dynamic", "world_seed": 500_300, "difficulty": 0.5}
        obs, _ = env.reset(seed=0, options=options)
        low, high = env.observation_space.low, env.observation_space.high
        for _ in range(20):
            assert obs.shape == (385,) and np.all(obs >= low) and np.all(obs <= high)
            obs, _, terminated, truncated, _ = env.step(np.array([0.5, 0.0, 0.0], np.float32))
            if terminated or truncated:
                break
    finally:
        env.close()
