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

``--reference GITREF`` adds the batched env of another commit (its tree exported to a temporary
directory by ``git archive``) as a third column, with the speed-up of this tree's over it: each
measurement then runs in a fresh process of its own, the trees taking turns, so both meet the same
load.

    python bench/bench_vecenv.py [--seconds 4] [--n 1 2 4 8 16 32] [--learn-steps 8192]
                                 [--learn-configs training/configs/nav.toml] [--skip-learn]
                                 [--reference GITREF] [--envs nav avoid]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
#: the tree whose simulator and training code are measured (a --reference child sets it)
CODE = Path(os.environ.get("BENCH_CODE_ROOT", REPO))
sys.path.insert(0, str(CODE))

from training.config import TrainConfig, load_train_config  # noqa: E402
from training.train import build_model  # noqa: E402
from training.vec_env import make_vec_env  # noqa: E402

ENVS = {  # config files relative to the tree measured
    "nav": ("LidarNav-v0 (nav.toml env)", "training/configs/nav.toml"),
    "avoid": ("LidarAvoid-v0 (shipped.toml env)", "training/configs/shipped.toml"),
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
            venv.step(rng.uniform(-1.0, 1.0, (n, *venv.action_space.shape)).astype(np.float32))
        steps, start, cpu = 0, time.perf_counter(), cpu_seconds(pids)
        while time.perf_counter() - start < seconds:
            for _ in range(10):
                venv.step(rng.uniform(-1.0, 1.0, (n, *venv.action_space.shape)).astype(np.float32))
            steps += 10 * n
        wall, cpu = time.perf_counter() - start, cpu_seconds(pids) - cpu
        return steps / wall, cpu / steps * 1e6
    finally:
        venv.close()


def learn_rate(config_path: Path | str, vec_env: str, steps: int) -> tuple[float, float, float]:
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


def run_one(code: Path, what: str, config: str, vec_env: str, n: int, seconds: float) -> tuple[float, ...]:
    """One measurement in this process of ``code``'s tree (``what`` = "env": :func:`env_rate` of
    ``n`` envs; "learn": :func:`learn_rate` of ``n`` steps; ``config`` relative to the tree)."""
    if what == "env":
        return env_rate(load_train_config(code / config, [f"vec_env='{vec_env}'"]), n, seconds)
    return learn_rate(code / config, vec_env, n)


def measure(
    code: Path | None, what: str, config: str, vec_env: str, n: int, seconds: float
) -> tuple[float, ...]:
    """:func:`run_one` here (``code`` None), or in a fresh process running ``code``'s tree."""
    if code is None:
        return run_one(REPO, what, config, vec_env, n, seconds)
    child = [sys.executable, __file__, "--child", what, config, vec_env, str(n), str(seconds)]
    out = subprocess.run(
        child, cwd=code, env={**os.environ, "BENCH_CODE_ROOT": str(code)}, capture_output=True, text=True
    )
    if out.returncode:
        raise SystemExit(f"measurement {child[2:]} in {code} failed:\n{out.stderr[-2000:]}")
    return tuple(json.loads(out.stdout.splitlines()[-1]))


def export_tree(ref: str, into: Path) -> Path:
    """``git archive`` of ``ref`` unpacked into ``into`` (exit 2 naming it when git refuses)."""
    archive = subprocess.run(["git", "-C", str(REPO), "archive", ref], capture_output=True)
    if archive.returncode:
        print(f"--reference {ref}: {archive.stderr.decode().strip()}", file=sys.stderr)
        raise SystemExit(2)
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive.stdout, check=True)
    return into


