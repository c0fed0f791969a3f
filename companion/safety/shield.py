"""The safety shield: a classic filter between the learned policy and the autopilot.

It does not trust the policy. Whatever the network asks for, the command that leaves the shield is
finite, within the speed and yaw-rate limits, slow enough to stop before the nearest return ahead
(or behind, when backing up), and grows no faster than the acceleration limits. Slowing down is
never delayed by the acceleration limit: braking is always allowed at once.

Emergency stop (a forward-sector return closer than ``estop_distance``): no forward motion, but
turning in place stays allowed and backing up too when the rear sector is clear, so the vehicle
can get itself out.

The vehicle does not go where its nose points: real autopilots lag the setpoint by up to a second
and slide 25-35° off the heading in a turn (``../shared/fixtures/autopilot-response``). So, given
the *measured* body velocity, the shield also watches the direction of travel: the clearance over
the arc from the course to the nose limits the speed, and when the measured speed could not stop
before that clearance (braking distance from the autopilot's own deceleration and lag,
:data:`AUTOPILOT_LIMITS`) it commands a stop: a setpoint against the measured motion, forward and
sideways, at most ``max_reverse_speed`` and only as far as the clearance behind the motion allows
(on the PX4 response this halves the stopping distance of a slide: 0.9 m instead of 1.6 m).
The yaw rate is never asked above what the autopilot will fly.

The autopilot closes its velocity loop on its own estimate, which wanders 0.2-0.4 m/s off the truth
(PX4), so the vehicle truly flies the setpoint minus that error. The policy makes up for it (its
frame carries the drift estimate, :mod:`companion.perception.drift`); the brake and the keep-out mean true
motions, so while either acts the setpoint can also carry the drift estimate (``drift_compensation``,
off by default).
"""

from __future__ import annotations

import collections
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from companion.perception.scan import N_BINS
from companion.perception.tracking import Mover
from companion.safety.backup import BackupGate, MoverModel, mover_rows
from companion.safety.envelope import ENVELOPES, ResponseEnvelope
from companion.safety.give_way import GiveWay, GiveWayConfig
from companion.safety.obstacle_memory import ObstacleMemory, return_spans, scan_points


@dataclass(frozen=True)
class Command:
    """A body-frame setpoint.

    :param forward: body x velocity, m/s (negative = backwards)
    :param yaw_rate: rad/s, FLU: counter-clockwise (to the left) positive
    :param lateral: body y velocity, m/s, left positive. A policy with a sideways action asks for
        one (the shield then judges the command with its course as the nose); the shield's active
        brake sets one against a measured sideways slide the autopilot would otherwise let creep
        on (PX4 SIH: 0.3-0.45 m/s for seconds after a zero setpoint)
    """

    forward: float
    yaw_rate: float
    lateral: float = 0.0


@dataclass(frozen=True)
class AutopilotLimits:
    """How an autopilot answers a setpoint, as far as the shield must assume.

    :param decel: deceleration it brakes with from a zero-velocity (or reversed) setpoint, m/s²
    :param reaction_time: delay before braking starts: scan age, control period and the
        autopilot's velocity-loop lag together, s
    :param max_yaw_rate: the highest yaw rate it flies, rad/s (a firmware parameter caps it)
    """

    decel: float
    reaction_time: float
    max_yaw_rate: float


#: Per autopilot, from the real-firmware recordings (``../shared/fixtures/autopilot-response``):
#: - ``ardupilot`` (ArduCopter 4.8-dev): the firmware envelope's (:data:`companion.safety.envelope.ARDUPILOT`,
#:   fitted to the companion's real SITL flights): a setpoint may still be flown 1.1 s after the next
#:   (``max_delay``), then it brakes at 3 m/s², so 1.1 s + 3 m/s² gives 2.9 m from 2 m/s (the step
#:   response alone, 2 → 0 m/s in 1.30 s over 1.68 m, is shorter than what the companion's own
#:   flights show; tests/sitl/test_ram_attack.py rams a box through it).
#:   Yaw is capped at ATC_RATE_WPY_MAX, 60°/s by default (1.05 rad/s flown for 1.5 asked);
#:   firmware_params raises it.
#: - ``px4`` (SIH, main May 2026): 1.8 → 0 m/s takes 1.2 m to reach 0.5 m/s and then creeps at
#:   0.3-0.45 m/s for seconds (2.7 m after 4.9 s); 2 → −1 m/s stops in 0.66 m. 0.8 s + 1.2 m/s²
#:   gives 2.8 m from 1.8 m/s, and the shield brakes with a reverse setpoint. Yaw: MC_YAWRATE_MAX,
#:   200°/s (PX4 flies 94 % of any rate asked).
#: - ``ideal``: the project's own simulated quad (the shield's original tuning).
#: - ``random``: the env's randomised response: the worst of both step responses (PX4's 1.2 m/s²
#:   after 0.8 s, ArduPilot's yaw cap); not ArduPilot's envelope-backed 1.1 s, which would change
#:   what the training env's shield lets through (only the companion flies ``ardupilot``).
AUTOPILOT_LIMITS: dict[str, AutopilotLimits] = {
    "ideal": AutopilotLimits(decel=2.0, reaction_time=0.8, max_yaw_rate=math.inf),
    "ardupilot": AutopilotLimits(
        decel=ENVELOPES["ardupilot"].decel,
        reaction_time=ENVELOPES["ardupilot"].max_delay,
        max_yaw_rate=ENVELOPES["ardupilot"].max_yaw_rate,
    ),
    "px4": AutopilotLimits(decel=1.2, reaction_time=0.8, max_yaw_rate=math.radians(200.0)),
    "random": AutopilotLimits(decel=1.2, reaction_time=0.8, max_yaw_rate=math.radians(60.0)),
}

#: The direction of each scan bin's centre, rad counter-clockwise from forward.
_BIN_CENTRES_RAD = np.radians(np.arange(N_BINS) + 0.5)
#: each bin centre's unit vector, ``(2, 360)``: cos and sin of its bearing
_BIN_UNIT = np.stack([np.cos(_BIN_CENTRES_RAD), np.sin(_BIN_CENTRES_RAD)])

#: Below this measured speed the direction of travel is noise, m/s.
MIN_TRAVEL_SPEED = 0.1


