"""The classical baseline's geometry and steering, on hand-made scans."""

import numpy as np
import pytest

from companion.perception.drift import DriftHoldConfig
from companion.perception.observation import ObservationLayout, build_frame, drift_features, goal_features
from training.baselines import (
    GapFollower,
    GapFollowerConfig,
    GoalFollower,
    GoalFollowerConfig,
    RandomController,
    StraightLine,
    corridor_clearance,
)


def _scan_with(bins: dict[int, float], max_range: float = 10.0) -> np.ndarray:
    scan = np.ones(360, dtype=np.float32)
    for i, r in bins.items():
        scan[i] = r / max_range
    return scan


def test_corridor_clearance_blocks_headings_within_the_body_width():
    ranges = np.full(360, np.inf)
    ranges[0] = 3.0  # one return 3 m straight ahead
    clearance = corridor_clearance(ranges, body_radius=0.5)
    assert clearance[0] == pytest.approx(3.0 * np.cos(0.0), abs=1e-9)
    # 5 degrees off: lateral offset 3 sin 5° = 0.26 m < 0.5 m, still blocked
    assert np.isfinite(clearance[5]) and np.isfinite(clearance[355])
    # 20 degrees off: 3 sin 20° = 1.03 m > 0.5 m, free; behind the vehicle is never blocked by it
    assert np.isinf(clearance[20]) and np.isinf(clearance[340]) and np.isinf(clearance[180])


def test_gap_follower_goes_straight_and_fast_in_the_open():
    action = GapFollower().act(np.ones(360, dtype=np.float32))
    assert action[0] == pytest.approx(GapFollowerConfig().cruise, abs=1e-3)
    assert abs(action[1]) < 0.05


@pytest.mark.parametrize(("blocked", "turn_sign"), [(range(350, 360), +1), (range(0, 10), -1)])
def test_gap_follower_turns_away_from_an_obstacle_ahead(blocked, turn_sign):
    # a wall segment 1.5 m ahead, slightly right (bins 350..359) or slightly left (bins 0..9)
    scan = _scan_with({i: 1.5 for i in blocked})
    action = GapFollower().act(scan)
    assert np.sign(action[1]) == turn_sign
    assert action[0] < GapFollowerConfig().cruise


def test_gap_follower_stops_but_turns_when_boxed_in_ahead():
    scan = _scan_with({i: 0.6 for i in [*range(0, 60), *range(300, 360)]})
    action = GapFollower().act(scan)
    assert action[0] == pytest.approx(0.0)
    assert abs(action[1]) == pytest.approx(1.0)


def test_random_controller_is_seeded_and_in_range():
    a = [RandomController(3).act(np.ones(360)) for _ in range(2)]
    np.testing.assert_array_equal(a[0], a[1])
    many = np.array([RandomController(i).act(np.ones(360)) for i in range(200)])
    assert many.min() >= -1.0 and many.max() <= 1.0 and many.std() > 0.3


def test_corridor_clearance_matches_the_brute_force_definition():
    rng = np.random.default_rng(0)
    angles = np.deg2rad(np.arange(360) + 0.5)
    delta = angles[None, :] - angles[:, None]  # [heading, return]
    for _ in range(20):
        ranges = np.where(rng.uniform(size=360) < 0.3, np.inf, rng.uniform(0.2, 10.0, size=360))
        r = np.where(np.isfinite(ranges), ranges, 0.0)[None, :]
        along, across = r * np.cos(delta), np.abs(r * np.sin(delta))
        blocking = np.isfinite(ranges)[None, :] & (along > 1e-9) & (across < 0.55)
        expected = np.where(blocking, along, np.inf).min(axis=1)
        np.testing.assert_allclose(corridor_clearance(ranges, 0.55), expected, rtol=1e-12)


# --- the goal task -------------------------------------------------------------------------------

GOAL_LAYOUT = ObservationLayout(goal=True, goal_range=30.0, velocity_scale=2.0)
DRIFT_LAYOUT = ObservationLayout(goal=True, goal_range=30.0, velocity_scale=2.0, drift=True)


def _frame(bins: dict[int, float], goal_deg: float, goal_m: float) -> np.ndarray:
    """A goal-layout frame: the scan of ``bins``, the goal at ``goal_deg`` CCW from the nose."""
    a = np.radians(goal_deg)
    features = goal_features(goal_m * np.cos(a), goal_m * np.sin(a), 0.0, 0.0, GOAL_LAYOUT)
    return build_frame(_scan_with(bins), features, GOAL_LAYOUT)


@pytest.mark.parametrize("kind", [StraightLine, GoalFollower])
def test_goal_controllers_fly_at_a_goal_in_the_open(kind):
    controller = kind(GOAL_LAYOUT)
    ahead = controller.reset(_frame({}, 0.0, 10.0))
    assert ahead[0] == pytest.approx(controller.config.cruise, abs=1e-3) and abs(ahead[1]) < 0.05
    left = controller.act(_frame({}, 60.0, 10.0))
    right = controller.act(_frame({}, -60.0, 10.0))
    assert left[1] > 0.5 and right[1] < -0.5 and left[0] < 0.5  # turn first, then go


