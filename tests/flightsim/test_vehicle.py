"""The JSBSim quadrotor under its cascaded controller: real JSBSim, real integration."""

from __future__ import annotations

import math

import numpy as np
import pytest

from flightsim.vehicle.control import ControllerConfig, Setpoint
from flightsim.vehicle.quadrotor import GEAR_HEIGHT_M, Vehicle, VehicleConfig


@pytest.fixture(scope="module")
def vehicle():
    v = Vehicle()
    yield v
    v.close()


def fly(vehicle: Vehicle, seconds: float, make_setpoint) -> list:
    """Step at the control rate for `seconds`, asking `make_setpoint(state)` each step."""
    states = []
    for _ in range(round(seconds * vehicle.config.control_hz)):
        states.append(vehicle.step(make_setpoint(vehicle.state)))
    return states


def test_airborne_reset_puts_the_vehicle_where_asked(vehicle):
    s = vehicle.reset((3.0, -4.0, 1.2), 0.7)
    np.testing.assert_allclose(s.position, [3.0, -4.0, 1.2], atol=1e-6)
    np.testing.assert_allclose(s.velocity, 0.0, atol=1e-9)
    assert s.yaw == pytest.approx(0.7)
    assert s.armed and not s.on_ground and s.time == 0.0


def test_hover_holds_altitude_for_10_s(vehicle):
    vehicle.reset((0.0, 0.0, 1.5), 0.3)
    states = fly(vehicle, 10.0, lambda s: Setpoint())
    z = np.array([s.position[2] for s in states])
    assert np.all(np.abs(z - 1.5) <= 0.1), (z.min(), z.max())
    assert states[-1].time == pytest.approx(10.0)
    assert np.hypot(*states[-1].position[:2]) < 0.05


def test_forward_step_reaches_1_8_within_2_s_without_overshoot(vehicle):
    vehicle.reset((0.0, 0.0, 1.5), 0.0)
    states = fly(vehicle, 4.0, lambda s: Setpoint.from_body(2.0, 0.0, s.yaw, altitude=1.5))
    speed = np.array([s.forward_speed for s in states])
    t = np.array([s.time for s in states])
    assert t[np.argmax(speed >= 1.8)] <= 2.0 and speed.max() >= 1.8
    assert speed.max() <= 2.4
    # Forward means along the nose: yaw 0 is East.
    assert states[-1].velocity[0] == pytest.approx(2.0, abs=0.1)
    assert abs(states[-1].velocity[1]) < 0.05


def test_forward_is_along_the_nose_for_any_heading(vehicle):
    yaw = 2.0
    vehicle.reset((0.0, 0.0, 1.5), yaw)
    s = fly(vehicle, 3.0, lambda s: Setpoint.from_body(1.5, 0.0, s.yaw, altitude=1.5))[-1]
    np.testing.assert_allclose(s.velocity[:2], 1.5 * np.array([math.cos(yaw), math.sin(yaw)]), atol=0.1)
    assert s.forward_speed == pytest.approx(1.5, abs=0.1)


def test_positive_yaw_rate_turns_the_nose_left(vehicle):
    vehicle.reset((0.0, 0.0, 1.5), 0.0)
    states = fly(vehicle, 1.0, lambda s: Setpoint(yaw_rate=1.0))
    yaws = np.unwrap([s.yaw for s in states])
    assert np.all(np.diff(yaws) > 0)
    assert 0.6 < yaws[-1] < 1.0
    nose = states[-1].rotation()[:, 0]  # body x in the world
    assert nose[1] > 0.5 and nose[0] > 0.0  # rotated from +x towards +y (North)
    assert states[-1].angular_rate[2] > 0.8


def test_altitude_holds_while_cruising_and_turning(vehicle):
    vehicle.reset((0.0, 0.0, 1.5), 0.0)
    states = fly(vehicle, 8.0, lambda s: Setpoint.from_body(2.0, 0.0, s.yaw, yaw_rate=1.5, altitude=1.5))
    z = np.array([s.position[2] for s in states])
    assert np.all(np.abs(z - 1.5) <= 0.2), (z.min(), z.max())
    # It did cruise and turn: a circle of radius ~ v / omega = 1.33 m, back near the start.
    yaw_turned = np.unwrap([s.yaw for s in states])[-1]
    assert yaw_turned > 1.5 * 8.0 * 0.9
    xy = np.array([s.position[:2] for s in states[30:]])
    assert 0.9 < np.ptp(xy[:, 0]) / 2 < 1.8


