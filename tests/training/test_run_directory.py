"""A run directory is never reused silently; Ctrl-C saves ``interrupted.zip`` and ``--resume`` goes on.

The Ctrl-C test is a real ``avoid-train train`` process (SB3 PPO, JSBSim simulators in forkserver
workers, an evaluation pool) sent SIGINT to its whole process group, as a terminal's Ctrl-C does.
"""

from __future__ import annotations

import math
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from companion.common.errors import UserError
from tests.foreground import start_foreground
from training.__main__ import main
from training.train import (
    EVAL_FIELDS,
    checkpoint_steps,
    read_eval_log,
    run_lock,
    truncate_eval_log,
    write_eval_log,
)

REPO = Path(__file__).resolve().parents[2]

TINY = """
name = "tiny"
seed = 1
total_timesteps = 100000
n_envs = 2
checkpoint_every = 128
progress_bar = true

[env]
max_steps = 40

[ppo]
n_steps = 64
batch_size = 64
n_epochs = 1
net_arch = [16, 16]

[eval]
every_steps = 256
n_worlds = 2
workers = 2
"""


def _row(steps: int, success: float, difficulty: float = 0.5) -> dict[str, float]:
    return dict(zip(EVAL_FIELDS, (steps, steps / 10, difficulty, success, 1.0, 0, 4, math.nan), strict=True))


def _start_training(config: Path, runs: Path, *extra: str) -> subprocess.Popen:
    return start_foreground("training", "train", "--config", str(config), f"run_root={runs}", *extra)


def test_ctrl_c_saves_interrupted_zip_exits_130_in_one_line_and_resume_continues(tmp_path):
    config = tmp_path / "tiny.toml"
    config.write_text(TINY)
    runs = tmp_path / "runs"
    run_dir = runs / "tiny-s1"
    proc = _start_training(config, runs)
    deadline = time.monotonic() + 240
    while not (run_dir / "eval.csv").is_file() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    assert proc.poll() is None, proc.communicate()[1]
    time.sleep(1.0)  # into the next rollout: simulators stepping in their workers
    os.killpg(proc.pid, signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-3000:]
    assert "Traceback" not in out + err and "KeyboardInterrupt" not in out + err
    last = err.strip().splitlines()[-1]
    assert last.startswith("avoid-train: interrupted after ") and "interrupted.zip" in last
    steps = checkpoint_steps(run_dir / "interrupted.zip")
    assert steps > 0 and f"after {steps} steps" in last

    # the same name again: refused, nothing touched
    before = (run_dir / "eval.csv").read_text()
    assert main(["train", "--config", str(config), f"run_root={runs}"]) == 2
    assert (run_dir / "eval.csv").read_text() == before

    # --resume without a file: from interrupted.zip (the newest), the step count and the log go on
    target = steps + 256
    assert main(["train", "--config", str(config), f"run_root={runs}", "progress_bar=false",
                 f"total_timesteps={target}", "--resume"]) == 0  # fmt: skip
    from stable_baselines3 import PPO

    assert PPO.load(run_dir / "final_model.zip", device="cpu").num_timesteps >= target
    rows = read_eval_log(run_dir / "eval.csv")
    timesteps = [r["timesteps"] for r in rows]
    assert timesteps == sorted(set(timesteps)), "timesteps never restart"
    assert timesteps[-1] >= target and any(t > steps for t in timesteps)
    walls = [r["wall_s"] for r in rows]
    assert walls == sorted(walls)


