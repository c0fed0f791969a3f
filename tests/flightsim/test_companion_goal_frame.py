"""The companion builds LidarNav-v0's goal/velocity features from the autopilot's messages.

The env computes them from its own state (world ENU, yaw counter-clockwise from east); the companion
from LOCAL_POSITION_NED, ATTITUDE and a waypoint in local NED (GoalTracker's goal_body, the link's
body velocity). The same vehicle, described both ways, must give the same five floats.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.autopilot.link import body_velocity
from companion.autopilot.mavlink_adapter import mavlink
from companion.config import CompanionConfig
from companion.guidance.goal import GoalTracker, NavInputs, Waypoint
from companion.guidance.route import RoutePlanner, enu_pose
from companion.perception.observation import goal_features, goal_in_body
from flightsim.envs.nav_env import LidarNavEnv, NavEnvConfig
from flightsim.worlds.world import Box, World

HALL = World("hall", (20.0, 8.0), 3.0, (), (-8.0, 0.0, 1.5), 30.0, ((6.0, 2.5, 1.5), (-4.0, -3.0, 1.5)))


@pytest.mark.parametrize("action", [(1.0, 0.6), (0.7, -0.8), (0.3, 0.0)])
def test_companion_features_equal_the_envs(action) -> None:
    env = LidarNavEnv(NavEnvConfig(autopilot_response="ideal", drift=True))  # measured velocity = the truth
    layout = CompanionConfig().policy.layout
    assert layout == env.layout  # the default companion config feeds what the env trains on
    try:
        obs, _ = env.reset(seed=3, options={"world": HALL})
        for _ in range(25):
            obs, *_ = env.step(np.array(action, np.float32))
        state = env._state
        x, y, z = map(float, state.position)
        vx, vy, _ = map(float, state.velocity)
        yaw_ned = math.pi / 2 - float(state.yaw)  # ENU counter-clockwise from east → NED from north
        nav = NavInputs()
        nav.on_message(mavlink.MAVLink_local_position_ned_message(0, y, x, -z, vy, vx, 0.0), now=1.0)
        nav.on_message(mavlink.MAVLink_attitude_message(0, 0.0, 0.0, yaw_ned, 0.0, 0.0, 0.0), now=1.0)
        tracker = GoalTracker(acceptance_radius=0.01, max_vertical_speed=0.5)
        gx, gy, gz = HALL.waypoints[0]
        tracker.set_waypoints([Waypoint(gy, gx, -gz)], None)
        out = tracker.update(nav, now=1.0)
        velocity = body_velocity(vy, vx, yaw_ned)
        assert out.goal_body is not None and velocity is not None
        features = goal_features(out.goal_body[0], out.goal_body[1], *velocity, layout)
        np.testing.assert_allclose(features, obs[360:365], atol=2e-5)
        assert abs(features[4]) > 0.01 or abs(features[3]) > 0.1  # moving: the velocity part is tested
    finally:
        env.close()


# the hall with a wall across it, a gap at its north side: the route matters
WALLED = World("walled", (20.0, 8.0), 3.0, (Box((-5.0, -1.0, 1.5), (0.3, 6.0, 3.0)),), (-8.0, 0.0, 1.5), 0.0,
               ((0.0, 0.0, 1.5),))


def test_the_companions_route_equals_the_envs() -> None:
    """The companion's planner, fed the same scans and the pose as the autopilot reports it (local
    NED through :func:`enu_pose`), sends the policy where the env's ``route`` does."""
    env = LidarNavEnv(NavEnvConfig(autopilot_response="ideal", route=True))
    layout = env.layout
    route = RoutePlanner(CompanionConfig().goal.route_planner, CompanionConfig().scan.max_range)
    gx, gy, _ = WALLED.waypoints[0]
    try:
        obs, _ = env.reset(seed=1, options={"world": WALLED})
        for step in range(40):
            state = env._state
            x, y, _ = map(float, state.position)
            pose = enu_pose(y, x, math.pi / 2 - float(state.yaw))  # LOCAL_POSITION_NED and ATTITUDE
            route.observe(obs[:360], *pose)
            goal_x, goal_y, _ = enu_pose(gy, gx, 0.0)
            sub = route.subgoal(*pose, goal_x, goal_y)
            features = goal_features(sub.forward, sub.left, 0.0, 0.0, layout)
            np.testing.assert_allclose(features[:3], obs[360:363], atol=2e-5)
            if step == 0:
                assert obs[361] > 0.3  # left, toward the gap: not straight at the waypoint ahead
            obs, *_ = env.step(np.array([0.8, 0.5 if step < 10 else 0.0], np.float32))
        assert route.plans > 1
    finally:
        env.close()


