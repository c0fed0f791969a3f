"""The goal-directed Gymnasium environment: fly through a world's waypoints, in order, on a lidar scan."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from gymnasium import spaces

from companion.guidance.route import RouteConfig, RoutePlanner
from companion.perception.drift import DriftConfig, DriftEstimator, DriftHoldConfig, held_drift
from companion.perception.observation import (
    ObservationLayout,
    build_frame,
    command_features,
    drift_features,
    firmware_features,
    goal_features,
    goal_in_body,
    mover_features,
)
from companion.perception.tracking import ScanTracker, TrackerOutput, without_movers
from flightsim.envs import seeds
from flightsim.envs.env import CONTROL_HZ, EnvConfig, LidarAvoidEnv, StepCommand, clip_unit
from flightsim.envs.reward import GoalRewardConfig, GoalStep, StepOutcome, goal_reward
from flightsim.worlds.families import ALL_FAMILIES, DYNAMIC_SUFFIX, FAMILIES, generate_family_world
from flightsim.worlds.planner import shortest_safe_path
from flightsim.worlds.render import render_rgb
from flightsim.worlds.world import World

_NAV_OPTION_KEYS = {"world", "family", "world_seed", "difficulty"}


@dataclass(frozen=True)
class NavEnvConfig(EnvConfig):
    """:class:`~flightsim.envs.env.EnvConfig` plus what the goal task adds (strict-loadable).

    ``difficulty`` and ``reward`` of the base config do not apply: difficulties are drawn from
    ``difficulty_range`` and the reward is :func:`flightsim.envs.reward.goal_reward`.

    :param families: world families training draws from, uniformly by entry (a family named twice is
        drawn twice as often): by default the static
        :data:`flightsim.worlds.families.FAMILIES`; any of
        :data:`~flightsim.worlds.families.ALL_FAMILIES` (the ``-dynamic`` ones have moving obstacles)
    :param difficulty_range: a generated world's difficulty is drawn uniformly in it
    :param acceptance_radius: a waypoint is reached when the vehicle's centre comes this close,
        horizontally, metres
    :param goal_range: metres a goal-distance feature of 1.0 stands for (farther reads 1.0)
    :param time_limit_per_m: seconds allowed per metre of the world's shortest safe path
    :param time_limit_slack_s: seconds allowed on top (turning to the first leg, braking)
    :param max_steps: hard cap on an episode, whatever the time limit says (3000 = 300 s)
    :param autopilot_response: as in :class:`~flightsim.envs.env.EnvConfig`, but ``"random"`` by default:
        a PX4- or ArduPilot-like response drawn per episode, so a policy meets both
    :param goal_reward: the reward's weights
    :param drift: each frame also carries the drift estimate
        (:class:`companion.perception.drift.DriftEstimator`
        on this episode's frames, as the companion computes it in flight)
    :param command: each frame also carries the command just flown (after the shield), as the
        companion's frames carry the last setpoint it sent
    :param firmware: each frame also says which firmware's structure the episode's response has
        (1.0 ArduPilot: shaped input; 0.0 PX4, or the ideal response), as the companion's frames
        carry its ``autopilot.type``
    :param drift_hold: each setpoint also carries the drift estimate, as far as
        ``drift_hold_limits`` say (the companion's ``[drift_hold]`` table): the autopilot flies the
        setpoint on its estimate, so the vehicle then truly flies the command less only the rest of
        the error; needs ``drift`` (the estimate is tracked only then)
    :param drift_hold_limits: those limits (:class:`companion.perception.drift.DriftHoldConfig`)
    :param route: the goal features point along a route planned on the scans seen so far
        (:class:`companion.guidance.route.RoutePlanner`, on the true pose, as the goal features are), not
        straight at the waypoint; the companion's ``goal.route`` does the same in flight
    :param route_planner: that planner's tuning
    :param sideways: the action has a third component, a sideways speed (left positive) in units
        of ``max_sideways_speed``: a multirotor need not turn its nose to move sideways, and a
        teacher that must corrects every sideways error by turning (docs/goal-policy.md). The
        shield judges such a command along its course; ``overspeed_penalty`` charges the forward
        part only
    :param max_sideways_speed: m/s that a sideways action of 1 stands for
    :param tracking: track what moves in every scan (:class:`companion.perception.tracking.ScanTracker`,
        on the true pose, as the route is), and keep the moving returns out of the drift estimate and
        the route's map, as the companion's ``[tracking]`` does in flight: a mover's motion is not the
        vehicle's, and where it stood is not an obstacle. Changes nothing where nothing moves
    :param movers: each frame also carries the 3 nearest movers the tracker reports, in the body
        axes: position / 10 m, velocity / 3 m/s, radius / 1 m, and a presence flag
        (:func:`companion.perception.observation.mover_features`), as the companion's
        ``policy.movers`` frames do: in the scan alone a walker looks like a wall. Needs ``tracking``
    """

    reward: Literal["goal"] = "goal"
    max_steps: int = field(default=3000, metadata={"min": 1})
    autopilot_response: Literal["ideal", "px4", "ardupilot", "random"] = "random"
    families: tuple[str, ...] = FAMILIES
    difficulty_range: tuple[float, float] = (0.0, 1.0)
    acceptance_radius: float = field(default=1.0, metadata={"min": 0.1, "max": 5.0})
    goal_range: float = field(default=30.0, metadata={"min": 1.0, "max": 100.0})
    time_limit_per_m: float = field(default=2.0, metadata={"min": 0.5, "max": 100.0})
    time_limit_slack_s: float = field(default=10.0, metadata={"min": 0.0, "max": 600.0})
    goal_reward: GoalRewardConfig = field(default_factory=GoalRewardConfig)
    drift: bool = False
    command: bool = False
    firmware: bool = False
    drift_hold: bool = False
    drift_hold_limits: DriftHoldConfig = field(default_factory=DriftHoldConfig)
    route: bool = False
    route_planner: RouteConfig = field(default_factory=RouteConfig)
    sideways: bool = False
    max_sideways_speed: float = field(default=1.0, metadata={"min": 0.1, "max": 5.0})
    tracking: bool = True
    movers: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        unknown = [f for f in self.families if f not in ALL_FAMILIES]
        if unknown or not self.families:
            raise ValueError(f"families: {unknown or 'none'} not among {', '.join(ALL_FAMILIES)}")
        if self.drift_hold and not self.drift:
            raise ValueError("drift_hold needs the drift estimate: set drift = true")
        if self.movers and not self.tracking:
            raise ValueError("movers are the tracker's: movers = true needs tracking = true")
        low, high = self.difficulty_range
        if not 0.0 <= low <= high <= 1.0:
            raise ValueError(f"difficulty_range {self.difficulty_range} must satisfy 0 <= low <= high <= 1")

    @property
    def keeps_drift_estimate(self) -> bool:
        """With ``drift``, the env tracks the drift estimate its frames carry."""
        return self.drift

    @property
    def layout(self) -> ObservationLayout:
        """One observation frame of this env (the companion and the ONNX metadata use the same)."""
        return ObservationLayout(
            n_bins=360, goal=True, goal_range=self.goal_range, velocity_scale=self.max_speed,
            drift=self.drift, command=self.command, yaw_rate_scale=self.max_yaw_rate,
            firmware=self.firmware, movers=self.movers,
        )  # fmt: skip


def time_limit_steps(shortest_path_m: float, config: NavEnvConfig) -> int:
    """Steps an episode may last: proportional to the shortest safe path, plus slack, within the cap."""
    seconds = config.time_limit_slack_s + config.time_limit_per_m * shortest_path_m
    return min(config.max_steps, math.ceil(seconds * CONTROL_HZ))


class LidarNavEnv(LidarAvoidEnv):
    """Fly through a world's waypoints, in order, on a 360° lidar scan, without touching anything.

    ## Description
    The vehicle, sensor and control of ``flightsim/LidarAvoid-v0`` (JSBSim quadrotor, ray-cast
    VLP-16, the companion's scan code, 10 Hz steps, the same domain randomisation and shield
    options, the autopilot response model — ``"random"`` by default here), in a world with
    waypoints (:mod:`flightsim.worlds.families`: rooms, forest, office, warehouse, pillars, staggered
    walls, concave traps, narrow gaps, mixed heights). The vehicle holds its start altitude; the
    waypoints lie at that altitude.

    ## Action Space
    As LidarAvoid-v0: ``Box(-1, 1, (2,), float32)``, ``a0`` forward speed × ``max_speed`` (2 m/s),
    ``a1`` yaw rate × ``max_yaw_rate`` (1.5 rad/s), counter-clockwise positive. With ``sideways``
    (off by default): ``Box(-1, 1, (3,), float32)``, ``a2`` speed to the left × ``max_sideways_speed``
    (1 m/s).

    ## Observation Space
    ``Box(low, high, (365,), float32)``, one frame of
    :class:`companion.perception.observation.ObservationLayout`
    ``scan360+goal(cos,sin,distance/30m)+velocity(forward,left/2m/s)``; with ``drift``,
    ``Box(low, high, (367,), float32)``, ``...+drift(forward,left/2m/s)``; with ``command`` as well,
    ``Box(low, high, (369,), float32)``, ``...+command(forward/2m/s,yaw/1.5rad/s)``; with
    ``firmware``, one float more, ``...+firmware(ardupilot=1,px4=0)``; with ``movers``, 18 floats
    more, ``...+movers(3x(forward,left/10m,velocity/3m/s,radius/1m,present))``:

    ========== ===================================================== ==========
    index      meaning                                               range
    ========== ===================================================== ==========
    0–359      the scan, as LidarAvoid-v0 (bin i = i° CCW from nose) [0, 1]
    360, 361   cos, sin of the current waypoint's bearing, body FLU  [-1, 1]
    362        its horizontal distance / ``goal_range`` (30 m)       [0, 1]
    363, 364   measured body velocity forward, left / ``max_speed``  [-1, 1]
               (:meth:`measured_body_velocity`: what the autopilot reports, estimate error included)
    365, 366   (``drift`` only) the drift estimate forward, left /   [-1, 1]
               ``max_speed``: the reported minus the scan-matched velocity, low-pass
               filtered (:class:`companion.perception.drift.DriftEstimator`, reset with the episode)
    next 2     (``command`` only) the command just flown, after the  [-1, 1]
               shield: forward / ``max_speed``, yaw rate / ``max_yaw_rate``; (0, 0) at reset
    next 1     (``firmware`` only) 1.0 when the episode's response   {0, 1}
               has ArduPilot's structure (shaped input), else 0.0
    last 18    (``movers`` only) the 3 nearest movers the tracker    [-1, 1]
               reports, nearest surface first, 6 floats each: centre forward, left / 10 m,
               velocity forward, left / 3 m/s, radius / 1 m, 1.0 (present); zeros for no mover
               (:func:`companion.perception.observation.mover_features`)
    ========== ===================================================== ==========

    The goal features are the current pose's; the scan follows ``latency_scans``. With ``route``
    they describe a subgoal instead of the waypoint (:class:`companion.guidance.route.RoutePlanner`: an
    occupancy grid of this episode's scans, the cheapest route on it, the farthest point of it in
    sight within 5 m), with the route's length as the distance; the drift estimate still guesses
    the turn from the waypoint's bearing. Frame stacking
    (4 frames in the project, the whole 365-float frame stacked, oldest first) is the training
    code's ``VecFrameStack`` and the companion's ``FrameStack``.

    ## Rewards
    :func:`flightsim.envs.reward.goal_reward` with ``config.goal_reward``: +1 per metre of progress
    toward the current waypoint, +10 on reaching each waypoint and +10 more on the last, −0.02 a
    step, −0.25 × the proximity penalty inside 1 m (up to 1 a step), −50 on a collision; and
    ``overspeed_penalty`` as in LidarAvoid-v0.

    ## Starting State
    Hovering at the world's start position and heading (generated worlds turn the start heading
    up to ±90° × difficulty away from the first leg), zero velocity.

    ## Episode End
    Terminated on a collision (clearance below ``vehicle_radius``) or on reaching the last
    waypoint (horizontal distance below ``acceptance_radius``, 1 m). Truncated at the world's time
    limit: ``time_limit_slack_s + time_limit_per_m × shortest safe path`` (10 s + 2 s/m), at most
    ``max_steps``.

    ## Info
    LidarAvoid-v0's (``collision``, ``min_distance``, ``distance``, ``position``, ``yaw``,
    ``world``, ``steps``) plus ``family``, ``waypoint`` (index being flown to; ``len(waypoints)``
    when done), ``waypoints`` (their number), ``goal_distance`` (m, horizontal),
    ``shortest_path_m``, ``time_limit_steps``, ``success`` (every waypoint reached, no collision).

    ## Arguments
    ``LidarNavEnv(config: NavEnvConfig | None = None, render_mode: "rgb_array" | None = None)``, or
    ``gymnasium.make("flightsim/LidarNav-v0", config=NavEnvConfig(...))``.

    ## Reset Options
    ``{"world": path or World}`` (with waypoints), or any of ``{"family": str, "world_seed": int,
    "difficulty": float}``: what is not given is drawn from ``self.np_random`` (family uniformly
    from ``config.families``, seed from :data:`flightsim.envs.seeds.TRAIN`, difficulty uniformly in
    ``config.difficulty_range``). Without options: ``config.world_file`` if set, else all drawn.

    ## Version History
    * v0: initial version (families, goal + velocity features, goal reward, path-proportional time
      limit). ``drift`` (off by default, so earlier configs keep their 365-float frame) adds the
      drift features; ``command`` (off by default too) adds the command features; ``firmware`` (off
      by default) adds the firmware feature; ``route`` (off by default) points the goal features
      along a route on the map of the scans so far, the same layout; ``tracking`` (on by default)
      keeps the returns of what moves out of the drift estimate and the route's map (where nothing
      is taken for moving, an episode is the same as without it); ``movers`` (off by default, needs
      ``tracking``) adds the tracked movers' features.
    """

    def __init__(self, config: NavEnvConfig | None = None, render_mode: str | None = None) -> None:
        """:param config: episode settings (defaults: :class:`NavEnvConfig`)
        :param render_mode: None or ``"rgb_array"`` (top-down, waypoints numbered, the current one
            highlighted)
        """
        config = config if config is not None else NavEnvConfig()
        if not isinstance(config, NavEnvConfig):
            raise TypeError(f"LidarNavEnv needs a NavEnvConfig, got {type(config).__name__}")
        super().__init__(config, render_mode)
        self.config: NavEnvConfig = config
        self.layout = config.layout
        low, high = self.layout.bounds()
        self.observation_space = spaces.Box(low, high, (self.layout.frame_size,), np.float32)
        if config.sideways:
            self.action_space = spaces.Box(-1.0, 1.0, (3,), np.float32)
        self.family = ""
        self.shortest_path_m = 0.0
        self.time_limit_steps = 0
        self._planned: dict[World, float] = {}
        self._drift = DriftEstimator(DriftConfig(max_range=config.scan.max_range))
        self._flown = np.zeros(2, np.float32)  # the action the last step flew (command features)
        self._route = RoutePlanner(config.route_planner, config.scan.max_range) if config.route else None
        self._tracker = ScanTracker(max_range=config.scan.max_range) if config.tracking else None
        self.tracked: TrackerOutput | None = None  # the newest frame's tracks (None: tracking off)

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        scan, info = super().reset(seed=seed, options=options)
        world = self.world
        if not world.waypoints:
            raise ValueError(f"world {world.name} has no waypoints: LidarNav-v0 needs at least one")
        self.shortest_path_m = self._shortest_path(world)
        self.time_limit_steps = time_limit_steps(self.shortest_path_m, self.config)
        self._waypoint = 0
        self._goal_distance = self._distance_to_goal()
        self._drift.reset()
        self._flown = np.zeros(2, np.float32)
        if self._route is not None:
            self._route.reset()
        if self._tracker is not None:
            self._tracker.reset()
        return self._frame(scan, info["measured_velocity_body"]), self._nav_info(info)

    def _split_action(self, action: np.ndarray) -> tuple[float, float, float]:
        """As the base env's; with ``sideways`` the third component is a speed to the left."""
        if not self.config.sideways:
            return super()._split_action(action)
        v0, v1, v2 = np.asarray(action, dtype=np.float32).reshape(3).tolist()
        return clip_unit(v0), clip_unit(v1), clip_unit(v2) * self.config.max_sideways_speed

    def _conclude(self, command: StepCommand, scan: np.ndarray):
        scan, reward, collided, truncated, info = super()._conclude(command, scan)
        finished = self._waypoint >= len(self.world.waypoints)
        terminated = collided or finished
        truncated = not terminated and (truncated or self._steps >= self.time_limit_steps)
        self._flown = command.action.copy()
        frame = self._frame(scan, info["measured_velocity_body"])
        return frame, reward, terminated, truncated, self._nav_info(info)

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array" or self.world is None:
            return None
        n = len(self.world.waypoints)
        title = (
            f"{self.world.name}  step {self._steps}/{self.time_limit_steps}  "
            f"waypoint {min(self._waypoint + 1, n)}/{n}  flown {self._distance:.1f} m"
        )
        return render_rgb(
            self.world, np.asarray(self._trajectory), scan=self._scan,
            pose=(self._state.position, self._state.yaw), scan_max_range=self.config.scan.max_range,
            vehicle_radius=self.config.vehicle_radius, collided=self._collided, title=title,
            active_waypoint=self._waypoint if self._waypoint < n else None, time=self.sim_time,
        )  # fmt: skip

    def shield_movers(self) -> dict[str, Any]:
        """The tracker's output for the newest frame (``tracking``), as the companion gives its shield:
        the moving bins and the movers in the body axes; empty with tracking off."""
        return {} if self.tracked is None else self.tracked.shield_inputs()

    def shield_drift(self) -> tuple[float, float] | None:
        """The newest frame's drift estimate less what the setpoint holds of it, as the companion
        gives the shield its own."""
        if not self.config.drift:
            return None
        forward, left = self._drift.bias.tolist()
        held_forward, held_left = self.drift_held()
        return forward - held_forward, left - held_left

    def shield_velocity(self) -> np.ndarray:
        """With ``drift``: the measured velocity less the newest frame's drift estimate, the true
        motion as the scans show it, as the companion's shield judges it (``_shield_motion``)."""
        measured = self.measured_body_velocity()
        return measured - self._drift.bias if self.config.drift else measured

    def drift_held(self) -> tuple[float, float]:
        """With ``drift_hold``: what the setpoint carries of the newest frame's drift estimate
        (:func:`companion.perception.drift.held_drift`)."""
        if not self.config.drift_hold:
            return 0.0, 0.0
        return held_drift(self._drift.bias, self.config.drift_hold_limits)

    @property
    def drift_estimate(self) -> np.ndarray:
        """(2,) the drift estimate of the newest frame (velocity estimate's error, body FLU, m/s):
        what the frame's drift features carry, unscaled (zeros without ``drift``)."""
        return self._drift.bias.copy()

    @property
    def last_command(self) -> np.ndarray:
        """(2,) the action the last step flew, after clipping and the shield (zeros at reset): what
        the command features carry, in action units, whether or not the layout has them."""
        return self._flown.copy()

    @property
    def waypoint_index(self) -> int:
        """The waypoint being flown to (``len(world.waypoints)`` once all are reached)."""
        return self._waypoint

    # ------------------------------------------------------------------ internals
    def _reward(self, outcome: StepOutcome) -> float:
        """Advance to the next waypoint when this one is reached, and pay for it (see the docstring)."""
        distance = self._distance_to_goal()
        progress = self._goal_distance - distance
        n = len(self.world.waypoints)
        reached = not outcome.collision and distance < self.config.acceptance_radius
        finished = reached and self._waypoint == n - 1
        if reached:
            self._waypoint += 1
            distance = self._distance_to_goal() if self._waypoint < n else 0.0
        self._goal_distance = distance
        return goal_reward(outcome, GoalStep(progress, reached, finished), self.config.goal_reward)

    def _choose_world(self, options: dict[str, Any]) -> World:
        unknown = sorted(set(options) - _NAV_OPTION_KEYS)
        if unknown:
            known = ", ".join(sorted(_NAV_OPTION_KEYS))
            raise ValueError(f"unknown reset option {unknown[0]!r}; known: {known}")
        if "world" in options or (self._fixed_world is not None and not options):
            if set(options) - {"world"}:
                raise ValueError("reset options: give either 'world' or 'family'/'world_seed'/'difficulty'")
            world = super()._choose_world(options)
            prefix = world.name.split("-")[0] + (DYNAMIC_SUFFIX if world.moving else "")
            self.family = prefix if prefix in ALL_FAMILIES else "custom"
            return world
        cfg, rng = self.config, self.np_random
        family = options.get("family")
        if family is None:
            family = cfg.families[int(rng.integers(len(cfg.families)))]
        seed = options.get("world_seed")
        if seed is None:
            seed = int(rng.integers(seeds.TRAIN.start, seeds.TRAIN.stop))
        difficulty = options.get("difficulty")
        if difficulty is None:
            difficulty = float(rng.uniform(*cfg.difficulty_range))
        self.family = str(family)
        return generate_family_world(
            self.family, int(seed), float(difficulty), vehicle_radius=cfg.vehicle_radius
        )

    def _shortest_path(self, world: World) -> float:
        """The world's stored shortest safe path, or planned now (world files carry none)."""
        if world.shortest_path_m is not None:
            return float(world.shortest_path_m)
        if world not in self._planned:  # a file flown every episode is planned once
            path = shortest_safe_path(world, vehicle_radius=self.config.vehicle_radius)
            if path is None:
                raise ValueError(
                    f"world {world.name}: no safe path through its waypoints for a vehicle radius of "
                    f"{self.config.vehicle_radius} m"
                )
            self._planned = {world: float(path.length)}
        return self._planned[world]

    def _distance_to_goal(self) -> float:
        goal = self.world.waypoints[self._waypoint]
        p = self._state.position
        return math.hypot(goal[0] - p[0], goal[1] - p[1])

    def _frame(self, scan: np.ndarray, velocity: np.ndarray) -> np.ndarray:
        """The observation at the current pose: ``scan`` and the goal features.

        :param velocity: the measured body velocity now (the info's, measured once a step)
        """
        n = len(self.world.waypoints)
        x, y, _ = self._state.position.tolist()
        yaw = float(self._state.yaw)
        moving = None
        if self._tracker is not None:  # as the companion: the scan, the pose, the time
            self.tracked = self._tracker.update(scan, (x, y, yaw), self.sim_time)
            moving = self.tracked.moving_bins
        goal = self.world.waypoints[min(self._waypoint, n - 1)]
        forward, left = goal_in_body(goal[0] - x, goal[1] - y, yaw)
        if self._waypoint >= n:  # done: the goal is where the vehicle is
            forward = left = 0.0
        toward = (forward, left)
        if self._route is not None:
            self._route.observe(scan, x, y, yaw, moving)
            if self._waypoint < n:
                subgoal = self._route.subgoal(x, y, yaw, goal[0], goal[1])
                toward = (subgoal.forward, subgoal.left)
        features = goal_features(*toward, *velocity.tolist(), self.layout)
        if self.layout.drift:
            static = scan if moving is None else without_movers(scan, moving)
            bias = self._drift.observe(static, velocity, forward, left, 1.0 / CONTROL_HZ)
            features = np.concatenate([features, drift_features(bias, self.layout)])
        if self.layout.command:
            forward, yaw_rate = self._flown.tolist()
            cfg = self.config
            sent = command_features(forward * cfg.max_speed, yaw_rate * cfg.max_yaw_rate, self.layout)
            features = np.concatenate([features, sent])
        if self.layout.firmware:
            ardupilot = self._response is not None and self._response.params.shapes_input
            features = np.concatenate([features, firmware_features(ardupilot, self.layout)])
        if self.layout.movers:  # the config makes sure the tracker runs
            assert self.tracked is not None
            features = np.concatenate([features, mover_features(self.tracked.movers(), self.layout)])
        return build_frame(scan, features, self.layout)

    def _nav_info(self, info: dict[str, Any]) -> dict[str, Any]:
        n = len(self.world.waypoints)
        info.update(
            family=self.family,
            waypoint=self._waypoint,
            waypoints=n,
            goal_distance=self._goal_distance,
            shortest_path_m=self.shortest_path_m,
            time_limit_steps=self.time_limit_steps,
            success=self._waypoint >= n and not self._collided,
        )
        return info
