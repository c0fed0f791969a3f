"""The backup gate: its separation test, its choices, and its promise against the worst vehicle."""

from __future__ import annotations

import copy
import dataclasses
import math

import numpy as np
import pytest

from companion.perception.tracking import Mover
from companion.safety.backup import MAX_HORIZON_S, N_DIRECTIONS, BackupGate, mover_rows, separation
from companion.safety.envelope import ARDUPILOT, ENVELOPES, PX4, STEP_S, ResponseEnvelope, worst_closing

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


def _verified_step(gate: BackupGate, wall: np.ndarray) -> tuple[float, float]:
    """One step towards ``wall`` that the gate verifies (at rest, no inflation): the setpoint sent."""
    gate.advance(0.1, 0.0, 0.0)
    sent, reason = gate.choose((1.0, 0.0), (0.0, 0.0), wall, _none(wall))
    assert reason in (None, "gate_slowed")
    return sent


def test_a_stop_verified_before_is_kept_while_the_inflation_grows_and_only_up_to_its_stop() -> None:
    """The proof's continuation: a remembered return's inflation grows with its age, so the stop a
    step verified may not pass a step later. Sending it again keeps the promise (its worst case is a
    part of the one verified) until that worst case has stopped; after that it is best effort."""
    gate = BackupGate(ARDUPILOT, CLEARANCE)
    wall = _wall(2.0)
    gate.record(_verified_step(gate, wall))
    _, room = BackupGate(ARDUPILOT, CLEARANCE).passes(np.zeros((1, 2)), (0.0, 0.0), wall, _none(wall))
    grown = np.full(len(wall), room[0] + 0.01)  # nothing passes with it: not even the stop from rest
    reasons = []
    for _ in range(int(MAX_HORIZON_S / 0.1)):
        gate.advance(0.1, 0.0, 0.0)
        sent, reason = gate.choose((1.0, 0.0), (0.0, 0.0), wall, grown)
        gate.record(sent)
        reasons.append(reason)
        if reason == "gate_backup_kept":
            assert sent == (0.0, 0.0)
    kept = reasons.count("gate_backup_kept")
    assert reasons[:kept] == ["gate_backup_kept"] * kept and kept >= 10  # the delay window and braking
    assert reasons[kept] == "gate_best_effort"  # (then its retreat, which a later stop may verify)


def test_a_setpoint_other_than_the_one_offered_ends_what_was_kept() -> None:
    gate = BackupGate(ARDUPILOT, CLEARANCE)
    wall = _wall(2.0)
    forward, _ = _verified_step(gate, wall)
    gate.record((forward + 0.3, 0.0))  # not what the gate offered: nothing it verified
    gate.advance(0.1, 0.0, 0.0)
    _, reason = gate.choose((1.0, 0.0), (0.0, 0.0), wall, np.full(len(wall), 2.0))
    assert reason == "gate_best_effort"


@pytest.mark.parametrize(("envelope", "expected"), [(ARDUPILOT, (-0.5, 0.0)), (PX4, (0.0, 0.0))],
                         ids=["ardupilot", "px4"])  # fmt: skip
def test_best_effort_retreats_where_the_envelope_has_the_vehicle_truly_move_away(
    envelope: ResponseEnvelope, expected: tuple[float, float]
) -> None:
    """Stopped closer to a wall than the creep allows, nothing passes and nothing was verified. A
    retreat raises no bound that decides (nothing behind), so it is sent where the envelope has it
    move away (ArduPilot: 0.5 m/s less 30 % undershoot beats its 0.3 m/s estimate error); with
    PX4's 0.65 m/s estimate error it may not, and the stop is sent."""
    gate = BackupGate(envelope, CLEARANCE, retreat_speed=0.5)
    wall = _wall(0.45)
    gate.advance(0.1, 0.0, 0.0)
    sent, reason = gate.choose((1.0, 0.0), (0.0, 0.0), wall, _none(wall))
    assert reason == "gate_best_effort"
    assert sent == pytest.approx(expected)