def test_straight_line_flies_into_what_is_in_the_way():
    wall = {i % 360: 1.0 for i in range(-40, 41)}
    assert StraightLine(GOAL_LAYOUT).reset(_frame(wall, 0.0, 10.0))[0] == pytest.approx(1.0, abs=1e-3)


def test_goal_follower_brakes_for_a_wall_and_heads_for_its_edge():
    # a wall 2 m ahead from 40° right to 20° left; beyond its left edge the way is open
    wall = {i % 360: 2.0 / np.cos(np.radians(i)) for i in range(-40, 21)}
    action = GoalFollower(GOAL_LAYOUT).reset(_frame(wall, 0.0, 10.0))
    assert action[1] > 0.3  # toward the near (left) edge, not the far one
    assert action[0] < 0.8  # slowed while it turns


def test_goal_follower_escapes_when_the_goal_comes_no_closer_and_resets_on_a_new_waypoint():
    config = GoalFollowerConfig(stall_steps=5)
    controller = GoalFollower(GOAL_LAYOUT, config)
    # a U around the goal direction: walls ahead and on both sides, the goal behind the bottom
    trap = {i % 360: 1.5 for i in range(-100, 101)}
    controller.reset(_frame(trap, 0.0, 8.0))
    for _ in range(6):
        controller.act(_frame(trap, 0.0, 8.0))
    assert controller._escape_side != 0
    controller.act(_frame({}, 0.0, 15.0))  # the next waypoint: distance jumps
    assert controller._escape_side == 0


def _moving_frame(
    scan_m: np.ndarray,
    goal_deg: float,
    goal_m: float,
    velocity: tuple[float, float],
    drift: tuple[float, float] | None = None,
) -> np.ndarray:
    """A goal-layout frame from ranges in metres (inf: nothing) and a measured body velocity, m/s;
    with ``drift`` (the env's drift estimate, m/s), a frame of :data:`DRIFT_LAYOUT`."""
    layout = GOAL_LAYOUT if drift is None else DRIFT_LAYOUT
    a = np.radians(goal_deg)
    features = goal_features(goal_m * np.cos(a), goal_m * np.sin(a), *velocity, layout)
    if drift is not None:
        features = np.concatenate([features, drift_features(np.array(drift), layout)])
    scan = np.where(np.isfinite(scan_m), np.minimum(scan_m / 10.0, 1.0), 1.0).astype(np.float32)
    return build_frame(scan, features, layout)


def _yaw_after_drifting(drift: float, controller: GoalFollower, estimate: bool = False) -> float:
    """The yaw action after 2 s of flying at a goal ahead while the autopilot reports 0.5 m/s
    straight ahead and the walls show ``drift`` m/s to the left as well (PX4's estimate error: its
    velocity loop flies the estimate, so the truth drifts by the error); with ``estimate``, the
    frames carry the env's drift estimate of it (reported minus true: ``-drift`` to the left)."""
    from tests.companion.test_scan_motion import room_scan

    x, y, action = -3.0, 0.0, None
    for k in range(20):
        scan = room_scan(x, y, 0.0, half=(8.0, 3.0), pillar=(-6.0, -2.0))
        bearing = float(np.degrees(np.arctan2(-y, 5.0 - x)))
        frame = _moving_frame(scan, bearing, 5.0 - x, (0.5, 0.0), (0.0, -drift) if estimate else None)
        action = controller.reset(frame) if k == 0 else controller.act(frame)
        x, y = x + 0.05, y + drift * 0.1
    return float(action[1])


def test_goal_follower_sees_a_drift_the_velocity_estimate_hides_and_crabs_against_it():
    assert abs(_yaw_after_drifting(0.0, GoalFollower(GOAL_LAYOUT))) < 0.1
    assert _yaw_after_drifting(0.3, GoalFollower(GOAL_LAYOUT)) < -0.3  # the nose leads right


def test_goal_follower_leaves_to_the_drift_hold_what_the_setpoint_already_carries():
    # the env's drift_hold puts the whole estimate (no deadband) on the setpoint: crabbing against
    # it as well would fly the error twice, so the nose stays on the goal (0.57 m right of the
    # line after 1.9 s of drift: bearing atan2(-0.57, 7.05))
    hold = DriftHoldConfig(lateral=0.6, deadband=0.0)
    on_goal = GoalFollowerConfig().turn_gain * np.arctan2(-0.57, 7.05)
    assert _yaw_after_drifting(0.3, GoalFollower(DRIFT_LAYOUT), estimate=True) < on_goal - 0.3
    held = _yaw_after_drifting(0.3, GoalFollower(DRIFT_LAYOUT, hold=hold), estimate=True)
    assert held == pytest.approx(on_goal, abs=0.05)
    with pytest.raises(ValueError, match="drift"):
        GoalFollower(GOAL_LAYOUT, hold=hold)