def test_takeoff_from_the_ground_and_disarmed_stays_down(vehicle):
    s = vehicle.reset((1.0, 1.0, 5.0), 0.0, on_ground=True)
    assert s.on_ground and not s.armed
    assert GEAR_HEIGHT_M - 0.01 < s.position[2] <= GEAR_HEIGHT_M
    # Disarmed: a climb demand does nothing.
    s = fly(vehicle, 2.0, lambda s: Setpoint(vz=1.0))[-1]
    assert s.on_ground and s.position[2] < GEAR_HEIGHT_M
    # Armed without a climb demand: idles on the floor, even asked to move sideways.
    vehicle.set_armed(True)
    s = fly(vehicle, 1.0, lambda s: Setpoint(vx=1.0))[-1]
    assert s.on_ground and s.armed
    np.testing.assert_allclose(s.position[:2], [1.0, 1.0], atol=1e-3)
    assert abs(s.roll) < 0.01 and abs(s.pitch) < 0.01
    # Climb at 1 m/s.
    states = fly(vehicle, 3.0, lambda s: Setpoint(vz=1.0))
    assert not states[-1].on_ground
    assert states[-1].velocity[2] == pytest.approx(1.0, abs=0.15)
    assert 2.0 < states[-1].position[2] < 3.5
    np.testing.assert_allclose(states[-1].position[:2], [1.0, 1.0], atol=0.05)
    # Hold: stays near where the climb stopped.
    z_stop = states[-1].position[2]
    s = fly(vehicle, 3.0, lambda s: Setpoint(vz=None))[-1]
    assert abs(s.position[2] - z_stop) < 0.4 and abs(s.velocity[2]) < 0.1


def test_disarming_in_flight_cuts_the_motors(vehicle):
    vehicle.reset((0.0, 0.0, 3.0), 0.0)
    vehicle.set_armed(False)
    s = fly(vehicle, 0.5, lambda s: Setpoint())[-1]
    assert s.velocity[2] < -3.0  # close to free fall: 0.5 s * 9.8 m/s^2, less the motor spin-down


@pytest.mark.parametrize("mass", [0.7, 2.0, 2.5])
def test_lighter_and_heavier_vehicles_hover_and_climb(vehicle, mass):
    vehicle.reset((0.0, 0.0, 1.5), 0.0, mass_kg=mass)
    assert vehicle.mass_kg == mass
    z = [s.position[2] for s in fly(vehicle, 3.0, lambda s: Setpoint())]
    assert max(abs(v - 1.5) for v in z) < 0.05
    s = fly(vehicle, 2.0, lambda s: Setpoint(vz=1.0))[-1]
    assert s.velocity[2] == pytest.approx(1.0, abs=0.1)


def test_wind_pushes_and_the_controller_leans_into_it(vehicle):
    vehicle.reset((0.0, 0.0, 1.5), 0.0)
    vehicle.set_wind(np.array([4.0, 0.0, 0.0]))  # blowing towards East, the nose's direction
    s = fly(vehicle, 6.0, lambda s: Setpoint())[-1]
    assert abs(s.velocity[0]) < 0.1  # holds zero ground speed...
    assert s.pitch < -0.02  # ...nose up: thrust tilted West, against the wind
    assert s.position[0] > 0.05  # after being blown downwind at first


def test_position_follows_the_integrated_velocity(vehicle):
    vehicle.reset((2.0, 3.0, 1.5), 1.0)
    states = fly(vehicle, 3.0, lambda s: Setpoint(vx=-1.0, vy=0.5, altitude=1.5))
    v = np.array([s.velocity for s in states])
    travelled = np.sum(v, axis=0) / vehicle.config.control_hz  # rectangle rule at 10 Hz
    np.testing.assert_allclose(states[-1].position - [2.0, 3.0, 1.5], travelled, atol=0.1)
    assert states[-1].velocity[0] < -0.8 and states[-1].velocity[1] > 0.4


