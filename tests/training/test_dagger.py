"""DAgger from the privileged teacher: the student flies, the teacher labels every state it
reaches, and a real PPO policy fitted to the labels acts like the teacher."""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import pytest

from companion.common.errors import UserError
from tests.training.test_pretrain import NAV
from training import dagger
from training.__main__ import main
from training.config import load_train_config
from training.sharded_vec_env import ShardedVecEnv
from training.train import build_model, read_eval_log
from training.vec_env import make_vec_env

#: test_pretrain's small goal-task run, taught by DAgger instead
DAGGER = ["name=dagger", "seed=2", "pretrain.method='dagger'"]


@contextmanager
def dagger_run(tmp_path, *overrides: str):
    """The small DAgger run's (config, venv, model), with ``overrides``; the venv closed after."""
    path = tmp_path / "dagger.toml"
    path.write_text(NAV)
    config = load_train_config(path, [*DAGGER, f"run_root={tmp_path}", *overrides])
    venv = make_vec_env(config, 2, config.seed)
    try:
        yield config, venv, build_model(config, venv, tmp_path, None)
    finally:
        venv.close()


@pytest.fixture
def one_torch_thread():
    """Torch on one thread, as ``avoid-train train`` runs it; the count before restored after."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture
def setup(tmp_path):
    with dagger_run(tmp_path) as run:
        yield run


@pytest.mark.parametrize("teacher", sorted(dagger.TEACHERS))
def test_the_teacher_labels_the_states_the_student_flies_into(setup, teacher):
    _, venv, model = setup
    rollouts = dagger.collect(
        venv, model.policy, 400, beta=0.0, gamma=0.9, rng=np.random.default_rng(0), teacher=teacher
    )
    assert rollouts.obs.shape == (400, 4 * 365) and rollouts.actions.shape == (400, 2)
    frame = rollouts.obs[:, 3 * 365 :]  # the newest of the 4 stacked frames
    # the untrained student (beta 0: it flew) hardly moves, while the labels would fly on
    assert np.abs(frame[:, 363]).max() < 0.25 and rollouts.actions[:, 0].mean() > 0.3
    # the labels are the teacher's: it turns toward the goal (bearing sin: feature 361)
    off = np.abs(frame[:, 361]) > 0.2
    assert off.sum() > 30
    # (the predictive one also holds its heading (a candidate yaw rate of 0) or goes round an obstacle)
    assert np.mean(np.sign(rollouts.actions[off, 1]) == np.sign(frame[off, 361])) > 0.8


@pytest.mark.parametrize("noise", [0.0, 0.3])
def test_with_teacher_noise_the_frame_shows_the_noisy_command_and_the_label_stays_clean(tmp_path, noise):
    with dagger_run(tmp_path, "env.command=true") as (config, venv, model):
        rollouts = dagger.collect(
            venv, model.policy, 200, beta=1.0, gamma=0.9, rng=np.random.default_rng(0),
            teacher="predictive_expert", teacher_noise=noise,
        )  # fmt: skip
    layout = config.env_config().layout
    stacks = rollouts.obs.reshape(100, 2, 4, layout.frame_size)  # per step and env, 4 frames
    flown = stacks[1:, :, 3, layout.slices()["command"]]  # what the step before flew (action units)
    labels = rollouts.actions.reshape(100, 2, 2)[:-1]
    # a frame stack just reset has empty (zero) older frames: no step before it in its episode
    same_episode = stacks[1:, :, 0].any(axis=-1)
    difference = (flown - labels)[same_episode]
    if noise == 0.0:  # the teacher flew its label: the frame after shows it
        np.testing.assert_allclose(difference, 0.0, atol=1e-6)
    else:  # it flew its label plus the noise (clipped to the action space), the label is clean
        inside = np.abs(labels[same_episode]) < 0.5
        assert 0.2 < difference[inside].std() < 0.4


def test_the_student_learns_the_teachers_actions(setup, tmp_path):
    config, venv, model = setup
    seen: list[int] = []
    data = dagger.run(
        venv, model, iterations=2, steps=400, beta0=0.5, epochs=30, batch_size=64,
        learning_rate=1e-3, seed=0, after_iteration=lambda k, n, rollouts: seen.append(n),
    )  # fmt: skip
    assert seen == [400, 800] and data.actions.shape == (800, 2)
    untrained = build_model(config, venv, tmp_path, None)

    def error(policy) -> float:
        predicted, _ = policy.predict(data.obs, deterministic=True)
        return float(np.mean((predicted - data.actions) ** 2))

    assert error(model) < 0.25 * error(untrained)


def test_the_sharded_envs_collect_what_the_batched_ones_do_with_the_labels_made_in_their_workers(tmp_path):
    # the same seeds, the same student, half the episodes flown by the teacher, several of them
    def collect(*overrides: str) -> dagger.Rollouts:
        with dagger_run(tmp_path, "env.max_steps=30", *overrides) as (_, venv, model):
            rng = np.random.default_rng(3)
            rollouts = dagger.collect(venv, model.policy, 240, 0.5, 0.9, rng, teacher="robust_expert")
            if overrides:
                assert isinstance(venv.unwrapped, ShardedVecEnv) and venv.unwrapped.teacher is None
            return rollouts

    batched, sharded = collect(), collect("vec_env='sharded'")
    assert batched.episodes > 0 and batched.student_episodes > 0
    np.testing.assert_array_equal(sharded.obs, batched.obs)
    np.testing.assert_array_equal(sharded.actions, batched.actions)
    np.testing.assert_array_equal(sharded.returns, batched.returns)
    assert sharded.episodes == batched.episodes and sharded.successes == batched.successes


def test_a_resumed_run_may_collect_a_different_number_of_steps(setup):
    _, venv, model = setup
    saved = dagger.collect(venv, model.policy, 300, beta=1.0, gamma=0.9, rng=np.random.default_rng(0))
    data = dagger.run(
        venv, model, iterations=2, steps=200, beta0=0.5, epochs=1, batch_size=64,
        learning_rate=1e-3, seed=0, previous=[saved],
    )  # fmt: skip
    assert data.actions.shape == (500, 2)
    np.testing.assert_array_equal(data.obs[:300], saved.obs)


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


def test_a_stopped_dagger_run_resumes_after_its_last_iteration_on_its_labels(tmp_path, caplog, capsys):
    path = tmp_path / "dagger.toml"
    path.write_text(NAV)
    small = [*DAGGER, f"run_root={tmp_path}", "total_timesteps=0", "pretrain.steps=200", "pretrain.epochs=2",
             "eval.n_worlds=1", "eval.workers=1", "env.max_steps=40"]  # fmt: skip
    run_dir = tmp_path / "dagger-s2"
    assert main(["train", "--config", str(path), *small, "pretrain.iterations=2"]) == 0
    assert sorted(p.name for p in (run_dir / "dagger").iterdir()) == ["iteration_1.npz", "iteration_2.npz"]
    assert (run_dir / "checkpoints" / "dagger_400_steps.zip").is_file()
    caplog.clear()
    with caplog.at_level("INFO", logger="training.dagger"):
        assert main(["train", "--config", str(path), *small, "pretrain.iterations=3", "--resume"]) == 0
    # only the third iteration was flown, and fitted on all three iterations' labels
    flown = [r.getMessage() for r in caplog.records if "dagger iteration" in r.getMessage()]
    assert len(flown) == 1 and flown[0].startswith("dagger iteration 3/3 (teacher share 0.25)")
    assert [row["timesteps"] for row in read_eval_log(run_dir / "eval.csv")] == [200, 400, 600]
    assert dagger.load_iterations(run_dir / "dagger", 600)[2].obs.shape == (200, 4 * 365)
    capsys.readouterr()
    assert main(["train", "--config", str(path), *small, "pretrain.iterations=3", "--resume"]) == 2
    assert capsys.readouterr().err.strip().endswith(
        "dagger_600_steps.zip has 3 DAgger iterations, pretrain.iterations is 3: raise it to go on"
    )


def test_with_a_sideways_action_the_student_learns_all_three_parts(tmp_path, one_torch_thread):
    """``env.sideways``: the teacher's labels have a sideways part, the student's action space
    three parts, and the fit brings the student close to each of them (on one thread, as training
    fits: the result of a fit this small depends on the thread count)."""
    with dagger_run(tmp_path, "env.sideways=true") as (config, venv, model):
        assert venv.action_space.shape == (3,) and model.action_space.shape == (3,)
        data = dagger.run(
            venv, model, iterations=1, steps=400, beta0=1.0, epochs=60, batch_size=64,
            learning_rate=1e-3, seed=0,
        )  # fmt: skip
        assert data.actions.shape == (400, 3) and np.abs(data.actions[:, 2]).max() > 0.2
        predicted, _ = model.predict(data.obs, deterministic=True)
        untrained, _ = build_model(config, venv, tmp_path, None).predict(data.obs, deterministic=True)
        errors = np.mean((predicted - data.actions) ** 2, axis=0)
        assert np.all(errors < 0.25 * np.mean((untrained - data.actions) ** 2, axis=0)), errors


def test_total_timesteps_bounds_dagger_and_counts_its_steps(tmp_path, caplog):
    """A short goal-task run is short: ``total_timesteps`` 300 over three iterations collects 100
    steps in each (not ``pretrain.steps`` 60,000) and leaves no PPO after them; the progress log
    says how much is left."""
    path = tmp_path / "dagger.toml"
    path.write_text(NAV)
    short = [*DAGGER, f"run_root={tmp_path}", "total_timesteps=300", "pretrain.steps=60000",
             "pretrain.iterations=3", "pretrain.epochs=1", "eval.n_worlds=1", "eval.workers=1",
             "env.max_steps=40", "progress_bar=false"]  # fmt: skip
    with caplog.at_level("INFO", logger="training.dagger"):
        assert main(["train", "--config", str(path), *short]) == 0
    run_dir = tmp_path / "dagger-s2"
    assert sorted(p.name for p in (run_dir / "checkpoints").glob("dagger_*")) == [
        "dagger_100_steps.zip", "dagger_200_steps.zip", "dagger_300_steps.zip"]  # fmt: skip
    assert not (run_dir / "tb" / "ppo_1").exists()  # DAgger took the whole budget
    flown = [r.getMessage() for r in caplog.records if "dagger iteration" in r.getMessage()]
    assert flown[0].endswith("dagger steps: 100/300 (33%), " + flown[0].split("(33%), ")[1])
    assert "left" in flown[0] and flown[-1].split("; ")[1].startswith("dagger steps: 300/300 (100%)")
