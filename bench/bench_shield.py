"""Figures: what the shield's lane and its backup gate cost per scan against the sectors, in the same run.

The lane (``[shield] lane_half_width`` > 0, the default) sweeps a lane along every heading within
``lane_spread_deg`` of the nose and of the travel arc, each over the bins that can lie near one
(``companion.safety.shield.lane_distance``), where the sectors take one minimum over a slice of the scan.
The backup gate (``[shield] backup_gate``) adds the firmware envelope's worst case and the
obstacle memory on top of the lane. This times :meth:`SafetyShield.filter` on the same scans,
velocities and commands under each, in alternating blocks (so a machine's drift hits all alike),
and prints per call the median and 99th percentile in microseconds, the median as a ratio to the
sectors', the p99 as a ratio to today's lane, and the p99 as a share of the 100 ms scan period.

    python bench/bench_shield.py [--calls 4000] [--blocks 4] [--seed 0]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from companion.safety.shield import Command, SafetyShield, ShieldConfig

MAX_RANGE = 10.0
SCAN_PERIOD_S = 0.1


Case = tuple[np.ndarray, tuple[float, float], Command]
"""A scan, the measured (forward, left) velocity and the policy's command."""


def inputs(rng: np.random.Generator, n: int) -> list[Case]:
    """Scans with returns 0.4-10 m, velocities of 0-2 m/s within 60° of the nose (forward flight
    with a slide, so the travel arc is swept), and commands of 0-2 m/s."""
    out = []
    for _ in range(n):
        scan = rng.uniform(0.04, 1.0, 360).astype(np.float32)
        speed, course = rng.uniform(0.0, 2.0), np.radians(rng.uniform(-60.0, 60.0))
        velocity = (float(speed * np.cos(course)), float(speed * np.sin(course)))
        out.append((scan, velocity, Command(float(rng.uniform(0.0, 2.0)), float(rng.uniform(-1.0, 1.0)))))
    return out


def time_calls(shield: SafetyShield, cases: list[Case]) -> list[float]:
    """Seconds per :meth:`SafetyShield.filter` call, one per case."""
    times = []
    for scan, velocity, command in cases:
        start = time.perf_counter()
        shield.filter(command, scan, SCAN_PERIOD_S, velocity=velocity, heading=0.0)
        times.append(time.perf_counter() - start)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=4000, help="filter calls per shield")
    parser.add_argument("--blocks", type=int, default=4, help="alternating blocks per shield")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    cases = inputs(np.random.default_rng(args.seed), args.calls // args.blocks)
    shields = {
        "sectors": SafetyShield(ShieldConfig(lane_half_width=0.0), MAX_RANGE, "random"),
        "lane": SafetyShield(ShieldConfig(), MAX_RANGE, "random"),
        "gate": SafetyShield(ShieldConfig(backup_gate=True), MAX_RANGE, "random"),
    }
    times: dict[str, list[float]] = {name: [] for name in shields}
    for shield in shields.values():  # warm up
        time_calls(shield, cases[:50])
    for _ in range(args.blocks):
        for name, shield in shields.items():
            times[name] += time_calls(shield, cases)
    median = {name: float(np.median(t)) for name, t in times.items()}
    p99 = {name: float(np.percentile(t, 99)) for name, t in times.items()}
    header = ("shield", "median µs", "p99 µs", "median/sectors", "p99/lane", "p99 of 100 ms")
    print(f"{header[0]:8} {header[1]:>10} {header[2]:>8} {header[3]:>14} {header[4]:>8} {header[5]:>13}")
    for name in times:
        print(
            f"{name:8} {median[name] * 1e6:10.1f} {p99[name] * 1e6:8.1f} "
            f"{median[name] / median['sectors']:14.2f} {p99[name] / p99['lane']:8.2f} "
            f"{p99[name] / SCAN_PERIOD_S:13.2%}"
        )


if __name__ == "__main__":
    main()
