"""A privileged teacher for the goal task: it follows the planned path with the true state.

The policy flies on what the drone has (scan, goal, the autopilot's velocity estimate). The
teacher reads the simulator instead: the world's map, the true pose and velocity, and the
autopilot's velocity-estimate error. It plans a path through the remaining waypoints that keeps a
margin beyond the vehicle's radius (:func:`flightsim.worlds.planner.shortest_safe_path`'s grid, less
inflated when a tighter passage is the only way), pursues a point ahead on it, and commands the
velocity that, after the autopilot tracks its own (erroneous) estimate, flies the path truly.
Behaviour cloning on its actions, in the states the student itself reaches (DAgger,
:mod:`training.dagger`), gives the student a teacher that is right where the classical baseline
is defeated: a drifting velocity estimate, a lagging autopilot, a concave trap.

It is a training tool: no figure of what a drone flies comes from it. ``avoid-train evaluate
--baselines path_expert`` flies it (:class:`ExpertController`) to measure what imitating it
can reach at most.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from flightsim.envs.nav_env import LidarNavEnv
from flightsim.worlds.planner import ClearanceGrid, astar_cells, clearance_grid, cost_to_go


def body_to_world(body: tuple[float, float], yaw: float) -> tuple[float, float]:
    """A body (forward, left) vector in world East, North for a heading of ``yaw`` (rad CCW from East)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return c * body[0] - s * body[1], s * body[0] + c * body[1]


@dataclass(frozen=True)
class PathExpertConfig:
    """The teacher's tuning (chosen by a random search on validation worlds, 6 per family).

    Path:

    :param resolution: planning grid cell, metres
    :param preferred_margin: clearance beyond the vehicle radius the path prefers, metres
    :param clearance_cost: extra cost per metre of a cell with no margin (falling linearly to 0 at
        ``preferred_margin``)
    :param replan_deviation: replan when the vehicle is this far off the path, metres

    Pursuit:

    :param lookahead: the pursuit point's distance ahead along the path, metres
    :param lead_s: the ideal response's lag, s (a drawn response's is computed from its parameters)
    :param lead_cap_s: the position is predicted at most this far ahead (a longer lag only slows), s

    Speed:

    :param min_speed: speed floor where clearance is tight, m/s
    :param clearance_speed_gain: speed allowed per metre of clearance beyond the radius, 1/s
    :param clearance_floor: clearance beyond the radius that counts as none, metres
    :param brake_accel: deceleration the stopping-distance limit assumes, m/s^2
    :param free_run_max: farthest the free run ahead is looked for, metres
    :param turn_slowdown: speed lost per radian of the path's turn ahead (fraction)
    :param speed_ramp: the forward command rises at most this much per step, m/s

    Command:

    :param velocity_gain: share of the true velocity's error added to the command
    :param min_aim_speed: below this commanded speed, aim along the path (not the command), m/s
    :param alignment_power: the move's share of the forward command is ``cos(heading error)`` to
        this power
    :param turn_in_place: beyond this heading error, rad, only turn (and hold)
    :param yaw_gain: yaw rate per radian of heading error, 1/s
    :param yaw_lead_s: the heading is predicted this far ahead along the true yaw rate, s
    :param sideways_yaw_gain: with a sideways action (the env's ``sideways``) the whole command is
        flown in the body frame, forward and sideways, and the nose turns towards the path at
        this rate per radian, 1/s (half ``yaw_gain``: the nose no longer steers the vehicle)
    """

    resolution: float = 0.1
    preferred_margin: float = 0.8
    clearance_cost: float = 8.0
    replan_deviation: float = 0.5
    lookahead: float = 1.2
    lead_s: float = 0.2
    lead_cap_s: float = 0.2
    min_speed: float = 0.5
    clearance_speed_gain: float = 2.0
    clearance_floor: float = 0.1
    brake_accel: float = 1.0
    free_run_max: float = 4.0
    turn_slowdown: float = 0.3
    speed_ramp: float = 0.2
    velocity_gain: float = 0.8
    min_aim_speed: float = 0.15
    alignment_power: float = 1.0
    turn_in_place: float = 0.8
    yaw_gain: float = 3.0
    yaw_lead_s: float = 0.25
    sideways_yaw_gain: float = 1.5


