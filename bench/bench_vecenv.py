"""Batched vector env against SubprocVecEnv: env steps per second by N, and training throughput.

Figures (issue 16), each measured side by side in this one run on this machine:

1. Env steps/s with random actions through the training path (``make_vec_env``: the vector env,
   VecMonitor, VecFrameStack), ``vec_env = "batched"`` (all N in this process, flown and scanned
   in compiled batches) against ``vec_env = "subproc"`` (SB3's SubprocVecEnv, forkserver, one
   process per env), for LidarNav-v0 with nav.toml's env settings and LidarAvoid-v0 with
   shipped.toml's (training's TrainingWorlds included), at N = 1, 2, 4, 8, 16, 32 (at N = 1 the
   "subproc" path is a DummyVecEnv in this process, as ``make_vec_env`` builds it). Episodes that
   end are reset (a new generated world each time) inside the timing. The batched/subproc ratio
   is printed beside both absolute rates, and beside it the CPU time one env step costs (all
   processes: this one and SubprocVecEnv's workers), which the neighbours' load moves far less.
2. Training throughput during ``learn`` (PPO with the config's hyperparameters and n_envs,
   checkpoints and evaluation off), batched against subproc: env steps per second including
   inference and the PPO updates, and how its wall-clock time splits between collecting rollouts
   (what the vector env changes) and the PPO updates (which it does not).

The machine is shared (a niced training run, other engineers): the load average is printed with
every row, and only ratios measured in the same run mean anything.

    python bench/bench_vecenv.py [--seconds 4] [--n 1 2 4 8 16 32] [--learn-steps 8192]
                                 [--learn-configs training/configs/nav.toml] [--skip-learn]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from training.config import TrainConfig, load_train_config  # noqa: E402
from training.train import build_model, make_vec_env  # noqa: E402

ENVS = {
    "LidarNav-v0 (nav.toml env)": REPO / "training/configs/nav.toml",
    "LidarAvoid-v0 (shipped.toml env)": REPO / "training/configs/shipped.toml",
}


def load() -> str:
    return f"load {os.getloadavg()[0]:.1f}"


def cpu_seconds(pids: list[int]) -> float:
    """User + system CPU seconds used so far by these processes (Linux ``/proc``)."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    for pid in pids:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        total += (int(fields[11]) + int(fields[12])) / tick  # utime, stime
    return total


def env_rate(config: TrainConfig, n: int, seconds: float) -> tuple[float, float]:
    """Env steps/s (wall clock) of ``make_vec_env`` with random actions, resets included, and the
    CPU time per env step of every process involved (this one and the workers), in µs."""
    venv = make_vec_env(config, n, seed=0)
    pids = [os.getpid(), *(p.pid for p in getattr(venv.unwrapped, "processes", []))]
    try:
        venv.reset()
        rng = np.random.default_rng(0)
        for _ in range(max(3, 30 // n)):  # warm-up: compiled kernels loaded, workers running
            venv.step(rng.uniform(-1.0, 1.0, (n, 2)).astype(np.float32))
        steps, start, cpu = 0, time.perf_counter(), cpu_seconds(pids)
        while time.perf_counter() - start < seconds:
            for _ in range(10):
                venv.step(rng.uniform(-1.0, 1.0, (n, 2)).astype(np.float32))
            steps += 10 * n
        wall, cpu = time.perf_counter() - start, cpu_seconds(pids) - cpu
        return steps / wall, cpu / steps * 1e6
    finally:
        venv.close()


def learn_rate(config_path: Path, vec_env: str, steps: int) -> tuple[float, float, float]:
    """Env steps/s during ``model.learn`` (inference and PPO updates included), and the wall-clock
    seconds of it spent collecting rollouts and in the PPO updates."""
    import torch

    torch.set_num_threads(1)  # as training.train does
    with tempfile.TemporaryDirectory() as tmp:
        config = load_train_config(config_path, [f"run_root='{tmp}'", f"vec_env='{vec_env}'"])
        venv = make_vec_env(config, config.resolved_n_envs, config.seed)
        try:
            model = build_model(config, venv, Path(tmp), None)
            model.verbose = 0
            spent = {"collect_rollouts": 0.0, "train": 0.0}
            for name in spent:  # time the two halves of learn where SB3 calls them
                method = getattr(model, name)

                def timed(*args, _method=method, _name=name, **kwargs):
                    start = time.perf_counter()
                    try:
                        return _method(*args, **kwargs)
                    finally:
                        spent[_name] += time.perf_counter() - start

                setattr(model, name, timed)
            rollout = config.ppo.n_steps * config.resolved_n_envs
            steps = max(rollout, steps // rollout * rollout)
            start = time.perf_counter()
            model.learn(total_timesteps=steps)
            return steps / (time.perf_counter() - start), spent["collect_rollouts"], spent["train"]
        finally:
            venv.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=4.0, help="timing per measurement")
    parser.add_argument("--n", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32])
    parser.add_argument("--learn-steps", type=int, default=8192, help="env steps of each learn run")
    parser.add_argument("--learn-configs", type=Path, nargs="+", default=[REPO / "training/configs/nav.toml"])
    parser.add_argument("--skip-learn", action="store_true")
    args = parser.parse_args()

    print(f"{os.cpu_count()} cores, {load()}")
    print("1. env steps/s, random actions, make_vec_env (VecMonitor + VecFrameStack), resets included")
    for name, path in ENVS.items():
        print(f"  {name}")
        print(f"    {'N':>3}  {'batched':>9}  {'subproc':>9}  ratio   CPU µs/step batched, subproc, ratio")
        for n in args.n:
            batched, b_cpu = env_rate(load_train_config(path, ["vec_env='batched'"]), n, args.seconds)
            subproc, s_cpu = env_rate(load_train_config(path, ["vec_env='subproc'"]), n, args.seconds)
            print(
                f"    {n:>3}  {batched:>9.0f}  {subproc:>9.0f}  {batched / subproc:4.1f}x   "
                f"{b_cpu:6.0f} {s_cpu:6.0f}  {s_cpu / b_cpu:4.1f}x  ({load()})"
            )
    if args.skip_learn:
        return
    print("2. training throughput during learn (PPO updates included; checkpoints and evaluation off)")
    for path in args.learn_configs:
        config = load_train_config(path)
        batched, b_roll, b_train = learn_rate(path, "batched", args.learn_steps)
        subproc, s_roll, s_train = learn_rate(path, "subproc", args.learn_steps)
        print(
            f"  {path.name} ({config.resolved_n_envs} envs, {args.learn_steps} steps): batched {batched:.0f} "
            f"env steps/s, subproc {subproc:.0f}: {batched / subproc:.1f}x ({load()})\n"
            f"    of which collecting rollouts {b_roll:.1f} s vs {s_roll:.1f} s ({s_roll / b_roll:.1f}x), "
            f"PPO updates {b_train:.1f} s vs {s_train:.1f} s (the same work either way)"
        )


if __name__ == "__main__":
    main()
