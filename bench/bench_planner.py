"""World generation and planning speed: can every training reset make a fresh, proven-feasible world?

Per family at difficulty 0.5 and 1: worlds/s of ``generate_family_world`` (layout, clear-point
checks, the planner proving feasibility, and any layout retries), the planner alone on those
worlds (ms), and the cost of one generated world as a fraction of one LidarAvoid-v0 episode of
``max_steps`` steps, timed in this same run (the reference: a reset happens once per episode).

    python bench/bench_planner.py [--worlds 20] [--episode-steps 1000]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from flightsim.envs.env import EnvConfig, LidarAvoidEnv  # noqa: E402
from flightsim.worlds.families import FAMILIES, generate_family_world  # noqa: E402
from flightsim.worlds.planner import shortest_safe_path  # noqa: E402
from flightsim.worlds.world import DEFAULT_VEHICLE_RADIUS  # noqa: E402


def env_step_seconds(steps: int = 400) -> float:
    """Wall seconds per LidarAvoid-v0 step (forward-biased random actions, resets included)."""
    env = LidarAvoidEnv(EnvConfig())
    rng = np.random.default_rng(0)
    acts = rng.uniform(-1.0, 1.0, (steps + 50, 2)).astype(np.float32)
    acts[:, 0] = 0.2 + 0.5 * np.abs(acts[:, 0])
    env.reset(seed=0)
    for a in acts[:50]:  # warm-up
        if any(env.step(a)[2:4]):
            env.reset()
    t0 = time.perf_counter()
    for a in acts[50:]:
        if any(env.step(a)[2:4]):
            env.reset()
    elapsed = time.perf_counter() - t0
    env.close()
    return elapsed / steps


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", type=int, default=20, help="worlds per family and difficulty (20)")
    parser.add_argument(
        "--episode-steps", type=int, default=1000, help="steps in the reference episode (1000)"
    )
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} (figures are comparable only on an idle machine)")
    for family in FAMILIES:  # warm-up: numba caches loaded
        generate_family_world(family, 10_000, 0.5)
    step = env_step_seconds()
    episode = step * args.episode_steps
    print(f"reference: one LidarAvoid-v0 step {step * 1e3:.2f} ms, "
          f"one {args.episode_steps}-step episode {episode:.2f} s")  # fmt: skip
    print(f"{'family':<10} {'d':>4} {'worlds/s':>9} {'gen ms':>8} {'plan ms':>8} {'path m':>7} "
          f"{'gen/episode':>12}")  # fmt: skip
    all_gen = []
    for family in FAMILIES:
        for d in (0.5, 1.0):
            t0 = time.perf_counter()
            worlds = [generate_family_world(family, seed, d) for seed in range(args.worlds)]
            gen = (time.perf_counter() - t0) / args.worlds
            t0 = time.perf_counter()
            for w in worlds:
                shortest_safe_path(w, vehicle_radius=DEFAULT_VEHICLE_RADIUS)
            plan = (time.perf_counter() - t0) / args.worlds
            all_gen.append(gen)
            length = np.mean([w.shortest_path_m for w in worlds])
            print(f"{family:<10} {d:>4.1f} {1 / gen:>9.1f} {gen * 1e3:>8.1f} {plan * 1e3:>8.1f} "
                  f"{length:>7.1f} {gen / episode:>11.2%}")  # fmt: skip
    mean = float(np.mean(all_gen))
    print(f"all families: {1 / mean:.1f} worlds/s, {mean * 1e3:.1f} ms per world "
          f"= {mean / episode:.2%} of one episode")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
