"""The Gymnasium environment: fly a JSBSim quadrotor through a room on a ray-cast VLP-16 scan."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar, Literal

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from companion.perception.scan import N_BINS, ScanConfig, scan_from_points
from companion.safety.shield import SafetyShield, ShieldConfig, command_from_action
from flightsim.envs.raycast import LidarConfig, VLP16Raycaster
from flightsim.envs.reward import REWARDS, StepOutcome
from flightsim.vehicle.autopilot_response import AutopilotResponse, ResponseParams, fly, response_params
from flightsim.vehicle.quadrotor import Vehicle, VehicleConfig, VehicleState
from flightsim.worlds.render import render_rgb
from flightsim.worlds.world import World, generate_world, load_world

TRAIN_SEED_OFFSET = 1_000_000
"""Generated training worlds use seeds in ``[TRAIN_SEED_OFFSET, 2**31)``; evaluation keeps the
seeds below it as held-out worlds the policy never trained on."""
SEED_LIMIT = 2**31
VEHICLE_MASS_KG = 1.5
#: control steps per second: one env step is one scan and one setpoint
CONTROL_HZ = 10
#: the seconds before a collision over which the moving obstacle hit is asked whether it kept its
#: velocity: a path's corner turns it at once, beyond the shield's ``mover_accel`` (3 m/s², a turn
#: back at 1.5 m/s takes a second), and the gate's worst case looks about this far ahead
MOVER_STEADY_WINDOW_S = 2.0
_OPTION_KEYS = {"world", "world_seed", "difficulty", "room_width"}


@dataclass(frozen=True)
class EnvConfig:
    """Everything that shapes an episode (strict-loadable with ``companion.common.tomlconfig.from_dict``).

    :param world_file: fly this world file every episode; None = a generated world per episode
    :param difficulty: of generated worlds, 0 (3 obstacles, big room) … 1 (10, narrow gaps)
    :param max_steps: episode length before truncation (10 steps = 1 s)
    :param vehicle_radius: collision when the nearest geometry is closer than this, metres
    :param max_speed: forward speed commanded by ``a0 = 1``, m/s
    :param max_yaw_rate: yaw rate commanded by ``a1 = 1``, rad/s counter-clockwise
    :param lidar: the simulated sensor (range noise and dropout live here)
    :param scan: the companion's scan geometry (the same code the drone flies)
    :param reward: ``"progress"`` (pays for flying) or ``"tutorial"`` (the seed tutorial's)
    :param mount_yaw_error_deg: domain randomisation: the sensor is mounted up to ± this many
        degrees off in yaw, drawn per episode (the scan does not know)
    :param latency_scans: domain randomisation: 1 = the observation is the previous step's scan
    :param mass_jitter: domain randomisation: take-off mass within ± this fraction of 1.5 kg
    :param wind_gust_max: domain randomisation: horizontal gusts up to this speed, m/s, each
        held 1–3 s
    :param shield: fly every action through the companion's safety shield (``shield_limits``)
        against the scan the policy saw, as the drone does; the reward sees what flew
    :param unshielded_fraction: with ``shield``, this fraction of the episodes (drawn per episode)
        flies without it, so a policy trained here cannot lean on the shield to stay clear
    :param overspeed_penalty: reward cost per step of asking for more forward speed than the
        shield lets through (:meth:`SafetyShield.forward_cap`), per ``max_speed`` of excess: a
        policy trained behind the shield then brakes by itself instead of leaving it to the shield
    :param overspeed_travel: the cap of ``overspeed_penalty`` also watches the measured velocity,
        as the shield does in flight: the clearance from the course round to the nose, and 0 where
        the shield would brake against the motion (:meth:`SafetyShield.forward_cap` given the
        velocity); off: the nose sector alone, as every run before it was trained
    :param autopilot_response: how the autopilot answers the setpoints
        (:mod:`flightsim.vehicle.autopilot_response`):
        ``"ideal"`` flies them as given (the vehicle of every result so far), ``"px4"`` and
        ``"ardupilot"`` as those firmwares do (calibrated on recordings of real SITL), ``"random"``
        a response drawn per episode over both firmwares plus a margin (domain randomisation)
    :param shield_limits: the limits of that shield and of the ``overspeed_penalty``'s cap, as the
        companion config's ``[shield]`` table gives them to the drone (the ``[env.shield_limits]``
        table of a training config); ``drift_compensation`` needs a drift estimate, which only
        ``LidarNav-v0`` with ``drift`` keeps
    """

    world_file: str | None = None
    difficulty: float = field(default=0.5, metadata={"min": 0.0, "max": 1.0})
    max_steps: int = field(default=1000, metadata={"min": 1})
    vehicle_radius: float = field(default=0.25, metadata={"min": 0.05, "max": 2.0})
    max_speed: float = field(default=2.0, metadata={"min": 0.1, "max": 10.0})
    max_yaw_rate: float = field(default=1.5, metadata={"min": 0.1, "max": 2.0})
    lidar: LidarConfig = field(default_factory=LidarConfig)
    scan: ScanConfig = field(default_factory=ScanConfig)
    reward: Literal["progress", "tutorial"] = "progress"
    mount_yaw_error_deg: float = field(default=0.0, metadata={"min": 0.0, "max": 45.0})
    latency_scans: int = field(default=0, metadata={"min": 0, "max": 1})
    mass_jitter: float = field(default=0.0, metadata={"min": 0.0, "max": 0.4})
    wind_gust_max: float = field(default=0.0, metadata={"min": 0.0, "max": 8.0})
    shield: bool = False
    unshielded_fraction: float = field(default=0.0, metadata={"min": 0.0, "max": 1.0})
    overspeed_penalty: float = field(default=0.0, metadata={"min": 0.0, "max": 100.0})
    overspeed_travel: bool = False
    autopilot_response: Literal["ideal", "px4", "ardupilot", "random"] = "ideal"
    shield_limits: ShieldConfig = field(default_factory=ShieldConfig)

    def __post_init__(self) -> None:
        if self.shield_limits.drift_compensation > 0.0 and not self.keeps_drift_estimate:
            raise ValueError(
                "shield_limits.drift_compensation needs a drift estimate: LidarNav-v0 with drift = true"
            )

    @property
    def keeps_drift_estimate(self) -> bool:
        """Whether the env tracks the drift estimate the shield's ``drift_compensation`` carries."""
        return False


