"""Route planner cost per scan: does mapping and planning fit the companion's 10 Hz loop?

Scans and poses are recorded from LidarNav-v0 episodes (the goal follower flying office, warehouse
and forest worlds at difficulty 0.8, so the maps fill as in flight), then replayed into a fresh
:class:`companion.route.RoutePlanner` and timed: the map update and the subgoal per scan, and the
scans that replan. Figures are ratios to the scan period (100 ms at 10 Hz), absolute times beside.

    python bench/bench_route.py [--steps 300]
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

from companion.route import RouteConfig, RoutePlanner  # noqa: E402
from flightsim.nav_env import LidarNavEnv, NavEnvConfig  # noqa: E402
from training.baselines import GoalFollower  # noqa: E402

SCAN_PERIOD_S = 0.1
FAMILIES = ("office", "warehouse", "forest")


def record(family: str, steps: int) -> list[tuple[np.ndarray, tuple[float, ...]]]:
    """(scan, (x, y, heading, goal_x, goal_y)) of every step of one goal-follower episode."""
    env = LidarNavEnv(NavEnvConfig(route=True))
    obs, _ = env.reset(seed=0, options={"family": family, "world_seed": 1_000_000, "difficulty": 0.8})
    follower = GoalFollower(env.layout)
    action = follower.reset(obs)
    frames = []
    for _ in range(steps):
        state = env._state
        goal = env.world.waypoints[min(env.waypoint_index, len(env.world.waypoints) - 1)]
        pose = (float(state.position[0]), float(state.position[1]), float(state.yaw), goal[0], goal[1])
        frames.append((obs[:360].copy(), pose))
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            break
        action = follower.act(obs)
    env.close()
    return frames


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300, help="steps recorded per family (300)")
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} (figures are comparable only on an idle machine)")
    config = RouteConfig()
    print(f"{'family':<10} {'scans':>6} {'plans':>6} {'median ms':>10} {'p99 ms':>8} {'max ms':>8} "
          f"{'p99/period':>11}")  # fmt: skip
    every = []
    period_ms = SCAN_PERIOD_S * 1e3
    for family in FAMILIES:
        frames = record(family, args.steps)
        planner = RoutePlanner(config, NavEnvConfig().scan.max_range)
        times = []
        for scan, (x, y, heading, gx, gy) in frames:
            t0 = time.perf_counter()
            planner.observe(scan, x, y, heading)
            planner.subgoal(x, y, heading, gx, gy)
            times.append(time.perf_counter() - t0)
        t = np.array(times) * 1e3
        every.append(t)
        p99 = np.percentile(t, 99)
        print(f"{family:<10} {len(t):>6} {planner.plans:>6} {np.median(t):>10.2f} {p99:>8.2f} "
              f"{t.max():>8.2f} {p99 / period_ms:>10.1%}")  # fmt: skip
    t = np.concatenate(every)
    median, p99 = np.median(t), np.percentile(t, 99)
    print(f"all: median {median:.2f} ms = {median / period_ms:.1%} of the scan period, "
          f"p99 {p99:.2f} ms = {p99 / period_ms:.1%}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