@dataclass(frozen=True)
class ShieldConfig:
    """Limits of the shield (the ``[shield]`` table of the companion config).

    :param max_speed: forward speed limit, m/s
    :param max_reverse_speed: backward speed limit, m/s; also the fastest retreat of the backup
        gate's best effort
    :param max_yaw_rate: rad/s, either direction
    :param max_accel: how fast the forward speed may grow, m/s². The autopilot shapes its own
        acceleration too (PX4's ``MPC_ACC_HOR``, 3 m/s² by default; ArduPilot's jerk-limited input
        shaping), so a slower ramp here only stacks a second lag on every recovery from a cap. 4 was
        chosen over 2 on the validation worlds: no collision either way, one timeout fewer, 0.6 s
        faster; 20 (no ramp) let a collision through (docs/goal-policy.md)
    :param max_yaw_accel: how fast the yaw rate may grow, rad/s²
    :param max_decel: braking the stopping-distance limit assumes, m/s²; 0: the autopilot's
        measured value (:data:`AUTOPILOT_LIMITS`)
    :param reaction_time: delay before braking starts (scan age, control period and the autopilot's
        velocity-loop lag), s; 0: the autopilot's measured value. 0.8 s is what the simulated
        quad needs to stop at ``estop_distance`` from a wall it meets at 2 m/s
        (``tests/flightsim/test_env.py``); measure a real vehicle's.
    :param estop_distance: a forward return (in the lane ahead, or the forward sector without one)
        closer than this stops all forward motion, m
    :param rear_clear_margin: backing up needs the rear sector clear beyond ``estop_distance`` plus this, m
    :param forward_sector_deg: half-width of the forward sector, degrees
    :param rear_sector_deg: half-width of the rear sector, degrees
    :param travel_sector_deg: half-width of the sector around each direction between the measured
        course and the nose, degrees
    :param lane_half_width: m; above 0, the forward and travel caps count only returns within
        this distance of the line the vehicle flies along (a lane along every heading within
        ``lane_spread_deg`` of the nose, or of the arc from the course round to it), each at the
        distance flown before it enters the lane: a pillar beside the line no longer slows the
        vehicle, as ArduPilot's avoidance limits only the velocity towards an obstacle; the
        emergency stop, too, counts only returns in the lane ahead (the keep-out watches every
        direction). 0: the nearest return in each sector, ``forward_sector_deg`` and
        ``travel_sector_deg``. 0.3 (the vehicle's 0.25 m radius and 5 cm) was chosen over the
        sectors on the validation worlds: as many collisions, fewer timeouts (docs/goal-policy.md)
    :param lane_spread_deg: how far either side of the nose (and beyond either end of the travel
        arc) the lane is also swept, degrees: the turn the course makes before a brake bites
    :param keepout_distance: a return closer than this, in any direction, pushes the vehicle away
        from it and removes what the command asks towards it, m (0: no keep-out at all). The push
        is what stops the drift a velocity estimate cannot show: PX4's velocity loop closes on an
        estimate that wanders 0.2-0.4 m/s off the truth, so with a zero setpoint the true vehicle
        drifts that fast. 0.45 (0.6 before the drift hold took over most of that drift): on the
        validation worlds as many collisions as 0.6 and 0.35, 6 timeouts fewer than 0.6 and one
        more than 0.35, which leaves only 0.1 m beyond the vehicle's radius (docs/goal-policy.md)
    :param keepout_gain: push speed per metre inside ``keepout_distance``, 1/s; the push adds twice
        the speed at which that return came closer since the previous scan (the scan sees the true
        motion, which the estimate may not)
    :param keepout_max_speed: the push's limit, m/s: above PX4's worst estimate bias (2σ 0.5 m/s),
        which the autopilot's own velocity loop would otherwise hold against the push
    :param drift_compensation: while the brake or the keep-out acts, the setpoint also carries the
        drift estimate given to :meth:`SafetyShield.filter` (the velocity estimate's error), each
        axis at most this, m/s: the autopilot flies the setpoint on its estimate, so the vehicle
        truly moves at the setpoint minus the error, and a push away from a wall the estimate drifts
        towards would otherwise be eaten by the drift. The clearance caps (stopping distance, the
        emergency stop, backing up) then hold the true motion too: the setpoint they let through is
        the cap plus the estimate along the course, within this (a cap on the setpoint held a
        vehicle whose estimate read 0.65 m/s fast still before a gap). 0 (the default here):
        never; the companion's ``[shield]`` carries 0.6
        (:class:`companion.config.CompanionShieldConfig`)
    :param backup_gate: the last word: every command, the rules' output included, passes only if
        braking to a stop after it keeps the firmware envelope's worst case clear of every
        remembered return (:mod:`companion.safety.backup`); otherwise the closest command that does,
        or the stop itself. Off by default: over the envelope the real firmware needs, the shipped
        policy (trained without it) reaches too few goals in time behind it (docs/safety.md)
    :param body_radius: the vehicle's radius the gate keeps clear, m
    :param margin: room the gate keeps beyond ``body_radius``, m
    :param memory_time: how long the gate remembers a return, s (:mod:`companion.safety.obstacle_memory`)
    :param mover_speed: the gate keeps clear of movers (:meth:`SafetyShield.filter`'s ``movers``)
        that move at up to this, m/s (1.5: a walker); one tracked faster is counted
        (``mover_too_fast``) and judged at its tracked speed, outside the promise
    :param mover_accel: how fast a mover's velocity may change from the tracked one, m/s² (3: a
        walker stopping or starting hard): what lets a mover's own course narrow where it may be
    :param mover_velocity_error: how far a mover's true velocity may be from the tracked one, m/s
    :param give_way: with the gate, where a mover at its tracked velocity would run into the vehicle
        as it stops, and into what the gate sends, step aside instead
        (:mod:`companion.safety.give_way`): of the sidesteps whose stop keeps clear of the returns,
        the one clear of the movers, or meeting them latest. The stop does not protect a vehicle in
        a walker's path; this is best effort, outside the mover promise (``gate_give_way``)
    """

    max_speed: float = field(default=2.0, metadata={"min": 0.0, "max": 20.0})
    max_reverse_speed: float = field(default=0.5, metadata={"min": 0.0, "max": 5.0})
    max_yaw_rate: float = field(default=1.5, metadata={"min": 0.0, "max": 6.0})
    max_accel: float = field(default=4.0, metadata={"min": 0.01, "max": 20.0})
    max_yaw_accel: float = field(default=4.0, metadata={"min": 0.01, "max": 50.0})
    max_decel: float = field(default=0.0, metadata={"min": 0.0, "max": 20.0})
    reaction_time: float = field(default=0.0, metadata={"min": 0.0, "max": 5.0})
    estop_distance: float = field(default=0.3, metadata={"min": 0.0, "max": 10.0})
    rear_clear_margin: float = field(default=0.2, metadata={"min": 0.0, "max": 10.0})
    forward_sector_deg: float = field(default=30.0, metadata={"min": 1.0, "max": 90.0})
    rear_sector_deg: float = field(default=30.0, metadata={"min": 1.0, "max": 90.0})
    travel_sector_deg: float = field(default=30.0, metadata={"min": 1.0, "max": 90.0})
    lane_half_width: float = field(default=0.3, metadata={"min": 0.0, "max": 5.0})
    lane_spread_deg: float = field(default=10.0, metadata={"min": 0.0, "max": 90.0})
    keepout_distance: float = field(default=0.45, metadata={"min": 0.0, "max": 10.0})
    keepout_gain: float = field(default=2.0, metadata={"min": 0.0, "max": 20.0})
    keepout_max_speed: float = field(default=1.0, metadata={"min": 0.0, "max": 5.0})
    drift_compensation: float = field(default=0.0, metadata={"min": 0.0, "max": 2.0})
    backup_gate: bool = False
    body_radius: float = field(default=0.25, metadata={"min": 0.0, "max": 5.0})
    margin: float = field(default=0.05, metadata={"min": 0.0, "max": 5.0})
    memory_time: float = field(default=0.5, metadata={"min": 0.0, "max": 5.0})
    mover_speed: float = field(default=1.5, metadata={"min": 0.0, "max": 20.0})
    mover_accel: float = field(default=3.0, metadata={"min": 0.0, "max": 1000.0})
    mover_velocity_error: float = field(default=0.3, metadata={"min": 0.0, "max": 5.0})
    give_way: bool = True