def test_the_companion_tracks_and_keeps_out_what_the_env_does() -> None:
    """The companion's tracker, fed the same scans at the pose the autopilot reports
    (LOCAL_POSITION_NED and ATTITUDE through :func:`tracking_pose`) and the same times, marks the
    same bins moving as LidarNav-v0's, so the drift estimate and the route's map are given the same
    scans; the walker crossing ahead is among them."""
    from companion.app import tracking_pose
    from companion.perception.tracking import ScanTracker
    from tests.flightsim.test_nav_tracking import CROSSING

    env = LidarNavEnv(NavEnvConfig(autopilot_response="ideal", drift=True, route=True))
    tracker = ScanTracker(max_range=CompanionConfig().scan.max_range)
    moving = 0
    try:
        obs, _ = env.reset(seed=0, options={"world": CROSSING})
        for step in range(40):
            state = env._state
            x, y, z = map(float, state.position)
            nav = NavInputs()
            nav.on_message(mavlink.MAVLink_local_position_ned_message(0, y, x, -z, 0.0, 0.0, 0.0), now=1.0)
            yaw_ned = math.pi / 2 - float(state.yaw)
            nav.on_message(mavlink.MAVLink_attitude_message(0, 0.0, 0.0, yaw_ned, 0.0, 0.0, 0.0), now=1.0)
            pose = tracking_pose(nav, now=1.0)
            assert pose is not None and np.allclose(pose, (x, y, float(state.yaw)), atol=1e-5)
            out = tracker.update(obs[:360], pose, env.sim_time)
            assert np.array_equal(out.moving_bins, env.tracked.moving_bins), step
            moving += bool(out.moving)
            obs, *_ = env.step(np.array([0.25, 0.0], np.float32))
        assert moving >= 20
        assert tracking_pose(nav, now=3.0) is None  # the position a second and more old: no pose
        # a position 0.05 s old, the vehicle flying 2 m/s north: the scan is placed 0.1 m farther north
        nav.on_message(mavlink.MAVLink_local_position_ned_message(0, 1.0, 4.0, -1.5, 2.0, 0.0, 0.0), now=5.0)
        assert tracking_pose(nav, now=5.05)[:2] == pytest.approx((4.0, 1.1))
    finally:
        env.close()


def test_the_companions_movers_frame_equals_the_envs_bit_for_bit(tmp_path) -> None:
    """A movers layout (``env.movers``, ``policy.movers``): the real companion (its model loaded in
    ONNX Runtime, its links on loopback sockets), its tracker given the env's scans at the env's pose
    and times, and the env's goal and measured velocity, builds LidarNav-v0's frames exactly, the
    walker crossing ahead in the first mover slot."""
    from companion.app import Companion, policy_spec
    from companion.autopilot.link import VehicleStatus
    from companion.config import load_config
    from companion.guidance.goal import GoalOutput
    from companion.notify import SystemdNotifier
    from tests.companion.companion_process import WEST_AND_UP, free_udp_port, write_config
    from tests.flightsim.test_nav_tracking import CROSSING
    from tests.onnx_models import write_policy

    model = tmp_path / "movers.onnx"
    extra = WEST_AND_UP.replace("[goal]\n", "[goal]\nroute = false\n")
    path = write_config(tmp_path, model, free_udp_port(), free_udp_port(), extra=extra)
    path.write_text(path.read_text().replace("[policy]\n", "[policy]\ndrift = false\nmovers = true\n"))
    config = load_config(path)
    write_policy(model, spec=policy_spec(config))
    companion = Companion(config, notifier=SystemdNotifier({}))
    env = LidarNavEnv(NavEnvConfig(autopilot_response="ideal", movers=True))
    assert companion.layout == env.layout and env.layout.movers
    movers = env.layout.slices()["movers"]
    seen = 0
    try:
        obs, info = env.reset(seed=0, options={"world": CROSSING})
        for _ in range(40):
            x, y, _ = env._state.position.tolist()
            yaw = float(env._state.yaw)
            goal_x, goal_y, _ = CROSSING.waypoints[0]
            goal = goal_in_body(goal_x - x, goal_y - y, yaw)
            companion._goal_output = GoalOutput(None, goal_body=(*goal, 0.0))
            velocity = tuple(info["measured_velocity_body"].tolist())
            companion._status = VehicleStatus(velocity_body=velocity, velocity_time=companion._clock())
            companion.tracked = companion.tracker.update(obs[:360], (x, y, yaw), env.sim_time)
            frame = companion._frame(obs[:360])
            assert isinstance(frame, np.ndarray) and frame.tobytes() == obs.tobytes()
            seen += bool(frame[movers][5])  # the first slot's presence
            obs, _, _, _, info = env.step(np.array([0.25, 0.0], np.float32))
        assert seen >= 30
    finally:
        env.close()
        companion.close()
