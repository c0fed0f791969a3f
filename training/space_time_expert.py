"""A privileged teacher for worlds with movers that plans in space and time: it reads where each
mover's track will take it, searches the earliest way to the waypoint that keeps clear of them
(:func:`flightsim.worlds.space_time.schedule`), and flies that schedule through the robust
teacher's filter.

The mover-aware robust teacher (:func:`training.predictive_expert.mover_expert`) judges each
command by whether the vehicle could stop clear after it. Where a mover's lane crosses the only way
on (a forklift pacing the end of the aisles, two drones shuttling across a gap between trees), no
stop in that lane is clear, so it waits at its edge until the episode ends: 4 and 6 of the 20
dynamic validation worlds of 500,400 and 500,410 timed out so. A way through needs a commitment (go
in behind the mover and out before it comes back) that only a plan over time can make.

This teacher's path expert (:class:`SpaceTimePath`) replans every ``replan_s`` from where the
vehicle is: a grid of the room at the flight altitude, the cells the static world leaves free by
the radius and a margin, and at every time step over ``horizon_s`` the cells every mover (where
its track puts it then) leaves free by the radius and ``mover_margin``. It flies towards where the
schedule will be ``lead_s`` plus the response's lag ahead, nose along the schedule further on. The
robust filter then keeps each command's stop clear of the static world as before, and the command
itself clear of where the movers will truly be over its first second
(:attr:`~training.predictive_expert.PredictiveExpertConfig.mover_oracle_s`): the schedule answers
for the rest.

The labels read the movers' future, which the student cannot see (its frames carry each mover's
position and velocity now). That is the privilege the static teachers have over the map beyond the
scans: the student learns what the teacher does on average in the situations it can tell apart.
In worlds without movers the schedule is never used and it is :func:`robust_expert`.

Alone on the 20 dynamic validation worlds of 500,400 (the random response) it reaches 90 %, no
collision, 2 timeouts (``mover_expert``: 80 %, 0, 4); on those of 500,410, flown once after, 95 %,
1 collision (``mover_expert``: 65 %, 1 collision, 6 timeouts).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from flightsim.envs.nav_env import LidarNavEnv
from flightsim.worlds.planner import ClearanceGrid, clearance_grid
from flightsim.worlds.space_time import cell_centres, free_cells, right_of_movers, sampling_margin, schedule
from training.path_expert import PathExpert, _cell_costs, cost_to_point
from training.predictive_expert import MOVERS, PredictiveExpert


@dataclass(frozen=True)
class SpaceTimeConfig:
    """The schedule's tuning (tried on the dynamic validation worlds 500,400-500,404).

    :param cell: the grid's cell, metres (one cell's diagonal per step is the schedule's top speed)
    :param dt: the schedule's time step, s
    :param horizon_s: the schedule looks this far ahead; a waypoint further off is approached
        through the reachable cell nearest it, s
    :param static_margin: clearance beyond the radius and half a cell's diagonal a cell keeps from
        the static world, metres
    :param mover_margin: clearance beyond the radius and the sampling margins a cell keeps from each
        mover, metres
    :param replan_s: the schedule is searched again this often, s
    :param lead_s: the vehicle flies towards where the schedule will be this far (plus the
        response's lag) ahead, s
    :param heading_s: the nose points to where the schedule will be this far ahead, s
    :param speed_fraction: the velocity asked is at most this fraction of the top speed
    :param keep_right: the schedule keeps out of each moving mover's right within this distance of
        its centre (:func:`~flightsim.worlds.space_time.right_of_movers`), so it passes an oncoming
        mover with it on the vehicle's left, unless that arrives more than ``keep_right_slack_s``
        later than a way that does not, metres (0: the search's tie-break picks the side)
    :param keep_right_slack_s: how much later keeping right may arrive, s
    :param commit_slack_s: at a replan the vehicle keeps the schedule it is flying while it is still
        on it (within ``commit_off`` of where it puts the vehicle now), every cell it passes is
        still free, and it arrives at most this much later than the new search's, so a near tie
        between two ways does not swap sides every replan, s (0: each replan starts afresh)
    :param commit_off: how far from where its schedule puts it the vehicle may be and keep it, metres
    :param constant_velocity: the schedule carries each mover on at its velocity now instead of
        reading its true track (:func:`~flightsim.worlds.space_time.mover_track`)
    :param mover_growth: each mover's clearance grows this much per second of look-ahead, m/s
    :param mover_growth_cap: and at most this much, metres
    """

    cell: float = 0.2
    dt: float = 0.2
    horizon_s: float = 16.0
    static_margin: float = 0.1
    mover_margin: float = 0.35
    replan_s: float = 0.5
    lead_s: float = 0.8
    heading_s: float = 2.0
    speed_fraction: float = 0.9
    keep_right: float = 0.0
    keep_right_slack_s: float = 1.0
    commit_slack_s: float = 0.0
    commit_off: float = 1.0
    constant_velocity: bool = False
    mover_growth: float = 0.0
    mover_growth_cap: float = 0.0


class SpaceTimePath(PathExpert):
    """A path expert that, among movers, flies a space-time schedule instead of the static path.

    :param env: the env whose true state, map and movers it reads
    :param config: the schedule's tuning
    """

    def __init__(self, env: LidarNavEnv, config: SpaceTimeConfig | None = None) -> None:
        super().__init__(env)
        self.schedule_config = config or SpaceTimeConfig()
        self._cells: ClearanceGrid | None = None
        self._static_free = np.zeros((0, 0), dtype=bool)
        self._cell_cost = np.zeros((0, 0))
        self._centres = np.zeros((0, 3))
        self._needed = 0.0
        self._to_goal = np.zeros((0, 0))
        self._goal_index = -1
        self._times = np.zeros(0)
        self._way = np.zeros((0, 2))
        self._replan_at = -np.inf

    def reset(self) -> np.ndarray:
        """A new episode: rasterise the world for the schedule, then as :meth:`PathExpert.reset`."""
        env, sc = self.env, self.schedule_config
        if not env.world.moving:
            return super().reset()
        radius, altitude = env.config.vehicle_radius, float(env.world.start_position[2])
        half_diagonal = sc.cell * math.sqrt(2.0) / 2.0
        cap = radius + half_diagonal + sc.static_margin + self.config.preferred_margin + sc.cell
        self._cells = clearance_grid(env.world, altitude, sc.cell, cap)
        self._static_free = self._cells.clearance >= radius + half_diagonal + sc.static_margin
        cfg = self.config
        self._cell_cost = _cell_costs(self._cells.clearance, radius, cfg.preferred_margin, cfg.clearance_cost)
        self._centres = cell_centres(self._cells, altitude)
        self._needed = radius + sc.mover_margin + sampling_margin(env.world, sc.cell, sc.dt)
        self._goal_index, self._replan_at = -1, -np.inf
        return super().reset()

    def _desired(self) -> tuple[np.ndarray, np.ndarray]:
        """Without movers, the path's; with them, towards where the schedule will be, and the
        schedule's direction further on (the nose holds where the schedule waits)."""
        env, sc = self.env, self.schedule_config
        if not env.world.moving:
            return super()._desired()
        now = env.sim_time
        if self._goal_index != env.waypoint_index or now >= self._replan_at - 1e-9:
            self._replan()
        state = env.true_state
        here = np.asarray(state.position[:2], dtype=np.float64)
        lead = sc.lead_s + self._lag()
        desired = (self._along(now + lead) - here) / lead
        top = sc.speed_fraction * env.config.max_speed
        speed = math.hypot(*desired)
        if speed > top:
            desired *= top / speed
        ahead = self._along(now + sc.heading_s) - here
        distance = math.hypot(*ahead)
        if distance > sc.cell:
            return desired, ahead / distance
        return desired, np.array([math.cos(state.yaw), math.sin(state.yaw)])

    def _along(self, time: float) -> np.ndarray:
        """Where the schedule puts the vehicle at ``time`` (its end after it), world metres."""
        return np.array([np.interp(time, self._times, self._way[:, k]) for k in (0, 1)])

    def _replan(self) -> None:
        """Search the schedule from the vehicle's cell now to the current waypoint, and fly it
        unless the one being flown is still good (``commit_slack_s``)."""
        env, sc, grid = self.env, self.schedule_config, self._cells
        assert grid is not None
        x, y = env.world.waypoints[env.waypoint_index][:2]
        goal = (float(x), float(y))
        same_goal = self._goal_index == env.waypoint_index
        if not same_goal:
            self._to_goal = cost_to_point(grid, self._cell_cost, goal)
            self._goal_index = env.waypoint_index
        now = env.sim_time
        times = now + sc.dt * np.arange(round(sc.horizon_s / sc.dt) + 1)
        free = free_cells(
            env.world, self._centres, times, self._needed, self._static_free,
            constant_velocity=sc.constant_velocity, growth=sc.mover_growth, growth_cap=sc.mover_growth_cap,
        )  # fmt: skip
        here = env.true_state.position
        start, end = grid.cell(*here[:2]), grid.cell(*goal)
        cells = schedule(free, start, end, self._to_goal)
        if sc.keep_right > 0.0:
            right = right_of_movers(
                env.world, self._centres, times, sc.keep_right, constant_velocity=sc.constant_velocity
            ).reshape(free.shape)
            kept = schedule(free & ~right, start, end, self._to_goal)
            if tuple(kept[-1]) == end and len(kept) <= len(cells) + round(sc.keep_right_slack_s / sc.dt):
                cells = kept
        self._replan_at = now + sc.replan_s
        by = float(times[len(cells) - 1]) + sc.commit_slack_s if tuple(cells[-1]) == end else math.inf
        if same_goal and sc.commit_slack_s > 0.0 and self._still_good(free, times, end, by):
            return
        self._way = np.asarray(grid.origin) + (cells + 0.5) * sc.cell
        self._way[0] = here[:2]  # from where it truly is, not its cell's centre
        self._times = times[: len(cells)]

    def _still_good(self, free: np.ndarray, times: np.ndarray, end: tuple[int, int], by: float) -> bool:
        """Whether the schedule being flown reaches the waypoint's cell ``end`` by ``by`` (s), the
        vehicle is still on it, and at each of ``times`` until then both cells it is between are
        ``free``."""
        sc, grid = self.schedule_config, self._cells
        assert grid is not None
        if grid.cell(*self._way[-1]) != end or self._times[-1] > by + 1e-9 or times[0] >= self._times[-1]:
            return False
        here = np.asarray(self.env.true_state.position[:2], dtype=np.float64)
        if math.dist(self._along(float(times[0])), here) > sc.commit_off:
            return False
        nx, ny = free.shape[1:]
        cells = np.floor((self._way - np.asarray(grid.origin)) / sc.cell).astype(int)
        cells = np.clip(cells, 0, [nx - 1, ny - 1])
        count = min(math.ceil((self._times[-1] - times[0]) / sc.dt - 1e-9) + 1, times.size)
        steps = np.arange(1, count)
        index = (times[steps] - self._times[0]) / sc.dt
        before = np.minimum(np.floor(index + 1e-9).astype(int), len(cells) - 1)
        after = np.minimum(before + 1, len(cells) - 1)
        return bool(
            free[steps, cells[before, 0], cells[before, 1]].all()
            and free[steps, cells[after, 0], cells[after, 1]].all()
        )


#: the space-time teacher's filter: :data:`~training.predictive_expert.MOVERS` with each mover's
#: true future over the first second of each prediction, the schedule answering for the rest
SPACE_TIME = dataclasses.replace(MOVERS, mover_oracle_s=1.0)


def space_time_expert(env: LidarNavEnv) -> PredictiveExpert:
    """The robust teacher flying a space-time schedule among the movers (``[pretrain] teacher =
    "space_time_expert"``): in a world without movers it is :func:`robust_expert`, command for
    command."""
    return PredictiveExpert(env, SPACE_TIME, path=SpaceTimePath(env))


#: how far from each mover's centre the keep-right teacher's schedule keeps off its right, metres
KEEP_RIGHT = 3.0
#: how much later than a new search the keep-right teacher's kept schedule may arrive, s
COMMIT_SLACK_S = 1.0


def keep_right_expert(env: LidarNavEnv) -> PredictiveExpert:
    """:func:`space_time_expert` passing each mover on its left or behind it where that costs at
    most ``keep_right_slack_s`` (``[pretrain] teacher = "keep_right_expert"``): the vehicle keeps
    right of one coming at it, as ships and most roads do.

    The space-time teacher passed a mover coming head-on on either side, whatever side of the
    vehicle's nose it was on: the search's tie-break decided, which the student cannot see, and a
    regression of those labels averaged them into flying straight at it. Here the side follows
    what the student's frame holds: the mover's heading where keeping right is cheap, its offset
    where it is not. It is not left-right symmetric, so DAgger's fit must not mirror its labels.

    It keeps the schedule it flies while that stays good (``commit_slack_s``): replanning afresh
    every 0.5 s, it took either of two ways that arrive about as early, and its sideways label
    swung from side to side.
    """
    schedule_config = SpaceTimeConfig(keep_right=KEEP_RIGHT, commit_slack_s=COMMIT_SLACK_S)
    return PredictiveExpert(env, SPACE_TIME, path=SpaceTimePath(env, schedule_config))


def present_expert(env: LidarNavEnv) -> PredictiveExpert:
    """:func:`keep_right_expert` knowing of the movers only what the student's frame holds
    (``[pretrain] teacher = "present_expert"``): where each mover is now and its velocity now.

    Its schedule carries each mover on in a straight line, keeping 0.1 m more clearance per second
    of look-ahead up to 0.5 m, and its filter reads no mover's future
    (:data:`~training.predictive_expert.MOVERS`). The privileged teachers' labels depend on where a
    walker will turn, which the student cannot tell from its frame, so it learns their average over
    what it cannot see; this teacher's labels are a function of what it can.
    """
    schedule_config = SpaceTimeConfig(
        keep_right=KEEP_RIGHT, commit_slack_s=COMMIT_SLACK_S,
        constant_velocity=True, mover_growth=0.1, mover_growth_cap=0.5,
    )  # fmt: skip
    return PredictiveExpert(env, MOVERS, path=SpaceTimePath(env, schedule_config))
