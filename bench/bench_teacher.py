"""Figure: the robust teacher's time per label (``PredictiveExpert.act``, what DAgger's ``collect``
spends most of its time in), against the teacher as it was before: the hardest response predicted
for every candidate, not only for those its pick needs. Measured in the same run, step by step on
the same states, with every label of both compared (a mismatch is a bug: the pick must be the same).

Episodes of training's env (the config's: sideways action, random response, drift) on training
worlds, flown as DAgger's student episodes are flown, by something other than the teacher: its
label plus Gaussian noise (``--noise``), so that some steps need the recovery (no candidate
predicted to stop clear), where the hardest response is predicted for every candidate again.

Prints the mean and median wall time per label of each, the ratio of the means (the share of
``collect``'s teacher time left), the share of recovery steps, the count of mismatched labels, and
the load average: the machine's speed and load move the absolute times, the ratio much less.

    python bench/bench_teacher.py [--config training/configs/nav.toml] [--steps 400] [--noise 0.3]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from flightsim.envs.nav_env import LidarNavEnv  # noqa: E402
from flightsim.envs.seeds import TRAIN  # noqa: E402
from training.config import load_train_config  # noqa: E402
from training.predictive_expert import ROBUST, PredictiveExpert, pick, robust_expert  # noqa: E402


class FullExpert(PredictiveExpert):
    """The robust teacher before: the hardest response predicted for every candidate."""

    def __init__(self, env: LidarNavEnv) -> None:
        super().__init__(env, ROBUST)
        self.recoveries = 0

    def _pick_through_hardest(
        self, commands: np.ndarray, steps: tuple[int, int, float], held: tuple[float, float],
        spare: np.ndarray, near: np.ndarray, score: np.ndarray,
    ) -> int:  # fmt: skip
        response, state = self.env.response, self.env.true_state
        assert response is not None
        slow = response.predict(float(state.yaw), commands, *steps, self._hardest, held)
        excess = self._excess(slow, state.position)[0]
        spare = np.minimum(spare, excess.min(axis=1))
        near = np.minimum(near, excess[:, : steps[0]].min(axis=1))
        self.recoveries += not (spare > 0.0).any()
        return pick(spare, near, score, self.config.recovery_tolerance)


def fly_episode(env: LidarNavEnv, noise: float, rng: np.random.Generator, labels: int) -> dict[str, list]:
    """One episode (``env`` just reset) flown on the teacher's label plus noise, up to ``labels``
    labels: each label's wall time per teacher, s (``"new"``, ``"full"``), and whether the two
    differed and whether the step was in recovery (``"mismatch"``, ``"recovery"``)."""
    new, full = robust_expert(env), FullExpert(env)
    label, _ = new.reset(), full.reset()
    out: dict[str, list] = {"new": [], "full": [], "mismatch": [], "recovery": []}
    while len(out["new"]) < labels:
        action = np.clip(label + rng.normal(0.0, noise, label.shape), -1.0, 1.0).astype(np.float32)
        _, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            break
        teachers = [("new", new), ("full", full)]
        chosen, recoveries = {}, full.recoveries
        for name, teacher in teachers if len(out["new"]) % 2 else teachers[::-1]:  # each first half the time
            start = time.perf_counter()
            chosen[name] = teacher.act()
            out[name].append(time.perf_counter() - start)
        out["mismatch"].append(not np.array_equal(chosen["new"], chosen["full"]))
        out["recovery"].append(full.recoveries > recoveries)
        label = chosen["new"]
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=ROOT / "training" / "configs" / "nav.toml")
    parser.add_argument("--steps", type=int, default=400, help="labels timed (env steps)")
    parser.add_argument("--noise", type=float, default=0.3, help="std of the noise on the flown label")
    parser.add_argument("--seed", type=int, default=0, help="the first training world's index")
    args = parser.parse_args()
    env = LidarNavEnv(load_train_config(args.config).env_config())
    rng = np.random.default_rng(args.seed)
    runs: dict[str, list] = {"new": [], "full": [], "mismatch": [], "recovery": []}
    episodes = 0
    while len(runs["new"]) < args.steps:
        env.reset(seed=TRAIN[args.seed + episodes])
        episodes += 1
        for name, values in fly_episode(env, args.noise, rng, args.steps - len(runs["new"])).items():
            runs[name] += values
    means = {name: float(np.mean(runs[name])) for name in ("new", "full")}
    for name, description in (("new", "the hardest as the pick needs"), ("full", "the hardest for all")):
        print(f"{name:4s} ({description}): mean {means[name] * 1e3:.2f} ms, median"
              f" {np.median(runs[name]) * 1e3:.2f} ms per label")  # fmt: skip
    print(f"new / full mean: {means['new'] / means['full']:.2f}x over {args.steps} labels in {episodes}"
          f" episodes, {np.mean(runs['recovery']):.1%} of them in recovery")  # fmt: skip
    mismatches = sum(runs["mismatch"])
    print(f"mismatched labels: {mismatches}")
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    return 1 if mismatches else 0


if __name__ == "__main__":
    sys.exit(main())
