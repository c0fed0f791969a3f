"""Figures: the narrowest corridor each firmware envelope's backup gate lets the vehicle fly along.

Two straight walls along the nose, their returns fresh (no memory age), the vehicle flying the
speed steadily for 3 s: for each envelope (:data:`companion.safety.envelope.ENVELOPES`) and speed,
the narrowest wall-to-wall width, to 1 cm, at which the gate passes that speed. A wall beside the
course is separated by its normal, so the width is twice the clearance (body radius + margin, the
default 0.3 m), the returns' own span, and what the envelope lets the vehicle drift sideways
before it is stopped: ArduPilot's position loop caps that at ``position_error``; without a
position loop (PX4's offboard velocity, and the ``random`` union) the estimate error carries it
over the whole delay window and the brake.

    python bench/bench_gate_corridor.py [--clearance 0.3]
"""

from __future__ import annotations

import argparse

import numpy as np

from companion.safety.backup import BackupGate
from companion.safety.envelope import ENVELOPES
from companion.safety.obstacle_memory import return_spans

SPEEDS = (0.0, 0.3, 1.0, 2.0)


def walls(width: float) -> tuple[np.ndarray, np.ndarray]:
    """Returns every 5 cm along two walls ``width`` apart, from 3 m behind to 6 m ahead, and their spans."""
    x = np.arange(-3.0, 6.0, 0.05)
    side = np.full_like(x, width / 2.0)
    points = np.concatenate([np.stack([x, side], axis=1), np.stack([x, -side], axis=1)])
    return points, return_spans(points)


def narrowest(envelope: str, speed: float, clearance: float) -> float:
    """The narrowest width, m, at which the gate passes ``speed`` along the corridor (inf: none to 5 m)."""
    for width in np.arange(0.5, 5.0, 0.01):
        gate = BackupGate(ENVELOPES[envelope], clearance)
        for _ in range(30):
            gate.advance(0.1, 0.0, 0.0)
            gate.record((speed, 0.0))
        gate.advance(0.1, 0.0, 0.0)
        points, inflation = walls(float(width))
        ok, _ = gate.passes(np.array([[speed, 0.0]]), (speed, 0.0), points, inflation)
        if ok[0]:
            return float(width)
    return float("inf")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clearance", type=float, default=0.3, help="body radius + margin, m")
    args = parser.parse_args()
    print(f"{'envelope':10} " + " ".join(f"{s:>9.1f} m/s" for s in SPEEDS))
    for name in ("ardupilot", "px4", "random"):
        print(f"{name:10} " + " ".join(f"{narrowest(name, s, args.clearance):11.2f} m" for s in SPEEDS))


if __name__ == "__main__":
    main()
