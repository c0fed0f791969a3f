"""The observation layout and its goal/velocity features (pure logic)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.perception.observation import (
    MOVER_FEATURES,
    ObservationLayout,
    build_frame,
    command_features,
    drift_features,
    firmware_features,
    goal_features,
    goal_in_body,
    mover_features,
)
from companion.perception.tracking import Mover

GOAL = ObservationLayout(goal=True, goal_range=10.0, velocity_scale=2.0)


def test_layouts_spell_out_sizes_slices_and_scales() -> None:
    scan = ObservationLayout()
    assert (scan.name, scan.frame_size, scan.slices()) == ("scan360", 360, {"scan": slice(0, 360)})
    assert GOAL.name == "scan360+goal(cos,sin,distance/10m)+velocity(forward,left/2m/s)"
    assert GOAL.frame_size == 365
    assert GOAL.slices() == {
        "scan": slice(0, 360),
        "goal_bearing": slice(360, 362),
        "goal_distance": slice(362, 363),
        "velocity": slice(363, 365),
    }
    low, high = GOAL.bounds()
    assert low[:360].tolist() == [0.0] * 360 and low[360:].tolist() == [-1, -1, 0, -1, -1]
    assert high.tolist() == [1.0] * 365
    with pytest.raises(ValueError):
        ObservationLayout(goal=True, goal_range=0.0)


def test_the_drift_layout_adds_two_features_after_the_goal() -> None:
    drift = ObservationLayout(goal=True, goal_range=10.0, velocity_scale=2.0, drift=True)
    assert drift.name == GOAL.name + "+drift(forward,left/2m/s)" and drift.frame_size == 367
    assert drift.slices() == GOAL.slices() | {"drift": slice(365, 367)}
    low, high = drift.bounds()
    assert low[365:].tolist() == [-1, -1] and high[365:].tolist() == [1, 1]
    np.testing.assert_allclose(drift_features(np.array([0.5, -3.0]), drift), [0.25, -1.0])
    features = np.concatenate([goal_features(1.0, 0.0, 0.0, 0.0, drift), drift_features(np.zeros(2), drift)])
    frame = build_frame(np.ones(360), features, drift)
    assert frame.shape == (367,)
    with pytest.raises(ValueError, match="drift needs goal"):
        ObservationLayout(drift=True)
    with pytest.raises(ValueError, match="finite"):
        drift_features(np.array([np.nan, 0.0]), drift)
    with pytest.raises(ValueError, match="no drift"):
        drift_features(np.zeros(2), GOAL)


def test_the_command_layout_adds_the_last_command_after_the_drift() -> None:
    command = ObservationLayout(goal=True, goal_range=10.0, drift=True, command=True, yaw_rate_scale=1.5)
    assert command.name == GOAL.name + "+drift(forward,left/2m/s)+command(forward/2m/s,yaw/1.5rad/s)"
    assert command.frame_size == 369
    assert command.slices() == GOAL.slices() | {"drift": slice(365, 367), "command": slice(367, 369)}
    low, high = command.bounds()
    assert low[365:].tolist() == [-1] * 4 and high[365:].tolist() == [1] * 4
    # forward / 2 m/s, yaw rate / 1.5 rad/s, clipped
    np.testing.assert_allclose(command_features(1.0, -0.75, command), [0.5, -0.5])
    np.testing.assert_allclose(command_features(-5.0, 4.0, command), [-1.0, 1.0])
    # without drift, the command follows the goal features directly
    no_drift = ObservationLayout(goal=True, goal_range=10.0, command=True)
    assert no_drift.slices()["command"] == slice(365, 367) and no_drift.frame_size == 367
    with pytest.raises(ValueError, match="command needs goal"):
        ObservationLayout(command=True)
    with pytest.raises(ValueError, match="finite"):
        command_features(math.inf, 0.0, command)
    with pytest.raises(ValueError, match="no command"):
        command_features(0.0, 0.0, GOAL)
    with pytest.raises(ValueError):
        ObservationLayout(goal=True, command=True, yaw_rate_scale=0.0)


def test_the_firmware_layout_ends_the_frame_with_one_flag_in_0_1() -> None:
    firmware = ObservationLayout(goal=True, goal_range=10.0, drift=True, firmware=True)
    assert firmware.name == GOAL.name + "+drift(forward,left/2m/s)+firmware(ardupilot=1,px4=0)"
    assert firmware.frame_size == 368
    assert firmware.slices() == GOAL.slices() | {"drift": slice(365, 367), "firmware": slice(367, 368)}
    low, high = firmware.bounds()
    assert low[365:].tolist() == [-1, -1, 0] and high[365:].tolist() == [1, 1, 1]
    assert firmware_features(True, firmware).tolist() == [1.0]
    assert firmware_features(False, firmware).dtype == np.float32
    assert firmware_features(False, firmware).tolist() == [0.0]
    # after the command, when both are there
    both = ObservationLayout(goal=True, drift=True, command=True, firmware=True)
    assert both.slices()["command"] == slice(367, 369) and both.slices()["firmware"] == slice(369, 370)
    assert both.name.endswith("+command(forward/2m/s,yaw/1.5rad/s)+firmware(ardupilot=1,px4=0)")
    with pytest.raises(ValueError, match="firmware needs goal"):
        ObservationLayout(firmware=True)
    with pytest.raises(ValueError, match="no firmware"):
        firmware_features(True, GOAL)


MOVERS = ObservationLayout(goal=True, goal_range=10.0, firmware=True, movers=True)


def test_the_movers_layout_ends_the_frame_with_three_slots_of_six() -> None:
    assert MOVERS.name == GOAL.name + (
        "+firmware(ardupilot=1,px4=0)+movers(3x(forward,left/10m,velocity/3m/s,radius/1m,present))"
    )
    assert len(MOVER_FEATURES) == 18 and MOVERS.frame_size == 365 + 1 + 18
    assert MOVERS.slices() == GOAL.slices() | {"firmware": slice(365, 366), "movers": slice(366, 384)}
    low, high = MOVERS.bounds()
    assert low[366:].tolist() == [-1, -1, -1, -1, 0, 0] * 3 and high[366:].tolist() == [1] * 18
    assert ObservationLayout(goal=True, movers=True).slices()["movers"] == slice(365, 383)
    with pytest.raises(ValueError, match="movers needs goal"):
        ObservationLayout(movers=True)
    with pytest.raises(ValueError, match="no mover"):
        mover_features([], GOAL)


def test_mover_features_nearest_surface_first_scaled_clipped_and_empty_slots_zero() -> None:
    walker = Mover((4.0, -2.0), (0.0, 1.5), 0.25)  # centre 4.47 m away, surface 4.22 m
    forklift = Mover((4.5, 1.0), (-6.0, 0.0), 1.2)  # centre 4.61 m, a wide one: surface 3.41 m
    drone = Mover((-12.0, 30.0), (3.0, -4.5), 0.4)  # far behind, fast
    f = mover_features([walker, drone, forklift], MOVERS).reshape(3, 6)
    assert f.dtype == np.float32
    np.testing.assert_allclose(f[0], [0.45, 0.1, -1.0, 0.0, 1.0, 1.0], rtol=1e-6)  # the forklift first
    np.testing.assert_allclose(f[1], [0.4, -0.2, 0.0, 0.5, 0.25, 1.0], rtol=1e-6)
    np.testing.assert_allclose(f[2], [-1.0, 1.0, 1.0, -1.0, 0.4, 1.0], rtol=1e-6)  # clipped
    # one mover: the other slots are zeros, presence 0; none: all zeros
    one = mover_features([walker], MOVERS).reshape(3, 6)
    np.testing.assert_array_equal(one[1:], 0.0)
    assert one[0, 5] == 1.0
    np.testing.assert_array_equal(mover_features([], MOVERS), np.zeros(18, np.float32))
    # more than three: the three nearest surfaces, a tie kept in the order given
    near = [Mover((2.0, 0.0), (0.0, 0.0), 0.5), Mover((0.0, -1.5), (0.0, 0.0), 0.0)]
    f = mover_features([drone, walker, forklift, *near], MOVERS).reshape(3, 6)
    np.testing.assert_array_equal(f[:, :2], np.array([[0.2, 0.0], [0.0, -0.15], [0.45, 0.1]], np.float32))
    with pytest.raises(ValueError, match="finite"):
        mover_features([Mover((1.0, math.nan), (0.0, 0.0), 0.3)], MOVERS)
    frame = build_frame(np.ones(360), np.concatenate([goal_features(1.0, 0.0, 0.0, 0.0, MOVERS),
                                                      firmware_features(True, MOVERS),
                                                      mover_features([walker], MOVERS)]), MOVERS)  # fmt: skip
    assert frame.shape == (384,) and frame[366 + 5] == 1.0


def test_goal_features_bearing_distance_and_velocity() -> None:
    f = goal_features(0.0, 5.0, 1.0, -3.0, GOAL)  # goal 5 m to the left, flying forward, sliding right
    assert f.dtype == np.float32
    np.testing.assert_allclose(f, [0.0, 1.0, 0.5, 0.5, -1.0], atol=1e-7)
    far_right_behind = goal_features(-30.0, -30.0, 0.0, 0.0, GOAL)
    np.testing.assert_allclose(far_right_behind[:3], [-math.sqrt(0.5), -math.sqrt(0.5), 1.0], atol=1e-6)
    np.testing.assert_allclose(goal_features(0.0, 0.0, 0.0, 0.0, GOAL), [1.0, 0.0, 0.0, 0.0, 0.0])


def test_non_finite_inputs_and_scan_only_layouts_are_refused() -> None:
    with pytest.raises(ValueError, match="finite"):
        goal_features(math.nan, 1.0, 0.0, 0.0, GOAL)
    with pytest.raises(ValueError, match="no goal features"):
        goal_features(1.0, 1.0, 0.0, 0.0, ObservationLayout())


def test_goal_in_body_rotates_world_offsets_into_flu() -> None:
    # heading north (+y): a goal to the east (+x) is on the right
    forward, left = goal_in_body(3.0, 0.0, math.pi / 2)
    assert forward == pytest.approx(0.0, abs=1e-12) and left == pytest.approx(-3.0)


@given(st.floats(-50, 50), st.floats(-50, 50), st.floats(-10, 10), st.floats(-10, 10), st.floats(-7, 7))
def test_features_stay_in_the_layout_bounds(dx: float, dy: float, vf: float, vl: float, yaw: float) -> None:
    f = goal_features(*goal_in_body(dx, dy, yaw), vf, vl, GOAL)
    low, high = GOAL.bounds()
    assert np.all(f >= low[360:]) and np.all(f <= high[360:])
    assert f[0] ** 2 + f[1] ** 2 == pytest.approx(1.0, abs=1e-6)


def test_build_frame_concatenates_and_checks_sizes() -> None:
    scan = np.full(360, 0.5, np.float32)
    frame = build_frame(scan, goal_features(1.0, 0.0, 0.0, 0.0, GOAL), GOAL)
    assert frame.shape == (365,) and frame[360] == 1.0
    assert build_frame(scan, None, ObservationLayout()).shape == (360,)
    with pytest.raises(ValueError, match="365 floats, got 360 scan \\+ 0 features"):
        build_frame(scan, None, GOAL)
