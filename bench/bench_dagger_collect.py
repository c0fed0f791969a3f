"""Figure: DAgger's collection speed with the teachers beside their envs in worker processes
(``vec_env = "sharded"``) against all in the training process (``"batched"``), in the same run.

Each way collects the same steps from the same seeds with the same fresh student, half the
episodes flown by the teacher; the episodes and labels are the same (tests/training/test_dagger.py
checks that), only the time differs. Prints env steps per second each way, the ratio, and the
load average: another process on the cores lowers the sharded figure most.

    python bench/bench_dagger_collect.py [--config training/configs/nav-movers.toml] [--steps 800]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from training import dagger  # noqa: E402
from training.config import load_train_config  # noqa: E402
from training.train import build_model  # noqa: E402
from training.vec_env import make_vec_env  # noqa: E402


def steps_per_second(config_path: Path, vec_env: str, steps: int) -> float:
    """Env steps per second of one DAgger collection of ``steps`` with ``vec_env``."""
    import torch

    torch.set_num_threads(1)  # as avoid-train train runs
    with tempfile.TemporaryDirectory() as tmp:
        config = load_train_config(config_path, [f"run_root={tmp}", f"vec_env={vec_env}"])
        venv = make_vec_env(config, config.resolved_n_envs, config.seed)
        try:
            model = build_model(config, venv, Path(tmp), None)
            rng = np.random.default_rng(0)
            start = time.perf_counter()
            dagger.collect(venv, model.policy, steps, 0.5, model.gamma, rng, config.pretrain.teacher)
            return steps / (time.perf_counter() - start)
        finally:
            venv.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=ROOT / "training" / "configs" / "nav-movers.toml")
    parser.add_argument("--steps", type=int, default=800, help="env steps each way, all envs together")
    args = parser.parse_args()
    rates = {kind: steps_per_second(args.config, kind, args.steps) for kind in ("batched", "sharded")}
    for kind, rate in rates.items():
        print(f"{kind}: {rate:.1f} env steps/s")
    print(f"sharded / batched: {rates['sharded'] / rates['batched']:.2f}x")
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    return 0


if __name__ == "__main__":
    sys.exit(main())