def test_rotation_matches_the_euler_angles(vehicle):
    vehicle.reset((0.0, 0.0, 1.5), 0.5)
    s = fly(vehicle, 0.5, lambda s: Setpoint(vx=3.0, vy=3.0))[-1]  # tilted and accelerating
    r = s.rotation()
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    assert math.atan2(r[1, 0], r[0, 0]) == pytest.approx(s.yaw)
    # Accelerating towards North-East: the thrust axis (body z) leans that way.
    assert r[0, 2] > 0.05 and r[1, 2] > 0.05


def test_step_accepts_whole_physics_steps_only(vehicle):
    vehicle.reset((0.0, 0.0, 1.5), 0.0)
    s = vehicle.step(Setpoint(), duration=0.025)  # 3 physics steps at 120 Hz
    assert s.time == pytest.approx(0.025)
    with pytest.raises(ValueError, match="whole number of physics steps"):
        vehicle.step(Setpoint(), duration=0.02)
    with pytest.raises(ValueError, match="whole number of physics steps"):
        vehicle.step(Setpoint(), duration=0.0)


def test_autopilot_loop_rate_with_a_faster_physics_rate():
    v = Vehicle(VehicleConfig(physics_hz=200, control_hz=10))
    v.reset((0.0, 0.0, 1.0), 0.0)
    for _ in range(100):
        s = v.step(Setpoint(vx=1.0, altitude=1.0), duration=0.02)
    assert s.time == pytest.approx(2.0)
    assert s.velocity[0] == pytest.approx(1.0, abs=0.15)
    v.close()


@pytest.mark.parametrize(("physics_hz", "control_hz"), [(125, 10), (100, 30)])
def test_physics_rate_must_be_a_multiple_of_control_rate(physics_hz, control_hz):
    with pytest.raises(ValueError, match=rf"physics_hz \({physics_hz}\).*control_hz \({control_hz}\)"):
        VehicleConfig(physics_hz=physics_hz, control_hz=control_hz)


def test_bad_masses_and_resets_are_refused(vehicle):
    with pytest.raises(ValueError, match="mass_kg"):
        VehicleConfig(mass_kg=0.2)
    with pytest.raises(ValueError, match="mass_kg"):
        vehicle.reset((0.0, 0.0, 1.0), 0.0, mass_kg=5.0)
    with pytest.raises(ValueError, match="z >="):
        vehicle.reset((0.0, 0.0, 0.01), 0.0)


def test_controller_config_is_part_of_the_vehicle_config():
    cfg = VehicleConfig(controller=ControllerConfig(max_tilt_deg=10.0))
    v = Vehicle(cfg)
    v.reset((0.0, 0.0, 1.5), 0.0)
    tilts = [math.acos(s.rotation()[2, 2]) for s in fly(v, 1.5, lambda s: Setpoint(vx=5.0))]
    assert max(tilts) < math.radians(13.0)
    v.close()


def _replay(vehicle: Vehicle) -> np.ndarray:
    s = vehicle.reset((2.345678, -3.21, 1.234567), 0.7, mass_kg=1.5)
    values = [*s.position, *s.velocity, s.roll, s.pitch, s.yaw, *s.angular_rate]
    for _ in range(3):
        s = vehicle.step(Setpoint(1.0, 0.5, yaw_rate=0.3, altitude=1.2))
        values += [*s.position, *s.velocity, s.roll, s.pitch, s.yaw, *s.angular_rate]
    return np.array(values)


def test_reset_is_bit_exact_whatever_the_previous_flight(vehicle):
    # JSBSim's initial-condition setters convert through the position they already hold; a seeded
    # episode must replay to the last bit however the previous one ended (no env-side double reset).
    rng = np.random.default_rng(5)
    reference = _replay(vehicle)
    for _ in range(8):
        start = (float(rng.uniform(-10, 10)), float(rng.uniform(-10, 10)), float(rng.uniform(0.5, 3.0)))
        vehicle.reset(start, float(rng.uniform(-3, 3)), mass_kg=float(rng.uniform(1.2, 1.8)))
        for _ in range(int(rng.integers(1, 10))):
            vehicle.step(Setpoint(float(rng.uniform(-2, 2)), float(rng.uniform(-2, 2)), yaw_rate=0.5))
        np.testing.assert_array_equal(_replay(vehicle), reference)