def test_overwrite_starts_afresh_and_the_two_options_exclude_each_other(tmp_path, capsys):
    config = tmp_path / "tiny.toml"
    config.write_text(TINY)
    runs = tmp_path / "runs"
    run_dir = runs / "tiny-s1"
    (run_dir / "checkpoints").mkdir(parents=True)
    write_eval_log(run_dir / "eval.csv", [_row(1024, 0.5), _row(2048, 0.9)])
    (run_dir / "checkpoints" / "ppo_2048_steps.zip").write_bytes(b"old")
    argv = ["train", "--config", str(config)]

    assert main([*argv, "--resume", "--overwrite", f"run_root={runs}"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert main([*argv, f"run_root={runs}", "--resume", "total_timesteps=9"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "overrides before --resume" in err

    assert main([*argv, "--overwrite", f"run_root={runs}", "progress_bar=false", "total_timesteps=256"]) == 0
    assert not (run_dir / "checkpoints" / "ppo_2048_steps.zip").exists()
    assert [r["timesteps"] for r in read_eval_log(run_dir / "eval.csv")] == [256]


def test_a_used_run_directory_is_refused_in_one_line(tmp_path, capsys):
    config = tmp_path / "tiny.toml"
    config.write_text(TINY)
    (tmp_path / "runs" / "tiny-s1").mkdir(parents=True)
    (tmp_path / "runs" / "tiny-s1" / "eval.csv").write_text("timesteps\n")
    assert main(["train", "--config", str(config), f"run_root={tmp_path / 'runs'}"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("avoid-train: error: ") and "\n" not in err
    assert "--resume" in err and "--overwrite" in err
    # --resume with nothing to resume from says so
    assert main(["train", "--config", str(config), f"run_root={tmp_path / 'runs'}", "--resume"]) == 2
    assert "no checkpoint" in capsys.readouterr().err


def test_a_run_directory_in_use_by_a_live_run_is_refused_even_after_it_was_deleted(tmp_path, capsys):
    """A second ``avoid-train train`` of the same run, even with ``--overwrite`` and even once the
    directory was deleted under the first, is refused in one line naming the first run's pid; the
    lock dies with the process that held it."""
    config = tmp_path / "tiny.toml"
    config.write_text(TINY)
    runs = tmp_path / "runs"
    run_dir = runs / "tiny-s1"
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "checkpoints" / "ppo_128_steps.zip").write_bytes(b"the live run's")
    hold = textwrap.dedent(f"""
        import time
        from pathlib import Path
        from training.train import run_lock
        with run_lock(Path({str(run_dir)!r})):
            print("held", flush=True)
            time.sleep(120)
    """)
    holder = subprocess.Popen([sys.executable, "-c", hold], cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        argv = ["train", "--config", str(config), f"run_root={runs}", "total_timesteps=256"]
        assert main([*argv, "--overwrite"]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and f"in use by another training run (pid {holder.pid})" in err
        assert (run_dir / "checkpoints" / "ppo_128_steps.zip").read_bytes() == b"the live run's"
        shutil.rmtree(run_dir)
        assert main(argv) == 2
        assert f"pid {holder.pid}" in capsys.readouterr().err
        assert not run_dir.exists()
    finally:
        holder.kill()
        holder.wait()
    with run_lock(run_dir):  # killed: its lock went with it
        pass


def test_resume_drops_the_evaluations_of_the_abandoned_continuation(tmp_path):
    (tmp_path / "best_model.zip").write_bytes(b"from the 3072-step evaluation")
    write_eval_log(tmp_path / "eval.csv", [_row(1024, 0.5), _row(2048, 0.6), _row(3072, 0.9)])
    truncate_eval_log(tmp_path, 2048, target_difficulty=0.5)
    assert [r["timesteps"] for r in read_eval_log(tmp_path / "eval.csv")] == [1024, 2048]
    # the best model came from the dropped row: it is gone, so the resumed run judges anew
    assert not (tmp_path / "best_model.zip").exists()


def test_resume_keeps_a_best_model_from_before_the_checkpoint(tmp_path):
    (tmp_path / "best_model.zip").write_bytes(b"from the 1024-step evaluation")
    write_eval_log(tmp_path / "eval.csv", [_row(1024, 0.9), _row(2048, 0.6), _row(3072, 0.7)])
    truncate_eval_log(tmp_path, 2048, target_difficulty=0.5)
    assert [r["timesteps"] for r in read_eval_log(tmp_path / "eval.csv")] == [1024, 2048]
    assert (tmp_path / "best_model.zip").is_file()


BLOCK_TRAIN_EXTRA = """
import importlib.abc, sys

class Missing(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {blocked!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None

sys.meta_path.insert(0, Missing())
from companion.common.errors import UserError
from training.__main__ import main
sys.exit(main(["train", "--config", {config!r}, "run_root={runs}"]))
"""


@pytest.mark.parametrize("blocked", [("torch", "stable_baselines3"), ("gymnasium", "jsbsim", "torch")])
def test_without_the_train_extra_one_line_says_what_to_install(tmp_path, blocked):
    """Installed with ``[sim]`` only (torch missing), or with the base install only."""
    config = tmp_path / "tiny.toml"
    config.write_text(TINY)
    script = tmp_path / "no_train_extra.py"
    script.write_text(
        textwrap.dedent(BLOCK_TRAIN_EXTRA).format(blocked=set(blocked), config=str(config), runs=tmp_path)
    )
    done = subprocess.run(
        [sys.executable, str(script)],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2, done.stderr
    err = done.stderr.strip()
    assert "Traceback" not in err
    assert err.splitlines()[-1].startswith("avoid-train: error: ") and ".[train]" in err.splitlines()[-1]


def test_ctrl_c_before_training_starts_is_one_line_130(monkeypatch, capsys, tmp_path):
    """Ctrl-C while the config loads or the simulators start: nothing to save, still no traceback."""
    import training.train

    def interrupted(*_args, **_kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(training.train, "load_train_config", interrupted)
    assert main(["train", "--config", str(tmp_path / "tiny.toml")]) == 130
    assert capsys.readouterr().err.strip() == "avoid-train: interrupted"


class _CutOffModel:
    """Writes part of a zip, then Ctrl-C arrives (as in a real save's middle)."""

    def save(self, path):
        Path(path).write_bytes(b"PK\x03\x04 cut off")
        raise KeyboardInterrupt


class _InterruptedModel:
    """A real SIGINT arrives halfway through writing the zip (CI once sent Ctrl-C inside torch's
    zip writer, which then raised ``RuntimeError: unexpected pos`` and the run exited 1)."""

    def save(self, path):
        with Path(path).open("wb") as f:
            f.write(b"first half ")
            os.kill(os.getpid(), signal.SIGINT)
            f.write(b"second half")


def test_ctrl_c_during_a_save_waits_for_the_save_then_interrupts(tmp_path):
    from training.train import save_atomically

    target = tmp_path / "checkpoint.zip"
    # Python's own handler, as `avoid-train train` runs (tests before may have left another one)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            save_atomically(_InterruptedModel(), target)
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler is back
    finally:
        signal.signal(signal.SIGINT, before)
    assert target.read_bytes() == b"first half second half"


def test_a_checkpoint_cut_off_by_ctrl_c_leaves_no_file_under_its_name(tmp_path):
    """A Ctrl-C during a periodic save once left ``ppo_<N>_steps.zip`` cut off; ``--resume`` then
    took it as the newest checkpoint and failed ("not a stable-baselines3 model")."""
    from training.train import atomic_checkpoint_callback, latest_checkpoint, save_atomically

    checkpoints = tmp_path / "checkpoints"
    checkpoints.mkdir()
    callback = atomic_checkpoint_callback()(save_freq=1, save_path=str(checkpoints), name_prefix="ppo")
    callback.model, callback.n_calls, callback.num_timesteps = _CutOffModel(), 1, 1152
    with pytest.raises(KeyboardInterrupt):
        callback._on_step()
    assert list(checkpoints.iterdir()) == []
    with pytest.raises(KeyboardInterrupt):
        save_atomically(_CutOffModel(), tmp_path / "interrupted.zip")
    assert not (tmp_path / "interrupted.zip").exists() and not list(tmp_path.glob(".partial-*"))
    with pytest.raises(UserError, match="no checkpoint to continue from"):
        latest_checkpoint(tmp_path)
