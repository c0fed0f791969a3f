"""Training figures: env steps per second during ``learn``, and wall-clock time to >= 95 % success.

Usage::

    python bench/bench_training.py [--config training/configs/shipped.toml] [--steps 16384] [--run-dir DIR]

1. Throughput: a short PPO run with the config's environments and hyperparameters (checkpoints and
   evaluation off), timed around ``model.learn``: environment steps per second including the
   policy updates. Against a reference measured in the same run: the same vector environment
   stepped with random actions and no learning (what ``learn`` would reach if inference and PPO
   updates cost nothing), as a ratio; and against the seed tutorial's real-time simulator (about
   28 hours per million steps, i.e. ~10 steps/s). The load average is printed.
2. Time to success: from the run directory's ``eval.csv`` (written by ``avoid-train train``), the
   first held-out evaluation at the target difficulty with success rate >= 95 %: its wall-clock
   seconds since the run started and its step count. Compared with the 30-minute target.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from training.config import load_train_config
from training.train import build_model, read_eval_log
from training.vec_env import make_vec_env

TUTORIAL_STEPS_PER_S = 1_000_000 / (28 * 3600)
TARGET_S = 30 * 60


def throughput(config_path: Path, steps: int) -> float:
    import torch

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        config = load_train_config(config_path, [f"run_root={tmp}"])
        venv = make_vec_env(config, config.resolved_n_envs, config.seed)
        try:
            model = build_model(config, venv, Path(tmp), None)
            model.verbose = 0
            rollout = config.ppo.n_steps * config.resolved_n_envs
            steps = max(rollout, steps // rollout * rollout)
            start = time.perf_counter()
            model.learn(total_timesteps=steps)
            elapsed = time.perf_counter() - start
        finally:
            venv.close()
    return steps / elapsed


def env_only(config_path: Path, steps: int) -> float:
    """Steps/s of the same vector env with random actions: no inference, no updates."""
    import numpy as np

    with tempfile.TemporaryDirectory() as tmp:
        config = load_train_config(config_path, [f"run_root={tmp}"])
        n = config.resolved_n_envs
        venv = make_vec_env(config, n, config.seed)
        try:
            venv.reset()
            rng = np.random.default_rng(0)
            actions = rng.uniform(-1.0, 1.0, (steps // n + 1, n, 2)).astype(np.float32)
            start = time.perf_counter()
            for a in actions:
                venv.step(a)
            elapsed = time.perf_counter() - start
        finally:
            venv.close()
    return len(actions) * n / elapsed


def time_to_success(run_dir: Path, target_difficulty: float, threshold: float = 0.95) -> dict | None:
    for row in read_eval_log(run_dir / "eval.csv"):
        if row["difficulty"] >= target_difficulty - 1e-9 and row["success_rate"] >= threshold:
            return row
    return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=Path("training/configs/shipped.toml"))
    parser.add_argument("--steps", type=int, default=16384, help="environment steps for the throughput run")
    parser.add_argument("--run-dir", type=Path, help="run directory with eval.csv (default: the config's)")
    args = parser.parse_args()

    config = load_train_config(args.config)
    print(f"config {args.config}: {config.resolved_n_envs} envs on {os.cpu_count()} cores")
    print(f"load average {os.getloadavg()[0]:.1f}")
    rate = throughput(args.config, args.steps)
    bare = env_only(args.config, args.steps)
    print(
        f"training throughput: {rate:.0f} env steps/s during learn (incl. PPO updates) = "
        f"{rate / bare:.0%} of the same envs stepped alone ({bare:.0f} steps/s, same run); "
        f"{rate / TUTORIAL_STEPS_PER_S:.0f}x the seed tutorial's real time "
        f"({TUTORIAL_STEPS_PER_S:.0f} steps/s); "
        f"1M steps take {1e6 / rate / 60:.0f} min (load average {os.getloadavg()[0]:.1f})"
    )
    run_dir = args.run_dir or config.run_dir
    row = time_to_success(run_dir, config.eval.difficulty)
    if row is None:
        print(f"time to >= 95 % success: not reached in {run_dir / 'eval.csv'}")
    else:
        verdict = "within" if row["wall_s"] <= TARGET_S else "over"
        print(
            f"time to >= 95 % held-out success ({int(row['episodes'])} worlds, "
            f"difficulty {row['difficulty']:.2f}): {row['wall_s'] / 60:.1f} min at {int(row['timesteps'])} "
            f"steps; target {TARGET_S / 60:.0f} min ({verdict})"
        )


if __name__ == "__main__":
    main()
