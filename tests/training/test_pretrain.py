"""The behaviour cloning warm start: returns cut at episode ends, and a real PPO policy fitted to a
real demonstrator flying LidarNav-v0 acts like it on what it saw."""

from __future__ import annotations

import itertools

import numpy as np

from training.config import load_train_config
from training.pretrain import Demonstrations, collect, discounted_returns, fit, proximity_weights
from training.train import build_model, label_mirror, label_weights
from training.vec_env import make_vec_env

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


def untrained_student(tmp_path, *overrides: str):
    """The config :data:`NAV` with ``overrides``, a fresh PPO model of it and its observation size."""
    path = tmp_path / "bc.toml"
    path.write_text(NAV)
    config = load_train_config(path, [f"run_root={tmp_path}", *overrides])
    venv = make_vec_env(config, 1, config.seed, subprocess=False)
    try:
        return config, build_model(config, venv, tmp_path, None), venv.observation_space.shape[0]
    finally:
        venv.close()


def test_returns_are_discounted_within_each_episode_only():
    rewards = np.array([[1.0, 0.0], [1.0, 2.0], [1.0, 4.0]], dtype=np.float32)
    dones = np.array([[False, False], [True, False], [False, False]])
    returns = discounted_returns(rewards, dones, 0.5)
    # env 0: an episode of two steps (1 + 0.5), then a new one cut by the data's end
    np.testing.assert_allclose(returns[:, 0], [1.5, 1.0, 1.0])
    np.testing.assert_allclose(returns[:, 1], [0.0 + 0.5 * 2.0 + 0.25 * 4.0, 2.0 + 0.5 * 4.0, 4.0])


def test_fitted_policy_imitates_the_goal_follower(tmp_path):
    """The fit as training runs it: one torch thread (``train.py`` sets it; a test before may too, so
    it is set here and put back), and epochs enough to converge on 400 samples: at 30 the final
    loss wandered 0.03-0.12 with the seed and the thread count."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _fit_and_check(tmp_path)
    finally:
        torch.set_num_threads(threads)


def _fit_and_check(tmp_path) -> None:
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
    losses = fit(model.policy, data, epochs=100, batch_size=64, learning_rate=1e-3, seed=0)
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


def test_labels_beside_obstacles_weigh_more_by_the_newest_scan_alone():
    """1 + near_weight x (1 - d / near_distance) within near_distance of the newest scan's nearest
    return, 1 beyond it; an older frame's obstacle does not count."""
    frame, n_bins = 6, 4
    obs = np.ones((4, 2 * frame), dtype=np.float32)  # 2 frames of 4 bins (max range 10 m) + 2 extras
    obs[1, frame + 2] = 0.075  # newest frame: 0.75 m, half of near_distance
    obs[2, frame + 0] = 0.0  # newest frame: touching
    obs[3, 1] = 0.0  # the older frame only
    weights = proximity_weights(obs, 2, n_bins, 10.0, near_weight=4.0, near_distance=1.5)
    np.testing.assert_allclose(weights, [1.0, 3.0, 5.0, 1.0], rtol=1e-6)


def test_a_weighted_fit_leans_to_the_heavier_labels(tmp_path):
    """The same observation labelled +0.5 with weight 9 and -0.5 with weight 1 fits to their
    weighted mean, 0.4; unweighted, to 0."""
    config, model, size = untrained_student(tmp_path, "pretrain.near_weight=8")
    obs = np.full((128, size), 0.5, dtype=np.float32)  # every observation the same: one action fits
    actions = np.where(np.arange(128)[:, None] % 2 == 0, 0.5, -0.5).repeat(2, axis=1).astype(np.float32)
    data = Demonstrations(obs, actions, np.zeros(128, np.float32), 0, 0)
    weights = np.where(np.arange(128) % 2 == 0, 9.0, 1.0).astype(np.float32)

    def fitted(w):
        fit(model.policy, data, epochs=300, batch_size=128, learning_rate=3e-3, seed=0, weights=w)
        return model.predict(obs[:1], deterministic=True)[0][0]

    np.testing.assert_allclose(fitted(weights), [0.4, 0.4], atol=0.03)
    np.testing.assert_allclose(fitted(None), [0.0, 0.0], atol=0.03)
    touching = np.ones((2, size), np.float32)
    touching[1, (config.n_stack - 1) * (size // config.n_stack) :][:4] = 0.0  # newest scan: 0 m
    np.testing.assert_allclose(label_weights(config)(touching), [1.0, 9.0])  # pretrain.near_weight=8


def test_a_mirrored_fit_also_answers_the_mirrored_state_it_never_saw(tmp_path):
    """Fitted on one state labelled (0.5 forward, 0.6 yaw) with ``pretrain.mirror``, the student
    turns the other way, as fast, in that state's mirror image; fitted as recorded, it does not."""
    config, model, size = untrained_student(tmp_path, "pretrain.mirror=true")
    state = np.random.default_rng(0).uniform(0.2, 0.9, (1, size))
    obs = np.repeat(state, 64, axis=0).astype(np.float32)
    labels = np.tile([0.5, 0.6], (64, 1)).astype(np.float32)
    data = Demonstrations(obs, labels, np.zeros(64, np.float32), 0, 0)
    mirror = label_mirror(config)
    seen, unseen = obs[:1], mirror.observations(obs[:1])

    def fitted(m):
        fit(model.policy, data, epochs=200, batch_size=64, learning_rate=3e-3, seed=0, mirror=m)
        return model.predict(seen, deterministic=True)[0][0], model.predict(unseen, deterministic=True)[0][0]

    here, there = fitted(mirror)
    np.testing.assert_allclose(here, [0.5, 0.6], atol=0.05)
    np.testing.assert_allclose(there, [0.5, -0.6], atol=0.05)
    here, there = fitted(None)  # refitted as recorded: the mirror image is unlearnt
    np.testing.assert_allclose(here, [0.5, 0.6], atol=0.05)
    assert there[1] > 0.0