def sector_bins(centre_deg: float, half_width_deg: float) -> np.ndarray:
    """Scan bins whose centre lies within ``half_width_deg`` of ``centre_deg`` (counter-clockwise).

    With the defaults, forward ±30° is bins 0..29 and 330..359; rear ±30° is bins 150..209.
    """
    centres = np.arange(N_BINS) + 0.5
    offset = (centres - centre_deg + 180.0) % 360.0 - 180.0
    return np.flatnonzero(np.abs(offset) <= half_width_deg)


def arc_bins(from_deg: float, to_deg: float, half_width_deg: float) -> np.ndarray:
    """Scan bins within ``half_width_deg`` of some direction on the shorter arc from ``from_deg`` to
    ``to_deg`` (counter-clockwise degrees): the directions the vehicle travels in while its course
    swings from ``from_deg`` round to ``to_deg``."""
    span = (to_deg - from_deg + 180.0) % 360.0 - 180.0
    centres = np.arange(N_BINS) + 0.5
    # offset of each bin from the arc's start, measured in the arc's own direction
    offset = ((centres - from_deg) * (1.0 if span >= 0 else -1.0) + 180.0) % 360.0 - 180.0
    beyond = np.where(offset > abs(span), offset - abs(span), np.where(offset < 0.0, -offset, 0.0))
    return np.flatnonzero(beyond <= half_width_deg)


def lane_distance(ranges: np.ndarray, headings_deg: np.ndarray, half_width: float) -> float:
    """The nearest return in the lanes along ``headings_deg`` (counter-clockwise degrees), m: for
    each return within ``half_width`` of a heading's line, the distance the centre flies before the
    return enters the lane, plus ``half_width`` (so a return dead ahead reads its range, as in a
    sector); inf when no lane holds a return. Returns behind a heading's abeam line never count.

    :param ranges: ``(360,)`` metres, bins counter-clockwise from forward
    """
    heading = np.radians(np.asarray(headings_deg, dtype=np.float64)).ravel()
    if heading.size == 0:
        return math.inf
    near = _near_some_lane(ranges, heading, half_width)
    if not near.any():
        return math.inf
    unit, r = _BIN_UNIT[:, near], ranges[near]
    ch, sh = np.cos(heading)[:, None], np.sin(heading)[:, None]
    # cos and sin of (bin bearing - heading), by the angle-difference identities
    cos = ch * unit[0] + sh * unit[1]
    sin = ch * unit[1] - sh * unit[0]
    along = r[None, :] * cos
    side = np.abs(r[None, :] * sin)
    inside = (cos > 0.0) & (side < half_width)
    if not inside.any():
        return math.inf
    entry = along - np.sqrt(np.maximum(half_width * half_width - side * side, 0.0)) + half_width
    return float(entry[inside].min())


def _near_some_lane(ranges: np.ndarray, heading_rad: np.ndarray, half_width: float) -> np.ndarray:
    """Which bins may lie in some heading's lane, ``(360,)`` bool: a return ``r`` at angle ``δ``
    from the nearest heading is at least ``r·sin δ`` off every line (``δ`` < 90°; beyond, behind
    them all). Only those bins are swept, so a scan costs what its returns near the lanes cost,
    not headings × 360 (the travel arc sweeps up to 200 headings); the test is widened by a
    rounding margin, so it never drops a bin the sweep would count."""
    sorted_headings = np.sort(np.mod(heading_rad, 2.0 * np.pi))
    after = np.searchsorted(sorted_headings, _BIN_CENTRES_RAD) % len(sorted_headings)
    off = np.minimum(
        np.abs(_wrap_pi(_BIN_CENTRES_RAD - sorted_headings[after])),
        np.abs(_wrap_pi(_BIN_CENTRES_RAD - sorted_headings[after - 1])),
    )
    with np.errstate(invalid="ignore"):  # an infinite range at 0° off reads nan: no return there
        return (off < np.pi / 2 + 1e-6) & (ranges * np.sin(np.minimum(off, np.pi / 2)) < half_width + 1e-6)


