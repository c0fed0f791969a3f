"""How the vehicle moved between two consecutive 360° scans: range-flow scan matching.

The goal baseline needs the vehicle's *true* motion: PX4's velocity estimate can be 0.2–0.4 m/s
off, and the autopilot closes its velocity loop on that estimate, so a vehicle told to hover
drifts at the estimate's error while reporting zero (tests/fixtures/autopilot-response). The
walls do not drift, so two scans 0.1 s apart show the motion the estimate cannot.

Method (the linearised range flow of polar scan matching): a return at range ``r`` and bearing
``θ`` in the first scan, after the vehicle moves ``(dx, dy)`` (body frame of the first scan, FLU)
and turns ``dψ`` (CCW), is seen at range ``r - dx cos θ - dy sin θ`` and bearing
``θ - dψ + (dx sin θ - dy cos θ) / r``. The second scan, read at that bearing, must show that
range; linearising the second scan around the predicted bearing gives one linear equation in
``(dx, dy, dψ)`` per bin. A few Gauss–Newton iterations with Huber weights solve them; bins at
obstacle edges (steep range gradient), empty bins and near-max ranges are left out. Pure numpy.
"""

from __future__ import annotations

import math

import numpy as np

#: a bin's range may change by at most this much to its neighbours (m per bin) to be matched:
#: steeper is an obstacle edge, where the linearisation does not hold
_MAX_GRADIENT = 0.15
#: Huber threshold of a range residual, m (the sensor's noise is 0.02 m)
_HUBER = 0.05


def scan_motion(
    previous: np.ndarray,
    current: np.ndarray,
    turn_guess: float = 0.0,
    max_range: float = 10.0,
    iterations: int = 4,
) -> tuple[float, float, float, int]:
    """The motion between two scans: ``(dx, dy, dpsi, used)``.

    :param previous: ``(n,)`` ranges of the first scan, m, ``inf`` where nothing was seen; bin
        ``i`` looks ``(i + 0.5) · 360/n`` degrees CCW from the nose
    :param current: the same for the second scan
    :param turn_guess: the turn ``dpsi`` expected (rad, CCW), the start of the iteration; a turn of
        more than a few bins is only found from a guess near it
    :param max_range: returns this far or farther are ignored (the scan saturates there)
    :param iterations: Gauss–Newton iterations
    :return: ``dx, dy`` (m, body frame of ``previous``, FLU), ``dpsi`` (rad, CCW), and the number
        of bins the last iteration used (0: nothing to match; the motion is then all zeros)
    """
    n = previous.shape[0]
    step = 2.0 * math.pi / n
    theta = (np.arange(n) + 0.5) * step
    seen0 = np.isfinite(previous) & (previous < 0.95 * max_range)
    r1 = np.where(np.isfinite(current) & (current < 0.95 * max_range), current, np.nan)
    cos, sin = np.cos(theta), np.sin(theta)
    x = np.array([0.0, 0.0, float(turn_guess)])
    used = 0
    for _ in range(iterations):
        dx, dy, dpsi = x
        r0 = np.where(seen0, previous, 1.0)
        predicted_range = r0 - dx * cos - dy * sin
        predicted_bearing = theta - dpsi + (dx * sin - dy * cos) / r0
        position = (predicted_bearing / step - 0.5) % n  # fractional bin index in the second scan
        low = np.floor(position).astype(int) % n
        high = (low + 1) % n
        frac = position - np.floor(position)
        a, b = r1[low], r1[high]
        read = a + frac * (b - a)
        gradient = (b - a) / step  # m per rad
        ok = seen0 & np.isfinite(read) & (np.abs(b - a) < _MAX_GRADIENT)
        used = int(ok.sum())
        if used < 12:
            return 0.0, 0.0, 0.0, 0
        g, c, s, r = gradient[ok], cos[ok], sin[ok], r0[ok]
        # d(read - predicted_range)/d(dx, dy, dpsi)
        jacobian = np.stack([g * s / r + c, -g * c / r + s, -g], axis=1)
        residual = read[ok] - predicted_range[ok]
        weight = np.minimum(1.0, _HUBER / np.maximum(np.abs(residual), 1e-9))
        jw = jacobian * weight[:, None]
        normal = jw.T @ jacobian + 1e-6 * np.eye(3)
        x = x - np.linalg.solve(normal, jw.T @ residual)
    return float(x[0]), float(x[1]), float(x[2]), used
