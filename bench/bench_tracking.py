"""Scan tracker against ground truth in the dynamic families: how well it tracks what moves.

The goal follower flies LidarNav-v0 episodes in each dynamic family (validation seeds, difficulty
0.6); every step's scan and the vehicle's pose go through :class:`companion.perception.tracking.ScanTracker`,
and the world's moving obstacles, where they were in the middle of the scan's sweep, judge it:

- position and velocity error of the moving track nearest each mover (within 1 m);
- the share of movers tracked as moving within 0.5 s of first sight (first sight: the first scan
  with a tracked-size segment within 0.5 m of the mover);
- once a mover has been tracked as moving, the share of the scans that show it (a tracked-size
  segment within 0.5 m) in which it still is: a track that drops out and back flickers in the
  policy's frame and the shield's movers;
- the share of scans with a mover moving faster than 0.3 m/s within 2 m of the vehicle (its
  surface from the vehicle's centre) in which it is tracked as moving: where the shield and the
  policy need it most;
- the share of scans with a moving track more than 1 m from every mover (a static return taken
  for moving, or a track left behind);
- the tracker's time per scan, as a share of the scan period.

Then the same follower in the static families (``--static`` worlds each, validation seeds too):
every moving track there is a static return taken for moving while the vehicle flies. By default
the env is LidarNav-v0's own (an exact lidar, the ideal response); ``--train-env`` flies training's
(``training/configs/nav.toml``: range noise and dropout, a random autopilot response, the drift
estimate and the route, kept clear of what the env's own tracker says moves).

    python bench/bench_tracking.py [--worlds 5] [--static 4] [--steps 300] [--train-env]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from companion.perception.tracking import ScanTracker  # noqa: E402
from flightsim.envs import seeds  # noqa: E402
from flightsim.envs.nav_env import LidarNavEnv, NavEnvConfig  # noqa: E402
from flightsim.envs.raycast import REVOLUTION_S  # noqa: E402
from flightsim.worlds.families import ALL_FAMILIES, DYNAMIC_FAMILIES, FAMILIES  # noqa: E402
from training.baselines import GoalFollower  # noqa: E402
from training.config import load_train_config  # noqa: E402

SCAN_PERIOD_S = 0.1


def episode(config: NavEnvConfig, family: str, seed: int, steps: int) -> dict[str, list[float]]:
    """One goal-follower episode: the tracker's errors and events against the truth."""
    env = LidarNavEnv(config)
    obs, _ = env.reset(seed=0, options={"family": family, "world_seed": seed, "difficulty": 0.6})
    follower = GoalFollower(env.layout)
    action = follower.reset(obs)
    tracker = ScanTracker(max_range=env.config.scan.max_range)
    movers = env.world.moving
    seen: dict[int, float] = {}
    tracked: dict[int, float] = {}
    out: dict[str, list[float]] = {k: [] for k in ("position", "velocity", "false", "ms", "kept", "close")}
    for _ in range(steps):
        state, t = env._state, env.sim_time
        pose = (float(state.position[0]), float(state.position[1]), float(state.yaw))
        t0 = time.perf_counter()
        result = tracker.update(obs[:360], pose, t)
        out["ms"].append((time.perf_counter() - t0) * 1e3)
        mid = t - REVOLUTION_S / 2.0
        truth = np.array([m.positions(mid)[0] for m in movers])
        velocity = np.array([(m.positions(mid + 0.05)[0] - m.positions(mid - 0.05)[0]) / 0.1 for m in movers])
        segments = tracker.segments(obs[:360], pose)
        for k in range(len(movers)):
            shown = any(np.hypot(*(s.centre - truth[k])) < 0.5 for s in segments)
            if k not in seen and shown:
                seen[k] = t
            near = [tr for tr in result.moving if np.hypot(*(tr.position - truth[k])) < 1.0]
            if shown and k in tracked:
                out["kept"].append(float(bool(near)))
            if np.hypot(*velocity[k]) > 0.3 and movers[k].clearance(state.position[None], mid)[0] < 2.0:
                out["close"].append(float(bool(near)))
            if near:
                best = min(near, key=lambda tr: np.hypot(*(tr.position - truth[k])))
                out["position"].append(float(np.hypot(*(best.position - truth[k]))))
                out["velocity"].append(float(np.hypot(*(best.velocity - velocity[k]))))
                tracked.setdefault(k, t)
        stray = [tr for tr in result.moving if not movers or np.min(np.hypot(*(truth - tr.position).T)) > 1.0]
        out["false"].append(float(bool(stray)))
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            break
        action = follower.act(obs)
    env.close()
    out["seen"] = [float(len(seen))]
    out["quick"] = [float(sum(k in tracked and tracked[k] - seen[k] <= 0.5 + 1e-9 for k in seen))]
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", type=int, default=5, help="validation worlds per family (5)")
    parser.add_argument("--static", type=int, default=4, help="validation worlds per static family (4)")
    parser.add_argument("--steps", type=int, default=300, help="steps per episode at most (300)")
    parser.add_argument(
        "--train-env", action="store_true", help="fly training's env (nav.toml), not the default"
    )
    args = parser.parse_args()
    config = NavEnvConfig(families=ALL_FAMILIES)
    if args.train_env:  # the follower asks no sideways speed
        train = load_train_config(REPO / "training/configs/nav.toml").env_config()
        config = replace(train, families=ALL_FAMILIES, sideways=False)
    print(f"load average {os.getloadavg()[0]:.2f} (the time figure is comparable only on an idle machine)")
    print(f"env: {'training/configs/nav.toml' if args.train_env else 'LidarNav-v0 defaults'}")
    print(f"{'family':<18} {'scans':>6} {'pos err m':>10} {'p95':>6} {'vel err m/s':>12} {'p95':>6} "
          f"{'tracked<=0.5s':>14} {'kept':>6} {'within 2 m':>16} {'false scans':>12} "
          f"{'p99/period':>11}")  # fmt: skip
    for families, worlds, offset in ((DYNAMIC_FAMILIES, args.worlds, 200), (FAMILIES, args.static, 300)):
        total: dict[str, list[float]] = {}
        if not worlds:
            continue
        for i, family in enumerate(families):
            first = seeds.VALIDATION.start + offset + 10 * i
            runs = [episode(config, family, first + j, args.steps) for j in range(worlds)]
            f = {key: [v for r in runs for v in r[key]] for key in runs[0]}
            for key, values in f.items():
                total.setdefault(key, []).extend(values)
            print(_row(family, f))
        if total:
            print(_row("all dynamic" if families == DYNAMIC_FAMILIES else "all static", total))
    return 0


def _row(name: str, f: dict[str, list[float]]) -> str:
    pos, vel, ms = np.array(f["position"]), np.array(f["velocity"]), np.array(f["ms"])
    quick = f"{sum(f['quick']):.0f}/{sum(f['seen']):.0f}"
    kept = f"{np.mean(f['kept']):.1%}" if f["kept"] else "-"
    close = f"{np.mean(f['close']):.1%} of {len(f['close'])}" if f["close"] else "-"
    errors = (
        f"{pos.mean():>10.3f} {np.percentile(pos, 95):>6.3f} "
        f"{vel.mean():>12.3f} {np.percentile(vel, 95):>6.3f}"
        if len(pos)
        else f"{'-':>10} {'-':>6} {'-':>12} {'-':>6}"
    )
    return (
        f"{name:<18} {len(ms):>6} {errors} {quick:>14} {kept:>6} {close:>16} {np.mean(f['false']):>11.2%} "
        f"{np.percentile(ms, 99) / (SCAN_PERIOD_S * 1e3):>10.1%}"
    )


if __name__ == "__main__":
    raise SystemExit(main())