@dataclass(frozen=True)
class StepCommand:
    """What one step flies, decided before the flight (:meth:`LidarAvoidEnv._command`).

    :param action: the action after clipping and the shield, ``(a0, a1)`` float32
    :param forward: commanded forward speed, m/s
    :param yaw_rate: commanded yaw rate, rad/s CCW
    :param lateral: commanded velocity to the left, m/s (the shield's brake; usually 0)
    :param overspeed: forward speed asked beyond the shield's cap, per ``max_speed``
    """

    action: np.ndarray
    forward: float
    yaw_rate: float
    lateral: float
    overspeed: float


def clip_unit(v: float) -> float:
    """Clip to [-1, 1]; NaN becomes 0 (a broken policy output must not become a command)."""
    return 0.0 if v != v else min(1.0, max(-1.0, v))


def slice_band(scan: ScanConfig) -> tuple[np.ndarray, float, float]:
    """The ``keep_band`` of :func:`flightsim.envs.raycast.grid_to_points` for a scan's height slice.

    Points the scan's slice drops anyway are not materialised: the scan is identical and cheaper.
    With the sensor mounted level at the body origin (the default) the band is the slice test
    itself to the bit (``|z| <`` the same float32 bound), so the scan keeps every point it gets
    and skips its own selection; otherwise it is the slice with the nominal mount, widened by
    1 mm against float32/float64 rounding.

    :param scan: the scan geometry
    """
    mount = scan.rotation()
    if scan.mount_rpy_deg == (0.0, 0.0, 0.0) and scan.mount_xyz == (0.0, 0.0, 0.0):
        return mount[2], 0.0, float(np.float32(scan.slice_height))
    return mount[2], float(scan.mount_xyz[2]), scan.slice_height + 1e-3


