"""Figures: Vehicle.step throughput, and the flight-response figures the vehicle tests bound.

Throughput: `Vehicle.step` (0.1 s of flight = 12 JSBSim steps at 120 Hz, with the controller,
the motor lag and the property I/O of each) per CPU-second, in the env's pattern (a
body-frame forward speed, a yaw rate and an altitude, new every step). It stands against the
floor JSBSim sets: the same number of bare `FGFDMExec.run()` calls on the same model with the
forces held constant (their ratio is the figure that travels between machines), and real time
(a step is 0.1 s of flight). Also `Vehicle.reset` per second (one per episode). The load average
is printed.

Response: hover altitude band over 10 s, time to 1.8 m/s and peak of a 2 m/s forward step,
yaw-rate rise, altitude band while cruising at 2 m/s and turning at 1.5 rad/s, take-off climb rate.

    python bench/bench_vehicle.py [--seconds 3]
"""

from __future__ import annotations

import argparse
import math
import os
import time

import jsbsim
import numpy as np

from flightsim.vehicle.control import Setpoint
from flightsim.vehicle.quadrotor import MODEL_NAME, MODEL_ROOT, Vehicle, VehicleConfig


def best_rate(fn, calls: int, repeats: int) -> float:
    """Calls per CPU-second of this process, the fastest of `repeats` runs (the machine is shared:
    CPU time moves far less with the neighbours' load than wall-clock time, and the best run is the
    least disturbed one)."""
    best = math.inf
    for _ in range(repeats):
        t0 = time.process_time()
        for _ in range(calls):
            fn()
        best = min(best, time.process_time() - t0)
    return calls / best


def throughput(physics_hz: int, seconds: float) -> None:
    vehicle = Vehicle(VehicleConfig(physics_hz=physics_hz))
    vehicle.reset((0.0, 0.0, 1.5), 0.0)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1.0, 1.0, size=(4096, 2))
    i = 0

    def env_step() -> None:
        nonlocal i
        a0, a1 = actions[i % len(actions)]
        i += 1
        s = vehicle.state
        vehicle.step(Setpoint.from_body(1.0 + a0, 0.0, s.yaw, yaw_rate=1.5 * a1, altitude=1.5))
        if i % 300 == 0:  # keep it inside a room-sized patch, as episodes do
            vehicle.reset((0.0, 0.0, 1.5), 0.0)

    env_step()  # compile the controller kernel outside the timing
    calls = max(50, int(seconds * 1500 / 3))
    steps_per_s = best_rate(env_step, calls, 3)

    # The floor: JSBSim's own integration of the same model, nothing of ours in the loop.
    fdm = jsbsim.FGFDMExec(root_dir=str(MODEL_ROOT))
    fdm.load_model(MODEL_NAME)
    fdm.set_dt(1.0 / physics_hz)
    fdm["ic/h-sl-ft"] = 5.0
    fdm.run_ic()
    for i in range(4):
        fdm[f"external_reactions/rotor{i}/magnitude"] = fdm["inertia/weight-lbs"] / 4.0
    n = physics_hz // vehicle.config.control_hz

    def bare() -> None:
        for _ in range(n):
            fdm.run()

    bare_per_s = best_rate(bare, calls, 3)
    resets_per_s = best_rate(lambda: vehicle.reset((1.0, 2.0, 1.5), 0.3), max(20, calls // 5), 3)
    print(
        f"physics {physics_hz} Hz: Vehicle.step(0.1 s) {steps_per_s:8.0f} steps/s "
        f"({steps_per_s / 10:5.0f}x real time, {1e6 / steps_per_s:5.0f} us/step)  |  "
        f"bare JSBSim {n} x run() {bare_per_s:8.0f} /s ({1e6 / bare_per_s:5.0f} us)  |  "
        f"ours on top: {1e6 / steps_per_s - 1e6 / bare_per_s:4.0f} us/step "
        f"(Vehicle.step / bare: {bare_per_s / steps_per_s:4.2f}x)  |  "
        f"reset {resets_per_s:6.0f} /s"
    )
    vehicle.close()


def fly(vehicle: Vehicle, seconds: float, make_setpoint) -> list:
    return [vehicle.step(make_setpoint(vehicle.state)) for _ in range(round(seconds * 10))]


def response() -> None:
    v = Vehicle()
    v.reset((0.0, 0.0, 1.5), 0.0)
    z = np.array([s.position[2] for s in fly(v, 10.0, lambda s: Setpoint())])
    print(f"hover 10 s: altitude error max {np.abs(z - 1.5).max() * 1000:.1f} mm   (test bound: 100 mm)")

    v.reset((0.0, 0.0, 1.5), 0.0)
    states = fly(v, 4.0, lambda s: Setpoint.from_body(2.0, 0.0, s.yaw, altitude=1.5))
    speed = np.array([s.forward_speed for s in states])
    t18 = states[int(np.argmax(speed >= 1.8))].time
    print(
        f"forward step 2 m/s: 1.8 m/s after {t18:.1f} s, peak {speed.max():.2f} m/s "
        f"({(speed.max() / 2.0 - 1.0) * 100:+.1f} %), at 4 s {speed[-1]:.2f} m/s   "
        "(test bounds: <= 2 s, peak <= 2.4 m/s)"
    )

    v.reset((0.0, 0.0, 1.5), 0.0)
    states = fly(v, 1.0, lambda s: Setpoint(yaw_rate=1.5))
    r = np.array([s.angular_rate[2] for s in states])
    t90 = states[int(np.argmax(r >= 0.9 * 1.5))].time
    print(f"yaw rate step 1.5 rad/s: 90 % after {t90:.1f} s, yaw after 1 s {states[-1].yaw:.2f} rad")

    v.reset((0.0, 0.0, 1.5), 0.0)
    states = fly(v, 8.0, lambda s: Setpoint.from_body(2.0, 0.0, s.yaw, yaw_rate=1.5, altitude=1.5))
    z = np.array([s.position[2] for s in states])
    print(
        f"cruise 2 m/s + turn 1.5 rad/s, 8 s: altitude error max {np.abs(z - 1.5).max() * 1000:.1f} mm"
        "   (test bound: 200 mm)"
    )

    v.reset((0.0, 0.0, 0.0), 0.0, on_ground=True)
    v.set_armed(True)
    states = fly(v, 3.0, lambda s: Setpoint(vz=1.0))
    lift = next(s.time for s in states if not s.on_ground)
    print(
        f"take-off vz = 1 m/s: off the ground after {lift:.1f} s, z {states[-1].position[2]:.2f} m "
        f"and vz {states[-1].velocity[2]:.2f} m/s after 3 s"
    )
    v.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="rough wall time per throughput figure")
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    for hz in (120, 240):
        throughput(hz, args.seconds)
    response()


if __name__ == "__main__":
    main()
