"""DAgger from the privileged teacher: the student flies, the teacher labels every state it
reaches, and a real PPO policy fitted to the labels acts like the teacher."""

from __future__ import annotations

import numpy as np
import pytest

from companion.errors import UserError
from tests.training.test_pretrain import NAV
from training import dagger
from training.config import load_train_config
from training.train import build_model, make_vec_env

#: test_pretrain's small goal-task run, taught by DAgger instead
DAGGER = ["name=dagger", "seed=2", "pretrain.method='dagger'"]


@pytest.fixture
def setup(tmp_path):
    path = tmp_path / "dagger.toml"
    path.write_text(NAV)
    config = load_train_config(path, [*DAGGER, f"run_root={tmp_path}"])
    venv = make_vec_env(config, 2, config.seed)
    model = build_model(config, venv, tmp_path, None)
    yield config, venv, model
    venv.close()


def test_the_teacher_labels_the_states_the_student_flies_into(setup):
    _, venv, model = setup
    rollouts = dagger.collect(venv, model.policy, 400, beta=0.0, gamma=0.9, rng=np.random.default_rng(0))
    assert rollouts.obs.shape == (400, 4 * 365) and rollouts.actions.shape == (400, 2)
    frame = rollouts.obs[:, 3 * 365 :]  # the newest of the 4 stacked frames
    # the untrained student (beta 0: it flew) hardly moves, while the labels would fly on
    assert np.abs(frame[:, 363]).max() < 0.25 and rollouts.actions[:, 0].mean() > 0.3
    # the labels are the teacher's: it turns toward the goal (bearing sin: feature 361)
    off = np.abs(frame[:, 361]) > 0.2
    assert off.sum() > 30
    assert np.mean(np.sign(rollouts.actions[off, 1]) == np.sign(frame[off, 361])) > 0.9


def test_the_student_learns_the_teachers_actions(setup, tmp_path):
    config, venv, model = setup
    seen: list[int] = []
    data = dagger.run(
        venv, model, iterations=2, steps=400, beta0=0.5, epochs=30, batch_size=64,
        learning_rate=1e-3, seed=0, after_iteration=lambda k, n: seen.append(n),
    )  # fmt: skip
    assert seen == [400, 800] and data.actions.shape == (800, 2)
    untrained = build_model(config, venv, tmp_path, None)

    def error(policy) -> float:
        predicted, _ = policy.predict(data.obs, deterministic=True)
        return float(np.mean((predicted - data.actions) ** 2))

    assert error(model) < 0.25 * error(untrained)


def test_dagger_needs_the_goal_task_and_the_envs_in_this_process(tmp_path):
    path = tmp_path / "dagger.toml"
    path.write_text(NAV)
    config = load_train_config(path, [*DAGGER, f"run_root={tmp_path}", "vec_env='subproc'"])
    venv = make_vec_env(config, 2, config.seed)  # SubprocVecEnv: the teacher cannot read the envs
    try:
        with pytest.raises(UserError, match='vec_env = "batched"'):
            dagger.nav_envs(venv)
    finally:
        venv.close()
    with pytest.raises(UserError, match="dagger"):
        load_train_config(path, [*DAGGER, 'env_id="flightsim/LidarAvoid-v0"', "env={}"])