class WorstVehicle:
    """A 1-D vehicle that flies the envelope's worst case towards +x: every setpoint flown for the
    longest delay, the most overshoot, the estimate reading ``estimate_error`` slow, rising as fast
    and braking as late as the envelope allows, until it is stopped: the creep a zero setpoint
    leaves is the keep-out's to answer, not the gate's (the gate's module doc). With a position
    loop (``position_error``), the creep adds up to no more than that in all. The gate sees
    ``measured``."""

    def __init__(self, envelope: ResponseEnvelope, v: float = 0.0) -> None:
        self.env = envelope
        self.v = v
        self.x = 0.0
        self.t = 0.0
        self.crept = 0.0  # how far the estimate error has carried it beyond the setpoints, m
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
            creep = env.estimate_error if flown != 0.0 and self.crept < env.position_error else 0.0
            self.crept += creep * step
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


def _reference_passes(
    gate: BackupGate,
    candidates: np.ndarray,
    velocity: tuple[float, float] | None,
    points: np.ndarray,
    inflation: np.ndarray,
    horizon: float | None = None,
) -> np.ndarray:
    """The gate's room, written plainly: the whole horizon for every candidate and direction at once,
    a loop over the setpoints sent, and the separation without pruning (every return, every direction).
    ``horizon`` (s) replaces the gate's own."""
    env = gate.envelope
    c, s = math.cos(gate._heading), math.sin(gate._heading)
    angles = np.radians(np.arange(N_DIRECTIONS) * 5.0)
    units = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    units_world = units @ np.array([[c, s], [-s, c]])
    forward, left = candidates[:, 0], candidates[:, 1]
    comp = np.stack([c * forward - s * left, s * forward + c * left], 1) @ units_world.T
    closing = np.full(N_DIRECTIONS, gate.unknown_speed) if velocity is None else units @ np.asarray(velocity)
    braking = [float(env.target(np.hypot(*v))) for v in gate._sent.vectors]  # from what was sent
    peak = max(float(closing.max()) + env.estimate_error, float(env.target(comp).max()), *braking)
    if horizon is None:
        horizon = min(gate.period + env.max_delay + max(peak, 0.0) / env.decel + STEP_S, MAX_HORIZON_S)
    times = STEP_S * np.arange(math.ceil(horizon / STEP_S))
    history = np.full((len(times), N_DIRECTIONS), -np.inf if gate._sent.times else 0.0)
    sent = np.asarray(gate._sent.times) - gate._time
    if len(sent):  # the hold before the first setpoint kept
        history[times <= sent[0] + env.max_delay] = 0.0
    for j, vector in enumerate(gate._sent.vectors):
        end = (sent[j + 1] if j + 1 < len(sent) else 0.0) + env.max_delay
        on = (times + STEP_S > sent[j] + env.min_delay) & (times <= end)
        history[on] = np.maximum(history[on], units_world @ vector)
    targets = np.empty((len(times), len(candidates), N_DIRECTIONS))
    for k, t in enumerate(times):
        highest = np.broadcast_to(history[k], comp.shape)
        if env.min_delay < t + STEP_S and t <= gate.period + env.max_delay:
            highest = np.maximum(highest, comp)
        if t + STEP_S > gate.period + env.min_delay:
            highest = np.maximum(highest, 0.0)
        targets[k] = env.target(highest)
    bound, displacement = worst_closing(np.broadcast_to(closing, comp.shape), targets, env)
    # up to the first step where only the backup is flown and the bound is down to its creep
    late = np.append(0.0, times + STEP_S) >= gate.period + env.max_delay
    stopped = late[:, None, None] & (bound <= env.target(0.0) + 1e-9)
    running = np.cumsum(stopped, axis=0) - stopped == 0
    reach = np.where(running, displacement, -np.inf).max(axis=0)
    along = points @ units.T - inflation[:, None]  # (p, 72)
    room = np.full(len(candidates), np.inf)
    for i in range(len(candidates)):
        if len(points):
            room[i] = (along - reach[i]).max(axis=1).min()
    return room - gate.clearance


