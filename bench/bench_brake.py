"""Figures: how far the shield's brake (its motion stop) takes to stop the vehicle, by brake size.

The shield stops a motion it cannot otherwise stop in time with a setpoint against it, as fast as
the motion up to ``[shield] max_reverse_speed`` (0.5 m/s). This flies that brake, a plain zero
setpoint and a brake of up to 1 m/s (tried, not taken: docs/goal-policy.md, the shield
variants) on the JSBSim vehicle through the env's randomised autopilot responses
(``flightsim.vehicle.autopilot_response.random_params``, the velocity-estimate error left out so the
brake sees the true motion): the vehicle is settled at about 1 m/s, then braked each 0.1 s with
``-min(brake, speed)`` until it is slower than 0.1 m/s. Printed per firmware structure (PX4-like:
the command reaches the velocity PID unshaped; ArduPilot-like: input shaping limits the
deceleration) and brake size: the median, 90th percentile and largest distance flown, and the
median as a ratio to the shield's brake's median over the same draws. The last column is the
shield's model of the stop for ``random`` (``AUTOPILOT_LIMITS``: 1.2 m/s² after 0.8 s) from the
same speed.

    python bench/bench_brake.py [--draws 40] [--seed 2]
"""

from __future__ import annotations

import argparse

import numpy as np

from companion.safety.shield import AUTOPILOT_LIMITS, ShieldConfig, stopping_distance
from flightsim.vehicle.autopilot_response import AutopilotResponse, ResponseParams, fly, random_params
from flightsim.vehicle.quadrotor import Vehicle

ALTITUDE = 1.5
SHIELD_BRAKE = ShieldConfig().max_reverse_speed
"""The shield's brake, m/s (its motion stop is at most ``max_reverse_speed``)."""
BRAKES = (0.0, SHIELD_BRAKE, 1.0)
"""Brake sizes, m/s: 0 is a plain zero setpoint."""


def braking_distance(
    vehicle: Vehicle, params: ResponseParams, speed: float, brake: float
) -> tuple[float, float]:
    """Settle the vehicle at about ``speed`` through ``params``, then brake; (speed braked from,
    distance flown until slower than 0.1 m/s or 8 s)."""
    state = vehicle.reset((0.0, 0.0, ALTITUDE), 0.0)
    response = AutopilotResponse(params)
    response.reset(0.0)
    command = speed
    for _ in range(60):  # 6 s, the command raised until the slow responses fly the speed too
        state = fly(vehicle, response, command, 0.0, altitude=ALTITUDE)
        command += 0.3 * (speed - float(state.velocity[0]))
    start_speed, start = float(state.velocity[0]), float(state.position[0])
    t = 0.0
    while float(state.velocity[0]) > 0.1 and t < 8.0:
        setpoint = -min(brake, float(state.velocity[0]))
        state = fly(vehicle, response, setpoint, 0.0, altitude=ALTITUDE)
        t += 0.1
    return start_speed, float(state.position[0]) - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=40, help="random responses drawn")
    parser.add_argument("--seed", type=int, default=2)
    parser.add_argument("--speed", type=float, default=1.0, help="speed braked from, m/s")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    vehicle = Vehicle()
    draws = [random_params(rng).without_estimate_error() for _ in range(args.draws)]
    limits = AUTOPILOT_LIMITS["random"]
    print(f"{'structure':<10} {'brake':>6} {'draws':>5} {'from m/s':>8} {'median m':>9} {'p90 m':>6} "
          f"{'max m':>6} {'/ shield brake (median)':>24} {'model m':>8}")  # fmt: skip
    for structure in ("px4", "ardupilot"):
        chosen = [p for p in draws if p.name.endswith(structure)]
        runs = {b: np.array([braking_distance(vehicle, p, args.speed, b) for p in chosen]) for b in BRAKES}
        for brake, result in runs.items():
            speeds, distances = result[:, 0], result[:, 1]
            ratio = np.median(distances) / np.median(runs[SHIELD_BRAKE][:, 1])
            model = np.median([stopping_distance(v, limits.decel, limits.reaction_time) for v in speeds])
            print(f"{structure:<10} {brake:>6.1f} {len(chosen):>5} {speeds.mean():>8.2f} "
                  f"{np.median(distances):>9.2f} {np.quantile(distances, 0.9):>6.2f} {distances.max():>6.2f} "
                  f"{ratio:>24.2f} {model:>8.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
