"""Training's batched vector env behaves as SB3's own: same stacked observations, rewards, dones,
infos (terminal observations, time-limit flags, VecMonitor's episode records) as a DummyVecEnv of
the same envs for the same seed and actions, and the curriculum's env_method reaches each env."""

from __future__ import annotations

import numpy as np
import pytest

from training.batched_vec_env import BatchedVecEnv
from training.config import load_train_config
from training.vec_env import make_vec_env


def _info_equal(a: dict, b: dict, where: str) -> None:
    assert a.keys() == b.keys(), where
    for key, value in a.items():
        if isinstance(value, dict):
            _info_equal(value, b[key], f"{where} {key}")
        elif key == "t":  # VecMonitor's wall-clock episode time
            continue
        elif key == "r":  # VecMonitor sums the episode in float32: from float64 or float32 rewards
            np.testing.assert_allclose(value, b[key], rtol=1e-6, err_msg=f"{where}: episode return")
        else:
            assert np.array_equal(np.asarray(value), np.asarray(b[key])), f"{where}: info[{key!r}]"


@pytest.mark.parametrize(
    ("config_file", "overrides"),
    [
        ("training/configs/shipped.toml", ["env.max_steps=30"]),
        ("training/configs/nav.toml", ["env.max_steps=30"]),
    ],
)
def test_batched_vec_env_steps_as_sb3s_dummy_vec_env(config_file: str, overrides: list[str]) -> None:
    n = 3
    batched_config = load_train_config(config_file, [*overrides, "vec_env='batched'"])
    dummy_config = load_train_config(config_file, [*overrides, "vec_env='subproc'"])
    batched = make_vec_env(batched_config, n, seed=11)
    dummy = make_vec_env(dummy_config, n, seed=11, subprocess=False)  # SB3's DummyVecEnv
    assert isinstance(batched.unwrapped, BatchedVecEnv) and not isinstance(dummy.unwrapped, BatchedVecEnv)
    try:
        np.testing.assert_array_equal(batched.reset(), dummy.reset())
        rng = np.random.default_rng(2)
        dones_seen = truncations = 0
        for t in range(80):
            actions = rng.uniform(-1.0, 1.0, (n, *batched.action_space.shape)).astype(np.float32)
            b_obs, b_rew, b_done, b_info = batched.step(actions)
            d_obs, d_rew, d_done, d_info = dummy.step(actions)
            np.testing.assert_array_equal(b_obs, d_obs, err_msg=f"step {t}")
            # DummyVecEnv keeps rewards in a float32 buffer; the batched env returns the float64
            # the env computed (as SubprocVecEnv does): equal to float32 rounding
            np.testing.assert_array_equal(b_rew.astype(np.float32), d_rew, err_msg=f"step {t}")
            np.testing.assert_array_equal(b_done, d_done)
            for i in range(n):
                _info_equal(b_info[i], d_info[i], f"step {t} env {i}")
            dones_seen += int(b_done.sum())
            truncations += sum(info["TimeLimit.truncated"] for info in b_info)
        assert dones_seen >= n and truncations >= 1  # auto-resets were compared
        assert all("terminal_observation" in i for i, d in zip(b_info, b_done, strict=True) if d)
    finally:
        batched.close()
        dummy.close()


def test_env_method_get_and_set_attr_reach_each_env() -> None:
    config = load_train_config("training/configs/shipped.toml")
    venv = make_vec_env(config, 2, seed=0)
    try:
        venv.env_method("set_difficulty", 0.9)  # the curriculum's call
        assert venv.get_attr("difficulty") == [0.9, 0.9]
        venv.set_attr("spread", 0.0, indices=[1])
        assert venv.get_attr("spread") == [0.35, 0.0]
        assert venv.env_is_wrapped(type(venv.unwrapped.envs[0])) == [True, True]
    finally:
        venv.close()


def test_subproc_keeps_sb3s_subprocess_vec_env() -> None:
    from stable_baselines3.common.vec_env import SubprocVecEnv

    config = load_train_config("training/configs/shipped.toml", ["vec_env='subproc'"])
    venv = make_vec_env(config, 2, seed=0)
    try:
        assert isinstance(venv.unwrapped, SubprocVecEnv)
        assert venv.reset().shape == (2, 4 * 360)
    finally:
        venv.close()
