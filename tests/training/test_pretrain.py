"""The behaviour cloning warm start: returns cut at episode ends, and a real PPO policy fitted to a
real demonstrator flying LidarNav-v0 acts like it on what it saw."""

from __future__ import annotations

import itertools

import numpy as np

from training.config import load_train_config
from training.pretrain import Demonstrations, collect, discounted_returns, fit
from training.train import build_model, make_vec_env

NAV = """
env_id = "flightsim/LidarNav-v0"
name = "bc"
seed = 1
n_envs = 2
progress_bar = false

[env]
families = ["rooms", "pillars"]
difficulty_range = [0.0, 0.3]

[ppo]
n_steps = 64
batch_size = 64
net_arch = [64, 64]
gamma = 0.9

[eval]
first_seed = 500000

[pretrain]
steps = 400
"""


def test_returns_are_discounted_within_each_episode_only():
    rewards = np.array([[1.0, 0.0], [1.0, 2.0], [1.0, 4.0]], dtype=np.float32)
    dones = np.array([[False, False], [True, False], [False, False]])
    returns = discounted_returns(rewards, dones, 0.5)
    # env 0: an episode of two steps (1 + 0.5), then a new one cut by the data's end
    np.testing.assert_allclose(returns[:, 0], [1.5, 1.0, 1.0])
    np.testing.assert_allclose(returns[:, 1], [0.0 + 0.5 * 2.0 + 0.25 * 4.0, 2.0 + 0.5 * 4.0, 4.0])


def test_fitted_policy_imitates_the_goal_follower(tmp_path):
    path = tmp_path / "bc.toml"
    path.write_text(NAV)
    config = load_train_config(path, [f"run_root={tmp_path}"])
    venv = make_vec_env(config, 2, config.seed, subprocess=False)
    try:
        data = collect(venv, config.n_stack, "goal_follower", config.env_config(), 400, config.ppo.gamma)
        model = build_model(config, venv, tmp_path, None)
    finally:
        venv.close()
    assert data.obs.shape == (400, 4 * 365) and data.actions.shape == (400, 2)
    assert np.all(np.abs(data.actions) <= 1.0) and data.actions[:, 0].max() > 0.3  # it flies forward
    log_std = model.policy.log_std.detach().clone()

    def error() -> float:
        predicted, _ = model.predict(data.obs, deterministic=True)
        return float(np.mean((predicted - data.actions) ** 2))

    before = error()
    losses = fit(model.policy, data, epochs=30, batch_size=64, learning_rate=1e-3, seed=0)
    assert error() < 0.25 * before and losses["action_mse"] < 0.05
    assert np.array_equal(model.policy.log_std.detach(), log_std)  # exploration noise as configured


def test_a_cosine_fit_ends_at_a_learning_rate_of_zero(monkeypatch, tmp_path):
    """``schedule = "cosine"`` anneals Adam's rate to 0 over the fit's batches; constant keeps it."""
    import torch

    rates: list[float] = []
    step = torch.optim.Adam.step

    def record(self, *args, **kwargs):
        rates.append(self.param_groups[0]["lr"])
        return step(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.Adam, "step", record)
    path = tmp_path / "bc.toml"
    path.write_text(NAV)
    config = load_train_config(path, [f"run_root={tmp_path}"])
    venv = make_vec_env(config, 1, config.seed, subprocess=False)
    try:
        model = build_model(config, venv, tmp_path, None)
        obs = np.random.default_rng(0).uniform(size=(64, venv.observation_space.shape[0])).astype(np.float32)
    finally:
        venv.close()
    data = Demonstrations(obs, np.zeros((64, 2), np.float32), np.zeros(64, np.float32), 0, 0)
    fit(model.policy, data, epochs=2, batch_size=16, learning_rate=1e-3, seed=0, schedule="cosine")
    assert len(rates) == 8 and rates[0] == 1e-3 and rates[-1] < 0.05e-3
    assert all(a > b for a, b in itertools.pairwise(rates))
    rates.clear()
    fit(model.policy, data, epochs=2, batch_size=16, learning_rate=1e-3, seed=0)
    assert rates == [1e-3] * 8