def env_table(reference: Path | None, seconds: float, ns: list[int], envs: list[str]) -> None:
    """Figure 1; with a reference tree every measurement runs in a fresh process, the trees alternating."""
    here = None if reference is None else REPO
    print("1. env steps/s, random actions, make_vec_env (VecMonitor + VecFrameStack), resets included")
    for key in envs:
        name, config = ENVS[key]
        print(f"  {name}")
        head = f"    {'N':>3}  {'batched':>9}"
        if reference is not None:
            head += f"  {'ref':>9}  vs ref"
        cpu_head = "batched, ref (ref/batched)" if reference else "batched"
        print(f"{head}  {'subproc':>9}  ratio   CPU µs/step {cpu_head}, subproc, ratio")
        for n in ns:
            batched, b_cpu = measure(here, "env", config, "batched", n, seconds)
            row = f"    {n:>3}  {batched:>9.0f}"
            cpus = f"{b_cpu:6.0f}"
            if reference is not None:
                ref, r_cpu = measure(reference, "env", config, "batched", n, seconds)
                row += f"  {ref:>9.0f}  {batched / ref:4.2f}x"
                cpus += f" {r_cpu:6.0f} ({r_cpu / b_cpu:4.2f}x)"
            subproc, s_cpu = measure(here, "env", config, "subproc", n, seconds)
            print(
                f"{row}  {subproc:>9.0f}  {batched / subproc:4.1f}x   {cpus} {s_cpu:6.0f}"
                f"  {s_cpu / b_cpu:4.1f}x  ({load()})"
            )


def learn_table(reference: Path | None, steps: int, configs: list[str]) -> None:
    """Figure 2, with the reference tree's batched env beside it when given."""
    here = None if reference is None else REPO
    print("2. training throughput during learn (PPO updates included; checkpoints and evaluation off)")
    for config in configs:
        n_envs = load_train_config(REPO / config).resolved_n_envs
        batched, b_roll, b_train = measure(here, "learn", config, "batched", steps, 0.0)
        line = f"  {Path(config).name} ({n_envs} envs, {steps} steps): batched {batched:.0f} env steps/s"
        if reference is not None:
            ref, r_roll, _ = measure(reference, "learn", config, "batched", steps, 0.0)
            line += f", ref {ref:.0f} ({batched / ref:.2f}x; rollouts {r_roll:.1f} s vs {b_roll:.1f} s)"
        subproc, s_roll, s_train = measure(here, "learn", config, "subproc", steps, 0.0)
        print(
            f"{line}, subproc {subproc:.0f}: {batched / subproc:.1f}x ({load()})\n"
            f"    of which collecting rollouts {b_roll:.1f} s vs {s_roll:.1f} s ({s_roll / b_roll:.1f}x), "
            f"PPO updates {b_train:.1f} s vs {s_train:.1f} s (the same work either way)"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=4.0, help="timing per measurement")
    parser.add_argument("--n", type=int, nargs="+", default=[1, 2, 4, 8, 16, 32])
    parser.add_argument("--envs", nargs="+", choices=list(ENVS), default=list(ENVS))
    parser.add_argument("--learn-steps", type=int, default=8192, help="env steps of each learn run")
    parser.add_argument("--learn-configs", nargs="+", default=["training/configs/nav.toml"])
    parser.add_argument("--skip-learn", action="store_true")
    parser.add_argument("--reference", metavar="GITREF", help="also measure this commit's batched env")
    parser.add_argument("--child", nargs=5, help=argparse.SUPPRESS)  # what config vec_env n seconds
    args = parser.parse_args()
    if args.child:  # one measurement for a parent run; prints it as JSON
        what, config, vec_env, n, seconds = args.child
        print(json.dumps(list(run_one(CODE, what, config, vec_env, int(n), float(seconds)))))
        return
    print(f"{os.cpu_count()} cores, {load()}")
    with tempfile.TemporaryDirectory() as tmp:
        reference = export_tree(args.reference, Path(tmp)) if args.reference else None
        if reference is not None:
            print(f"reference: {args.reference} (each figure measured in a fresh process)")
        env_table(reference, args.seconds, args.n, args.envs)
        if not args.skip_learn:
            learn_table(reference, args.learn_steps, args.learn_configs)


if __name__ == "__main__":
    main()
