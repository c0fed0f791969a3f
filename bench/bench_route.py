"""Route planner cost per scan: does mapping and planning fit the companion's 10 Hz loop?

Scans and poses are recorded from LidarNav-v0 episodes (the goal follower flying office, warehouse
and forest worlds at difficulty 0.8, so the maps fill as in flight), then replayed into a fresh
:class:`companion.guidance.route.RoutePlanner` and timed: the map update and the subgoal per scan, and the
scans that replan. Figures are ratios to the scan period (100 ms at 10 Hz), absolute times beside,
and the time with ``switch_margin`` on (each plan also marks the cells near the way flown) against
the default's, on the same scans.

    python bench/bench_route.py [--steps 300] [--switch-margin 1.0]
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

from companion.guidance.route import RouteConfig, RoutePlanner  # noqa: E402
from flightsim.envs.nav_env import LidarNavEnv, NavEnvConfig  # noqa: E402
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
    parser.add_argument("--switch-margin", type=float, default=1.0, help="the margin timed against 0 (1.0)")
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} (figures are comparable only on an idle machine)")
    config = RouteConfig()
    print(f"{'family':<10} {'scans':>6} {'plans':>6} {'median ms':>10} {'p99 ms':>8} {'max ms':>8} "
          f"{'p99/period':>11} {'margin/0':>9}")  # fmt: skip
    every, margin = [], []
    period_ms = SCAN_PERIOD_S * 1e3
    for family in FAMILIES:
        frames = record(family, args.steps)
        t, plans = replay(frames, config)
        t_margin, _ = replay(frames, dataclasses.replace(config, switch_margin=args.switch_margin))
        every.append(t)
        margin.append(t_margin)
        p99 = np.percentile(t, 99)
        print(f"{family:<10} {len(t):>6} {plans:>6} {np.median(t):>10.2f} {p99:>8.2f} "
              f"{t.max():>8.2f} {p99 / period_ms:>10.1%} {t_margin.sum() / t.sum():>8.2f}x")  # fmt: skip
    t, t_margin = np.concatenate(every), np.concatenate(margin)
    median, p99 = np.median(t), np.percentile(t, 99)
    print(
        f"all: median {median:.2f} ms = {median / period_ms:.1%} of the scan period, "
        f"p99 {p99:.2f} ms = {p99 / period_ms:.1%}; switch_margin {args.switch_margin}: "
        f"{t_margin.sum():.0f} ms in all, {t_margin.sum() / t.sum():.2f}x the default's {t.sum():.0f} ms"
    )
    return 0


def replay(frames: list[tuple[np.ndarray, tuple[float, ...]]], config: RouteConfig) -> tuple[np.ndarray, int]:
    """Each frame's map update and subgoal through a fresh planner: the times (ms), and its plans."""
    planner = RoutePlanner(config, NavEnvConfig().scan.max_range)
    times = []
    for scan, (x, y, heading, gx, gy) in frames:
        t0 = time.perf_counter()
        planner.observe(scan, x, y, heading)
        planner.subgoal(x, y, heading, gx, gy)
        times.append(time.perf_counter() - t0)
    return np.array(times) * 1e3, planner.plans


if __name__ == "__main__":
    raise SystemExit(main())