class PathExpert:
    """Fly one :class:`~flightsim.envs.nav_env.LidarNavEnv` (unwrapped) along its planned path.

    :param env: the env whose true state it reads (``reset`` it before :meth:`reset`)
    :param config: tuning
    """

    def __init__(self, env: LidarNavEnv, config: PathExpertConfig | None = None) -> None:
        self.env = env
        self.config = config or PathExpertConfig()
        self._grid: ClearanceGrid | None = None
        self._path = np.zeros((0, 2))
        self._costs = np.zeros((0, 0))
        self._segment = 0
        self._planned_waypoint = -1
        self._forward = 0.0

    def reset(self) -> np.ndarray:
        """A new episode: rasterise the world, plan, and return the first action."""
        env, cfg = self.env, self.config
        cap = env.config.vehicle_radius + cfg.preferred_margin + cfg.resolution
        self._grid = clearance_grid(env.world, float(env.world.start_position[2]), cfg.resolution, cap)
        self._costs = _cell_costs(
            self._grid.clearance, env.config.vehicle_radius, cfg.preferred_margin, cfg.clearance_cost
        )
        self._planned_waypoint = -1
        self._forward = 0.0
        return self.act()

    def act(self) -> np.ndarray:
        """The action for the env's current true state, ``(a0, a1)`` in ``[-1, 1]`` (with the env's
        ``sideways``, ``(a0, a1, a2)``)."""
        env, cfg = self.env, self.config
        state = env.true_state
        true_velocity = np.asarray(state.velocity[:2], dtype=np.float64)
        desired, direction = self._desired()
        # the autopilot flies its estimate (reported = true + error): asking for the error holds
        # still; the velocity gain also damps the true velocity's error
        error_xy = self._estimate_error()
        move = desired * (1.0 + cfg.velocity_gain)
        hold = error_xy - cfg.velocity_gain * true_velocity
        command = move + hold
        magnitude = math.hypot(*command)
        aim = command if magnitude > cfg.min_aim_speed else direction
        heading = math.atan2(aim[1], aim[0])
        yaw = float(state.yaw) + cfg.yaw_lead_s * float(state.angular_rate[2])
        error = math.remainder(heading - yaw, math.tau)
        nose = np.array([math.cos(yaw), math.sin(yaw)])
        if env.config.sideways:
            return self._sideways_action(command, direction, nose, yaw)
        # the forward command is what the nose can carry: the hold's share always (it cancels the
        # drift along the nose), the move's share once the nose points roughly its way
        gate = max(0.0, math.cos(error)) ** cfg.alignment_power if abs(error) < cfg.turn_in_place else 0.0
        forward = float((hold + move * gate) @ nose)
        # a jerk-limited autopilot overshoots a step up: ramp the speed up, cut it at once
        forward = min(forward, self._forward + cfg.speed_ramp)
        self._forward = forward
        yaw_rate = cfg.yaw_gain * error
        return np.clip(
            np.array([forward / env.config.max_speed, yaw_rate / env.config.max_yaw_rate], dtype=np.float32),
            -1.0, 1.0,
        )  # fmt: skip

    # ------------------------------------------------------------------ internals
    def _desired(self) -> tuple[np.ndarray, np.ndarray]:
        """The true velocity to fly now (world m/s) and the path's direction there (a unit vector):
        the pursuit point on the planned path, at the speed its clearance, the free run and the
        path's turn ahead allow."""
        env, cfg = self.env, self.config
        state = env.true_state
        true_velocity = np.asarray(state.velocity[:2], dtype=np.float64)
        lag = self._lag()
        here = np.asarray(state.position[:2], dtype=np.float64)
        # where the lags will have carried it by the time a command acts
        position = here + min(lag, cfg.lead_cap_s) * true_velocity
        if self._needs_plan(here):
            self._plan(here)
        target, turn = self._pursuit(position, 2.0 * cfg.lookahead + lag * math.hypot(*true_velocity))
        offset = target - position
        distance = math.hypot(*offset)
        clearance = env.world.clearance(state.position) - env.config.vehicle_radius
        free = self._free_run(here, offset / max(distance, 1e-6))
        moving = math.hypot(*true_velocity)
        if moving > cfg.min_speed:  # where it is going anyway, until the command takes hold
            free = min(free, self._free_run(here, true_velocity / moving))
        speed = min(
            env.config.max_speed,
            cfg.min_speed + cfg.clearance_speed_gain * max(clearance - cfg.clearance_floor, 0.0),
            _stopping_speed(free, cfg.brake_accel, lag),
        )
        speed *= max(0.2, 1.0 - cfg.turn_slowdown * turn)
        direction = offset / max(distance, 1e-6)
        return direction * speed, direction

    def _sideways_action(
        self, command: np.ndarray, direction: np.ndarray, nose: np.ndarray, yaw: float
    ) -> np.ndarray:
        """With a sideways action: ``command`` (world m/s) flown whole in the body frame, the forward
        part ramped up as the nose-only command is, the nose turned towards the path's ``direction``."""
        env, cfg = self.env, self.config
        forward = min(float(command @ nose), self._forward + cfg.speed_ramp)
        self._forward = forward
        left = float(command @ np.array([-nose[1], nose[0]]))
        heading_error = math.remainder(math.atan2(direction[1], direction[0]) - yaw, math.tau)
        scales = (env.config.max_speed, env.config.max_yaw_rate, env.config.max_sideways_speed)
        wanted = (forward, cfg.sideways_yaw_gain * heading_error, left)
        return np.clip(np.array(wanted) / np.array(scales), -1.0, 1.0).astype(np.float32)

    def _estimate_error(self) -> np.ndarray:
        """The velocity estimate's error the command makes up for, world ENU m/s. With the drift
        features it is the drift estimate the student sees in its frame (so the labels follow
        from what the student has: 87 % of 54 validation worlds, against 91 % on the simulator's
        truth and 48 % without it, aiming along the path), less what the setpoint already holds of
        it (``drift_hold``); else the truth (privileged)."""
        env = self.env
        if not env.layout.drift:
            return np.asarray(env.estimate_error, dtype=np.float64)
        forward, left = env.drift_estimate - np.asarray(env.drift_held())
        return np.array(body_to_world((float(forward), float(left)), float(env.true_state.yaw)))

    def _lag(self) -> float:
        """Seconds from a command to the vehicle's answer: the drawn response's delay, tilt lag and
        input shaping (privileged), or ``lead_s`` for the ideal response."""
        params = self.env.response_params
        if params is None:
            return self.config.lead_s
        shaping = params.shape_accel_max / params.shape_jerk_max if params.shape_jerk_max > 0 else 0.0
        return params.command_delay_s + params.tilt_lag_s + shaping

    def _free_run(self, position: np.ndarray, direction: np.ndarray) -> float:
        """Metres the vehicle can fly from ``position`` along ``direction`` before its clearance
        drops under the radius plus ``clearance_floor`` (up to ``free_run_max``)."""
        grid, cfg = self._grid, self.config
        assert grid is not None
        limit = self.env.config.vehicle_radius + cfg.clearance_floor
        step = grid.resolution
        for k in range(1, int(cfg.free_run_max / step) + 1):
            x, y = position + direction * (k * step)
            if grid.clearance[grid.cell(x, y)] < limit:
                return (k - 1) * step
        return cfg.free_run_max

    def _visible_target(self, position: np.ndarray, point: np.ndarray) -> np.ndarray:
        """The pursuit point: ``lookahead`` along the path, pulled back until the straight line to
        it keeps the radius (plus ``clearance_floor``): past a corner, it would cut the corner."""
        grid, cfg = self._grid, self.config
        assert grid is not None
        limit = self.env.config.vehicle_radius + cfg.clearance_floor
        target = point
        for d in np.linspace(cfg.lookahead, 0.2, 6):
            target = _along(self._path, self._segment, point, float(d))
            offset = target - position
            samples = int(math.hypot(*offset) / grid.resolution) + 1
            if all(
                grid.clearance[grid.cell(*(position + offset * (k / samples)))] >= limit
                for k in range(1, samples + 1)
            ):
                return target
        return target

    def _needs_plan(self, position: np.ndarray) -> bool:
        """A new waypoint, or off the path. Not on a timer: replanning from a slightly different
        spot can flip the route to the other side of an obstacle, and the vehicle with it."""
        if self._planned_waypoint != self.env.waypoint_index:
            return True
        return self._deviation(position) > self.config.replan_deviation

    def _plan(self, position: np.ndarray) -> None:
        """Plan from here through the remaining waypoints, preferring clearance (see :func:`_cell_costs`)."""
        env, grid = self.env, self._grid
        assert grid is not None
        remaining = env.world.waypoints[env.waypoint_index :]
        stops = [position] + [np.asarray(w[:2], dtype=np.float64) for w in remaining]
        self._planned_waypoint = env.waypoint_index
        self._segment = 0
        costs = self._costs
        points = [position[None, :]]
        for a, b in itertools.pairwise(stops):
            ia, ib = grid.cell(*a), grid.cell(*b)
            passable = costs.copy()
            passable[ia] = passable[ib] = 1.0  # the vehicle and the waypoint are where they are
            cells = astar_cells(passable, ia[0], ia[1], ib[0], ib[1])
            if cells.shape[0] == 0:  # no safe route from here (inside an inflated obstacle): go direct
                points.append(b[None, :])
                continue
            centres = (cells[1:-1] + 0.5) * grid.resolution + np.asarray(grid.origin)
            points.extend([centres, b[None, :]])
        self._path = np.concatenate(points)

    def _deviation(self, position: np.ndarray) -> float:
        a, b = self._path[self._segment], self._path[min(self._segment + 1, len(self._path) - 1)]
        return _point_segment_distance(position, a, b)

    def _pursuit(self, position: np.ndarray, horizon: float) -> tuple[np.ndarray, float]:
        """The point ``lookahead`` along the path past the vehicle's projection, and the path's
        largest turn (radians) from there within ``horizon`` metres."""
        path = self._path
        while self._segment < len(path) - 2:
            if _progress(position, path[self._segment], path[self._segment + 1]) < 1.0:
                break
            self._segment += 1
        a, b = path[self._segment], path[min(self._segment + 1, len(path) - 1)]
        t = min(max(_progress(position, a, b), 0.0), 1.0)
        point = a + t * (b - a)
        target = self._visible_target(position, point)
        first = target - point
        turn = 0.0
        if np.hypot(*first) > 1e-6:
            bearing = math.atan2(first[1], first[0])
            for d in np.arange(self.config.lookahead + 0.3, horizon + 1e-9, 0.3):
                second = _along(path, self._segment, point, float(d)) - target
                if np.hypot(*second) > 1e-6:
                    bend = math.remainder(math.atan2(second[1], second[0]) - bearing, math.tau)
                    turn = max(turn, abs(bend))
        return target, turn


