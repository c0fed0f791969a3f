"""Environment throughput: LidarAvoid-v0 steps per second, and where a step's time goes.

Figures (issue 2), each against the target of 5,000 env steps/s per core with 16 × 360 rays:

    one env in one process             1° azimuth (16 × 360 rays) and 0.2° (16 × 1,800, the real sensor)
    SB3 SubprocVecEnv with 2 envs      the same two, total steps/s across both workers

then LidarNav-v0 against LidarAvoid-v0 in the same process (issue 12: the goal task's env adds
goal/velocity features, waypoint bookkeeping, and a family world generated and planned on every
reset; its resets are counted as they come), then a per-step breakdown over the poses of a real
flight: JSBSim vehicle (12 physics steps of JSBSim plus the compiled cascaded controller), ray cast
and point cloud (apart, and in the one call the env makes), the companion's ``scan_from_points``,
clearance/collision, and the rest (reward,
info, bookkeeping, resets). Actions are a
fixed random sequence (forward-biased); episodes that end are reset (a new generated world each
time), and the resets are counted in the figures. Each figure stands beside references measured in
the same run: real time (a step is 0.1 s of flight, so steps/s ÷ 10 = × real time), the bare
vehicle alone (the floor no env can beat), and, for the ray cast, the previous two-call
implementation (``cast`` then ``grid_to_points``, still the path with lidar noise or dropout)
against ``cast_points``. The load average is printed: compare ratios, not absolute rates.

    /work/venv/bin/python bench/bench_env.py [--steps 3000] [--difficulty 0.5] [--skip-subproc] [--nav-only]
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

from companion.perception.scan import scan_from_points  # noqa: E402
from flightsim.envs.env import CONTROL_HZ, EnvConfig, LidarAvoidEnv  # noqa: E402
from flightsim.envs.raycast import LidarConfig, grid_to_points  # noqa: E402
from flightsim.vehicle.control import Setpoint  # noqa: E402

TARGET_PER_CORE = 5000.0


def actions(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.uniform(-1.0, 1.0, (n, 2)).astype(np.float32)
    a[:, 0] = 0.2 + 0.5 * np.abs(a[:, 0])
    return a


def run_single(cfg: EnvConfig, n: int, env_class: type = LidarAvoidEnv) -> tuple[float, float, int]:
    """Steps/s of one env in this process by wall clock and by CPU time, and the resets included."""
    env = env_class(cfg)
    acts = actions(n)
    env.reset(seed=0)
    for a in acts[:50]:  # warm-up: numba caches loaded, first allocations done
        if any(env.step(a)[2:4]):
            env.reset()
    env.reset(seed=1)
    resets = 0
    t0, c0 = time.perf_counter(), time.process_time()
    for a in acts:
        _, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()
            resets += 1
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
    env.close()
    return n / elapsed, n / cpu, resets


def _make(cfg: EnvConfig):
    return lambda: LidarAvoidEnv(cfg)


def run_subproc(cfg: EnvConfig, n: int, n_envs: int = 2) -> float:
    """Total steps/s of an SB3 SubprocVecEnv (auto-resetting workers)."""
    from stable_baselines3.common.vec_env import SubprocVecEnv

    vec = SubprocVecEnv([_make(cfg) for _ in range(n_envs)])
    vec.seed(0)
    vec.reset()
    acts = actions(n)
    for a in acts[:50]:
        vec.step(np.stack([a] * n_envs))
    t0 = time.perf_counter()
    for a in acts:
        vec.step(np.stack([a] * n_envs))
    elapsed = time.perf_counter() - t0
    vec.close()
    return n * n_envs / elapsed


def breakdown(cfg: EnvConfig, n: int) -> dict[str, float]:
    """CPU seconds per step of each part, timed separately over the poses of one flight."""
    env = LidarAvoidEnv(cfg)
    env.reset(seed=2)
    acts = actions(n, seed=2)
    states, setpoints, worlds = [], [], []
    for a in acts:  # record a flight: vehicle states and the setpoints that produced them
        state = env._state
        setpoints.append(
            Setpoint.from_body(float(a[0]) * cfg.max_speed, 0.0, state.yaw,
                               yaw_rate=float(a[1]) * cfg.max_yaw_rate, altitude=env._altitude)
        )  # fmt: skip
        _, _, terminated, truncated, _ = env.step(a)
        states.append(env._state)
        worlds.append(env.world)
        if terminated or truncated:
            env.reset()
    caster, band, scan_cfg = env._caster, env._slice_band, cfg.scan
    poses = [(s.position, s.rotation()) for s in states]
    out: dict[str, float] = {}

    vehicle = env._vehicle
    vehicle.reset(states[0].position, states[0].yaw)
    t0 = time.process_time()
    for sp in setpoints:
        vehicle.step(sp)
    out["JSBSim vehicle (12 physics steps + controller)"] = (time.process_time() - t0) / n

    t0 = time.process_time()
    grids = [caster.cast(w, p, r) for w, (p, r) in zip(worlds, poses, strict=True)]
    out["lidar ray cast (cast)"] = (time.process_time() - t0) / n
    t0 = time.process_time()
    for g in grids:
        grid_to_points(g, band)
    out["point cloud (grid_to_points)"] = (time.process_time() - t0) / n
    t0 = time.process_time()
    clouds = [caster.cast_points(w, p, r, None, band) for w, (p, r) in zip(worlds, poses, strict=True)]
    out["both in one call, as the env does (cast_points)"] = (time.process_time() - t0) / n
    t0 = time.process_time()
    for c in clouds:
        scan_from_points(c, scan_cfg)
    out["companion scan_from_points"] = (time.process_time() - t0) / n
    t0 = time.process_time()
    for w, (p, _) in zip(worlds, poses, strict=True):
        w.clearance(p)
    out["clearance (collision check)"] = (time.process_time() - t0) / n
    out["points per scan (after slice pre-filter)"] = float(np.mean([len(c) for c in clouds]))

    env.reset(seed=2)
    t0 = time.process_time()
    for a in acts:
        if any(env.step(a)[2:4]):
            env.reset()
    out["whole env.step"] = (time.process_time() - t0) / n
    parts = ("JSBSim vehicle", "both in one call", "companion scan", "clearance")
    out["the rest (env bookkeeping, reward, info, resets)"] = out["whole env.step"] - sum(
        v for k, v in out.items() if k.startswith(parts)
    )
    env.close()
    return out


def nav_vs_avoid(n: int, rounds: int = 3) -> None:
    """LidarNav-v0 and LidarAvoid-v0 (default configs), alternated ``rounds`` times so that load
    changes hit both alike; the CPU-time rates are the comparable ones. LidarNav-v0 flies the random
    autopilot response by default, LidarAvoid-v0 the ideal one: a third row shows the nav env with
    the ideal response, so the goal task's own cost and the response model's are apart."""
    from flightsim.envs.nav_env import LidarNavEnv, NavEnvConfig

    envs = (
        ("LidarAvoid-v0", EnvConfig(), LidarAvoidEnv),
        ("LidarNav-v0", NavEnvConfig(), LidarNavEnv),
        ("LidarNav-v0 ideal", NavEnvConfig(autopilot_response="ideal"), LidarNavEnv),
    )
    totals = {name: [0.0, 0.0, 0] for name, _, _ in envs}
    for _ in range(rounds):
        for name, cfg, cls in envs:
            rate, cpu_rate, resets = run_single(cfg, n // rounds, cls)
            totals[name][0] += n // rounds / rate
            totals[name][1] += n // rounds / cpu_rate
            totals[name][2] += resets
    steps = rounds * (n // rounds)
    print(f"\nLidarNav-v0 vs LidarAvoid-v0 (default configs, {steps} steps each, alternated {rounds}x):")
    print(f"{'env':18s} {'steps/s':>9s} {'per CPU-s':>9s} {'resets':>7s}  vs LidarAvoid-v0 per CPU-s")
    avoid = totals["LidarAvoid-v0"][1]
    for name, (wall, cpu, resets) in totals.items():
        print(f"{name:18s} {steps / wall:9.0f} {steps / cpu:9.0f} {resets:7d}  {avoid / cpu:.2f}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000, help="timed steps per figure")
    parser.add_argument("--difficulty", type=float, default=0.5)
    parser.add_argument("--skip-subproc", action="store_true", help="only the single-process figures")
    parser.add_argument("--nav-only", action="store_true", help="only LidarNav-v0 vs LidarAvoid-v0")
    args = parser.parse_args()
    if args.nav_only:
        print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}, cpus: {os.cpu_count()}")
        nav_vs_avoid(args.steps)
        print(f"\nload average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
        return 0

    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}, cpus: {os.cpu_count()}")
    print(f"target: >= {TARGET_PER_CORE:,.0f} env steps/s per core with 16 x 360 rays\n")
    rows = []
    for step_deg in (1.0, 0.2):
        cfg = EnvConfig(difficulty=args.difficulty, lidar=LidarConfig(azimuth_step_deg=step_deg))
        rays = 16 * round(360 / step_deg)
        rate, cpu_rate, resets = run_single(cfg, args.steps)
        rows.append((f"1 env, 1 process, {step_deg} deg ({rays} rays)", rate, rate, cpu_rate, resets))
        if not args.skip_subproc:
            total = run_subproc(cfg, args.steps // 2)
            rows.append((f"SubprocVecEnv x2, {step_deg} deg ({rays} rays)", total, total / 2, None, None))
    print("steps/s by wall clock; 'per CPU-s' = steps per second of this process's own CPU time (less")
    print("sensitive to other load; not available for the subprocess workers)")
    print(
        f"{'configuration':44s} {'x real time':>11s} {'steps/s':>9s} {'per core':>9s} {'per CPU-s':>9s} "
        f"{'vs target':>9s}"
    )
    for name, rate, per_core, cpu_rate, resets in rows:
        note = f"   ({resets} resets incl.)" if resets is not None else ""
        best = cpu_rate if cpu_rate is not None else per_core
        cpu = f"{cpu_rate:9.0f}" if cpu_rate is not None else f"{'-':>9s}"
        print(
            f"{name:44s} {rate / CONTROL_HZ:10.0f}x {rate:9.0f} {per_core:9.0f} {cpu} "
            f"{best / TARGET_PER_CORE:8.0%}{note}"
        )

    nav_vs_avoid(args.steps)
    print("\nwhere a step's CPU time goes (1 deg azimuth, same flight, each part timed on its own):")
    parts = breakdown(EnvConfig(difficulty=args.difficulty), min(args.steps, 2000))
    total = parts["whole env.step"]
    for name, value in parts.items():
        if name.startswith("points"):
            print(f"  {name:50s} {value:8.0f}")
        else:
            print(f"  {name:50s} {value * 1e6:8.1f} us  {value / total:6.1%}")
    print("  (the env's share of a step = vehicle + cast_points + scan + clearance + the rest; cast and")
    print("   grid_to_points are shown apart for reference; parts timed alone run warmer than in the loop)")
    vehicle = parts["JSBSim vehicle (12 physics steps + controller)"]
    two_calls = parts["lidar ray cast (cast)"] + parts["point cloud (grid_to_points)"]
    one_call = parts["both in one call, as the env does (cast_points)"]
    print("ratios, same run:")
    print(f"  whole env.step / bare vehicle step:              {total / vehicle:5.2f}x")
    print(f"  previous cast + grid_to_points / cast_points:     {two_calls / one_call:5.2f}x")
    print(f"  env.step CPU time vs real time (0.1 s a step):   {0.1 / total:5.0f}x faster")
    print(f"\nload average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
