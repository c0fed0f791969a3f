"""The firmware envelope: what the shield assumes of how the true vehicle answers its setpoints.

One model, per direction. For a unit vector ``n`` in the horizontal plane, ``w(t)`` is the true
velocity's component along ``n`` (the *closing speed* towards whatever lies that way) and ``c(t)``
the setpoints' component. The envelope bounds ``w`` from above by ``W``:

* now: ``W(0) = w_measured + estimate_error`` (the measured velocity is the autopilot's estimate,
  less the drift estimate when the caller has one);
* a setpoint may still be flown from ``min_delay`` to ``max_delay`` after it was sent (scan and
  estimate age, the link, the firmware's input shaping and tilt lag together), so at time ``t``
  the target is the highest of the setpoints in force somewhere in that window;
* the target bound of a setpoint component ``c`` is ``c + overshoot * max(c, 0) - undershoot *
  min(c, 0) + estimate_error``: the firmware may overshoot a setpoint towards ``n``, fall short of
  one away from ``n`` (PX4's drag-limited approach) and fly its own velocity estimate's error;
* ``W`` rises towards its target at ``accel`` at most; it falls towards a lower target at a rate
  that starts at 0 and grows by ``jerk`` per second up to ``decel`` (the firmware's jerk-limited
  braking), at least.

With a position loop (ArduPilot's GUIDED velocity control integrates the setpoints into a position
target and corrects towards it), the estimate error does not add up: the true displacement exceeds
the worst case without it by at most ``position_error``. ``W`` and its target are shifted by the
estimate error alike, so the worst case without it is ``X(t) - estimate_error·t``, and the bound is
``X(t) - max(estimate_error·t - position_error, 0)``.

The displacement towards ``n``, ``X(t) = ∫ W`` (less that cap), bounds the true one for every
``n`` at once; and for a point ``o`` now at distance ``d`` in direction ``n``, ``|o - x(t)| >= o·n -
X(t)``: a worst case per direction is a worst case in the plane. :func:`worst_closing` integrates it.

Calibrated so that the real ArduCopter and PX4 SITL flights of the companion
and the simulator's random firmware draws lie inside it (``tests/companion/test_envelope.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

#: the integration step of the worst case, s: a setpoint counts over every step it is in force
#: for any part of, so a coarser step only widens the bound
STEP_S = 0.05


@dataclass(frozen=True)
class ResponseEnvelope:
    """A bound on how the true horizontal velocity answers velocity setpoints.

    :param name: what it bounds
    :param min_delay: a setpoint is flown no sooner than this after it is sent, s
    :param max_delay: a setpoint may still be flown this long after the next one is sent, s
    :param accel: the fastest the velocity along any direction grows, m/s²
    :param decel: the slowest it falls towards a lower target once braking is under way, m/s²
    :param jerk: how fast that braking builds up from 0, m/s³ (inf: at once)
    :param overshoot: how far beyond a setpoint component towards a direction the velocity may go,
        as a fraction of that component
    :param undershoot: how far short of a component away from a direction it may stay, fraction
    :param estimate_error: the true velocity's largest difference from the measured one (less the
        drift estimate), and from a steady setpoint, m/s
    :param max_yaw_rate: the highest yaw rate the firmware flies (its rate cap), rad/s
    :param position_error: with a position loop, the most the true displacement exceeds the worst
        case without the estimate error, m (inf: no position loop, the estimate error adds up)
    :param velocity_lag: how late the measured velocity may be, s: odometry integrated from it is
        off by this times the velocity's change (:mod:`companion.safety.obstacle_memory`)
    """

    name: str
    min_delay: float
    max_delay: float
    accel: float
    decel: float
    jerk: float
    overshoot: float
    undershoot: float
    estimate_error: float
    max_yaw_rate: float
    position_error: float = math.inf
    velocity_lag: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name != "name" and not value >= 0.0:  # inf is a limit that never acts
                raise ValueError(f"envelope {self.name}: {f.name} must be >= 0, got {value}")
        if self.decel <= 0.0 or self.accel <= 0.0 or self.jerk <= 0.0:
            raise ValueError(f"envelope {self.name}: accel, decel and jerk must be positive")
        if self.min_delay > self.max_delay:
            raise ValueError(f"envelope {self.name}: min_delay {self.min_delay} > max_delay {self.max_delay}")

    def covering(self, other: ResponseEnvelope, name: str) -> ResponseEnvelope:
        """The smallest envelope of this shape that contains both."""
        return ResponseEnvelope(
            name=name,
            min_delay=min(self.min_delay, other.min_delay),
            max_delay=max(self.max_delay, other.max_delay),
            accel=max(self.accel, other.accel),
            decel=min(self.decel, other.decel),
            jerk=min(self.jerk, other.jerk),
            overshoot=max(self.overshoot, other.overshoot),
            undershoot=max(self.undershoot, other.undershoot),
            estimate_error=max(self.estimate_error, other.estimate_error),
            max_yaw_rate=max(self.max_yaw_rate, other.max_yaw_rate),
            position_error=max(self.position_error, other.position_error),
            velocity_lag=max(self.velocity_lag, other.velocity_lag),
        )

    def target(self, component: np.ndarray) -> np.ndarray:
        """The bound on the closing speed a setpoint component settles to, m/s."""
        c = np.asarray(component, dtype=np.float64)
        return (
            c
            + self.overshoot * np.maximum(c, 0.0)
            - self.undershoot * np.minimum(c, 0.0)
            + self.estimate_error
        )


#: Fitted to the real SITL flights in ``../shared/fixtures/real-sitl-flights`` (the companion's own
#: setpoints and the SITL's ground truth) and the step responses in ``tests/fixtures/autopilot-response``.
ARDUPILOT = ResponseEnvelope(
    name="ardupilot",
    min_delay=0.05,
    max_delay=1.1,
    accel=5.66,
    decel=3.0,
    jerk=math.inf,
    overshoot=0.3,
    undershoot=0.3,
    estimate_error=0.3,
    max_yaw_rate=math.radians(60.0),
    # the real flights need 0.24 m over 2.5 s and 4 s (tests/companion/test_envelope.py)
    position_error=0.3,
    # the real flights' remembered returns need more than 0.06 s (tests/companion/test_envelope.py)
    velocity_lag=0.08,
)
#: PX4 SIH's velocity estimate departs from the truth by up to 1.3 m/s in those flights; less the
#: companion's drift estimate, by up to 0.63 m/s
PX4 = ResponseEnvelope(
    name="px4",
    min_delay=0.05,
    max_delay=1.0,
    accel=5.0,
    decel=2.0,
    jerk=math.inf,
    overshoot=0.3,
    undershoot=0.6,
    estimate_error=0.65,
    max_yaw_rate=math.radians(200.0),
    # the real flights' remembered returns need 0.24 s (tests/companion/test_envelope.py)
    velocity_lag=0.25,
)
#: the project's own simulated quad flying the command as given
IDEAL = ResponseEnvelope(
    name="ideal",
    min_delay=0.0,
    max_delay=0.6,
    accel=6.0,
    decel=2.0,
    jerk=math.inf,
    overshoot=0.1,
    undershoot=0.1,
    estimate_error=0.05,
    max_yaw_rate=math.inf,
)
ENVELOPES: dict[str, ResponseEnvelope] = {
    "ideal": IDEAL,
    "ardupilot": ARDUPILOT,
    "px4": PX4,
    "random": ARDUPILOT.covering(PX4, "random"),
}


def window_targets(
    sent_times: np.ndarray,
    components: np.ndarray,
    times: np.ndarray,
    envelope: ResponseEnvelope,
    step: float = STEP_S,
) -> np.ndarray:
    """The highest setpoint component that may be flown during each step.

    Setpoint ``j`` may be flown from ``min_delay`` after it is sent until ``max_delay`` after the
    next one is sent; it counts over a step ``[t, t + step)`` that this span touches.

    :param sent_times: ``(k,)`` when each setpoint was sent, s, ascending; before the first one the
        vehicle held still (a zero setpoint)
    :param components: ``(k, ...)`` each setpoint's component along each direction, m/s
    :param times: ``(m,)`` the start of each step, s
    :return: ``(m, ...)`` target bounds (:meth:`ResponseEnvelope.target` of the highest component)
    """
    sent = np.asarray(sent_times, dtype=np.float64)
    comps = np.asarray(components, dtype=np.float64)
    # the first setpoint whose span reaches the step: its successor was sent at or after t - max_delay
    first = np.searchsorted(sent, times - envelope.max_delay, side="left") - 1
    # the last one flown within the step: sent before t + step - min_delay
    last = np.searchsorted(sent, times + step - envelope.min_delay, side="left")
    out = np.full((len(times), *comps.shape[1:]), -np.inf)
    for i, (a, b) in enumerate(zip(first, last, strict=True)):
        if a < 0:  # the hold before the first setpoint is still in the window
            out[i] = 0.0
        if b > max(a, 0):
            out[i] = np.maximum(out[i], comps[max(a, 0) : b].max(axis=0))
    return envelope.target(out)


def worst_closing(
    closing_now: np.ndarray, targets: np.ndarray, envelope: ResponseEnvelope, step: float = STEP_S
) -> tuple[np.ndarray, np.ndarray]:
    """The bound ``W`` on the closing speed and ``X`` on the displacement at each step.

    :param closing_now: ``(...)`` the measured closing speed now, m/s
    :param targets: ``(m, ...)`` the target bound in force during each step
    :return: ``W`` and ``X``, each ``(m + 1, ...)``; ``X`` integrates the larger end of each step,
        less what the position loop takes off the estimate error's share (the module doc)
    """
    w = np.asarray(closing_now, dtype=np.float64) + envelope.estimate_error
    targets = np.asarray(targets, dtype=np.float64)
    ws = np.empty((len(targets) + 1, *np.broadcast_shapes(w.shape, targets.shape[1:])))
    xs = np.empty_like(ws)
    ws[0], xs[0] = w, 0.0
    if math.isinf(envelope.jerk):
        _closing_at_once(ws, xs, targets, envelope, step)
    else:
        rise, ramp = envelope.accel * step, envelope.jerk * step
        braking = np.zeros_like(ws[0])  # the deceleration built up so far, m/s²
        for k, target in enumerate(targets):
            w = ws[k]
            above = w > target
            braking = np.where(above, np.minimum(braking + ramp, envelope.decel), 0.0)
            nxt = np.where(above, np.maximum(w - braking * step, target), np.minimum(w + rise, target))
            ws[k + 1] = nxt
            xs[k + 1] = xs[k] + np.maximum(w, nxt) * step
    if math.isfinite(envelope.position_error):
        held = envelope.estimate_error * step * np.arange(len(xs)) - envelope.position_error
        xs -= np.maximum(held, 0.0).reshape(-1, *([1] * (xs.ndim - 1)))
    return ws, xs


def _closing_at_once(
    ws: np.ndarray, xs: np.ndarray, targets: np.ndarray, envelope: ResponseEnvelope, step: float
) -> None:
    """:func:`worst_closing` into ``ws[1:]`` and ``xs[1:]`` where braking is full at once (no jerk
    limit): each step's bound then follows from the last one's alone, so the displacement is summed
    after it (the same arithmetic, in fewer array operations)."""
    rise, brake = envelope.accel * step, envelope.decel * step
    for k, target in enumerate(targets):
        w = ws[k]
        ws[k + 1] = np.where(w > target, np.maximum(w - brake, target), np.minimum(w + rise, target))
    flown = np.maximum(ws[:-1], ws[1:]) * step
    for k in range(len(flown)):
        xs[k + 1] = xs[k] + flown[k]
