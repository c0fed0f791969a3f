"""The safety shield: a classic filter between the learned policy and the autopilot.

It does not trust the policy. Whatever the network asks for, the command that leaves the shield is
finite, within the speed and yaw-rate limits, slow enough to stop before the nearest return ahead
(or behind, when backing up), and grows no faster than the acceleration limits. Slowing down is
never delayed by the acceleration limit: braking is always allowed at once.

Emergency stop (a forward-sector return closer than ``estop_distance``): no forward motion, but
turning in place stays allowed and backing up too when the rear sector is clear, so the vehicle
can get itself out.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field

import numpy as np

from companion.scan import N_BINS


@dataclass(frozen=True)
class Command:
    """A body-frame setpoint.

    :param forward: body x velocity, m/s (negative = backwards)
    :param yaw_rate: rad/s, FLU: counter-clockwise (to the left) positive
    """

    forward: float
    yaw_rate: float


@dataclass(frozen=True)
class ShieldConfig:
    """Limits of the shield (the ``[shield]`` table of the companion config).

    :param max_speed: forward speed limit, m/s
    :param max_reverse_speed: backward speed limit, m/s
    :param max_yaw_rate: rad/s, either direction
    :param max_accel: how fast the forward speed may grow, m/s²
    :param max_yaw_accel: how fast the yaw rate may grow, rad/s²
    :param max_decel: braking the stopping-distance limit assumes, m/s²
    :param reaction_time: delay before braking starts (scan age, control period and the autopilot's
        velocity-loop lag), s. 0.8 s is what the simulated quad needs to stop at ``estop_distance``
        from a wall it meets at 2 m/s (``tests/flightsim/test_env.py``); measure a real vehicle's.
    :param estop_distance: a forward return closer than this stops all forward motion, m
    :param rear_clear_margin: backing up needs the rear sector clear beyond ``estop_distance`` plus this, m
    :param forward_sector_deg: half-width of the forward sector, degrees
    :param rear_sector_deg: half-width of the rear sector, degrees
    """

    max_speed: float = field(default=2.0, metadata={"min": 0.0, "max": 20.0})
    max_reverse_speed: float = field(default=0.5, metadata={"min": 0.0, "max": 5.0})
    max_yaw_rate: float = field(default=1.5, metadata={"min": 0.0, "max": 6.0})
    max_accel: float = field(default=2.0, metadata={"min": 0.01, "max": 20.0})
    max_yaw_accel: float = field(default=4.0, metadata={"min": 0.01, "max": 50.0})
    max_decel: float = field(default=2.0, metadata={"min": 0.1, "max": 20.0})
    reaction_time: float = field(default=0.8, metadata={"min": 0.0, "max": 5.0})
    estop_distance: float = field(default=0.3, metadata={"min": 0.0, "max": 10.0})
    rear_clear_margin: float = field(default=0.2, metadata={"min": 0.0, "max": 10.0})
    forward_sector_deg: float = field(default=30.0, metadata={"min": 1.0, "max": 90.0})
    rear_sector_deg: float = field(default=30.0, metadata={"min": 1.0, "max": 90.0})


def sector_bins(centre_deg: float, half_width_deg: float) -> np.ndarray:
    """Scan bins whose centre lies within ``half_width_deg`` of ``centre_deg`` (counter-clockwise).

    With the defaults, forward ±30° is bins 0..29 and 330..359; rear ±30° is bins 150..209.
    """
    centres = np.arange(N_BINS) + 0.5
    offset = (centres - centre_deg + 180.0) % 360.0 - 180.0
    return np.flatnonzero(np.abs(offset) <= half_width_deg)


def stopping_speed(distance: float, max_decel: float, reaction_time: float) -> float:
    """Highest speed from which the vehicle still stops within ``distance``.

    Solves ``v·t_r + v²/(2a) = d`` for ``v``: ``v = −a·t_r + sqrt((a·t_r)² + 2·a·d)``.
    """
    d = max(distance, 0.0)
    at = max_decel * reaction_time
    return -at + math.sqrt(at * at + 2.0 * max_decel * d)


def command_from_action(action: np.ndarray, max_speed: float, max_yaw_rate: float) -> Command:
    """Scale a policy action ``a ∈ [−1, 1]²`` to a command, as training did.

    :param action: ``(2,)``: a0 forward speed, a1 yaw rate (counter-clockwise positive)
    :param max_speed: m/s that a0 = 1 stands for (the model's training value)
    :param max_yaw_rate: rad/s that a1 = 1 stands for (the model's training value)
    """
    a = np.asarray(action, dtype=np.float64).reshape(-1)
    if a.shape[0] != 2:
        raise ValueError(f"action must have 2 values, got {a.shape[0]}")
    return Command(forward=float(a[0]) * max_speed, yaw_rate=float(a[1]) * max_yaw_rate)


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


def _slew(target: float, previous: float, step: float) -> float:
    """Limit how fast ``target`` moves away from zero; moving towards zero is never limited."""
    lo = min(previous, 0.0) - step
    hi = max(previous, 0.0) + step
    return min(max(target, lo), hi)


class SafetyShield:
    """Filters every policy command against the latest scan.

    :param config: the limits
    :param max_range: metres that a scan value of 1.0 stands for
    """

    def __init__(self, config: ShieldConfig, max_range: float) -> None:
        if not max_range > 0:
            raise ValueError(f"max_range must be positive, got {max_range}")
        self.config = config
        self.max_range = float(max_range)
        self.interventions: collections.Counter[str] = collections.Counter()
        self._forward_bins = sector_bins(0.0, config.forward_sector_deg)
        self._rear_bins = sector_bins(180.0, config.rear_sector_deg)
        self._previous = Command(0.0, 0.0)

    def reset(self) -> None:
        """Forget the previous command, so the next one ramps up from standstill (e.g. after HOLD)."""
        self._previous = Command(0.0, 0.0)

    def forward_cap(self, scan: np.ndarray) -> float:
        """The fastest forward speed the shield lets through against ``scan`` (0 inside
        ``estop_distance``), m/s: what a policy that needs no shield asks for at most.

        :param scan: ``(360,)`` normalised ranges, bins counter-clockwise from forward
        """
        values, _ = _finite_scan(scan)
        return self._allowed_speed(float(values[self._forward_bins].min()) * self.max_range)

    def filter(self, requested: Command, scan: np.ndarray, dt: float) -> Command:
        """Return the command that is safe to send.

        :param requested: what the policy asked for
        :param scan: ``(360,)`` normalised ranges, bins counter-clockwise from forward
        :param dt: seconds since the previous command (for the acceleration limits); a
            non-positive or non-finite ``dt`` allows no increase at all
        """
        cfg = self.config
        count = self.interventions
        forward, yaw_rate = float(requested.forward), float(requested.yaw_rate)
        if not (math.isfinite(forward) and math.isfinite(yaw_rate)):
            count["nan"] += 1
            forward, yaw_rate = 0.0, 0.0

        values, had_non_finite = _finite_scan(scan)
        if had_non_finite:
            count["scan_nan"] += 1
        front = float(values[self._forward_bins].min()) * self.max_range
        rear = float(values[self._rear_bins].min()) * self.max_range

        if forward > cfg.max_speed:
            count["speed_limit"] += 1
            forward = cfg.max_speed
        elif forward < -cfg.max_reverse_speed:
            count["speed_limit"] += 1
            forward = -cfg.max_reverse_speed
        if abs(yaw_rate) > cfg.max_yaw_rate:
            count["yaw_limit"] += 1
            yaw_rate = math.copysign(cfg.max_yaw_rate, yaw_rate)

        forward_cap = self._clearance_cap(forward, front, "estop")
        reverse_cap = self._clearance_cap(-forward, rear - cfg.rear_clear_margin, "reverse_blocked")

        step = max(dt, 0.0) if math.isfinite(dt) else 0.0
        slewed = _slew(forward, self._previous.forward, cfg.max_accel * step)
        if slewed != forward:
            count["accel_limit"] += 1
        slewed_yaw = _slew(yaw_rate, self._previous.yaw_rate, cfg.max_yaw_accel * step)
        if slewed_yaw != yaw_rate:
            count["yaw_accel_limit"] += 1
        # The clearance caps bound the slewed value too: a slew never holds speed towards an obstacle.
        out = Command(forward=min(max(slewed, -reverse_cap), forward_cap), yaw_rate=slewed_yaw)
        self._previous = out
        return out

    def _allowed_speed(self, clearance: float) -> float:
        """Largest speed towards a sector with ``clearance`` metres: 0 inside ``estop_distance``,
        else the speed that still stops at ``estop_distance``."""
        cfg = self.config
        if clearance < cfg.estop_distance:
            return 0.0
        return stopping_speed(clearance - cfg.estop_distance, cfg.max_decel, cfg.reaction_time)

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