def _reference_choose(
    gate: BackupGate,
    asked: np.ndarray,
    velocity: tuple[float, float] | None,
    points: np.ndarray,
    grown: np.ndarray,
) -> tuple[tuple[float, float], str | None]:
    """:meth:`BackupGate.choose` on :func:`_reference_passes`: the asked alone, then every candidate;
    when none passes, the stop kept while a verified one runs, else the best effort."""
    if _reference_passes(gate, asked[None], velocity, points, grown)[0] >= 0.0:
        return (float(asked[0]), float(asked[1])), None
    nearest = points[int(np.argmin(np.hypot(points[:, 0], points[:, 1]) - grown))]
    towards = nearest / max(float(np.hypot(*nearest)), 1e-9)
    slide = asked - max(float(asked @ towards), 0.0) * towards
    scales = np.linspace(1.0, 0.0, 11)
    candidates = np.concatenate([asked[None], scales[1:, None] * asked, scales[:-1, None] * slide])
    room = _reference_passes(gate, candidates, velocity, points, grown)
    if (room >= 0.0).any():
        pick = int(np.argmin(np.where(room >= 0.0, np.hypot(*(candidates - asked).T), np.inf)))
        reason = "gate_slowed" if np.any(candidates[pick]) else "gate_backup"
    elif gate._time < gate._kept_until:
        pick, reason = 10, "gate_backup_kept"
    else:
        pick, reason = int(np.argmax(room)), "gate_best_effort"
        speeds = [v for v in gate.retreat_speed * np.array([1.0, 0.5, 0.2]) if gate.envelope.target(-v) < 0.0]
        if speeds:  # the fastest retreat that leaves as much room as the stop, judged with it
            backing = np.concatenate([np.zeros((1, 2)), -np.array(speeds)[:, None] * towards])
            backed = _reference_passes(gate, backing, velocity, points, grown)
            if (backed[1:] >= backed[0]).any():
                chosen = backing[1 + int(np.argmax(backed[1:] >= backed[0]))]
                return (float(chosen[0]), float(chosen[1])), reason
    return (float(candidates[pick][0]), float(candidates[pick][1])), reason


Case = tuple[BackupGate, np.ndarray, tuple[float, float] | None, np.ndarray]


def _random_case(rng: np.random.Generator) -> Case:
    """A gate with a random envelope, heading and setpoint history; a random scan (a wall at any bearing,
    scattered returns, or a full ring); a velocity (sometimes unknown)."""
    envelopes = [*ENVELOPES.values(), dataclasses.replace(ARDUPILOT, jerk=8.0)]
    gate = BackupGate(envelopes[rng.integers(len(envelopes))], CLEARANCE)
    heading = rng.uniform(-math.pi, math.pi)
    for _ in range(rng.integers(0, 14)):
        gate.advance(rng.uniform(0.05, 0.15), heading + rng.uniform(-0.3, 0.3), 0.0)
        gate.record(tuple(rng.uniform(-2.5, 2.5, 2)))
    gate.advance(0.1, heading, 0.0)
    kind = rng.integers(3)
    if kind == 0:
        angle = rng.uniform(-math.pi, math.pi)
        rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
        points = _wall(rng.uniform(0.8, 6.0)) @ rotation.T
    elif kind == 1:
        points = rng.uniform(-8.0, 8.0, (rng.integers(1, 300), 2))
    else:
        r, bearing = rng.uniform(0.5, 10.0, 180), np.radians(np.arange(180) * 2.0 + 1.0)
        points = np.stack([r * np.cos(bearing), r * np.sin(bearing)], axis=1)
    velocity = None if rng.random() < 0.1 else (float(rng.uniform(-2.0, 2.0)), float(rng.uniform(-2.0, 2.0)))
    return gate, points, velocity, rng.uniform(0.0, 0.2, len(points))


@pytest.mark.parametrize("seed", range(4))
def test_the_gate_agrees_with_a_plain_reference(seed: int) -> None:
    """The pruned separation, the shared worst case, the shortened integration and the batched choice
    give the room and the choice of the plain computation, case by case (240 cases)."""
    rng = np.random.default_rng(seed)
    for _ in range(60):
        gate, points, velocity, grown = _random_case(rng)
        candidates = rng.uniform(-2.0, 2.0, (rng.integers(1, 22), 2))
        ok, room = gate.passes(candidates, velocity, points, grown)
        expected = _reference_passes(gate, candidates, velocity, points, grown)
        assert room == pytest.approx(expected, abs=1e-9)
        assert (ok == (expected >= 0.0)).all()
        # twice: after a refusal the asked is judged in the candidates' batch, after a pass alone first
        for asked in rng.uniform(-2.0, 2.0, 2), rng.uniform(-0.5, 0.5, 2):
            assert gate.choose(tuple(asked), velocity, points, grown) == _reference_choose(
                gate, asked, velocity, points, grown
            )


