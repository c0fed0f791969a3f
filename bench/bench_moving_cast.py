"""What moving obstacles cost the lidar: the cast of a dynamic world against the same world without
its movers, from the same poses, in the same run (single caster and the batched lidar).

Each dynamic family's world (validation seed, difficulty 0.6) is cast from 200 poses along its start's
first leg, at the env's 1° columns; the figure is the ratio of the times, absolute times beside.
Last, a whole LidarNav-v0 step (vehicle, lidar, scan, reward) in the dynamic world against the
static family's same world (the same seed: the same room), the goal follower flying.

    python bench/bench_moving_cast.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from companion.perception.scan import ScanConfig  # noqa: E402
from flightsim.envs import seeds  # noqa: E402
from flightsim.envs.batch_lidar import BatchLidar  # noqa: E402
from flightsim.envs.env import slice_band  # noqa: E402
from flightsim.envs.nav_env import LidarNavEnv, NavEnvConfig  # noqa: E402
from flightsim.envs.raycast import LidarConfig, VLP16Raycaster  # noqa: E402
from flightsim.worlds.families import DYNAMIC_FAMILIES, generate_family_world  # noqa: E402
from training.baselines import GoalFollower  # noqa: E402

POSES = 200


def poses(world) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Sensor positions from the start toward the first waypoint, level, 0.1 s apart."""
    start = np.asarray(world.start_position, dtype=float)
    goal = np.asarray(world.waypoints[0], dtype=float)
    out = []
    for k in range(POSES):
        p = start + (goal - start) * k / POSES
        out.append((p, np.eye(3), 0.1 * k))
    return out


def time_single(world, at, repeats: int) -> float:
    caster = VLP16Raycaster(LidarConfig())
    caster.cast_points(world, *at[0][:2], time=0.0)  # compile
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        for position, rotation, t in at:
            caster.cast_points(world, position, rotation, time=t)
        best = min(best, time.perf_counter() - t0)
    return best / len(at) * 1e3


def time_batch(world, at, repeats: int, n: int = 8) -> float:
    scan = ScanConfig()
    lidar = BatchLidar(n, LidarConfig(), scan, slice_band(scan))
    rngs = [np.random.default_rng(i) for i in range(n)]
    worlds = [world] * n
    lidar.scans(worlds, np.array([at[0][0]] * n), np.array([at[0][1]] * n), rngs, [0.0] * n)  # compile
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        for position, rotation, t in at:
            lidar.scans(worlds, np.array([position] * n), np.array([rotation] * n), rngs, [t] * n)
        best = min(best, time.perf_counter() - t0)
    return best / len(at) / n * 1e3


def time_env(family: str, seed: int, steps: int = 200) -> float:
    """Milliseconds per LidarNav-v0 step, the goal follower flying (resets where an episode ends)."""
    env = LidarNavEnv(NavEnvConfig(families=DYNAMIC_FAMILIES))
    options = {"family": family, "world_seed": seed, "difficulty": 0.6}
    obs, _ = env.reset(seed=0, options=options)
    follower = GoalFollower(env.layout)
    action = follower.reset(obs)
    env.step(action)  # compile
    t0 = time.perf_counter()
    for _ in range(steps):
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            t_reset = time.perf_counter()
            obs, _ = env.reset(seed=0, options=options)
            t0 += time.perf_counter() - t_reset  # the reset's world generation is not a step
            action = follower.reset(obs)
        else:
            action = follower.act(obs)
    return (time.perf_counter() - t0) / steps * 1e3


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="best of this many passes (5)")
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} (figures are comparable only on an idle machine)")
    print(f"{'family':<18} {'movers':>6} {'static ms':>10} {'moving ms':>10} {'ratio':>6} "
          f"{'batch static':>13} {'batch moving':>13} {'ratio':>6}")  # fmt: skip
    for i, family in enumerate(DYNAMIC_FAMILIES):
        world = generate_family_world(family, seeds.VALIDATION.start + 300 + i, 0.6)
        still = dataclasses.replace(world, moving=())
        at = poses(world)
        s, m = time_single(still, at, args.repeats), time_single(world, at, args.repeats)
        bs, bm = time_batch(still, at, args.repeats), time_batch(world, at, args.repeats)
        print(f"{family:<18} {len(world.moving):>6} {s:>10.3f} {m:>10.3f} {m / s:>5.2f}x "
              f"{bs:>13.3f} {bm:>13.3f} {bm / bs:>5.2f}x")  # fmt: skip
    print(f"{'env step':<18} {'static ms':>10} {'moving ms':>10} {'ratio':>6}")
    for i, family in enumerate(DYNAMIC_FAMILIES):
        seed = seeds.VALIDATION.start + 300 + i
        s, m = time_env(family.removesuffix("-dynamic"), seed), time_env(family, seed)
        print(f"{family:<18} {s:>10.3f} {m:>10.3f} {m / s:>5.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
