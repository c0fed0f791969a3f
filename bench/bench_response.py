"""Figures: how closely the simulated autopilots respond like the real firmware, before and after.

Every recorded command sequence of a real PX4 SIH SITL and a real ArduCopter SITL
(tests/fixtures/autopilot-response/) is replayed on the JSBSim vehicle twice: through the ideal
autopilot (the env's vehicle before the response model: "before") and through the calibrated
firmware response (flightsim.vehicle.autopilot_response: "after"). Printed per sequence: the RMS error of
ground speed (m/s), yaw rate (rad/s) and sideslip (deg, where both move faster than 0.5 m/s)
against the recording's ground truth, beside the run-to-run spread of two real recordings of the
same sequence (the floor no model can beat).

Then the real flights (the companion flying real ArduCopter SITL and PX4 SITL, the shared
recordings in ../shared/fixtures/real-sitl-flights or $LIDAR_AVOID_SHARED; skipped where absent):
each flight's setpoints flown through the calibrated response, per flight the RMS error of ground
speed (m/s), its mean (negative: the model slower) and the RMS course error (deg).

Then "never easier": the figures of the recordings' analysis (t90 of a 1 m/s step, steady speed
after 4 s, yaw rate held at a 1.5 rad/s command, speed and median |sideslip| in the 2 m/s 1 rad/s
turn) for both real recordings, the model and the ideal vehicle; the velocity-estimate error
(median |estimate - truth|) of the recordings beside the model's; and the cost of an env step
through a response, as a ratio to the ideal env step measured in the same run.

    python bench/bench_response.py [--steps 300]
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import numpy as np

from flightsim.envs.env import EnvConfig, LidarAvoidEnv
from flightsim.vehicle.autopilot_response import PRESETS, AutopilotResponse
from flightsim.vehicle.quadrotor import Vehicle
from flightsim.vehicle.response_replay import (
    FIRMWARES,
    SEQUENCES,
    compare,
    hardness,
    load_recording,
    recording_path,
    replay,
    replay_flight,
)

FLIGHTS = Path(os.environ.get("LIDAR_AVOID_SHARED", Path(__file__).resolve().parents[2] / "shared")) / (
    "fixtures/real-sitl-flights"
)


class _Hover:
    """A vehicle state at rest (what the model reads of it)."""

    yaw = 0.0
    velocity = np.zeros(3)


_HOVER = _Hover()


def _fmt(e) -> str:
    slip = "   -" if math.isnan(e.slip_deg) else f"{e.slip_deg:4.1f}"
    return f"{e.speed:5.2f} {e.yaw_rate:5.2f} {slip}"


def error_table(vehicle: Vehicle, firmware: str) -> None:
    print(f"\n{firmware}: RMS error against the real firmware's truth (speed m/s, yaw rate rad/s, slip deg)")
    print(f"{'sequence':<14} {'before (ideal)':>16}   {'after (calibrated)':>18}   {'real run-to-run':>16}")
    for sequence in SEQUENCES:
        rec = load_recording(recording_path(firmware, sequence))
        duration = rec.duration + 1.0
        before = compare(replay(vehicle, None, rec), rec.truth, duration)
        after = compare(replay(vehicle, PRESETS[firmware], rec), rec.truth, duration)
        spread = ""
        if sequence + "-rep2" in SEQUENCES:
            rep2 = load_recording(recording_path(firmware, sequence + "-rep2"))
            spread = _fmt(compare(rep2.truth, rec.truth, duration))
        print(f"{sequence:<14} {_fmt(before):>16}   {_fmt(after):>18}   {spread:>16}")


def flight_table(vehicle: Vehicle, firmware: str) -> None:
    from flightsim.vehicle.envelope_check import load_flight

    paths = sorted(FLIGHTS.glob(f"{firmware}-*.mcap")) if FLIGHTS.is_dir() else []
    if not paths:
        print(f"\n{firmware}: no real flights in {FLIGHTS}")
        return
    print(f"\n{firmware}: the real flights' setpoints through the calibrated response, against truth")
    print(f"{'flight':<50} {'speed RMS':>9} {'mean':>7} {'course RMS':>10}")
    speeds = []
    for path in paths:
        e = replay_flight(vehicle, PRESETS[firmware], load_flight(path))
        speeds.append(e.speed)
        print(f"{path.stem:<50} {e.speed:9.3f} {e.bias:+7.3f} {e.course_deg:9.1f}°")
    above = sum(s > 0.15 for s in speeds)
    print(f"{'all ' + str(len(speeds)):<50} {min(speeds):.3f}-{max(speeds):.3f} m/s, {above} above 0.15")


def hardness_table(vehicle: Vehicle, firmware: str) -> None:
    runs = {
        "real": ("forward", "yaw", "turn"),
        "real rep2": ("forward-rep2", "yaw", "turn-rep2"),
    }
    recs = [load_recording(recording_path(firmware, s)) for s in runs["real"]]
    rows = {name: hardness(*(load_recording(recording_path(firmware, s)).truth for s in seqs))
            for name, seqs in runs.items()}  # fmt: skip
    rows["model"] = hardness(*(replay(vehicle, PRESETS[firmware], r) for r in recs))
    rows["ideal"] = hardness(*(replay(vehicle, None, r) for r in recs))
    print(f"\n{firmware}: how hard to fly (truth; the model must be no easier than the real rows)")
    print(f"{'':<10} {'t90 1 m/s':>9} {'v @4 s':>7} {'yaw @1.5':>8} {'turn v':>7} {'turn slip':>9}")
    for name, h in rows.items():
        t90 = "  >4 s" if math.isinf(h.t90_s) else f"{h.t90_s:6.2f}"
        print(f"{name:<10} {t90:>9} {h.steady_speed:7.2f} {h.yaw_cap:8.2f} {h.turn_speed:7.2f} "
              f"{h.turn_slip_deg:8.1f}°")  # fmt: skip


def estimate_table() -> None:
    print("\nvelocity estimate error, median |estimate - truth| (m/s)")
    for firmware, prefix in FIRMWARES.items():
        recorded = []
        for sequence in ("turn", "random"):
            rec = load_recording(recording_path(firmware, sequence))
            t = rec.truth.t
            est = rec.estimate.at(t)
            recorded.append(float(np.median(np.hypot(est.vx - rec.truth.vx, est.vy - rec.truth.vy))))
        model = AutopilotResponse(PRESETS[firmware], np.random.default_rng(0))
        errors = []
        for _ in range(8000):  # 200 s hovering
            model.setpoint(_HOVER)
            errors.append(float(np.linalg.norm(model.estimate_error)))
        print(
            f"{prefix:<15} recorded (turn, random) {recorded[0]:.2f}, {recorded[1]:.2f}"
            f"   model {np.median(errors):.2f}"
        )


def step_cost(steps: int) -> None:
    print(f"\nenv step cost ({steps} steps each, best of 5, same run)")
    rates = {}
    for response in ("ideal", "px4", "ardupilot"):
        env = LidarAvoidEnv(EnvConfig(autopilot_response=response))
        env.reset(seed=0)
        rng = np.random.default_rng(0)
        actions = rng.uniform(-1.0, 1.0, size=(steps, 2))
        best = math.inf
        for _ in range(5):
            env.reset(seed=0)
            t0 = time.perf_counter()
            for a in actions:
                _, _, terminated, truncated, _ = env.step(a)
                if terminated or truncated:
                    env.reset()
            best = min(best, time.perf_counter() - t0)
        rates[response] = steps / best
        env.close()
    for response, rate in rates.items():
        print(f"  {response:<10} {rate:7.0f} steps/s   {rates['ideal'] / rate:5.2f} x the ideal step's time")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300, help="env steps per timing run")
    args = parser.parse_args()
    vehicle = Vehicle()
    for firmware in FIRMWARES:
        error_table(vehicle, firmware)
    for firmware in FIRMWARES:
        flight_table(vehicle, firmware)
    for firmware in FIRMWARES:
        hardness_table(vehicle, firmware)
    estimate_table()
    step_cost(args.steps)


if __name__ == "__main__":
    main()
