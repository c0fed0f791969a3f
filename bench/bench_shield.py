"""Figures: what the shield's lane and its backup gate cost per scan against the sectors, in the same run.

The lane (``[shield] lane_half_width`` > 0, the default) sweeps a lane along every heading within
``lane_spread_deg`` of the nose and of the travel arc, each over the bins that can lie near one
(``companion.safety.shield.lane_distance``), where the sectors take one minimum over a slice of the scan.
The backup gate (``[shield] backup_gate``) adds the firmware envelope's worst case and the
obstacle memory on top of the lane; with movers (``gate+0 movers``: the tracker's arguments given,
nothing moving; ``gate+N movers``: ``--movers`` walkers within 1-8 m, their returns in the scan and
marked moving) it also keeps clear of each along its motion, and gives way where one's course meets
the stop (``[shield] give_way``; ``no give-way``: the same without). This times :meth:`SafetyShield.filter`
on the same scans, velocities and commands under each, in alternating blocks (so a machine's drift
hits all alike), and prints per call the median and 99th percentile in microseconds, the median as
a ratio to the sectors', the p99 as a ratio to today's lane and to the gate without movers, and the
p99 as a share of the 100 ms scan period; then the share of the calls with movers that gave way.

    python bench/bench_shield.py [--calls 4000] [--blocks 4] [--seed 0] [--movers 5]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from companion.perception.scan import N_BINS
from companion.perception.tracking import Mover
from companion.safety.shield import Command, SafetyShield, ShieldConfig

MAX_RANGE = 10.0
SCAN_PERIOD_S = 0.1


Case = tuple[np.ndarray, tuple[float, float], Command, np.ndarray, list[Mover]]
"""A scan, the measured (forward, left) velocity, the policy's command, the moving bins and the movers."""


def inputs(rng: np.random.Generator, n: int, movers: int) -> list[Case]:
    """Scans with returns 0.4-10 m, velocities of 0-2 m/s within 60° of the nose (forward flight
    with a slide, so the travel arc is swept), and commands of 0-2 m/s; ``movers`` walkers 0.25 m
    in radius, 1-8 m away at up to 1.5 m/s, their near side in the scan's bins and marked moving."""
    out = []
    bearing = np.radians(np.arange(N_BINS) + 0.5)
    for _ in range(n):
        scan = rng.uniform(0.04, 1.0, N_BINS).astype(np.float32)
        speed, course = rng.uniform(0.0, 2.0), np.radians(rng.uniform(-60.0, 60.0))
        velocity = (float(speed * np.cos(course)), float(speed * np.sin(course)))
        moving = np.zeros(N_BINS, dtype=bool)
        walkers = []
        for _ in range(movers):
            distance, at = rng.uniform(1.0, 8.0), rng.uniform(-np.pi, np.pi)
            centre = distance * np.array([np.cos(at), np.sin(at)])
            walk, heading = rng.uniform(0.0, 1.5), rng.uniform(-np.pi, np.pi)
            walkers.append(Mover(tuple(centre), (walk * np.cos(heading), walk * np.sin(heading)), 0.25))
            off = np.abs((bearing - at + np.pi) % (2.0 * np.pi) - np.pi)
            hit = off < np.arcsin(0.25 / distance)
            moving |= hit
            scan[hit] = (distance - 0.25) / MAX_RANGE
        command = Command(float(rng.uniform(0.0, 2.0)), float(rng.uniform(-1.0, 1.0)))
        out.append((scan, velocity, command, moving, walkers))
    return out


def time_calls(shield: SafetyShield, cases: list[Case], tracked: bool) -> list[float]:
    """Seconds per :meth:`SafetyShield.filter` call, one per case; ``tracked``: with the tracker's
    moving bins and movers, else the call as before."""
    times = []
    for scan, velocity, command, moving, walkers in cases:
        start = time.perf_counter()
        if tracked:
            shield.filter(
                command,
                scan,
                SCAN_PERIOD_S,
                velocity=velocity,
                heading=0.0,
                moving_bins=moving,
                movers=walkers,
            )
        else:
            shield.filter(command, scan, SCAN_PERIOD_S, velocity=velocity, heading=0.0)
        times.append(time.perf_counter() - start)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=4000, help="filter calls per shield")
    parser.add_argument("--blocks", type=int, default=4, help="alternating blocks per shield")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--movers", type=int, default=5, help="walkers in every scan of the last shield")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    still = inputs(rng, args.calls // args.blocks, 0)
    walked = inputs(rng, args.calls // args.blocks, args.movers)
    gate = ShieldConfig(backup_gate=True)
    # (shield, cases, with the tracker's arguments) by name
    runs = {
        "sectors": (SafetyShield(ShieldConfig(lane_half_width=0.0), MAX_RANGE, "random"), still, False),
        "lane": (SafetyShield(ShieldConfig(), MAX_RANGE, "random"), still, False),
        "gate": (SafetyShield(gate, MAX_RANGE, "random"), still, False),
        "gate+0 movers": (SafetyShield(gate, MAX_RANGE, "random"), still, True),
        f"gate+{args.movers} movers": (SafetyShield(gate, MAX_RANGE, "random"), walked, True),
        "  no give-way": (SafetyShield(replace(gate, give_way=False), MAX_RANGE, "random"), walked, True),
    }
    times: dict[str, list[float]] = {name: [] for name in runs}
    for shield, cases, tracked in runs.values():  # warm up
        time_calls(shield, cases[:50], tracked)
    walking = runs[f"gate+{args.movers} movers"][0]
    warm = walking.interventions["gate_give_way"]
    for _ in range(args.blocks):
        for name, (shield, cases, tracked) in runs.items():
            times[name] += time_calls(shield, cases, tracked)
    median = {name: float(np.median(t)) for name, t in times.items()}
    p99 = {name: float(np.percentile(t, 99)) for name, t in times.items()}
    header = ("shield", "median µs", "p99 µs", "median/sectors", "p99/lane", "p99/gate", "p99 of 100 ms")
    print(
        f"{header[0]:14} {header[1]:>10} {header[2]:>8} {header[3]:>14} {header[4]:>8} {header[5]:>8} "
        f"{header[6]:>13}"
    )
    for name in times:
        print(
            f"{name:14} {median[name] * 1e6:10.1f} {p99[name] * 1e6:8.1f} "
            f"{median[name] / median['sectors']:14.2f} {p99[name] / p99['lane']:8.2f} "
            f"{p99[name] / p99['gate']:8.2f} {p99[name] / SCAN_PERIOD_S:13.2%}"
        )
    gave = walking.interventions["gate_give_way"] - warm
    print(f"gave way in {gave / len(times[f'gate+{args.movers} movers']):.1%} of the calls with movers")


if __name__ == "__main__":
    main()