def _rz(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class LidarAvoidEnv(gym.Env):
    """Fly forward through a room of obstacles on a 360° lidar scan without touching anything.

    ## Description
    A 1.5 kg quadrotor simulated by JSBSim and flown by an autopilot-like cascaded controller
    holds its start altitude in a walled room with boxes and cylinders (a world file or a world
    generated from a seed and a difficulty). A ray-cast Velodyne VLP-16 (16 lasers, −15°…+15°)
    sees the room; the companion computer's own ``scan_from_points`` turns its point cloud into
    the observation, exactly as on the drone. Each step is 0.1 s (10 Hz control).

    ## Action Space
    ``Box(-1, 1, (2,), float32)``: ``a0`` forward speed × ``max_speed`` (2.0 m/s; negative flies
    backwards), ``a1`` yaw rate × ``max_yaw_rate`` (1.5 rad/s), counter-clockwise positive (FLU).
    Out-of-range values are clipped, NaN counts as 0.

    ## Observation Space
    ``Box(0, 1, (360,), float32)``: bin ``i`` is the nearest return in ``[i°, i+1°)``
    counter-clockwise from the nose (bin 90 = left, 270 = right), horizontal range / 10 m,
    1.0 = nothing in range; only returns within ±0.5 m of the sensor's height count. Frame
    stacking (4 scans in the project) is the training code's ``VecFrameStack``.

    ## Rewards
    ``config.reward`` selects one of :mod:`flightsim.envs.reward`:
    ``"progress"`` (default): forward speed flown / max speed, minus the proximity penalty
    ``(0.1 − min(scan))·10`` inside 1 m, minus ``0.05·|a1|``, minus 0.1 while slower than 0.2 m/s;
    collision −100. ``"tutorial"``: the seed tutorial's (+1 survival, +0.5·a0 forward, the same
    proximity penalty, −0.2 sharp turn, collision −200). Success is flying ≥ 40 m in 100 s without
    a collision: the tutorial's reward lets a hovering policy score well, "progress" does not.
    With ``overspeed_penalty`` > 0, asking for more forward speed than the safety shield would let
    through costs that much per step per ``max_speed`` of excess, with or without the shield (with
    ``overspeed_travel``, what it would let through given the measured velocity too).

    ## Starting State
    Hovering at the world's start position and heading, motors at hover thrust, zero velocity.

    ## Episode End
    Terminated on collision: the geometric clearance from the vehicle's centre to any wall or
    obstacle drops below ``vehicle_radius`` (0.25 m). Truncated after ``max_steps`` (1000 = 100 s).

    ## Info
    ``collision`` (bool), ``min_distance`` (current clearance, m), ``distance`` (path flown so far,
    m), ``position`` ((3,) world ENU, m), ``yaw`` (rad, CCW from +x), ``world`` (its name),
    ``steps``, ``measured_velocity_body`` ((2,) forward, left m/s: what the autopilot would report,
    estimate error included, see :meth:`LidarAvoidEnv.measured_body_velocity`),
    ``collision_mover_speed`` (on a collision with a moving obstacle, its speed, m/s; else None),
    ``collision_mover_steady_s`` (then, how long it had kept its velocity before the contact, up to
    :data:`MOVER_STEADY_WINDOW_S`, s; else None).

    ## Arguments
    ``LidarAvoidEnv(config: EnvConfig | None = None, render_mode: "rgb_array" | None = None)``, or
    ``gymnasium.make("flightsim/LidarAvoid-v0", config=EnvConfig(...))``. Domain randomisation
    (range noise, dropout, mount yaw error, one-scan latency, mass jitter, wind gusts) is off by
    default; see :class:`EnvConfig`.

    ## Reset Options
    ``reset(seed=..., options=...)`` is deterministic for a seed. ``options`` may hold
    ``{"world": path or World}`` or ``{"world_seed": int, "difficulty": float}`` (either key
    alone; the other comes from the config or ``self.np_random``), optionally with
    ``"room_width": float`` (a generated room only that wide, metres, ≥ 6). Without options the world is
    ``config.world_file`` if set, else a fresh generated one with a seed drawn from
    ``self.np_random`` in ``[TRAIN_SEED_OFFSET, 2**31)``: seeds below ``TRAIN_SEED_OFFSET`` are
    held out for evaluation.

    ## Version History
    * v0: initial version (JSBSim vehicle, VLP-16 ray caster, companion scan, "progress" reward).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, config: EnvConfig | None = None, render_mode: str | None = None) -> None:
        """:param config: episode settings (defaults: :class:`EnvConfig`)
        :param render_mode: None or ``"rgb_array"`` (a top-down picture, see :mod:`flightsim.worlds.render`)
        """
        self.config = config if config is not None else EnvConfig()
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            modes = self.metadata["render_modes"]
            raise ValueError(f"render_mode must be one of {modes} or None, got {render_mode!r}")
        self.render_mode = render_mode
        self.observation_space = spaces.Box(0.0, 1.0, (N_BINS,), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
        self._vehicle = Vehicle(VehicleConfig(mass_kg=VEHICLE_MASS_KG, physics_hz=120, control_hz=CONTROL_HZ))
        self._caster = VLP16Raycaster(self.config.lidar)
        cfg = self.config
        self._shield: SafetyShield | None = None
        if cfg.shield or cfg.overspeed_penalty > 0.0:
            self._shield = SafetyShield(cfg.shield_limits, cfg.scan.max_range, cfg.autopilot_response)
        self._fixed_world = load_world(self.config.world_file) if self.config.world_file else None
        self._scan_mount = self.config.scan.rotation()
        self._mount_xyz = np.asarray(self.config.scan.mount_xyz, dtype=np.float64)
        self._slice_band = slice_band(self.config.scan)
        self.world: World | None = None  # the current episode's
        self.mount_yaw_error_deg = 0.0  # the sensor's yaw error drawn for the current episode, CCW

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        self.world = self._choose_world(options or {})
        cfg, rng = self.config, self.np_random
        self.mount_yaw_error_deg = float(rng.uniform(-cfg.mount_yaw_error_deg, cfg.mount_yaw_error_deg))
        self._sensor_to_body = _rz(math.radians(self.mount_yaw_error_deg)) @ self._scan_mount
        mass = VEHICLE_MASS_KG * (1.0 + rng.uniform(-cfg.mass_jitter, cfg.mass_jitter))
        start = np.asarray(self.world.start_position, dtype=np.float64)
        yaw0 = math.radians(self.world.start_yaw_deg)
        self._state = self._vehicle.reset(start, yaw0, mass_kg=mass)
        self._response = None
        params = response_params(cfg.autopilot_response, rng)
        if params is not None:  # drawn only when used (same streams for "ideal")
            self._response = AutopilotResponse(params, rng)
            self._response.reset(yaw0)
        self._altitude = float(start[2])
        self._wind_steps_left = 0
        if cfg.wind_gust_max > 0.0:
            self._update_wind()
        self._steps = 0
        self._distance = 0.0
        self._collided = False
        # a moving obstacle collided with: its speed, m/s, and how long it had kept its velocity, s
        self._mover_hit: tuple[float, float] | None = None
        self._clearance = self.world.clearance_at(self._state.position, self.sim_time)
        self._trajectory = [self._state.position.copy()]
        self._scan = self._fresh_scan()
        self._previous_scan = self._scan
        self._shielded = self.config.shield
        if self._shielded and cfg.unshielded_fraction > 0.0:  # drawn only when used (same streams)
            self._shielded = bool(rng.uniform() >= cfg.unshielded_fraction)
        if self._shield is not None:
            self._shield.reset()
        self._lateral = 0.0
        return self._scan.copy(), self._info()

    def step(self, action: np.ndarray):
        command = self._command(action)
        state = fly(
            self._vehicle, self._response, command.forward, command.yaw_rate,
            altitude=self._altitude, duration=1.0 / CONTROL_HZ, lateral=command.lateral,
        )  # fmt: skip
        self._arrive(state)
        return self._conclude(command, self._fresh_scan())

    # The three phases of a step. ``step`` runs them with this env's own vehicle and lidar; the
    # batched env (flightsim.envs.batch_env) runs the same phases for N envs and flies and scans all N
    # in between in compiled batches, so both are one code path apart from those two.
    def _command(self, action: np.ndarray) -> StepCommand:
        """Before the flight: clip the action, apply the shield, the overspeed cost, the wind."""
        if self.world is None:
            raise RuntimeError("call reset() before step()")
        a0, a1, sideways = self._split_action(action)
        cfg = self.config
        seen = self._previous_scan if cfg.latency_scans else self._scan
        # as in flight: the shield also watches the velocity the autopilot measures (read only when used)
        velocity = None
        if self._shielded or (cfg.overspeed_penalty > 0.0 and cfg.overspeed_travel):
            measured = self.shield_velocity()
            velocity = (float(measured[0]), float(measured[1]))
        overspeed = 0.0
        if cfg.overspeed_penalty > 0.0:
            travel = cfg.overspeed_travel
            drift = self.shield_drift() if travel else None
            cap = self._shield.forward_cap(seen, velocity if travel else None, drift)
            overspeed = max(0.0, a0 - cap / cfg.max_speed)
        lateral, self._lateral = self._lateral + sideways, 0.0
        if self._shielded:
            request = command_from_action((a0, a1), cfg.max_speed, cfg.max_yaw_rate)
            safe = self._shield.filter(
                replace(request, lateral=sideways),
                seen,
                1.0 / CONTROL_HZ,
                velocity=velocity,
                drift=self.shield_drift(),
                heading=self.shield_heading(),
                **self.shield_movers(),
            )
            a0, a1 = safe.forward / cfg.max_speed, safe.yaw_rate / cfg.max_yaw_rate
            lateral = safe.lateral
        if cfg.wind_gust_max > 0.0:
            self._update_wind()
        action = np.array([a0, a1], dtype=np.float32)
        held_forward, held_left = self.drift_held()
        forward = a0 * cfg.max_speed + held_forward
        return StepCommand(action, forward, a1 * cfg.max_yaw_rate, lateral + held_left, overspeed)

    def _split_action(self, action: np.ndarray) -> tuple[float, float, float]:
        """``(a0, a1)`` clipped, and the sideways speed the action asks for, m/s (none here)."""
        v0, v1 = np.asarray(action, dtype=np.float32).reshape(2).tolist()
        return clip_unit(v0), clip_unit(v1), 0.0

    def shield_heading(self) -> float:
        """The heading a shield watching this env reads, rad counter-clockwise: the vehicle's, as
        the autopilot's attitude estimate reports it."""
        return float(self._state.yaw)

    def shield_drift(self) -> tuple[float, float] | None:
        """The drift estimate a shield's ``drift_compensation`` carries (body forward, left, m/s),
        for this env's own shield and evaluation's; None: this env keeps none."""
        return None

    def shield_movers(self) -> dict[str, Any]:
        """What moves in the newest frame's scan, as the companion gives its shield (the ``moving_bins``
        and ``movers`` keywords of :meth:`~companion.safety.shield.SafetyShield.filter`); empty: this
        env tracks nothing."""
        return {}

    def drift_held(self) -> tuple[float, float]:
        """What the next setpoint carries of the drift estimate on top of its command (body forward,
        left, m/s), as the companion's ``[drift_hold]`` does; (0, 0): this env holds none."""
        return 0.0, 0.0

    def shield_velocity(self) -> np.ndarray:
        """The velocity a shield judges the motion by (body forward, left, m/s), as the companion
        gives its own: the measured one (this env keeps no drift estimate to take off it)."""
        return self.measured_body_velocity()

    def _arrive(self, state: VehicleState) -> None:
        """After the flight: the new pose, the path flown, the clearance and collision."""
        previous = self._state.position
        self._state = state
        position = state.position
        self._distance += math.dist(position.tolist(), previous.tolist())
        self._trajectory.append(position.copy())
        self._steps += 1
        self._clearance = self.world.clearance_at(position, self.sim_time)
        self._collided = self._clearance < self.config.vehicle_radius
        if self._collided and self.world.moving:
            p = np.asarray(position, dtype=np.float64)[:3].reshape(1, 3)
            hit = [
                m for m in self.world.moving if m.clearance(p, self.sim_time)[0] < self.config.vehicle_radius
            ]
            if hit:
                mover = max(hit, key=lambda m: m.speed)
                self._mover_hit = (mover.speed, mover.steady_for(self.sim_time, MOVER_STEADY_WINDOW_S))

    def _conclude(self, command: StepCommand, scan: np.ndarray):
        """With the fresh scan from the new pose: reward, observation, episode end, info."""
        cfg = self.config
        self._previous_scan, self._scan = self._scan, scan
        outcome = StepOutcome(
            action=command.action,
            scan_min=float(self._scan.min()),
            forward_speed=self._state.forward_speed,
            max_speed=cfg.max_speed,
            collision=self._collided,
        )
        reward = self._reward(outcome) - cfg.overspeed_penalty * command.overspeed
        observation = self._previous_scan if cfg.latency_scans else self._scan
        truncated = self._steps >= cfg.max_steps and not self._collided
        return observation.copy(), reward, self._collided, truncated, self._info()

    def command_lateral(self, lateral: float) -> None:
        """Fly ``lateral`` (m/s, body left) with the next step's action: the companion shield's
        active brake against a sideways slide, which the policy's 2-D action cannot carry."""
        self._lateral = float(lateral)

    @property
    def response_params(self) -> ResponseParams | None:
        """The autopilot response drawn for this episode (None: the ideal one); evaluation reports
        it per episode, so a failure can be traced to the response it flew."""
        return None if self._response is None else self._response.params

    @property
    def response(self) -> AutopilotResponse | None:
        """The firmware response model flying this episode (None: the ideal autopilot). Privileged,
        as :attr:`true_state`: a teacher may predict with it, a policy never reads it."""
        return self._response

    @property
    def true_state(self) -> VehicleState:
        """The vehicle as it truly is now (privileged: a teacher may read it, a policy never does)."""
        return self._state

    @property
    def estimate_error(self) -> np.ndarray:
        """(2,) the autopilot's velocity-estimate error now, world ENU m/s (reported = true + this;
        zeros for the ideal response). Privileged, as :attr:`true_state`."""
        return np.zeros(2) if self._response is None else self._response.estimate_error

    def measured_body_velocity(self) -> np.ndarray:
        """The horizontal velocity the autopilot would report now: (forward, left) m/s, body FLU.

        With an autopilot response it carries that firmware's estimate error; ideal: the truth.
        """
        if self.world is None:
            raise RuntimeError("call reset() before measured_body_velocity()")
        if self._response is not None:
            return self._response.measured_body_velocity(self._state)
        return self.true_body_velocity()

    def true_body_velocity(self) -> np.ndarray:
        """The horizontal velocity the vehicle truly has: (forward, left) m/s, body FLU. Privileged,
        as :attr:`true_state` (a trace shows it beside :meth:`measured_body_velocity`)."""
        c, s = math.cos(self._state.yaw), math.sin(self._state.yaw)
        vx, vy = float(self._state.velocity[0]), float(self._state.velocity[1])
        return np.array([c * vx + s * vy, -s * vx + c * vy])

    def render(self) -> np.ndarray | None:
        if self.render_mode != "rgb_array" or self.world is None:
            return None
        title = f"{self.world.name}  step {self._steps}  flown {self._distance:.1f} m"
        return render_rgb(
            self.world, np.asarray(self._trajectory), scan=self._scan,
            pose=(self._state.position, self._state.yaw), scan_max_range=self.config.scan.max_range,
            vehicle_radius=self.config.vehicle_radius, collided=self._collided, title=title,
            time=self.sim_time,
        )  # fmt: skip

    def close(self) -> None:
        self._vehicle.close()
        super().close()

    # ------------------------------------------------------------------ internals
    def _reward(self, outcome: StepOutcome) -> float:
        """This step's reward before the overspeed penalty (LidarNavEnv pays for its goals here)."""
        return float(REWARDS[self.config.reward](outcome))

    def _choose_world(self, options: dict[str, Any]) -> World:
        unknown = sorted(set(options) - _OPTION_KEYS)
        if unknown:
            raise ValueError(f"unknown reset option {unknown[0]!r}; known: {', '.join(sorted(_OPTION_KEYS))}")
        if "world" in options:
            if set(options) & {"world_seed", "difficulty", "room_width"}:
                raise ValueError("reset options: give either 'world' or 'world_seed'/'difficulty', not both")
            world = options["world"]
            if isinstance(world, World):
                return world
            if isinstance(world, (str, Path)):
                return load_world(world, vehicle_radius=self.config.vehicle_radius)
            raise ValueError(f"reset option 'world' must be a path or a World, got {type(world).__name__}")
        if self._fixed_world is not None and not options:
            return self._fixed_world
        seed = options.get("world_seed")
        if seed is None:
            seed = int(self.np_random.integers(TRAIN_SEED_OFFSET, SEED_LIMIT))
        difficulty = float(options.get("difficulty", self.config.difficulty))
        room_width = options.get("room_width")
        return generate_world(
            int(seed),
            difficulty,
            self.config.vehicle_radius,
            room_width=None if room_width is None else float(room_width),
        )

    def _sensor_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The lidar's origin (world ENU, m) and sensor-to-world rotation at the current pose."""
        body = self._state.rotation()
        return self._state.position + body @ self._mount_xyz, body @ self._sensor_to_body

    def _fresh_scan(self) -> np.ndarray:
        """Cast the lidar from the current pose and reduce it with the companion's scan code."""
        origin, rotation = self._sensor_pose()
        points = self._caster.cast_points(
            self.world, origin, rotation, self.np_random, self._slice_band, self.sim_time
        )
        return scan_from_points(points, self.config.scan)

    @property
    def sim_time(self) -> float:
        """Seconds since the episode began (where the world's moving obstacles are), 0.1 s a step."""
        return self._steps / CONTROL_HZ

    def _update_wind(self) -> None:
        """Piecewise-constant horizontal gusts: a new random wind every 1–3 s."""
        if self._wind_steps_left <= 0:
            rng = self.np_random
            speed = rng.uniform(0.0, self.config.wind_gust_max)
            heading = rng.uniform(0.0, 2.0 * math.pi)
            self._wind = np.array([speed * math.cos(heading), speed * math.sin(heading), 0.0])
            self._vehicle.set_wind(self._wind)
            self._wind_steps_left = int(rng.integers(10, 31))
        self._wind_steps_left -= 1

    def _info(self) -> dict[str, Any]:
        position = self._state.position
        return {
            "collision": self._collided,
            "min_distance": float(self._clearance),
            "distance": self._distance,
            "position": position.copy(),
            "yaw": float(self._state.yaw),
            "world": self.world.name,
            "steps": self._steps,
            "measured_velocity_body": self.measured_body_velocity(),
            "collision_mover_speed": None if self._mover_hit is None else self._mover_hit[0],
            "collision_mover_steady_s": None if self._mover_hit is None else self._mover_hit[1],
        }