def _batch(asked: np.ndarray, points: np.ndarray, grown: np.ndarray, movers: np.ndarray) -> np.ndarray:
    """The candidates :meth:`BackupGate.choose` judges once it refuses the asked, as
    :func:`_reference_choose` makes them (the slides only where they differ from the scaled asked)."""
    centres = np.concatenate([points, movers[:, :2]])
    gaps = np.hypot(centres[:, 0], centres[:, 1]) - np.concatenate([grown, movers[:, 4]])
    nearest = centres[int(np.argmin(gaps))]
    towards = nearest / max(float(np.hypot(*nearest)), 1e-9)
    slide = asked - max(float(asked @ towards), 0.0) * towards
    scales = np.linspace(1.0, 0.0, 11)
    scaled = scales[:, None] * asked
    return scaled if np.array_equal(slide, asked) else np.concatenate([scaled, scales[:-1, None] * slide])


@pytest.mark.parametrize("seed", range(3))
def test_choose_beside_chooses_as_choose_and_judges_the_alternatives_with_the_stop(seed: int) -> None:
    """On twin gates, :meth:`BackupGate.choose_beside` sends what :meth:`BackupGate.choose` sends; an
    alternative is ``ok`` where its stop leaves the returns as much room as the plain reference's,
    judged on one horizon with the stop and the gate's own candidates, or clear where the stop is,
    and ``verified`` where it is ok and its worst case keeps clear of the movers too."""
    rng = np.random.default_rng(100 + seed)
    sidesteps = np.array([(math.cos(a), math.sin(a)) for a in np.radians(np.arange(0, 360, 22.5))])
    verified_seen = unverified_seen = 0
    for _ in range(40):
        gate, points, velocity, grown = _random_case(rng)
        twin = copy.deepcopy(gate)
        at, walk = rng.uniform(-6.0, 6.0, (3, 2)), rng.uniform(-1.5, 1.5, (3, 2))
        movers = mover_rows([Mover(tuple(p), tuple(v), 0.25) for p, v in zip(at, walk, strict=True)])
        alternatives = sidesteps[rng.random(len(sidesteps)) < 0.6]
        for asked in rng.uniform(-2.0, 2.0, 2), rng.uniform(-0.5, 0.5, 2):
            sent, reason = twin.choose(tuple(asked), velocity, points, grown, movers)
            batch = np.concatenate([_batch(asked, points, grown, movers), np.zeros((1, 2)), alternatives])
            room = _reference_passes(gate, batch, velocity, points, grown)[-len(alternatives) - 1 :]
            _, mover_room = gate.passes(batch, velocity, np.zeros((0, 2)), np.zeros(0), movers)
            got = gate.choose_beside(tuple(asked), velocity, points, grown, movers, alternatives)
            assert got[:2] == (sent, reason)
            ok, verified = got[2:]
            np.testing.assert_array_equal(ok, room[1:] >= min(room[0], 0.0))
            np.testing.assert_array_equal(verified, ok & (mover_room[-len(alternatives) :] >= 0.0))
            verified_seen += int(verified.sum())
            unverified_seen += int((ok & ~verified).sum())
            for one in gate, twin:
                one.record(sent)
                one.advance(0.1, one._heading, 0.0)
    assert verified_seen and unverified_seen  # both outcomes met