def test_goal_follower_backs_off_from_a_return_inside_its_keep_out():
    near = {i % 360: 0.4 for i in range(-10, 30)}  # something 0.4 m off the nose, to the left
    action = GoalFollower(GOAL_LAYOUT).reset(_frame(near, 0.0, 10.0))
    assert action[0] < -0.05


def test_goal_follower_brakes_when_it_slides_toward_a_wall_beside_it():
    # heading clear to the goal ahead, but the vehicle slides left at 0.9 m/s toward a wall 0.9 m away
    wall = np.full(360, np.inf)
    for i in range(30, 151):
        wall[i] = 0.9 / np.sin(np.radians(i + 0.5))
    action = GoalFollower(GOAL_LAYOUT).reset(_moving_frame(wall, 0.0, 10.0, (0.3, 0.9)))
    assert action[0] < 0.05
    open_room = GoalFollower(GOAL_LAYOUT).reset(_moving_frame(wall, 0.0, 10.0, (0.3, 0.0)))
    assert open_room[0] > 0.3


def test_goal_follower_reaches_a_validation_forest_it_used_to_hit_a_tree_in():
    # validation world forest-500000 (difficulty 0.1) through the randomised autopilot response of
    # reset seed 0 (PX4-like, yaw rate capped at 0.88 rad/s): the old controller hit a tree after 6 s
    from training.episodes import NAV_ENV_ID, make_eval_env, run_episode

    env = make_eval_env({"autopilot_response": "random", "wind_gust_max": 0.5}, NAV_ENV_ID)
    layout = env.unwrapped.config.layout
    result = run_episode(
        env, GoalFollower(layout), {"family": "forest", "world_seed": 500_000, "difficulty": 0.1}, seed=0
    )
    assert not result.collision and result.success


def test_goal_follower_ends_an_escape_with_nothing_beside_instead_of_spinning():
    controller = GoalFollower(GOAL_LAYOUT, GoalFollowerConfig(stall_steps=5))
    trap = {i % 360: 1.5 for i in range(-100, 101)}
    controller.reset(_frame(trap, 0.0, 8.0))
    for _ in range(6):
        controller.act(_frame(trap, 0.0, 8.0))
    assert controller._escape_side != 0
    action = controller.act(_frame({}, 0.0, 8.0))  # the open: no boundary left to follow
    assert abs(action[1]) < 0.1 and action[0] > 0.3


def test_goal_follower_asks_for_more_from_an_autopilot_that_settles_short():
    # a PX4-like velocity loop that delivers 70 % of any steady forward command
    controller = GoalFollower(GOAL_LAYOUT)
    action = controller.reset(_moving_frame(np.full(360, np.inf), 0.0, 25.0, (0.0, 0.0)))
    for _ in range(80):
        delivered = 0.7 * float(action[0]) * GOAL_LAYOUT.velocity_scale
        action = controller.act(_moving_frame(np.full(360, np.inf), 0.0, 25.0, (delivered, 0.0)))
    assert float(action[0]) * 0.7 == pytest.approx(controller.config.cruise, abs=0.08)


@pytest.mark.parametrize("kind", [GoalFollower, StraightLine])
def test_goal_controllers_take_a_goal_a_hair_right_of_the_nose(kind):
    # a bearing of -1e-17 rad is -5.7e-16 degrees, and that % 360.0 is 360.0: one past the last bin
    # (a GoalFollower indexed its clearance with it and raised IndexError mid-evaluation)
    scan = _scan_with({})
    features = goal_features(10.0, -1e-16, 0.0, 0.0, GOAL_LAYOUT)
    action = kind(GOAL_LAYOUT).reset(build_frame(scan, features, GOAL_LAYOUT))
    assert action[0] > 0.5 and abs(action[1]) < 0.05


def test_goal_follower_matches_scans_out_to_its_own_max_range():
    """A 20 m scan (GoalFollowerConfig.max_range, as the evaluation sets it from the env) in a hall
    whose walls are all 12-18 m away: the drift is seen (a matcher reading 10 m saturates on all)."""
    from tests.companion.test_scan_motion import room_scan

    controller = GoalFollower(GOAL_LAYOUT, GoalFollowerConfig(max_range=20.0))
    for k in range(20):  # standing still while the autopilot reports 0.4 m/s forward
        scan_m = room_scan(0.0, 0.0, 0.0, half=(15.0, 13.0), pillar=(12.0, 9.0))
        scan = np.minimum(scan_m / 20.0, 1.0).astype(np.float32)
        features = goal_features(10.0, 0.0, 0.4, 0.0, GOAL_LAYOUT)
        frame = build_frame(scan, features, GOAL_LAYOUT)
        if k == 0:
            controller.reset(frame)
        else:
            controller.act(frame)
    assert controller._bias == pytest.approx([0.4, 0.0], abs=0.05)
