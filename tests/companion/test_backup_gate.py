"""The backup gate: its separation test, its choices, and its promise against the worst vehicle."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.safety.backup import N_DIRECTIONS, BackupGate, separation
from companion.safety.envelope import ARDUPILOT, ENVELOPES, PX4, ResponseEnvelope

CLEARANCE = 0.3


def _wall(distance: float, half_width: float = 4.0) -> np.ndarray:
    """Points every 5 cm along a wall across the nose at ``distance`` m (body frame)."""
    y = np.arange(-half_width, half_width + 1e-9, 0.05)
    return np.stack([np.full_like(y, distance), y], axis=1)


def _none(points: np.ndarray) -> np.ndarray:
    """No inflation."""
    return np.zeros(len(points))


def test_a_return_is_clear_when_some_direction_separates_it() -> None:
    angles = np.radians(np.arange(N_DIRECTIONS) * 5.0)
    displacement = 1.5 * np.maximum(np.cos(angles), 0.0)[None]  # the worst case: up to 1.5 m straight ahead
    ahead, beside = np.array([[2.0, 0.0]]), np.array([[1.0, 1.0]])
    assert separation(ahead, _none(ahead), displacement)[0] == pytest.approx(0.5)
    # beside the course: separated by the direction to the left, which the worst case never moves along
    assert separation(beside, _none(beside), displacement)[0] == pytest.approx(1.0)


def test_inflation_takes_from_the_separation() -> None:
    point = np.array([[2.0, 0.0]])
    assert separation(point, np.array([0.5]), np.zeros((1, N_DIRECTIONS)))[0] == pytest.approx(1.5)


def test_a_far_return_is_bounded_without_the_full_search() -> None:
    """Far returns are bounded by their own bearing; the result is the least over all of them."""
    rng = np.random.default_rng(0)
    points = rng.uniform(-10.0, 10.0, size=(400, 2))
    displacement = rng.uniform(0.0, 2.0, size=(3, N_DIRECTIONS))
    angles = np.radians(np.arange(N_DIRECTIONS) * 5.0)
    full = (points @ np.stack([np.cos(angles), np.sin(angles)]))[None] - displacement[:, None, :]
    exact = full.max(axis=2).min(axis=1)
    got = separation(points, _none(points), displacement)
    assert (got <= exact + 1e-9).all() and (got >= exact - 1e-9).all()


def test_in_the_open_anything_passes() -> None:
    gate = BackupGate(ARDUPILOT, CLEARANCE)
    none = np.zeros((0, 2))
    ok, _ = gate.passes(np.array([[2.0, 0.0], [-1.0, 1.0]]), (2.0, 0.0), none, _none(none))
    assert ok.all()


def test_towards_a_near_wall_the_gate_slows_and_away_from_it_passes() -> None:
    gate = BackupGate(ARDUPILOT, CLEARANCE)
    wall = _wall(2.0)
    (forward, lateral), reason = gate.choose((2.0, 0.0), (0.0, 0.0), wall, _none(wall))
    assert reason == "gate_slowed" and 0.0 < forward < 2.0 and lateral == pytest.approx(0.0)
    ok, _ = gate.passes(np.array([[forward, 0.0]]), (0.0, 0.0), wall, _none(wall))
    assert ok[0]
    (forward, lateral), reason = gate.choose((-0.5, 0.0), (0.0, 0.0), wall, _none(wall))
    assert reason is None and forward == -0.5


def test_a_command_along_a_wall_beside_keeps_its_speed() -> None:
    """The projection counts only what lies towards each direction: a wall 1 m to the left does not
    slow a command along it."""
    gate = BackupGate(ARDUPILOT, CLEARANCE)
    beside = _wall(1.0)[:, ::-1]  # the wall along the nose, 1 m to the left
    (forward, _), reason = gate.choose((1.0, 0.0), (1.0, 0.0), beside, _none(beside))
    assert reason is None and forward == 1.0


class WorstVehicle:
    """A 1-D vehicle that flies the envelope's worst case towards +x: every setpoint flown for the
    longest delay, the most overshoot, the estimate reading ``estimate_error`` slow, rising as fast
    and braking as late as the envelope allows, until it is stopped: the creep a zero setpoint
    leaves is the keep-out's to answer, not the gate's (the gate's module doc). The gate sees
    ``measured``."""

    def __init__(self, envelope: ResponseEnvelope, v: float = 0.0) -> None:
        self.env = envelope
        self.v = v
        self.x = 0.0
        self.t = 0.0
        self.sent: list[tuple[float, float]] = [(-math.inf, 0.0)]

    @property
    def measured(self) -> float:
        return self.v - self.env.estimate_error

    def send(self, setpoint: float) -> None:
        self.sent.append((self.t, setpoint))

    def fly(self, seconds: float, step: float = 0.01) -> float:
        """Fly ``seconds``; the farthest x reached."""
        env, far = self.env, self.x
        for _ in range(round(seconds / step)):
            window = [c for i, (t, c) in enumerate(self.sent) if t <= self.t - env.min_delay and (
                i + 1 == len(self.sent) or self.sent[i + 1][0] >= self.t - env.max_delay)]  # fmt: skip
            flown = max(window) if window else 0.0
            creep = env.estimate_error if flown != 0.0 else 0.0
            goal = flown + env.overshoot * max(flown, 0.0) - env.undershoot * min(flown, 0.0) + creep
            v_next = (
                min(self.v + env.accel * step, goal)
                if goal > self.v
                else max(self.v - env.decel * step, goal)
            )
            self.x += max(self.v, v_next) * step
            self.v = v_next
            self.t += step
            far = max(far, self.x)
        return far


@pytest.mark.parametrize("envelope", [ARDUPILOT, PX4, ENVELOPES["random"]], ids=lambda e: e.name)
@pytest.mark.parametrize("start", [3.0, 6.0, 12.0])
def test_the_worst_vehicle_rammed_at_a_wall_never_comes_closer_than_the_clearance(
    envelope: ResponseEnvelope, start: float
) -> None:
    """The promise, against the envelope's own worst case: a controller asking full speed at a wall
    for 15 s, the gate between them, a vehicle that does the worst the envelope allows."""
    gate = BackupGate(envelope, CLEARANCE)
    vehicle = WorstVehicle(envelope)
    wall = start
    closest = math.inf
    for _ in range(150):
        gate.advance(0.1, 0.0, 0.0)
        points = _wall(wall - vehicle.x)
        (forward, _), _ = gate.choose((2.0, 0.0), (vehicle.measured, 0.0), points, _none(points))
        gate.record((forward, 0.0))
        vehicle.send(forward)
        closest = min(closest, wall - vehicle.fly(0.1))
    assert closest >= CLEARANCE - 1e-6
    assert vehicle.x > start - 4.0  # it did fly towards the wall, not hold back from the start


def test_without_the_gate_the_worst_vehicle_hits_the_wall() -> None:
    """The test above can fail: the same vehicle, sent what the controller asks, crosses the clearance."""
    vehicle = WorstVehicle(ARDUPILOT)
    closest = math.inf
    for _ in range(60):
        vehicle.send(2.0)
        closest = min(closest, 6.0 - vehicle.fly(0.1))
    assert closest < CLEARANCE


def test_a_tighter_gate_than_its_vehicle_lets_it_through() -> None:
    """A gate that assumes a quicker firmware than the one flying loses its promise: the envelope matters."""
    assumed = dataclasses.replace(ARDUPILOT, max_delay=0.1, estimate_error=0.0, overshoot=0.0)
    gate = BackupGate(assumed, CLEARANCE)
    vehicle = WorstVehicle(ARDUPILOT)
    closest = math.inf
    for _ in range(100):
        gate.advance(0.1, 0.0, 0.0)
        points = _wall(6.0 - vehicle.x)
        (forward, _), _ = gate.choose((2.0, 0.0), (vehicle.measured, 0.0), points, _none(points))
        gate.record((forward, 0.0))
        vehicle.send(forward)
        closest = min(closest, 6.0 - vehicle.fly(0.1))
    assert closest < CLEARANCE