def test_the_horizon_covers_braking_from_the_setpoints_still_in_force() -> None:
    """Just after 2 m/s was sent, the vehicle has not sped up yet, but the firmware may still fly
    those setpoints for ``max_delay`` and then brake from them: the gate must count that whole
    stop, never claiming more room than the worst case integrated for as long as it can last."""
    gate = BackupGate(ARDUPILOT, 0.3)
    for _ in range(5):
        gate.advance(0.1, 0.0, 0.0)
        gate.record((2.0, 0.0))
    gate.advance(0.1, 0.0, 0.0)
    stop, still = np.zeros((1, 2)), (0.0, 0.0)
    points, inflation = np.array([[6.0, 0.0]]), np.zeros(1)
    _, room = gate.passes(stop, still, points, inflation)
    whole = _reference_passes(gate, stop, still, points, inflation, horizon=MAX_HORIZON_S)
    assert room[0] <= whole[0] + 1e-9


def test_a_second_call_at_the_same_instant_still_judges_the_command() -> None:
    """At ``dt = 0`` after the first setpoint, the hold before it is still in force: the room is a
    number (it was NaN, and the asked went out unjudged) and a command towards a near return fails."""
    gate = BackupGate(ARDUPILOT, 0.3)
    gate.advance(0.1, 0.0, 0.0)
    gate.record((1.0, 0.0))
    gate.advance(0.0, 0.0, 0.0)
    points, inflation = np.array([[1.0, 0.0]]), np.zeros(1)
    ok, room = gate.passes(np.array([[1.0, 0.0]]), (0.5, 0.0), points, inflation)
    assert np.isfinite(room[0]) and not ok[0]


def test_the_whole_horizon_is_integrated_when_the_guess_falls_short(monkeypatch: pytest.MonkeyPatch) -> None:
    """The shortened integration only saves time: with a guess of one step, the same room."""
    monkeypatch.setattr(BackupGate, "_settling_steps", lambda *_: 1)
    rng = np.random.default_rng(7)
    for _ in range(30):
        gate, points, velocity, grown = _random_case(rng)
        candidates = rng.uniform(-2.0, 2.0, (5, 2))
        _, room = gate.passes(candidates, velocity, points, grown)
        assert room == pytest.approx(_reference_passes(gate, candidates, velocity, points, grown), abs=1e-9)


def test_a_far_return_the_reach_comes_to_is_not_pruned_behind_many_near_ones() -> None:
    """Hundreds of returns close behind and beside, the one that binds 3.5 m ahead of a vehicle at
    2 m/s: a pruning by distance alone (or one that forgot the reach) would pass the command."""
    gate = BackupGate(ARDUPILOT, CLEARANCE)
    gate.advance(0.1, 0.0, 0.0)
    bearing = np.radians(np.linspace(100.0, 260.0, 600))
    near = 1.2 * np.stack([np.cos(bearing), np.sin(bearing)], axis=1)
    points = np.concatenate([near, [[3.5, 0.0]]])
    grown = _none(points)
    ok, room = gate.passes(np.array([[2.0, 0.0]]), (2.0, 0.0), points, grown)
    near_ok, near_room = gate.passes(np.array([[2.0, 0.0]]), (2.0, 0.0), near, _none(near))
    assert near_ok[0] and not ok[0]  # the far return alone makes the difference
    assert room[0] < near_room[0]
    expected = _reference_passes(gate, np.array([[2.0, 0.0]]), (2.0, 0.0), points, grown)
    assert room == pytest.approx(expected, abs=1e-9)


def test_a_return_whose_bound_lies_a_millimetre_under_its_room_is_still_searched() -> None:
    """64 returns (a chunk) 3 m out on directions, one 3.002 m out between two: the last has the
    highest bound (so it comes alone in the next chunk) and yet the least room, by 0.9 mm. A bound
    that promised even a millimetre more than it may would leave it out."""
    angles = np.radians(np.arange(N_DIRECTIONS) * 5.0)
    on = 3.0 * np.stack([np.cos(angles), np.sin(angles)], axis=1)[:64]
    between = 3.002 * np.array([[math.cos(math.radians(2.5)), math.sin(math.radians(2.5))]])
    points = np.concatenate([on, between])
    displacement = np.ones((1, N_DIRECTIONS))
    exact = (points @ np.stack([np.cos(angles), np.sin(angles)]) - displacement).max(axis=1).min()
    assert exact == pytest.approx(3.002 * math.cos(math.radians(2.5)) - 1.0)
    assert separation(points, _none(points), displacement)[0] == exact
