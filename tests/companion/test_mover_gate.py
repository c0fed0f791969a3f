"""The backup gate against movers: what it refuses, what it lets through, and its promise against
movers that keep within the model, by an independent simulation of both."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.perception.scan import N_BINS
from companion.perception.tracking import Mover
from companion.safety.backup import N_DIRECTIONS, BackupGate, MoverModel, mover_rows
from companion.safety.envelope import ARDUPILOT, ENVELOPES, PX4, STEP_S, ResponseEnvelope, worst_closing
from companion.safety.shield import Command, SafetyShield, ShieldConfig
from tests.companion.test_backup_gate import CLEARANCE, WorstVehicle

NONE = np.zeros((0, 2))
NO_INFLATION = np.zeros(0)
RADIUS = 0.25  # a walker
MAX_RANGE = 10.0


def _gate(envelope: ResponseEnvelope = ARDUPILOT, model: MoverModel | None = None) -> BackupGate:
    gate = BackupGate(envelope, CLEARANCE, movers=model)
    gate.advance(0.1, 0.0, 0.0)
    return gate


def _walker(x: float, y: float, vx: float, vy: float) -> np.ndarray:
    return mover_rows([Mover((x, y), (vx, vy), RADIUS)])


def test_a_walker_coming_head_on_is_refused_where_the_gate_without_movers_passes_full_speed() -> None:
    """8 m ahead, walking in at 1.5 m/s: alone, nothing stands in the way of 2 m/s; with it, the
    backup after 2 m/s would meet it, so the gate slows."""
    walker = _walker(8.0, 0.0, -1.5, 0.0)
    assert _gate().choose((2.0, 0.0), (0.0, 0.0), NONE, NO_INFLATION) == ((2.0, 0.0), None)
    (forward, _), reason = _gate().choose((2.0, 0.0), (0.0, 0.0), NONE, NO_INFLATION, walker)
    assert reason == "gate_slowed" and 0.0 < forward < 2.0


def test_a_walker_crossing_ahead_is_refused() -> None:
    """3 m to the right of a point 4 m ahead, walking left across the course at 1.5 m/s."""
    gate = _gate()
    ok, room = gate.passes(
        np.array([[2.0, 0.0]]), (0.0, 0.0), NONE, NO_INFLATION, _walker(4.0, -3.0, 0.0, 1.5)
    )
    assert not ok[0] and room[0] < 0.0
    ok, _ = gate.passes(np.array([[2.0, 0.0]]), (0.0, 0.0), NONE, NO_INFLATION)
    assert ok[0]


def test_a_walker_walking_away_lets_through_what_one_standing_or_coming_does_not() -> None:
    """8 m ahead: walking away at 1.5 m/s, full speed passes; the same walker standing, or coming
    in, holds it back (with a speed bound alone, all three would be judged alike)."""
    gate = _gate()
    full = np.array([[2.0, 0.0]])
    rooms = {
        vx: gate.passes(full, (0.0, 0.0), NONE, NO_INFLATION, _walker(7.5, 0.0, vx, 0.0))[1][0]
        for vx in (1.5, 0.0, -1.5)
    }
    assert rooms[1.5] >= 0.0 > rooms[0.0] > rooms[-1.5]


def test_a_far_walker_does_not_restrict() -> None:
    ok, _ = _gate().passes(
        np.array([[2.0, 0.0]]), (2.0, 0.0), NONE, NO_INFLATION, _walker(15.0, 0.0, -1.5, 0.0)
    )
    assert ok[0]


def test_no_command_keeps_clear_of_a_walker_inside_the_reach_and_the_most_room_is_sent() -> None:
    """At 1.5 m/s, a walker first seen 1.5 m ahead, coming at 1.5 m/s (outside the promise): not
    even the stop keeps clear while the vehicle still moves; the gate sends the candidate leaving
    it the most room and says so."""
    walker = _walker(1.5, 0.0, -1.5, 0.0)
    (forward, lateral), reason = _gate().choose((1.0, 0.0), (1.5, 0.0), NONE, NO_INFLATION, walker)
    assert reason == "gate_mover_best_effort"
    candidates = np.array([[1.0, 0.0], [0.5, 0.0], [0.0, 0.0]])
    _, rooms = _gate().passes(candidates, (1.5, 0.0), NONE, NO_INFLATION, walker)
    _, sent = _gate().passes(np.array([[forward, lateral]]), (1.5, 0.0), NONE, NO_INFLATION, walker)
    assert rooms.max() < 0.0 and sent[0] >= rooms.max() - 1e-9


def test_a_walker_lost_from_sight_is_judged_from_where_it_was_last_seen() -> None:
    """A walker standing 8.5 m ahead of a vehicle flying at 2 m/s: seen now, full speed passes; lost
    from sight 1 s ago, it may have walked at the vehicle since, and full speed is refused."""
    fresh = mover_rows([Mover((8.5, 0.0), (0.0, 0.0), RADIUS)])
    lost = mover_rows([Mover((8.5, 0.0), (0.0, 0.0), RADIUS, 1.0)])
    full = np.array([[2.0, 0.0]])
    assert _gate().passes(full, (2.0, 0.0), NONE, NO_INFLATION, fresh)[0][0]
    assert not _gate().passes(full, (2.0, 0.0), NONE, NO_INFLATION, lost)[0][0]


def test_a_vehicle_at_rest_may_stay_at_rest_whatever_walks_at_it() -> None:
    """Standing still (to within the creep), the vehicle closes on nothing: the stop passes with a
    walker 1 m ahead coming at it (the contact, if it comes, is the walker's), and going at it does not."""
    walker = _walker(1.0, 0.0, -1.5, 0.0)
    ok, _ = _gate().passes(np.array([[0.0, 0.0], [0.5, 0.0]]), (0.0, 0.0), NONE, NO_INFLATION, walker)
    assert ok.tolist() == [True, False]


def test_a_mover_tracked_faster_than_the_bound_is_counted_and_judged_at_its_speed() -> None:
    """A forklift at 2.5 m/s, above the 1.5 m/s bound: counted per scan, and kept clear of at its
    tracked speed (a bound it may break: outside the promise)."""
    shield = SafetyShield(ShieldConfig(backup_gate=True), MAX_RANGE, "ardupilot")
    fast = [Mover((9.0, 0.0), (-2.5, 0.0), 0.7)]
    clear = np.ones(N_BINS)
    shield.filter(Command(0.0, 0.0), clear, 0.1, (0.0, 0.0), heading=0.0, movers=fast)
    assert shield.interventions["mover_too_fast"] == 1
    gate = _gate()
    assert gate.mover_caps(mover_rows(fast))[0] == pytest.approx(2.5 + gate.movers.velocity_error)
    slow = mover_rows([Mover((9.0, 0.0), (-1.5, 0.0), 0.7)])
    _, room_fast = gate.passes(np.array([[1.5, 0.0]]), (0.0, 0.0), NONE, NO_INFLATION, mover_rows(fast))
    _, room_slow = gate.passes(np.array([[1.5, 0.0]]), (0.0, 0.0), NONE, NO_INFLATION, slow)
    assert room_fast[0] < room_slow[0]


def _scan_with_return(bins: np.ndarray, distance: float) -> np.ndarray:
    scan = np.ones(N_BINS)
    scan[bins] = distance / MAX_RANGE
    return scan


def test_moving_returns_stay_out_of_the_memory() -> None:
    """A walker 1.2 m ahead in one scan, gone from the next: marked moving, it leaves no remembered
    return, and 1 m/s ahead passes; unmarked, the memory keeps it for ``memory_time`` and refuses."""
    ahead = np.arange(-5, 6) % N_BINS
    moving = np.zeros(N_BINS, dtype=bool)
    moving[ahead] = True
    walker = [Mover((1.45, 0.0), (0.0, 1.5), RADIUS)]
    results = {}
    for marked in (True, False):
        shield = SafetyShield(ShieldConfig(backup_gate=True, keepout_distance=0.0), MAX_RANGE, "ardupilot")
        extra = {"moving_bins": moving, "movers": walker} if marked else {}
        shield.filter(Command(0.0, 0.0), _scan_with_return(ahead, 1.2), 0.1, (0.0, 0.0), heading=0.0, **extra)
        results[marked] = shield.filter(Command(1.0, 0.0), np.ones(N_BINS), 0.1, (0.0, 0.0), heading=0.0)
        assert shield._memory.update(np.zeros((0, 2)), 0.0, (0.0, 0.0), 0.0, 0.0)[0].shape[0] == (
            0 if marked else len(ahead)
        )
    assert results[False].forward < 0.5 and results[True].forward > results[False].forward


def test_a_moving_return_no_mover_covers_still_counts_in_its_own_scan() -> None:
    """Marked moving but with no mover there (the tracker's bins and tracks disagree): in the scan
    it came in, the return is judged as a standing one where it is seen, as if it were not marked."""
    ahead = np.arange(-5, 6) % N_BINS
    moving = np.zeros(N_BINS, dtype=bool)
    moving[ahead] = True
    scan = _scan_with_return(ahead, 1.0)
    config = ShieldConfig(backup_gate=True, keepout_distance=0.0, estop_distance=0.0, lane_half_width=0.0)
    sent = {}
    for marked in (True, False):
        shield = SafetyShield(config, MAX_RANGE, "ardupilot")
        extra = {"moving_bins": moving} if marked else {}
        sent[marked] = shield.filter(Command(1.0, 0.0), scan, 0.1, (0.0, 0.0), heading=0.0, **extra)
    assert sent[True] == sent[False] and sent[True].forward < 0.5


@pytest.mark.parametrize(
    "broken_mover",
    [Mover((1.25, 0.0), (math.nan, 0.0), RADIUS), Mover((1.25, 0.0), (0.0, 0.0), RADIUS, -0.5)],
    ids=["nan", "negative-age"],
)
def test_a_mover_that_is_not_finite_is_counted_and_its_returns_stand(broken_mover: Mover) -> None:
    """A broken track (NaN velocity, or seen after the scan) is dropped and counted; its returns,
    marked moving, are then covered by no mover and judged as standing ones, as if not marked."""
    ahead = np.arange(-5, 6) % N_BINS
    moving = np.zeros(N_BINS, dtype=bool)
    moving[ahead] = True
    scan = _scan_with_return(ahead, 1.0)
    config = ShieldConfig(backup_gate=True, keepout_distance=0.0, estop_distance=0.0, lane_half_width=0.0)
    broken = SafetyShield(config, MAX_RANGE, "ardupilot")
    sent = broken.filter(
        Command(1.0, 0.0), scan, 0.1, (0.0, 0.0), heading=0.0, moving_bins=moving,
        movers=[broken_mover],
    )  # fmt: skip
    unmarked = SafetyShield(config, MAX_RANGE, "ardupilot").filter(
        Command(1.0, 0.0), scan, 0.1, (0.0, 0.0), heading=0.0
    )
    assert broken.interventions["mover_nan"] == 1 and sent == unmarked


def test_no_movers_given_changes_nothing() -> None:
    """The tracker's arguments with nothing moving give what the call without them gives, bit for bit."""
    rng = np.random.default_rng(3)
    plain, tracked = (SafetyShield(ShieldConfig(backup_gate=True), MAX_RANGE, "random") for _ in range(2))
    for _ in range(60):
        scan = rng.uniform(0.05, 1.0, N_BINS)
        velocity = tuple(rng.uniform(-1.5, 1.5, 2))
        command = Command(*rng.uniform(-1.0, 2.0, 2), float(rng.uniform(-0.5, 0.5)))
        a = plain.filter(command, scan, 0.1, velocity, heading=0.0)
        b = tracked.filter(
            command, scan, 0.1, velocity, heading=0.0, moving_bins=np.zeros(N_BINS, bool), movers=()
        )
        assert a == b
    assert plain.interventions == tracked.interventions


def test_moving_bins_of_the_wrong_size_are_refused() -> None:
    shield = SafetyShield(ShieldConfig(backup_gate=True), MAX_RANGE)
    with pytest.raises(ValueError, match="moving_bins must have 360 bins, got 10"):
        shield.filter(Command(0.0, 0.0), np.ones(N_BINS), 0.1, (0.0, 0.0), moving_bins=np.zeros(10, bool))


def _plain_worst_case(
    gate: BackupGate, command: np.ndarray, velocity: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The worst case of ``command`` written plainly (a loop over the setpoints sent, the whole
    horizon): ``(k + 1, 72)`` the farthest displacement so far towards each direction at each step,
    ``(72,)`` the step each direction stops at, and ``(k + 1,)`` whether the vehicle may move faster
    than the creep at each step (heading 0)."""
    env = gate.envelope
    units = np.stack(
        [
            np.cos(np.radians(np.arange(N_DIRECTIONS) * 5.0)),
            np.sin(np.radians(np.arange(N_DIRECTIONS) * 5.0)),
        ],
        1,
    )
    comp = units @ command
    closing = units @ np.asarray(velocity)
    times = STEP_S * np.arange(math.ceil(8.0 / STEP_S))
    history = np.full((len(times), N_DIRECTIONS), -np.inf if gate._sent.times else 0.0)
    sent = np.asarray(gate._sent.times) - gate._time
    if len(sent):
        history[times <= sent[0] + env.max_delay] = 0.0
    for j, vector in enumerate(gate._sent.vectors):
        end = (sent[j + 1] if j + 1 < len(sent) else 0.0) + env.max_delay
        on = (times + STEP_S > sent[j] + env.min_delay) & (times <= end)
        history[on] = np.maximum(history[on], units @ vector)
    targets = np.empty((len(times), N_DIRECTIONS))
    for k, t in enumerate(times):
        highest = history[k]
        if env.min_delay < t + STEP_S and t <= gate.period + env.max_delay:
            highest = np.maximum(highest, comp)
        if t + STEP_S > gate.period + env.min_delay:
            highest = np.maximum(highest, 0.0)
        targets[k] = env.target(highest)
    bound, displacement = worst_closing(closing, targets, env)
    late = np.append(0.0, times + STEP_S) >= gate.period + env.max_delay
    creep = bound <= env.target(0.0) + 1e-9
    stopped = late[:, None] & creep
    return np.maximum.accumulate(displacement, axis=0), stopped.argmax(axis=0), ~creep.all(axis=1)


def _true_mover(
    rng: np.random.Generator, tracked: np.ndarray, model: MoverModel, seconds: float, dt: float = 0.01
) -> np.ndarray:
    """A mover's true centre every ``dt`` from when it was seen, within the model: its velocity first
    within ``velocity_error`` of the tracked one, then changed at up to ``accel`` (towards the vehicle
    at the origin, or a random way held for a while), never faster than ``speed``."""

    def capped(v: np.ndarray) -> np.ndarray:
        return v * min(1.0, model.speed / max(float(np.hypot(*v)), 1e-12))

    error = rng.uniform(-1.0, 1.0, 2)
    v = capped(tracked[2:4] + error * model.velocity_error / max(1.0, float(np.hypot(*error))))
    p = tracked[:2].copy()
    pursue = rng.random() < 0.5
    out = [p.copy()]
    push = np.zeros(2)
    for k in range(round(seconds / dt)):
        if pursue:
            push = -p / max(float(np.hypot(*p)), 1e-9)
        elif k % 30 == 0:
            angle = rng.uniform(-math.pi, math.pi)
            push = np.array([math.cos(angle), math.sin(angle)]) * rng.uniform(0.0, 1.0)
        v = capped(v + push * model.accel * dt)  # the cap is a projection: the change stays within a·dt
        p = p + v * dt
        out.append(p.copy())
    return np.array(out)


@pytest.mark.parametrize("seed", range(3))
def test_every_command_sent_keeps_its_worst_case_clear_of_movers_within_the_model(seed: int) -> None:
    """The promise, one decision at a time: a random envelope, setpoint history and asked command,
    a mover of a random model tracked somewhere within 2-10 m, its true motion simulated inside the
    model (up to a period old when seen, and half of them lost from sight up to 1 s before that,
    carried on at their tracked velocity; half of them pursuing the vehicle). Whatever the gate sends
    but its best effort, its worst case (integrated plainly, up to each direction's stop) stays
    clear of the true mover over every step where the vehicle may move faster than the creep, by
    the separating bound. 3 x 80 decisions."""
    rng = np.random.default_rng(100 + seed)
    envelopes = [*ENVELOPES.values(), dataclasses.replace(ARDUPILOT, jerk=8.0)]
    units = np.stack(
        [
            np.cos(np.radians(np.arange(N_DIRECTIONS) * 5.0)),
            np.sin(np.radians(np.arange(N_DIRECTIONS) * 5.0)),
        ],
        1,
    )
    judged = 0
    for _ in range(80):
        model = MoverModel(rng.uniform(0.5, 2.0), rng.uniform(0.5, 5.0), rng.uniform(0.0, 0.5))
        gate = BackupGate(envelopes[rng.integers(len(envelopes))], CLEARANCE, movers=model)
        for _ in range(rng.integers(0, 10)):
            gate.advance(0.1, 0.0, 0.0)
            gate.record(tuple(rng.uniform(-2.0, 2.0, 2)))
        gate.advance(0.1, 0.0, 0.0)
        distance, bearing = rng.uniform(2.0, 10.0), rng.uniform(-math.pi, math.pi)
        walk = rng.uniform(0.0, model.speed) * np.array(
            [math.cos(a := rng.uniform(-math.pi, math.pi)), math.sin(a)]
        )
        lost = rng.uniform(0.0, 1.0) if rng.random() < 0.5 else 0.0  # seen this long before the scan
        tracked = np.array(
            [distance * math.cos(bearing), distance * math.sin(bearing), *walk, rng.uniform(0.2, 0.6), lost]
        )
        seen = np.concatenate([tracked[:2] - lost * walk, tracked[2:]])  # where it was when last seen
        velocity = tuple(rng.uniform(-1.5, 1.5, 2))
        sent, reason = gate.choose(
            tuple(rng.uniform(-2.0, 2.0, 2)), velocity, NONE, NO_INFLATION, tracked[None]
        )
        if reason in ("gate_mover_best_effort", "gate_best_effort"):
            continue
        judged += 1
        reach, stop, fast = _plain_worst_case(gate, np.asarray(sent), velocity)
        age = lost + rng.uniform(0.0, gate.period)  # seen this long before now
        path = _true_mover(rng, seen, model, age + STEP_S * int(stop.max()) + 0.02)
        for j in range(1, int(stop.max()) + 1):
            if not (fast[j - 1] or fast[j]):  # at rest (to within the creep): a contact is the mover's
                continue
            bound = reach[np.minimum(j, stop), np.arange(N_DIRECTIONS)]  # (72,)
            # the mover over the step [t_j-1, t_j], 0.01 s apart, from when it was seen
            during = path[round((age + STEP_S * (j - 1)) / 0.01) : round((age + STEP_S * j) / 0.01) + 1]
            room = (during @ units.T - bound).max(axis=1).min() - tracked[4]
            assert room >= CLEARANCE - 1e-9, (j, room, sent, reason)
    assert judged > 40  # most decisions were inside the promise, and so were checked


def _fly_at_a_walker(
    envelope: ResponseEnvelope, start: float, walk: float, movers: bool, seconds: float = 12.0
) -> tuple[float, float]:
    """The worst vehicle (:class:`WorstVehicle`) asked 2 m/s for ``seconds`` at a walker ``start`` m
    ahead that walks at ``walk`` m/s along the course and then makes for the vehicle as hard as the
    model allows (1.5 m/s, 3 m/s²), until they touch. The gate sees the walker with its motion
    (``movers``) or, as before movers, its returns as standing ones (its near side). Returns the
    least gap to the walker's body while the vehicle moved faster than the creep, and while it did
    not, m."""
    model = MoverModel()
    gate = BackupGate(envelope, CLEARANCE, movers=model)
    vehicle = WorstVehicle(envelope)
    x, v = start, walk
    moving, still = math.inf, math.inf
    for _ in range(round(seconds / 0.1)):
        gate.advance(0.1, 0.0, 0.0)
        ahead = x - vehicle.x
        if movers:
            row = _walker(ahead, 0.0, v, 0.0)
            (forward, _), _ = gate.choose((2.0, 0.0), (vehicle.measured, 0.0), NONE, NO_INFLATION, row)
        else:
            side = np.array([[ahead - RADIUS, 0.0]])
            (forward, _), _ = gate.choose((2.0, 0.0), (vehicle.measured, 0.0), side, np.zeros(1))
        gate.record((forward, 0.0))
        vehicle.send(forward)
        for _ in range(10):
            vehicle.fly(0.01)
            v = max(v - model.accel * 0.01, -model.speed)  # towards the vehicle
            x += v * 0.01
            gap = x - vehicle.x - RADIUS
            if vehicle.v > envelope.estimate_error:  # faster than the creep a stop leaves
                moving = min(moving, gap)
            else:
                still = min(still, gap)
            if gap < 0.0:  # they touch
                return moving, still
    return moving, still


@pytest.mark.parametrize("envelope", [ARDUPILOT, PX4, ENVELOPES["random"]], ids=lambda e: e.name)
@pytest.mark.parametrize(("start", "walk"), [(6.0, -1.5), (10.0, 0.0), (12.0, 1.5)])
def test_the_worst_vehicle_never_closes_on_a_walker_making_for_it_while_it_moves(
    envelope: ResponseEnvelope, start: float, walk: float
) -> None:
    """Passive safety in closed loop: the worst vehicle the envelope allows, asked full speed at a
    walker that comes for it within the model, never gets within the clearance of it while it
    moves faster than the creep; the contact, when the walker keeps coming, is the walker's, at a
    vehicle stopped (to within the creep)."""
    moving, still = _fly_at_a_walker(envelope, start, walk, movers=True)
    assert moving >= CLEARANCE - 1e-6
    assert still < 0.0  # the pursuit went on to the standing vehicle: what the promise leaves out


def test_a_gate_that_takes_the_walker_for_a_standing_return_closes_on_it_while_moving() -> None:
    """The test above can fail: the gate judging the walker's returns as standing ones (the memory
    before movers) lets the vehicle run into it while it still moves."""
    moving, _ = _fly_at_a_walker(ARDUPILOT, 10.0, 0.0, movers=False)
    assert moving < 0.0