def _progress(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Where p projects on segment a-b, as a fraction of it (unclamped)."""
    d = b - a
    n = float(d @ d)
    return 1.0 if n < 1e-12 else float((p - a) @ d) / n


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    t = min(max(_progress(p, a, b), 0.0), 1.0)
    return float(np.hypot(*(p - (a + t * (b - a)))))


def _along(path: np.ndarray, segment: int, point: np.ndarray, distance: float) -> np.ndarray:
    """The point ``distance`` metres along the path from ``point`` (on ``segment``), or the path's end."""
    current = point
    for k in range(segment + 1, len(path)):
        step = float(np.hypot(*(path[k] - current)))
        if step >= distance:
            return current + (path[k] - current) * (distance / step)
        distance -= step
        current = path[k]
    return path[-1].copy()


def cost_to_point(grid: ClearanceGrid, costs: np.ndarray, point: tuple[float, float]) -> np.ndarray:
    """Each cell's clearance-weighted cost to ``point`` over ``grid``, metres (unreachable: 1e4).

    :param costs: the cells' cost multipliers (:func:`_cell_costs`); the point's own cell counts as free
    """
    gi, gj = grid.cell(*point)
    costs = costs.copy()
    costs[gi, gj] = 1.0  # the point is where it is
    to_point = cost_to_go(costs, gi, gj) * grid.resolution
    return np.where(np.isfinite(to_point), to_point, 1e4)


def _cell_costs(clearance: np.ndarray, radius: float, margin: float, weight: float) -> np.ndarray:
    """Per-cell cost multiplier: 1 with ``margin`` to spare, up to ``1 + weight`` at the radius,
    infinite inside it."""
    spare = np.clip((clearance - radius) / margin, 0.0, 1.0)
    costs = 1.0 + weight * (1.0 - spare)
    costs[clearance < radius] = np.inf
    return costs


def _stopping_speed(free: float, accel: float, lag: float) -> float:
    """The speed from which the vehicle stops within ``free`` metres: ``lag`` seconds at speed,
    then braking at ``accel``."""
    return -accel * lag + math.sqrt((accel * lag) ** 2 + 2.0 * accel * max(free, 0.0))


class ExpertController:
    """A teacher as an evaluation controller: it ignores the frames it is given and reads the env
    it flies (privileged), so its success rate bounds what a student imitating it can reach.

    :param expert: a teacher built on the unwrapped env it flies (:class:`PathExpert`,
        :class:`~training.predictive_expert.PredictiveExpert`; the evaluation resets the env before
        :meth:`reset`)
    """

    def __init__(self, expert: Any) -> None:
        self._expert = expert

    def reset(self, obs: np.ndarray) -> np.ndarray:
        return self._expert.reset()

    def act(self, obs: np.ndarray) -> np.ndarray:
        return self._expert.act()
