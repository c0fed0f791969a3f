"""The drift estimate finds the velocity estimate's error from consecutive scans of a room."""

import math

import numpy as np
import pytest

from companion.perception.drift import DriftEstimator, DriftHoldConfig, held_drift
from tests.companion.test_scan_motion import room_scan


def _fly(estimator, error, true_velocity=(0.3, 0.0), yaw_rate=0.0, steps=30, dt=0.1):
    """Fly a room at ``true_velocity`` (body, m/s) while the autopilot reports it plus ``error``
    (world frame, as an estimator's bias is); returns the estimate and the error in the last body frame."""
    x, y, yaw = -1.0, -0.5, 0.2
    goal = np.array([3.0, 2.0])
    bias = np.zeros(2)
    for _ in range(steps):
        c, s = math.cos(yaw), math.sin(yaw)
        rel = goal - (x, y)
        bearing = math.atan2(-s * rel[0] + c * rel[1], c * rel[0] + s * rel[1])
        in_body = np.array([c * error[0] + s * error[1], -s * error[0] + c * error[1]])
        reported = np.asarray(true_velocity) + in_body
        bias = estimator.update(room_scan(x, y, yaw), reported, bearing, float(np.hypot(*rel)), dt)
        x += dt * (c * true_velocity[0] - s * true_velocity[1])
        y += dt * (s * true_velocity[0] + c * true_velocity[1])
        yaw += dt * yaw_rate
    return bias, in_body


@pytest.mark.parametrize("yaw_rate", [0.0, 0.8])
def test_the_error_the_reported_velocity_hides_is_found(yaw_rate):
    error = np.array([0.2, -0.15])
    bias, truth = _fly(DriftEstimator(), error, yaw_rate=yaw_rate)
    assert bias == pytest.approx(truth, abs=0.04)


def test_no_error_reads_none():
    assert np.abs(_fly(DriftEstimator(), np.zeros(2))[0]).max() < 0.03


def test_scans_too_far_apart_are_not_matched():
    estimator = DriftEstimator()
    bias, _ = _fly(estimator, np.array([0.3, 0.0]), dt=0.5)  # every gap longer than max_gap_s
    assert np.all(bias == 0.0)


def test_reset_forgets_the_error():
    estimator = DriftEstimator()
    _fly(estimator, np.array([0.3, 0.0]))
    estimator.reset()
    assert np.all(estimator.bias == 0.0)
    assert np.all(estimator.update(room_scan(0.0, 0.0, 0.0), np.zeros(2), 0.0, 5.0, 0.1) == 0.0)


def test_the_setpoint_holds_the_sideways_drift_beyond_the_deadband_within_its_bound():
    hold = DriftHoldConfig()  # the defaults: sideways only, 0.15 m/s deadband, at most 0.6 m/s
    assert held_drift(np.array([0.5, 0.4]), hold) == pytest.approx((0.0, 0.25))
    assert held_drift(np.array([0.0, -0.35]), hold) == pytest.approx((0.0, -0.2))
    assert held_drift(np.array([0.0, 0.12]), hold) == (0.0, 0.0)  # within the estimate's noise
    assert held_drift(np.array([0.0, -1.5]), hold) == pytest.approx((0.0, -0.6))
    both = DriftHoldConfig(forward=0.2, lateral=0.6, deadband=0.0)
    assert held_drift(np.array([-0.5, 0.4]), both) == pytest.approx((-0.2, 0.4))


@pytest.mark.parametrize("bias", [(math.nan, 0.4), (0.0, math.inf)])
def test_a_non_finite_drift_estimate_is_never_held(bias):
    assert held_drift(np.array(bias), DriftHoldConfig(forward=0.6)) == (0.0, 0.0)