def _wrap_pi(angle: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-π, π)."""
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


def stopping_distance(speed: float, decel: float, reaction_time: float) -> float:
    """Distance flown while stopping from ``speed``: ``v·t_r + v²/(2a)``."""
    v = max(speed, 0.0)
    return v * reaction_time + v * v / (2.0 * decel)


def stopping_speed(distance: float, max_decel: float, reaction_time: float) -> float:
    """Highest speed from which the vehicle still stops within ``distance``.

    Solves ``v·t_r + v²/(2a) = d`` for ``v``: ``v = −a·t_r + sqrt((a·t_r)² + 2·a·d)``.
    """
    d = max(distance, 0.0)
    at = max_decel * reaction_time
    return -at + math.sqrt(at * at + 2.0 * max_decel * d)


def command_from_action(
    action: np.ndarray, max_speed: float, max_yaw_rate: float, max_sideways_speed: float = 0.0
) -> Command:
    """Scale a policy action ``a ∈ [−1, 1]²`` (or ``[−1, 1]³``) to a command, as training did.

    :param action: ``(2,)``: a0 forward speed, a1 yaw rate (counter-clockwise positive); ``(3,)``
        with ``max_sideways_speed``: a2 speed to the left
    :param max_speed: m/s that a0 = 1 stands for (the model's training value)
    :param max_yaw_rate: rad/s that a1 = 1 stands for (the model's training value)
    :param max_sideways_speed: m/s that a2 = 1 stands for; 0: the action has no a2
    """
    a = np.asarray(action, dtype=np.float64).reshape(-1)
    size = 3 if max_sideways_speed > 0.0 else 2
    if a.shape[0] != size:
        raise ValueError(f"action must have {size} values, got {a.shape[0]}")
    lateral = float(a[2]) * max_sideways_speed if size == 3 else 0.0
    return Command(forward=float(a[0]) * max_speed, yaw_rate=float(a[1]) * max_yaw_rate, lateral=lateral)


def _turned(command: Command, angle: float) -> Command:
    """``command`` with its (forward, lateral) velocity turned by ``angle`` rad counter-clockwise."""
    forward, lateral = _turned_pair((command.forward, command.lateral), angle)
    return Command(forward, command.yaw_rate, lateral)


def _turned_pair(vector: tuple[float, float] | None, angle: float) -> tuple[float, float] | None:
    """A (forward, left) vector turned by ``angle`` rad counter-clockwise (None stays None)."""
    if vector is None:
        return None
    c, s = math.cos(angle), math.sin(angle)
    return c * vector[0] - s * vector[1], s * vector[0] + c * vector[1]


def _finite_scan(scan: np.ndarray) -> tuple[np.ndarray, bool]:
    """``scan`` as ``(360,)`` float64 with NaN/−inf as 0 (unknown = blocked) and +inf as 1.0, and
    whether anything had to be replaced.

    :raises ValueError: when the scan does not have 360 bins
    """
    values = np.asarray(scan, dtype=np.float64).reshape(-1)
    if values.shape[0] != N_BINS:
        raise ValueError(f"scan must have {N_BINS} bins, got {values.shape[0]}")
    if np.isfinite(values).all():
        return values, False
    return np.nan_to_num(values, nan=0.0, posinf=1.0, neginf=0.0), True


def _moving_bins(moving_bins: np.ndarray | None) -> np.ndarray | None:
    """``moving_bins`` as ``(360,)`` bool (None stays None).

    :raises ValueError: when it does not have 360 bins
    """
    if moving_bins is None:
        return None
    moving = np.asarray(moving_bins, dtype=bool).reshape(-1)
    if moving.shape[0] != N_BINS:
        raise ValueError(f"moving_bins must have {N_BINS} bins, got {moving.shape[0]}")
    return moving


def _finite_pair(pair: tuple[float, float] | None) -> bool:
    """Whether ``pair`` is given and both its values are finite."""
    return pair is not None and math.isfinite(float(pair[0])) and math.isfinite(float(pair[1]))


def _commanded_side(course: float, heading: float) -> float:
    """Where the arc the command's own speed is flown along ends: the course, or 90° from
    ``heading`` towards it when the course points farther away (degrees).

    While the velocity changes from the measured one to the command's, what points more than 90°
    off the command is never faster than the measured motion (its part across the command only
    shrinks), so only the motion's stop watches those directions. Capping the command there too
    held a forward command that brakes a backward slide at 0.
    """
    swing = (course - heading + 180.0) % 360.0 - 180.0
    return course if abs(swing) <= 90.0 else heading + math.copysign(90.0, swing)


def _motion(velocity: tuple[float, float]) -> tuple[float, float]:
    """The speed (m/s) and the course (degrees counter-clockwise from the nose) of a finite
    measured velocity (body forward, left)."""
    v_forward, v_left = float(velocity[0]), float(velocity[1])
    return math.hypot(v_forward, v_left), math.degrees(math.atan2(v_left, v_forward))


def _course(velocity: tuple[float, float] | None) -> float | None:
    """The direction of the measured motion (degrees counter-clockwise from the nose), or None when
    it is not known or too slow to say (:data:`MIN_TRAVEL_SPEED`)."""
    if not _finite_pair(velocity):
        return None
    speed, course = _motion(velocity)
    return course if speed >= MIN_TRAVEL_SPEED else None


def _slew(target: float, previous: float, step: float) -> float:
    """Limit how fast ``target`` moves away from zero; moving towards zero is never limited."""
    lo = min(previous, 0.0) - step
    hi = max(previous, 0.0) + step
    return min(max(target, lo), hi)


@dataclass(frozen=True)
class _Aside:
    """The sidesteps ``give_way`` may send this scan (:meth:`SafetyShield._sidesteps`).

    :param candidates: ``(a, 2)`` those a mover meets later than the stop (body forward, left), m/s
    :param nearest: ``(a,)`` their :meth:`GiveWay.encounters`: the distance, m
    :param first: ``(a,)`` and the seconds to the first conflict
    :param stop: the stop's (seconds to the first conflict, distance)
    :param velocity: the body velocity they were predicted from, m/s
    :param movers: the movers they were predicted against
    """

    candidates: np.ndarray
    nearest: np.ndarray
    first: np.ndarray
    stop: tuple[float, float]
    velocity: tuple[float, float]
    movers: list[Mover]


class SafetyShield:
    """Filters every policy command against the latest scan and the measured motion.

    :param config: the limits
    :param max_range: metres that a scan value of 1.0 stands for
    :param autopilot: what the autopilot does with a setpoint: a key of :data:`AUTOPILOT_LIMITS`
        or the limits themselves (``max_decel`` and ``reaction_time`` in ``config`` win when not 0)
    :param autopilot_yaw_rate: the autopilot's yaw-rate limit as read from it (rad/s), when known;
        otherwise its firmware default from ``autopilot``
    """

    def __init__(
        self,
        config: ShieldConfig,
        max_range: float,
        autopilot: str | AutopilotLimits = "ideal",
        autopilot_yaw_rate: float | None = None,
    ) -> None:
        if not max_range > 0:
            raise ValueError(f"max_range must be positive, got {max_range}")
        limits = AUTOPILOT_LIMITS[autopilot] if isinstance(autopilot, str) else autopilot
        self.config = config
        self.max_range = float(max_range)
        #: braking the stopping distances assume, m/s², and the delay before it starts, s
        self.max_decel = config.max_decel or limits.decel
        self.reaction_time = config.reaction_time or limits.reaction_time
        ap_yaw = autopilot_yaw_rate if autopilot_yaw_rate is not None else limits.max_yaw_rate
        #: the yaw rate never asked above this, rad/s: the shield's limit or the autopilot's
        self.max_yaw_rate = min(config.max_yaw_rate, ap_yaw)
        self.interventions: collections.Counter[str] = collections.Counter()
        self._forward_bins = sector_bins(0.0, config.forward_sector_deg)
        self._rear_bins = sector_bins(180.0, config.rear_sector_deg)
        self._previous = Command(0.0, 0.0)
        self._previous_nearest: float | None = None  # nearest return of the previous scan, m
        #: the firmware envelope the gate assumes
        self.envelope: ResponseEnvelope = ENVELOPES[autopilot if isinstance(autopilot, str) else "random"]
        clearance = config.body_radius + config.margin
        movers = MoverModel(config.mover_speed, config.mover_accel, config.mover_velocity_error)
        self._gate = (
            BackupGate(self.envelope, clearance, movers=movers, retreat_speed=config.max_reverse_speed)
            if config.backup_gate
            else None
        )
        self._memory = ObstacleMemory(
            config.memory_time, self.envelope.estimate_error, self.envelope.velocity_lag
        )
        self._gated_yaw_rate = 0.0  # the yaw rate last sent, flown until the next scan
        self._give_way = (
            GiveWay(GiveWayConfig(vehicle_radius=config.body_radius))
            if config.backup_gate and config.give_way
            else None
        )
        self._stepping: tuple[float, float] | None = None  # the sidestep being flown

    def reset(self) -> None:
        """Forget the previous command, so the next one ramps up from standstill (e.g. after HOLD),
        and the remembered returns."""
        self._previous = Command(0.0, 0.0)
        self._previous_nearest = None
        self._memory.reset()
        if self._gate is not None:
            self._gate.reset()
        self._stepping = None

    def forward_cap(
        self,
        scan: np.ndarray,
        velocity: tuple[float, float] | None = None,
        drift: tuple[float, float] | None = None,
    ) -> float:
        """The fastest forward speed the shield lets through against ``scan`` (0 inside
        ``estop_distance``), m/s: what a policy that needs no shield asks for at most. Counts no
        intervention and changes no state.

        :param scan: ``(360,)`` normalised ranges, bins counter-clockwise from forward
        :param velocity: the measured body velocity (forward, left), m/s; given, the cap also
            holds along the travel as in :meth:`filter` (the clearance from the course round to
            the nose, at most 90° off it), and is 0 where the shield would brake against the
            motion or where the velocity is not finite; None: the nose sector alone
        :param drift: the drift estimate, as :meth:`filter` takes it: with a finite velocity and
            ``drift_compensation``, the cap holds the true motion and is raised by the estimate
            along the nose (lowered where the estimate reads slow), never below 0
        """
        values, _ = _finite_scan(scan)
        cap = self._allowed_speed(self._front_clearance(values))
        if velocity is None:
            return cap
        if not _finite_pair(velocity):
            return 0.0
        speed, course = _motion(velocity)
        if speed >= MIN_TRAVEL_SPEED:
            along, whole = self._travel_clearances(values, course, 0.0)
            if not self._can_stop(speed, whole):
                return 0.0
            cap = min(cap, self._allowed_speed(along))
        return max(cap + self._drift_along(velocity, drift), 0.0)

    def filter(
        self,
        requested: Command,
        scan: np.ndarray,
        dt: float,
        velocity: tuple[float, float] | None = None,
        drift: tuple[float, float] | None = None,
        heading: float | None = None,
        *,
        moving_bins: np.ndarray | None = None,
        movers: Sequence[Mover] = (),
    ) -> Command:
        """Return the command that is safe to send.

        A command with a sideways part is judged with its course as the nose: the scan, the
        velocity, the drift and the previous command are turned (to the whole degree) so that the
        course is straight ahead, the speed along it is filtered as a forward command would be, and
        the result is turned back. Every limit then holds along the way the vehicle is asked to go.

        :param requested: what the policy asked for
        :param scan: ``(360,)`` normalised ranges, bins counter-clockwise from forward
        :param dt: seconds since the previous command (for the acceleration limits); a
            non-positive or non-finite ``dt`` allows no increase at all
        :param velocity: the measured body velocity (forward, left), m/s; None: not known, the
            nose alone is watched (the companion HOLDs instead of flying without it)
        :param drift: the drift estimate (the velocity estimate's error, reported minus true, body
            forward and left), m/s, carried by the setpoint while the brake or the keep-out acts
            (``drift_compensation``); None or not finite: none
        :param heading: the vehicle's heading, rad counter-clockwise (any fixed origin), for the
            gate's memory and setpoint history; None: the yaw rates sent, integrated
        :param moving_bins: ``(360,)`` bool, the scan bins whose return belongs to something moving
            (:class:`~companion.perception.tracking.ScanTracker`): the gate's memory never keeps
            them (a walker leaves no trail of returns); None: none moves
        :param movers: what moves, as the tracker gives it: the gate keeps clear of each along its
            motion (:mod:`companion.safety.backup`, "Movers"). The rules before it judge every
            return of the scan, moving or not, as standing where it is seen
        """
        out = self._rules(requested, scan, dt, velocity, drift)
        if self._gate is None:
            return out
        return self._gated(out, scan, dt, velocity, heading, moving_bins, movers)

    def _gated(
        self,
        out: Command,
        scan: np.ndarray,
        dt: float,
        velocity: tuple[float, float] | None,
        heading: float | None,
        moving_bins: np.ndarray | None,
        movers: Sequence[Mover],
    ) -> Command:
        """``out`` through the backup gate (:mod:`companion.safety.backup`).

        A moving return is never remembered. In the scan it came in, it is replaced by the mover
        that covers it (within the mover's radius and the return's own span); one that no mover
        covers still counts there, as a return standing where it is seen, for that scan alone.
        A mover that is not finite (or whose age is negative) is dropped and counted (``mover_nan``)."""
        values, _ = _finite_scan(scan)
        ranges = values * self.max_range
        known = velocity if _finite_pair(velocity) else None
        yaw_rate = self._gated_yaw_rate
        moving = _moving_bins(moving_bins)
        still = ranges if moving is None else np.where(moving, self.max_range, ranges)
        points, inflation = self._memory.update(
            scan_points(still, self.max_range), dt, known, heading, yaw_rate
        )
        rows = mover_rows(movers)
        broken = ~np.isfinite(rows).all(axis=1) | (rows[:, 5] < 0.0)  # not finite, or seen in the future
        if broken.any():  # dropped: its returns count as standing ones below, as no mover covers them
            self.interventions["mover_nan"] += int(np.count_nonzero(broken))
            rows = rows[~broken]
        if moving is not None and moving.any():
            seen = scan_points(np.where(moving, ranges, self.max_range), self.max_range)
            spans = return_spans(seen)
            gaps = np.hypot(seen[:, None, 0] - rows[None, :, 0], seen[:, None, 1] - rows[None, :, 1])
            alone = ~(gaps <= rows[None, :, 4] + spans[:, None]).any(axis=1)
            points = np.concatenate([points, seen[alone]])
            inflation = np.concatenate([inflation, spans[alone]])
        too_fast = int(np.count_nonzero(np.hypot(rows[:, 2], rows[:, 3]) > self.config.mover_speed))
        if too_fast:
            self.interventions["mover_too_fast"] += too_fast
        self._gate.advance(dt, heading, yaw_rate)
        asked, turn = (out.forward, out.lateral), out.yaw_rate
        aside = self._sidesteps(known, rows)
        if aside is None:
            moving = rows if len(rows) else None
            (forward, lateral), reason = self._gate.choose(asked, known, points, inflation, moving)
        else:
            (forward, lateral), reason, ok, verified = self._gate.choose_beside(
                asked, known, points, inflation, rows, aside.candidates
            )
            step = self._step_aside(aside, (forward, lateral), ok, verified)
            if step is not None:  # judged as flown in the body axes of now: the heading is held
                (forward, lateral), turn, reason = step, 0.0, "gate_give_way"
        if reason is not None:
            self.interventions[reason] += 1
            out = Command(forward, turn, lateral)
        self._gate.record((out.forward, out.lateral))
        self._gated_yaw_rate = out.yaw_rate
        self._previous = out
        return out

    def _sidesteps(self, velocity: tuple[float, float] | None, movers: np.ndarray) -> _Aside | None:
        """The sidesteps ``give_way`` may send this scan: where the stop meets a mover at its tracked
        velocity within the rule's ``wait_time``, those that meet it later, or as late and less deep
        (judged by the gate beside its own candidates, :meth:`BackupGate.choose_beside`); None where
        the stop is clear (nothing steps aside, and what was being stepped is over)."""
        rule = self._give_way
        if rule is None or velocity is None or len(movers) == 0:
            self._stepping = None
            return None
        tracked = [Mover((m[0], m[1]), (m[2], m[3]), m[4]) for m in movers]
        horizon = rule.config.wait_time
        held, met = rule.encounter((0.0, 0.0), velocity, tracked, horizon)
        if held >= 0.0:  # the stop is clear: no sidestep is predicted
            self._stepping = None
            return None
        candidates = rule.sidesteps(self.config.max_reverse_speed)
        nearest, first = rule.encounters(candidates, velocity, tracked, horizon)
        later = np.flatnonzero((first > met) | ((first == met) & (nearest > held)))
        if len(later) == 0:
            self._stepping = None
            return None
        return _Aside(candidates[later], nearest[later], first[later], (met, held), velocity, tracked)

    def _step_aside(
        self, aside: _Aside, sent: tuple[float, float], ok: np.ndarray, verified: np.ndarray
    ) -> tuple[float, float] | None:
        """The sidestep to send instead of ``sent`` (``give_way``), or None: where ``sent`` held also
        meets a mover within ``wait_time``, of the sidesteps met later than the stop and ``sent`` both,
        the first by :meth:`GiveWay.preference` whose own stop keeps clear of the returns (the gate's
        static promise holds), or, where the stop itself does not (the gate's best effort), leaves
        them as much room as the stop (``ok``); of those, the ones the gate passes with the movers too
        (``verified``, the whole promise) go first. With none such, ``sent`` stands."""
        rule = self._give_way
        assert rule is not None
        held, met = rule.encounter(sent, aside.velocity, aside.movers, rule.config.wait_time)
        current, self._stepping = self._stepping, None
        if held >= 0.0:  # the command is clear
            return None
        worse = max(aside.stop, (met, held))  # met the latest, then the least deep
        later = (aside.first > worse[0]) | ((aside.first == worse[0]) & (aside.nearest > worse[1]))
        whole = verified & later
        usable = whole if whole.any() else ok & later
        order = rule.preference(aside.candidates, aside.nearest, aside.first, current)
        best = [i for i in order if usable[i]]
        if best:
            step = aside.candidates[best[0]]
            self._stepping = (float(step[0]), float(step[1]))
        return self._stepping

    def _rules(
        self,
        requested: Command,
        scan: np.ndarray,
        dt: float,
        velocity: tuple[float, float] | None,
        drift: tuple[float, float] | None,
    ) -> Command:
        """The rules before the gate: limits, caps, brake, keep-out, ramps (see the module doc)."""
        forward, left = float(requested.forward), float(requested.lateral)
        if not math.isfinite(left):
            left = forward = math.nan  # counted and zeroed as a non-finite forward command is
        if left == 0.0 or not math.isfinite(forward):
            return self._filter_along_nose(Command(forward, requested.yaw_rate), scan, dt, velocity, drift)
        shift = round(math.degrees(math.atan2(left, forward))) % N_BINS
        course = math.radians(shift)
        self._previous = _turned(self._previous, -course)
        along = self._filter_along_nose(
            Command(math.hypot(forward, left), requested.yaw_rate), np.roll(np.asarray(scan), -shift), dt,
            _turned_pair(velocity, -course), _turned_pair(drift, -course),
        )  # fmt: skip
        self._previous = out = _turned(along, course)
        return out

    def _filter_along_nose(
        self,
        requested: Command,
        scan: np.ndarray,
        dt: float,
        velocity: tuple[float, float] | None,
        drift: tuple[float, float] | None,
    ) -> Command:
        """:meth:`filter` for a command without a sideways part (its ``lateral`` is not read)."""
        cfg = self.config
        count = self.interventions
        forward, yaw_rate = float(requested.forward), float(requested.yaw_rate)
        if not (math.isfinite(forward) and math.isfinite(yaw_rate)):
            count["nan"] += 1
            forward, yaw_rate = 0.0, 0.0

        values, had_non_finite = _finite_scan(scan)
        if had_non_finite:
            count["scan_nan"] += 1
        front = self._front_clearance(values)
        rear = float(values[self._rear_bins].min()) * self.max_range

        if forward > cfg.max_speed:
            count["speed_limit"] += 1
            forward = cfg.max_speed
        elif forward < -cfg.max_reverse_speed:
            count["speed_limit"] += 1
            forward = -cfg.max_reverse_speed
        if abs(yaw_rate) > self.max_yaw_rate:
            count["yaw_limit"] += 1
            yaw_rate = math.copysign(self.max_yaw_rate, yaw_rate)

        # The caps bound the true motion. The autopilot flies the setpoint on its estimate, so the
        # setpoint that truly moves at a cap is that cap plus the drift estimate along the nose.
        drift_along = self._drift_along(velocity, drift)
        true_forward = forward - drift_along
        front_cap = self._clearance_cap(true_forward, front, "estop")
        rear_cap = self._clearance_cap(-true_forward, rear - cfg.rear_clear_margin, "reverse_blocked")
        travel_cap, brake = self._travel_limit(values, velocity, true_forward)
        forward_cap, reverse_cap = front_cap, rear_cap
        if true_forward >= 0.0:
            forward_cap = min(front_cap, travel_cap)
        else:
            reverse_cap = min(rear_cap, travel_cap)

        step = max(dt, 0.0) if math.isfinite(dt) else 0.0
        slewed = _slew(forward, self._previous.forward, cfg.max_accel * step)
        if slewed != forward:
            count["accel_limit"] += 1
        slewed_yaw = _slew(yaw_rate, self._previous.yaw_rate, cfg.max_yaw_accel * step)
        if slewed_yaw != yaw_rate:
            count["yaw_accel_limit"] += 1
        # The clearance caps bound the slewed value too: a slew never holds speed towards an obstacle.
        forward = min(max(slewed, drift_along - reverse_cap), forward_cap + drift_along)
        lateral = 0.0
        if brake is not None:
            # The measured motion cannot stop before what lies along it: stop, braking against the
            # motion (never slew-limited), forward no further than the nose and tail sectors allow.
            lowest = -min(rear_cap, cfg.max_reverse_speed)
            forward = min(max(brake[0], lowest), max(min(front_cap, cfg.max_speed), 0.0))
            lateral = brake[1]
        forward, lateral, push = self._keep_out(values, forward, lateral, step)
        if (brake is not None or push) and _finite_pair(velocity):  # the estimate is drift's base
            forward, lateral = self._compensate(forward, lateral, drift)
        # The sector caps hold for all. The travel cap bounds the policy's command alone: the brake
        # and the push point away from what they answer, each bounded by the room on its far side,
        # and the travel's arc can hold the very return they move away from.
        forward = min(max(forward, drift_along - rear_cap), front_cap + drift_along)
        if push:
            course = _course(velocity) if push == "closing" else None
            carried = self._carried_drift(drift) if _finite_pair(velocity) else None
            forward, lateral = self._within_room(values, forward, lateral, course, carried)
        out = Command(forward=forward, yaw_rate=slewed_yaw, lateral=lateral)
        self._previous = out
        return out

    def _travel_limit(
        self, values: np.ndarray, velocity: tuple[float, float] | None, forward: float
    ) -> tuple[float, tuple[float, float] | None]:
        """What the measured motion allows: the speed cap from the clearance along the travel (over
        the arc from where the command points round to the course, at most 90°: see
        :func:`_commanded_side`), and None while the motion can stop before the clearance over the
        whole arc from the course round to the command, else the brake: the (forward, left)
        setpoint against the motion.
        """
        if velocity is None:
            return math.inf, None
        if not _finite_pair(velocity):
            self.interventions["velocity_nan"] += 1
            return 0.0, (0.0, 0.0)
        speed, course = _motion(velocity)
        if speed < MIN_TRAVEL_SPEED:
            return math.inf, None
        heading = 0.0 if forward >= 0.0 else 180.0
        along, whole = self._travel_clearances(values, course, heading)
        cap = self._clearance_cap(abs(forward), along, "estop_travel")
        if self._can_stop(speed, whole):
            return cap, None
        self.interventions["motion_stop"] += 1
        # brake against the motion, no faster than max_reverse_speed nor than the room behind it allows
        width = self.config.travel_sector_deg
        behind = float(values[sector_bins((course + 180.0) % 360.0, width)].min()) * self.max_range
        magnitude = min(speed, self.config.max_reverse_speed, self._allowed_speed(behind))
        return cap, (-float(velocity[0]) / speed * magnitude, -float(velocity[1]) / speed * magnitude)

    def _front_clearance(self, values: np.ndarray) -> float:
        """What limits forward flight, m: the lane's distance along the nose ±``lane_spread_deg``,
        or without a lane the nearest return in the forward sector."""
        if self.config.lane_half_width <= 0.0:
            return float(values[self._forward_bins].min()) * self.max_range
        spread = self.config.lane_spread_deg
        return self._lane(values, np.linspace(-spread, spread, 2 * math.ceil(spread) + 1))

    def _lane(self, values: np.ndarray, headings_deg: np.ndarray) -> float:
        """:func:`lane_distance` over ``headings_deg`` for the normalised scan ``values``, m, at
        most ``max_range`` (no return in the lane reads as the clearest scan)."""
        ranges = values * self.max_range
        return min(lane_distance(ranges, headings_deg, self.config.lane_half_width), self.max_range)

    def _travel_clearances(self, values: np.ndarray, course: float, heading: float) -> tuple[float, float]:
        """The clearance along the travel for the command's speed (from ``heading`` round towards
        ``course``, at most 90°: :func:`_commanded_side`) and for the measured motion's stop (the
        whole arc), m; one sweep when the course is within 90° of ``heading``, as it mostly is."""
        whole = self._travel_clearance(values, course, heading)
        side = _commanded_side(course, heading)
        return (whole if side == course else self._travel_clearance(values, side, heading)), whole

    def _travel_clearance(self, values: np.ndarray, course: float, heading: float) -> float:
        """What limits flight along the motion, m, over the arc from ``course`` round to ``heading``
        (degrees counter-clockwise from the nose; 0: the nose, 180: the tail): the lane's distance,
        swept ``lane_spread_deg`` beyond both ends, or without a lane the nearest return within
        ±``travel_sector_deg``."""
        if self.config.lane_half_width > 0.0:
            span = (heading - course + 180.0) % 360.0 - 180.0
            beyond = math.copysign(self.config.lane_spread_deg, span if span else 1.0)
            start, end = course - beyond, course + span + beyond
            return self._lane(values, np.linspace(start, end, math.ceil(abs(end - start)) + 1))
        bins = arc_bins(course, heading, self.config.travel_sector_deg)
        return float(values[bins].min()) * self.max_range

    def _can_stop(self, speed: float, clearance: float) -> bool:
        """Whether the measured ``speed`` stops short of ``estop_distance`` before ``clearance``."""
        margin = clearance - self.config.estop_distance
        return stopping_distance(speed, self.max_decel, self.reaction_time) < margin

    def _keep_out(
        self, values: np.ndarray, forward: float, lateral: float, dt: float
    ) -> tuple[float, float, str]:
        """Near the nearest return: drop what the setpoint asks towards it and push away from it,
        no faster than the room on the far side allows; and why it acted: ``"near"`` (inside
        ``keepout_distance``), ``"closing"`` (farther out) or ``""`` (it did not).

        It acts inside ``keepout_distance``, and farther out too when the scan shows the vehicle
        closing on that return faster than it could stop: the nearest distance of two scans is the
        true closing speed, whatever the velocity estimate says, and turning does not change it.
        """
        cfg = self.config
        if cfg.keepout_distance <= 0.0:
            return forward, lateral, ""
        previous, self._previous_nearest = self._previous_nearest, float(values.min()) * self.max_range
        nearest = int(np.argmin(values))
        distance = self._previous_nearest
        closing = 0.0
        if previous is not None and dt > 0.0:
            closing = max(0.0, (previous - distance) / dt)
        stopping = stopping_distance(closing, self.max_decel, self.reaction_time)
        too_fast = stopping >= distance - cfg.estop_distance
        if distance >= cfg.keepout_distance and not (closing > 0.0 and too_fast):
            return forward, lateral, ""
        self.interventions["keepout"] += 1
        towards = math.radians(nearest + 0.5)
        ux, uy = math.cos(towards), math.sin(towards)
        along = forward * ux + lateral * uy
        if along > 0.0:
            forward, lateral = forward - along * ux, lateral - along * uy
        away = float(values[sector_bins((nearest + 180.5) % 360.0, cfg.travel_sector_deg)].min())
        push = min(
            cfg.keepout_max_speed,
            cfg.keepout_gain * max(cfg.keepout_distance - distance, 0.0) + 2.0 * closing,
            self._allowed_speed(away * self.max_range),
        )
        forward, lateral = forward - push * ux, lateral - push * uy
        limit = max(cfg.max_reverse_speed, cfg.keepout_max_speed)
        reason = "near" if distance < cfg.keepout_distance else "closing"
        return min(max(forward, -limit), cfg.max_speed), min(max(lateral, -limit), limit), reason

    def _within_room(
        self,
        values: np.ndarray,
        forward: float,
        lateral: float,
        course: float | None,
        carried: tuple[float, float] | None = None,
    ) -> tuple[float, float]:
        """The setpoint (``forward``, ``lateral``) whose true motion (less the ``carried`` drift
        estimate) is slowed, its direction kept, to what stops before the clearance along that
        direction, or with ``course`` (degrees) along the way the velocity swings there from it
        (:func:`_commanded_side`, as the policy's command is judged). Scaling the setpoint itself
        would scale the drift it carries too, and could turn the true motion round.

        The push is bounded by the room behind it and the command by the room along its course, but
        their sum points elsewhere, where neither bound holds: a policy's sideways command plus a push
        from a wall on the other side asked 1.7 m/s where 0.96 stopped in time (a demo collision).
        A push that answers a return closing in from beyond ``keepout_distance`` is given the course:
        nothing is near yet, and it must not make a hazard on its way (a 1 m/s push to the left,
        the vehicle flying straight on at 1.6 m/s, slid it into a corridor's other wall in SITL);
        judging a push from a return already near that way held it back in warehouse aisles (3
        validation collisions, docs/goal-policy.md)."""
        shift_forward, shift_left = carried if carried is not None else (0.0, 0.0)
        true_forward, true_left = forward - shift_forward, lateral - shift_left
        speed = math.hypot(true_forward, true_left)
        if speed == 0.0:
            return forward, lateral
        direction = math.degrees(math.atan2(true_left, true_forward))
        side = direction if course is None else _commanded_side(course, direction)
        room = self._allowed_speed(self._travel_clearance(values, side, direction))
        if speed <= room:
            return forward, lateral
        self.interventions["keepout_room"] += 1
        return true_forward * room / speed + shift_forward, true_left * room / speed + shift_left

    def _compensate(
        self, forward: float, lateral: float, drift: tuple[float, float] | None
    ) -> tuple[float, float]:
        """The setpoint whose true motion is (``forward``, ``lateral``): plus the drift estimate,
        each axis within ``drift_compensation``."""
        carried = self._carried_drift(drift)
        if carried is None:
            if drift is not None and self.config.drift_compensation > 0.0:
                self.interventions["drift_nan"] += 1
            return forward, lateral
        self.interventions["drift_compensation"] += 1
        return forward + carried[0], lateral + carried[1]

    def _drift_along(self, velocity: tuple[float, float] | None, drift: tuple[float, float] | None) -> float:
        """The drift estimate along the nose that the setpoint carries, m/s; 0 without a finite
        velocity (the estimate's base)."""
        carried = self._carried_drift(drift)
        return carried[0] if carried is not None and _finite_pair(velocity) else 0.0

    def _carried_drift(self, drift: tuple[float, float] | None) -> tuple[float, float] | None:
        """The drift estimate, each axis within ``drift_compensation``, m/s; None when none is
        carried: off, no estimate, or one that is not finite."""
        bound = self.config.drift_compensation
        if bound <= 0.0 or drift is None or not _finite_pair(drift):
            return None
        return min(max(float(drift[0]), -bound), bound), min(max(float(drift[1]), -bound), bound)

    def _allowed_speed(self, clearance: float) -> float:
        """Largest speed towards a sector with ``clearance`` metres: 0 inside ``estop_distance``,
        else the speed that still stops at ``estop_distance``."""
        cfg = self.config
        if clearance < cfg.estop_distance:
            return 0.0
        return stopping_speed(clearance - cfg.estop_distance, self.max_decel, self.reaction_time)

    def _clearance_cap(self, speed: float, clearance: float, blocked_reason: str) -> float:
        """:meth:`_allowed_speed`, counting when it bites.

        :param speed: requested speed towards that sector (negative = away from it)
        :param clearance: nearest return in that sector, metres
        :param blocked_reason: counter name when the sector is inside ``estop_distance``
        """
        cap = self._allowed_speed(clearance)
        if speed > cap:
            blocked = clearance < self.config.estop_distance
            self.interventions[blocked_reason if blocked else "stopping_distance"] += 1
        return cap
