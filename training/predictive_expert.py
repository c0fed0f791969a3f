"""A privileged teacher that looks ahead: it predicts each candidate command through the episode's
own autopilot response and flies the path expert's command, or the least change of it that can
still stop clear.

:class:`~training.path_expert.PathExpert` follows a planned path with feedback and collides where
the autopilot's lag carries the vehicle into an obstacle while it brakes and turns (78 % of the
held-out worlds). This teacher wraps it in a sampling model-predictive safety filter. Every step it
takes a fixed set of (forward, yaw rate) commands, plus the path expert's own command and that
command slowed, and for each it predicts the vehicle's path with
:meth:`flightsim.vehicle.autopilot_response.AutopilotResponse.predict` (privileged: the drawn firmware's
delays and state, the commands already in flight): the command sent for ``command_s``, then a hold
for ``stop_s``. A candidate is safe if the whole prediction
keeps the vehicle's radius plus a margin that grows with the look-ahead (the prediction's error
grows too). Of the safe ones it flies the one of least cost: mostly the distance from the path
expert's command (so it flies that command wherever it is predicted safe, and otherwise the
gentlest change that is: a student imitates smooth labels far better than a choice that jumps
across a grid), plus the cost to the current waypoint from the predicted end
(:func:`flightsim.worlds.planner.cost_to_go` over the clearance-weighted grid the path expert plans on)
and small costs on turning and on changing the command from the one the last step flew (the
env's, not this teacher's last label: when the student flies, that is the student's command, which
its frame shows). With no safe candidate, it flies the least costly of those that keep the most
clearance while the command is sent (within ``recovery_tolerance``).

On the 54 validation worlds (6 per family) it reaches 52 (the path expert 46); scored on the
cost to go alone, with a bonus for the path expert's command, it reached 51 and 27 % faster, but
a DAgger student fitted to those jumping labels reached 11 % of the validation worlds after the
first iteration (the path expert's student: 41 %). The robust teacher (:func:`robust_expert`)
reaches 97.8 % of the 90 validation worlds (10 per family) alone and 97.8 % behind the companion's
shield; 95.6 / 93.3 % before the recovery weighed the clearance while the command is sent (not
the whole prediction's) and before the prediction let the estimate error decay: a drift held
for the whole stop made no candidate safe near a wall, and the cost chose one through it.

With the ideal autopilot (no response model) there is nothing to predict with: it is the path
expert. It is a training tool, as the path expert is; ``avoid-train evaluate --baselines
predictive_expert`` measures it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flightsim.envs.nav_env import LidarNavEnv
from flightsim.vehicle.autopilot_response import ResponseParams, hardest_params
from flightsim.worlds.moving import MovingObstacle
from flightsim.worlds.planner import ClearanceGrid, clearance_grid
from flightsim.worlds.space_time import mover_state
from training.path_expert import PathExpert, PathExpertConfig, _cell_costs, body_to_world, cost_to_point

#: s between commands (the env's control period)
PERIOD_S = 0.1
#: metres a candidate that comes inside its static margin while sent ranks below every one that
#: does not, in the recovery among movers (more than any room a mover can take)
STATIC_FIRST = 1e3


@dataclass(frozen=True)
class PredictiveExpertConfig:
    """The teacher's tuning (chosen on the validation worlds, 6 per family).

    :param forward_options: candidate forward commands, fractions of the top speed
    :param yaw_options: candidate yaw-rate commands, fractions of the top yaw rate
    :param command_s: each candidate is sent this long, s
    :param stop_s: then a hold is predicted this long (the vehicle must be able to stop clear), s
    :param margin: clearance beyond the vehicle's radius every predicted point keeps, metres
    :param margin_growth: the margin grows by this much per second of look-ahead, m/s
    :param growth_cap: up to this much, metres
    :param path_expert_bonus: the path expert's command scores this much better (metres of cost)
    :param follow_weight: cost per unit of distance (in action units) from the path expert's command
    :param slowdowns: the path expert's command at these fractions of its forward speed are
        candidates too (the gentlest way to make its command safe is often to slow it)
    :param yaw_cost: cost per unit of yaw-rate command (fraction of the top rate)
    :param forward_change_cost: cost per unit of change of the forward command from the last flown
    :param yaw_change_cost: cost per unit of change of the yaw-rate command from the last flown
    :param resolution: the cost-to-go grid's cell, metres
    :param preferred_margin: clearance beyond the radius the cost-to-go prefers, metres
    :param clearance_cost: extra cost per metre in a cell with no margin (as the path expert's)
    :param recovery_tolerance: with no safe candidate, those within this much of the most clearance
        while the command is sent are equals and the least cost decides among them, metres (the
        first of a tie was an arbitrary, jumping label)
    :param hardest_response: a candidate must also stop clear through the drawn firmware's hardest
        response (:func:`flightsim.vehicle.autopilot_response.hardest_params`): the student cannot see the
        draw, so a label that brakes for a slow draw only and flies on for a quick one is, to the
        student, the same state with two answers, which regression averages into too fast for both
    :param sideways_options: with a sideways action (the env's ``sideways``), each candidate
        also with each of these sideways commands, fractions of the top sideways speed; the path
        expert's command is a candidate with and without its sideways part too
    :param movers: every predicted point also keeps the radius, ``mover_margin`` and the growth from
        each of the world's moving obstacles, predicted from its true position and velocity now
        (what its track shows, not its scripted future: a label a student can learn from the
        tracks); against movers, a candidate whose command kept through the whole prediction
        keeps clear (of the static world too) is as good as one whose stop does: a hold in a
        mover's way is no refuge, stepping on out of it is
    :param mover_margin: clearance beyond the vehicle's radius kept from a mover's shape, metres
    :param mover_turn_s: a mover may also turn back now, for this long (after that the teacher,
        choosing again every period, has seen it turn): each point keeps clear of it anywhere on
        its line from there to where it would be carried on, s. Walkers, forklifts and drones
        turn at their tracks' ends, within 2 m of the vehicle in every collision without it; 0.6
        and 0.8 s left 3 and 4 collisions in the 20 dynamic validation worlds, the whole
        look-ahead 11 timeouts (waiting for a gap that never came)
    :param mover_oracle_s: above 0: each mover is where its track will truly put it (privileged,
        as the static map is), and a candidate keeps clear of it over this many seconds of its
        prediction only, s. For a teacher whose path already keeps clear of the movers' futures
        (:mod:`training.space_time_expert`): a stop in a mover's way is then no refuge to demand,
        the way on is
    """

    forward_options: tuple[float, ...] = (-0.25, 0.0, 0.15, 0.3, 0.5, 0.7, 0.85, 1.0)
    yaw_options: tuple[float, ...] = (-1.0, -0.6, -0.3, -0.12, 0.0, 0.12, 0.3, 0.6, 1.0)
    command_s: float = 1.0
    stop_s: float = 2.5
    margin: float = 0.1
    margin_growth: float = 0.1
    growth_cap: float = 0.15
    path_expert_bonus: float = 0.0
    follow_weight: float = 3.0
    slowdowns: tuple[float, ...] = (0.75, 0.5, 0.25, 0.0)
    yaw_cost: float = 0.15
    forward_change_cost: float = 0.3
    yaw_change_cost: float = 0.1
    resolution: float = 0.1
    preferred_margin: float = 0.8
    clearance_cost: float = 8.0
    recovery_tolerance: float = 0.05
    hardest_response: bool = False
    sideways_options: tuple[float, ...] = (-0.5, 0.0, 0.5)
    movers: bool = False
    mover_margin: float = 0.3
    mover_turn_s: float = 1.0
    mover_oracle_s: float = 0.0


def pick(spare: np.ndarray, near: np.ndarray, score: np.ndarray, recovery_tolerance: float) -> int:
    """The candidate to fly: the least ``score`` of those with clearance to spare (``spare > 0``,
    metres), or, when none has, of those within ``recovery_tolerance`` of the most spare while
    the command is sent (``near``).

    The whole prediction's spare was the recovery rule before: where every candidate's stop
    drifts into a wall alike (the estimate error carries the hold), it tied them all, and the cost
    sent the vehicle at the wall now."""
    eligible = spare > 0.0
    if not eligible.any():
        eligible = near >= near.max() - recovery_tolerance
    return int(np.argmin(np.where(eligible, score, np.inf)))


class PredictiveExpert:
    """Fly one :class:`~flightsim.envs.nav_env.LidarNavEnv` (unwrapped) by predicting its autopilot.

    :param env: the env whose true state and response model it reads (``reset`` it before :meth:`reset`)
    :param config: tuning
    :param path_config: the tuning of the path expert whose command it filters
    :param path: the path expert whose command it filters, if not a :class:`PathExpert` of
        ``path_config`` (one that plans among the movers)
    """

    def __init__(
        self, env: LidarNavEnv, config: PredictiveExpertConfig | None = None,
        path_config: PathExpertConfig | None = None, path: PathExpert | None = None,
    ) -> None:  # fmt: skip
        self.env = env
        self.config = config or PredictiveExpertConfig()
        cfg = self.config
        self._candidates = np.array([(f, r) for f in cfg.forward_options for r in cfg.yaw_options])
        if env.config.sideways:
            self._candidates = np.array([(*c, s) for c in self._candidates for s in cfg.sideways_options])
        self._path_expert = path or PathExpert(env, path_config)
        self._grid: ClearanceGrid | None = None
        self._costs = np.zeros((0, 0))
        self._to_goal = np.zeros((0, 0))
        self._goal_index = -1
        self._hardest: ResponseParams | None = None  # the episode's slowest response, when asked for
        self._movers: tuple[MovingObstacle, ...] = ()  # the world's, when the config gives way to them

    def reset(self) -> np.ndarray:
        """A new episode: rasterise the world and return the first action."""
        env, cfg = self.env, self.config
        radius = env.config.vehicle_radius
        cap = radius + cfg.margin + cfg.growth_cap + cfg.preferred_margin + cfg.resolution
        self._grid = clearance_grid(env.world, float(env.world.start_position[2]), cfg.resolution, cap)
        self._costs = _cell_costs(self._grid.clearance, radius, cfg.preferred_margin, cfg.clearance_cost)
        self._goal_index = -1
        self._movers = env.world.moving if cfg.movers else ()
        response = env.response
        self._hardest = hardest_params(response.params) if cfg.hardest_response and response else None
        return self._choose(self._path_expert.reset())

    def act(self) -> np.ndarray:
        """The action for the env's current true state, ``(a0, a1)`` in ``[-1, 1]`` (with the env's
        ``sideways``, ``(a0, a1, a2)``)."""
        return self._choose(self._path_expert.act())  # every step: it keeps its own state

    def _choose(self, planned: np.ndarray) -> np.ndarray:
        """The best candidate, the path expert's ``planned`` action among them."""
        env, cfg = self.env, self.config
        response = env.response
        if response is None:
            return planned
        if self._goal_index != env.waypoint_index:
            self._to_goal = self._cost_to_waypoint(env.waypoint_index)
            self._goal_index = env.waypoint_index
        if env.config.sideways:
            scale = np.array([env.config.max_speed, env.config.max_yaw_rate, env.config.max_sideways_speed])
            slowed = [planned * (s, 1.0, s) for s in cfg.slowdowns] + [planned * (1.0, 1.0, 0.0)]
        else:
            scale = np.array([env.config.max_speed, env.config.max_yaw_rate])
            slowed = [planned * (s, 1.0) for s in cfg.slowdowns]
        candidates = np.vstack([self._candidates, *slowed, planned[None].astype(np.float64)])
        state = env.true_state
        command_steps = round(cfg.command_s / PERIOD_S)
        total_steps = command_steps + round(cfg.stop_s / PERIOD_S)
        steps = (command_steps, total_steps, PERIOD_S)
        held = body_to_world(env.drift_held(), float(state.yaw))  # what each setpoint carries on top
        commands = candidates * scale
        spare, near, cells = self._room(commands, steps, held)
        end = cells[:, -1]
        flown = env.last_command.astype(np.float64)
        score = (
            self._to_goal[end[:, 0], end[:, 1]]
            + cfg.yaw_cost * np.abs(candidates[:, 1])
            + cfg.forward_change_cost * np.abs(candidates[:, 0] - flown[0])
            + cfg.yaw_change_cost * np.abs(candidates[:, 1] - flown[1])
            + cfg.follow_weight * np.abs(candidates - planned).sum(axis=1)
        )
        score[-1] -= cfg.path_expert_bonus
        if self._hardest is None:
            best = pick(spare, near, score, cfg.recovery_tolerance)
        else:
            best = self._pick_through_hardest(commands, steps, held, spare, near, score)
        return candidates[best].astype(np.float32)

    def _pick_through_hardest(
        self, commands: np.ndarray, steps: tuple[int, int, float], held: tuple[float, float],
        spare: np.ndarray, near: np.ndarray, score: np.ndarray,
    ) -> int:  # fmt: skip
        """:func:`pick` over the least of the drawn response's clearance and the hardest
        response's, predicting the hardest for as few candidates as that needs.

        The hardest prediction costs as much as the drawn one, and a candidate the drawn response
        already brings inside its margin (``spare <= 0``) is unsafe whatever the hardest says. So
        the others are predicted through the hardest in order of ``score`` (ties in the candidates'
        order, as :func:`pick` breaks them), in chunks that double: the first that stays safe is
        the one :func:`pick` takes (in most steps the first: one candidate predicted). Only when none
        does (recovery) are the rest predicted, and only while the command is sent: ``near`` is all
        the recovery reads. Each candidate's prediction starts from the same state, so its rows are
        the ones a prediction of all of them gives, and the pick is the same.

        :param commands: ``(K, 3)`` or ``(K, 2)`` body commands, m/s and rad/s
        :param steps: periods the command is sent for, periods predicted, and the period (s)
        :param held: velocity every setpoint carries on top, world m/s (:meth:`AutopilotResponse.predict`)
        :param spare: each candidate's least clearance to spare through the drawn response, metres
        :param near: the same while the command is sent
        :param score: each candidate's cost
        :return: the candidate's index
        """
        command_steps, total_steps, period = steps
        hard_spare, hard_near = np.full(len(score), np.inf), np.full(len(score), np.inf)
        hopeful = np.flatnonzero(spare > 0.0)
        order = hopeful[np.argsort(score[hopeful], kind="stable")]
        start, size = 0, 1
        while start < len(order):
            chunk = order[start : start + size]
            hard_spare[chunk], hard_near[chunk], _ = self._room(commands[chunk], steps, held, self._hardest)
            safe = np.flatnonzero(hard_spare[chunk] > 0.0)
            if len(safe):
                return int(chunk[safe[0]])
            start, size = start + size, 2 * size
        rest = np.flatnonzero(~(spare > 0.0))
        predicted = total_steps if self._movers else command_steps  # a mover's room: the whole prediction
        recovery = (command_steps, predicted, period)
        _, hard_near[rest], _ = self._room(commands[rest], recovery, held, self._hardest)
        spare, near = np.minimum(spare, hard_spare), np.minimum(near, hard_near)  # no candidate has any spare
        return pick(spare, near, score, self.config.recovery_tolerance)

    def _room(
        self, commands: np.ndarray, steps: tuple[int, int, float], held: tuple[float, float],
        params: ResponseParams | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
        """Each candidate's least clearance to spare over its whole prediction and while its
        command is sent (``near``, what the recovery weighs), metres, ``(K,)`` each; and the grid
        cells of its predicted points.

        With movers, a candidate's room from them is the more of its stop's and, where the
        prediction goes on after the command, of its command kept to the end (with that path's
        static clearance: a way out of a walker's path into a shelf is none). ``near`` ranks first
        the candidates that keep clear of the static world while sent, by that room over the
        whole prediction (a walker that reaches the vehicle after the command is sent still does:
        with no candidate safe, the one that keeps the most room steps aside or backs off), then
        the others by their static clearance, shifted :data:`STATIC_FIRST` below: a vehicle that
        backs off a forklift into a wall hits the wall.

        :param commands: ``(K, 3)`` or ``(K, 2)`` body commands, m/s and rad/s
        :param steps: periods the command is sent for, periods predicted, and the period (s)
        :param held: velocity every setpoint carries on top, world m/s (:meth:`AutopilotResponse.predict`)
        :param params: predict through this response instead of the drawn one (the hardest)
        """
        response, state = self.env.response, self.env.true_state
        assert response is not None
        command_steps, total_steps, period = steps
        yaw, position = float(state.yaw), state.position
        paths = response.predict(yaw, commands, *steps, params, held)
        excess, cells = self._excess(paths, position)
        spare, near = excess.min(axis=1), excess[:, :command_steps].min(axis=1)
        if self._movers:
            room = self._mover_excess(paths, position).min(axis=1)
            if total_steps > command_steps and not self.config.mover_oracle_s:
                kept = response.predict(yaw, commands, total_steps, total_steps, period, params, held)
                way_out = np.minimum(self._mover_excess(kept, position), self._excess(kept, position)[0])
                room = np.maximum(room, way_out.min(axis=1))
            spare, near = (
                np.minimum(spare, room),
                np.where(near > 0.0, np.minimum(near, room), near - STATIC_FIRST),
            )
        return spare, near, cells

    def _mover_excess(self, paths: np.ndarray, position: np.ndarray) -> np.ndarray:
        """Each predicted point's clearance from every mover beyond what it must keep (the radius,
        :attr:`~PredictiveExpertConfig.mover_margin` and the growth), metres, ``(K, steps)``: each
        mover anywhere on its line from where its velocity now
        (:func:`~flightsim.worlds.space_time.mover_state`) carries it to where it would be had
        it turned back now (for at most :attr:`~PredictiveExpertConfig.mover_turn_s`), the nearest
        of those places to the point;
        or, with :attr:`~PredictiveExpertConfig.mover_oracle_s`, where its track puts it (and no
        limit beyond that horizon).

        :param paths: ``(K, steps, 3)`` displacements from ``position``
        :param position: the vehicle now, world metres
        """
        cfg, now = self.config, self.env.sim_time
        ahead = PERIOD_S * np.arange(1, paths.shape[1] + 1)
        required = (
            self.env.config.vehicle_radius
            + cfg.mover_margin
            + np.minimum(cfg.margin_growth * ahead, cfg.growth_cap)
        )
        points = np.concatenate(
            [paths[:, :, :2] + np.asarray(position[:2]), np.full((*paths.shape[:2], 1), float(position[2]))],
            axis=-1,
        )
        least = np.full(paths.shape[:2], np.inf)
        if cfg.mover_oracle_s:
            checked = ahead <= cfg.mover_oracle_s + 1e-9  # beyond it: no limit
            seen, near, when = points[:, checked], least[:, checked], now + ahead[checked]
            for mover in self._movers:
                near = np.minimum(near, mover.clearance_from(seen, mover.positions(when)[None]))
            least[:, checked] = near
            return least - required
        back = -np.minimum(ahead, cfg.mover_turn_s) / ahead  # turned back: this much of the way carried on
        for mover in self._movers:
            here, velocity = mover_state(mover, now)
            carried = np.outer(ahead, velocity)  # (steps, 2)
            along = np.einsum("ksj,sj->ks", points[..., :2] - here, carried) / np.maximum(
                np.einsum("sj,sj->s", carried, carried), 1e-12
            )
            centres = here + np.clip(along, back, 1.0)[..., None] * carried  # stopped where it is: 0
            least = np.minimum(least, mover.clearance_from(points, centres))
        return least - required

    def _excess(self, paths: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each predicted point's clearance beyond what it must keep (the radius, the margin and
        its growth with the look-ahead), metres, ``(K, steps)``; and the grid cells they are in.

        :param paths: ``(K, steps, 3)`` displacements from ``position`` (:meth:`AutopilotResponse.predict`)
        :param position: the vehicle now, world metres
        """
        cfg, grid = self.config, self._grid
        assert grid is not None
        ahead = PERIOD_S * np.arange(1, paths.shape[1] + 1)
        growth = np.minimum(cfg.margin_growth * ahead, cfg.growth_cap)
        required = self.env.config.vehicle_radius + cfg.margin + growth
        cells = self._cells(paths[:, :, :2] + np.asarray(position[:2]))
        return grid.clearance[cells[..., 0], cells[..., 1]] - required, cells

    def _cost_to_waypoint(self, index: int) -> np.ndarray:
        """Each cell's clearance-weighted cost to waypoint ``index``, metres (unreachable: 1e4)."""
        assert self._grid is not None
        goal = self.env.world.waypoints[index]
        return cost_to_point(self._grid, self._costs, (float(goal[0]), float(goal[1])))

    def _cells(self, points: np.ndarray) -> np.ndarray:
        """Grid cells (clamped into the grid) of ``(..., 2)`` points, ``(..., 2)`` ints."""
        grid = self._grid
        assert grid is not None
        index = np.floor((points - np.asarray(grid.origin)) / grid.resolution).astype(np.int64)
        return np.clip(index, 0, np.array(grid.clearance.shape) - 1)


#: the robust teacher's filter: every command also stops clear through the drawn firmware's
#: hardest response (one definition for the teachers and ``bench/bench_teacher.py``)
ROBUST = PredictiveExpertConfig(hardest_response=True)


#: the mover-aware robust teacher's filter: :data:`ROBUST`, and every prediction also keeps clear
#: of each moving obstacle carried on at its velocity now, stopped or turned back
MOVERS = PredictiveExpertConfig(hardest_response=True, movers=True)


def robust_expert(env: LidarNavEnv) -> PredictiveExpert:
    """The predictive teacher whose every command also stops clear through the hardest response
    of the drawn firmware (``[pretrain] teacher = "robust_expert"``)."""
    return PredictiveExpert(env, ROBUST)


def mover_expert(env: LidarNavEnv) -> PredictiveExpert:
    """The robust teacher giving way to what moves (:data:`MOVERS`, ``[pretrain] teacher =
    "mover_expert"``): in a world without movers it is :func:`robust_expert`, command for command."""
    return PredictiveExpert(env, MOVERS)


#: the path expert's yaw loop for :func:`smooth_expert`: at its default gain (3/s) and lead
#: (0.25 s) the nose swings from side to side as it turns the sideways drift into the path, and
#: the labels with it (mean step-to-step change of the yaw label 0.130 of the top rate on 54
#: validation episodes, 500,000-2 x2); this one 0.096, and the robust filter's success is the same
#: (54 of 54). A gain of 1.5/s gave 0.080 and a collision; a longer lead made it swing more.
SMOOTH_YAW = PathExpertConfig(yaw_gain=2.0, yaw_lead_s=0.1)


def smooth_expert(env: LidarNavEnv) -> PredictiveExpert:
    """The robust teacher filtering a path expert with a gentler yaw loop (:data:`SMOOTH_YAW`,
    ``[pretrain] teacher = "smooth_expert"``)."""
    return PredictiveExpert(env, ROBUST, SMOOTH_YAW)
