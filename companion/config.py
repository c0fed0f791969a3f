"""The companion's one configuration object, loaded from TOML (``avoid-companion run --config``).

Each table of the file is one dataclass below (``[scan]``, ``[shield]`` and ``[supervisor]`` are
the pure modules' own config classes). Loading is strict (:mod:`companion.common.tomlconfig`): an unknown
key, a wrong type or a value out of range stops start-up with a message naming the dotted key.
Relative file paths (the model, the parameter file) written in the file are taken relative to the
file, so a deployment directory can be moved as a whole; those given on the command line
(``--set policy.model=...``) relative to the working directory, as a shell user expects.
``config/companion.example.toml`` documents every key.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import itertools
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from companion.autopilot.connection import Connection, parse_connection
from companion.autopilot.signing import load_signing_key
from companion.common.errors import UserError
from companion.common.tomlconfig import apply_overrides, from_dict, load_toml
from companion.guidance.route import RouteConfig
from companion.lidar.can_ring import CanConfig
from companion.perception.drift import DriftHoldConfig
from companion.perception.observation import ObservationLayout
from companion.perception.scan import N_BINS, ScanConfig
from companion.safety.shield import ShieldConfig
from companion.safety.supervisor import SupervisorConfig

#: Default connection per autopilot: pymavlink strings for ArduPilot, MAVSDK URLs for PX4.
DEFAULT_CONNECT = {"ardupilot": "udpin:0.0.0.0:14550", "px4": "udpin://0.0.0.0:14540"}


@dataclass(frozen=True)
class VelodyneConfig:
    """VLP-16 data packets over UDP.

    :param host: address to listen on (``0.0.0.0``: every interface)
    :param port: UDP data port (the sensor's default is 2368)
    :param decoder: ``numpy`` (the project's vectorised decoder) or ``velodyne-decoder`` (the C++
        package); both give the same cloud
    :param sensor_ip: the sensor's IPv4 address (factory default 192.168.1.201): datagrams from any
        other address are counted and dropped, as the ROS driver's ``device_ip`` does; empty accepts
        every sender (a warning at start-up)
    """

    host: str = "0.0.0.0"
    port: int = field(default=2368, metadata={"min": 1, "max": 65535})
    decoder: Literal["numpy", "velodyne-decoder"] = "numpy"
    sensor_ip: str = ""

    def __post_init__(self) -> None:
        if self.sensor_ip:
            try:
                ipaddress.IPv4Address(self.sensor_ip)
            except ValueError:
                raise ValueError(f"sensor_ip: {self.sensor_ip!r} is not an IPv4 address") from None


@dataclass(frozen=True)
class LidarConfig:
    """Where the point clouds come from.

    :param source: ``velodyne`` (VLP-16 UDP) or ``can`` (rangefinder ring)
    """

    source: Literal["velodyne", "can"] = "velodyne"
    velodyne: VelodyneConfig = field(default_factory=VelodyneConfig)
    can: CanConfig = field(default_factory=CanConfig)

    def __post_init__(self) -> None:
        if self.source == "can" and not self.can.sensors:
            raise ValueError("source is 'can' but can.sensors lists no rangefinder")


@dataclass(frozen=True)
class CompanionShieldConfig(ShieldConfig):
    """The drone's ``[shield]``: :class:`~companion.safety.shield.ShieldConfig` carrying the drift estimate.

    A student that flies sideways (one of the shipped pair) struck in three validation episodes
    behind the shield where the velocity estimate was wrong; carrying the estimate (0.6 m/s a side,
    while the brake or the keep-out acts) left none, and the shipped pair strikes in none behind
    it (docs/goal-policy.md). The clearance caps hold the true motion by the same estimate. The
    estimate comes from the goal frame's drift features (``policy.drift``); without them the
    shield carries nothing. Only the default differs from the class's: the env's
    ``shield_limits`` keeps 0, as LidarAvoid-v0 tracks no estimate.
    """

    drift_compensation: float = field(default=0.6, metadata={"min": 0.0, "max": 2.0})


@dataclass(frozen=True)
class PolicyConfig:
    """The ONNX policy and what it was trained with (checked against the model's metadata).

    :param model: path of the ``.onnx`` file (relative: to the config file)
    :param providers: ONNX Runtime providers to try in order; empty = TensorRT, CUDA, CPU,
        whichever are available
    :param stack: scans per observation (the training frame stack)
    :param max_speed: forward speed that action 1.0 stands for, m/s (as in training)
    :param max_yaw_rate: yaw rate that action 1.0 stands for, rad/s (as in training)
    :param max_sideways_speed: speed to the left that a third action value of 1.0 stands for, m/s:
        a model trained with ``env.sideways = true`` has one (1.0, the default: the shipped one
        does); 0: the action is forward and yaw rate only, as models before it. The metadata says
        which
    :param observation: the frame the model was trained on: ``goal`` (LidarNav-v0: the scan, the
        goal's bearing and distance, the measured body velocity / ``max_speed``) or ``scan``
        (LidarAvoid-v0: the scan alone); the model's metadata must say the same
    :param goal_range: metres a goal-distance feature of 1.0 stands for (``observation = "goal"``)
    :param drift: the frame also carries the drift estimate
        (:class:`companion.perception.drift.DriftEstimator`,
        from consecutive scans): a model trained with ``env.drift = true``, as the shipped one is;
        the metadata says which. Goal frames only: a scan frame has none, whatever this says
    :param command: the frame also carries the last setpoint sent (forward / ``max_speed``, yaw rate
        / ``max_yaw_rate``): a model trained with ``env.command = true``; the metadata says which.
        Goal frames only
    :param firmware: the frame also says which firmware flies the setpoints (1.0 for
        ``autopilot.type = "ardupilot"``, 0.0 for ``"px4"``): a model trained with
        ``env.firmware = true``; the metadata says which. Goal frames only
    :param movers: the frame also carries the 3 nearest movers the tracker reports, in the body
        axes: position / 10 m, velocity / 3 m/s, radius / 1 m, and a presence flag: a model
        trained with ``env.movers = true``; the metadata says which. Goal frames only; needs
        ``tracking.enabled`` and a goal source (the tracker places the scans at the autopilot's
        position)
    :param trt_cache_dir: directory for TensorRT's engine cache (empty: no cache; relative: to the
        config file); the service's StateDirectory is meant for it
    :param sha256: the model file's SHA-256 (64 hex digits, as ``avoid-train export`` prints it);
        when set, any other file is refused at start-up; empty: not checked (the hash is logged)
    """

    model: str = ""
    sha256: str = ""
    providers: tuple[str, ...] = ()
    trt_cache_dir: str = ""
    stack: int = field(default=4, metadata={"min": 1, "max": 64})
    max_speed: float = field(default=2.0, metadata={"min": 0.01, "max": 20.0})
    max_yaw_rate: float = field(default=1.5, metadata={"min": 0.01, "max": 6.0})
    max_sideways_speed: float = field(default=1.0, metadata={"min": 0.0, "max": 5.0})
    observation: Literal["goal", "scan"] = "goal"
    goal_range: float = field(default=30.0, metadata={"min": 1.0, "max": 100.0})
    drift: bool = True
    command: bool = False
    firmware: bool = False
    movers: bool = False

    @property
    def layout(self) -> ObservationLayout:
        """One frame as ``observation`` says, scaled as LidarNav-v0 scales it (``goal_range``, and
        ``max_speed`` for the velocity, ``max_yaw_rate`` for the yaw-rate command)."""
        goal = self.observation == "goal"
        return ObservationLayout(n_bins=N_BINS, goal=goal, goal_range=self.goal_range,
                                 velocity_scale=self.max_speed, drift=self.drift and goal,
                                 command=self.command and goal, yaw_rate_scale=self.max_yaw_rate,
                                 firmware=self.firmware and goal, movers=self.movers and goal)

    @property
    def sideways_speed(self) -> float:
        """m/s that the action's third value stands for: ``max_sideways_speed`` for a goal model, 0
        (two values) for a scan-only one, which LidarAvoid-v0 never gives a third."""
        return self.max_sideways_speed if self.observation == "goal" else 0.0

    def __post_init__(self) -> None:
        if self.sha256 and not re.fullmatch(r"[0-9a-fA-F]{64}", self.sha256):
            raise ValueError(f"sha256: {self.sha256!r} is not 64 hexadecimal digits")


@dataclass(frozen=True)
class AutopilotConfig:
    """The autopilot connection.

    :param type: ``ardupilot`` (pymavlink, GUIDED) or ``px4`` (MAVSDK, OFFBOARD)
    :param connect: a pymavlink string (``udpin:0.0.0.0:14550``, ``tcp:127.0.0.1:5760``, ``/dev/ttyTHS1``)
        or a MAVSDK URL (``udpin://0.0.0.0:14540``, ``serial:///dev/ttyTHS1:921600``), for either
        autopilot (:mod:`companion.autopilot.connection`); empty = the type's default
    :param baud: serial baud rate of a device path written without one
    :param source_system: MAVLink system id the companion sends as (the vehicle's own, normally 1)
    :param source_component: MAVLink component id (191 = MAV_COMP_ID_ONBOARD_COMPUTER)
    :param system_id: the autopilot's system id: the only system the companion listens to
    :param component_id: the autopilot's component id (1 = MAV_COMP_ID_AUTOPILOT1)
    :param signing_key: MAVLink 2 signing key file (64 hex digits, mode 0600; relative: to the
        config file); empty = no signing
    :param stream_rate_hz: rate asked for the status messages the supervisor needs
    :param obstacle_distance: send OBSTACLE_DISTANCE every scan (the autopilot's own avoidance layer)
    """

    type: Literal["ardupilot", "px4"] = "ardupilot"
    connect: str = ""
    baud: int = field(default=921600, metadata={"min": 1200, "max": 12_000_000})
    source_system: int = field(default=1, metadata={"min": 1, "max": 255})
    source_component: int = field(default=191, metadata={"min": 1, "max": 255})
    system_id: int = field(default=1, metadata={"min": 1, "max": 255})
    component_id: int = field(default=1, metadata={"min": 1, "max": 255})
    signing_key: str = ""
    stream_rate_hz: float = field(default=10.0, metadata={"min": 0.5, "max": 50.0})
    obstacle_distance: bool = True

    def __post_init__(self) -> None:
        # parse now: a bad string is a config error naming the key, not a failure at start-up
        _ = self.link

    @property
    def connection(self) -> str:
        """``connect``, or the type's default when empty."""
        return self.connect or DEFAULT_CONNECT[self.type]

    @property
    def link(self) -> Connection:
        """The connection parsed (pymavlink string or MAVSDK URL, for either autopilot)."""
        try:
            return parse_connection(self.connection, self.baud)
        except UserError as exc:
            raise ValueError(f"connect: {exc}") from None


@dataclass(frozen=True)
class ParamsCheckConfig:
    """Compare the autopilot's parameters with a reference file at start-up.

    :param mode: ``off``; ``warn`` (log + STATUSTEXT each mismatch, carry on); ``refuse`` (exit)
    :param file: ``.parm`` (ArduPilot) or ``.params`` (PX4) file (relative: to the config file);
        empty: the project's own file for ``autopilot.type`` (``firmware_params/``)
    :param timeout: how long to wait for the autopilot's parameters, s
    :param allow_missing: parameters this autopilot may lack (``params --allow-missing``: a SITL
        has no TELEM2, so ``["MAV_1_CONFIG", "SER_TEL2_BAUD"]`` on PX4 SITL); empty = all must exist
    """

    mode: Literal["off", "warn", "refuse"] = "off"
    file: str = ""
    timeout: float = field(default=30.0, metadata={"min": 1.0, "max": 600.0})
    allow_missing: tuple[str, ...] = ()


@dataclass(frozen=True)
class RuntimeConfig:
    """The main loop.

    :param poll_interval: longest wait for lidar data before servicing the autopilot link, s
    :param log_interval: period of the counters log line, s
    :param heartbeat_interval: period of the companion's HEARTBEAT, s
    """

    poll_interval: float = field(default=0.02, metadata={"min": 0.001, "max": 0.1})
    log_interval: float = field(default=30.0, metadata={"min": 1.0, "max": 3600.0})
    heartbeat_interval: float = field(default=1.0, metadata={"min": 0.1, "max": 5.0})


@dataclass(frozen=True)
class RecorderConfig:
    """The flight recorder (:mod:`companion.recording`): every flight to MCAP files, viewable in Foxglove.

    :param enabled: record (a recorder that cannot write turns itself off; the flight goes on)
    :param directory: where the ``flight-*.mcap`` files go (relative: to the config file); empty
        and enabled: :func:`default_recording_directory` (the service's logs directory, else the
        user's state directory)
    :param budget_mb: the recordings in ``directory`` never take more than this; the oldest go first
    :param file_mb: a file is closed and a new one started at this size
    :param cloud_decimation: 0 = no point cloud; N = every N-th point of each revolution (1 = all:
        ``avoid-companion replay`` then starts from the clouds themselves)
    :param queue_size: records waiting for the writer thread; beyond it they are dropped and counted
    """

    enabled: bool = False
    directory: str = ""
    budget_mb: float = field(default=2000.0, metadata={"min": 1.0, "max": 10_000_000.0})
    file_mb: float = field(default=100.0, metadata={"min": 1.0, "max": 100_000.0})
    cloud_decimation: int = field(default=0, metadata={"min": 0, "max": 100_000})
    queue_size: int = field(default=512, metadata={"min": 8, "max": 1_000_000})

    def __post_init__(self) -> None:
        if self.file_mb > self.budget_mb:
            raise ValueError(f"file_mb {self.file_mb:g} is larger than budget_mb {self.budget_mb:g}")


@dataclass(frozen=True)
class FixedWaypointConfig:
    """One configured waypoint, local NED metres from the autopilot's origin (EKF origin).

    :param acceptance_radius: reached within this, metres (0: ``goal.acceptance_radius``)
    """

    north: float = field(default=0.0, metadata={"min": -100_000.0, "max": 100_000.0})
    east: float = field(default=0.0, metadata={"min": -100_000.0, "max": 100_000.0})
    down: float = field(default=0.0, metadata={"min": -10_000.0, "max": 10_000.0})
    acceptance_radius: float = field(default=0.0, metadata={"min": 0.0, "max": 100.0})


@dataclass(frozen=True)
class GoalConfig:
    """Where the goal-directed policy's goal comes from (``[goal]``).

    :param source: ``none`` (no goal), ``fixed`` (``waypoints`` below) or ``mission`` (the mission
        uploaded to the autopilot, downloaded over MAVLink)
    :param waypoints: the ``fixed`` waypoints, in order
    :param acceptance_radius: a waypoint without its own radius is reached within this, metres
    :param acceptance_altitude: PX4: a mission item is reached within its radius horizontally and
        this vertically, metres (PX4's NAV_MC_ALT_RAD); ArduPilot judges the radius in 3D
    :param max_vertical_speed: bound of the climb/descent toward a waypoint's height, m/s
    :param height_hold: measure the height above the floor with the lidar's downward lasers and,
        while the autopilot's altitude estimate is off from it by more than ``height_tolerance``,
        climb or descend to the waypoint's height on the lidar's measure
    :param height_tolerance: the estimate's error the height hold lets pass, m
    :param on_complete: after the last waypoint: ``hold`` (zero velocity; the companion never
        changes the mode), or request ``land`` / ``rtl`` once
    :param download_timeout: wait for each mission-protocol reply, s
    :param download_retries: repeats of an unanswered mission request before the download fails
    :param route: the policy's goal features point along a route planned on a map of the scans
        (:class:`companion.guidance.route.RoutePlanner`), not straight at the waypoint: the evaluation's
        ``env.route``. Needs a goal source (the map lives in the autopilot's local frame)
    :param route_planner: that planner's tuning (``[goal.route_planner]``)
    """

    source: Literal["none", "fixed", "mission"] = "none"
    waypoints: tuple[FixedWaypointConfig, ...] = ()
    acceptance_radius: float = field(default=1.0, metadata={"min": 0.1, "max": 100.0})
    acceptance_altitude: float = field(default=0.8, metadata={"min": 0.05, "max": 100.0})
    max_vertical_speed: float = field(default=0.5, metadata={"min": 0.05, "max": 5.0})
    height_hold: bool = True
    height_tolerance: float = field(default=0.3, metadata={"min": 0.05, "max": 5.0})
    on_complete: Literal["hold", "land", "rtl"] = "hold"
    download_timeout: float = field(default=1.0, metadata={"min": 0.1, "max": 10.0})
    download_retries: int = field(default=5, metadata={"min": 0, "max": 50})
    route: bool = True
    route_planner: RouteConfig = field(default_factory=RouteConfig)

    def __post_init__(self) -> None:
        if self.source == "fixed" and not self.waypoints:
            raise ValueError("source is 'fixed' but waypoints lists none")


@dataclass(frozen=True)
class TrackingConfig:
    """Tracking what moves, from the scans (``[tracking]``):
    :class:`companion.perception.tracking.ScanTracker` on every scan, at the autopilot's local
    position and heading (LidarNav-v0's ``tracking``).

    :param enabled: track; the returns of what moves are kept out of the drift estimate and the
        route's map (a mover's motion is not the vehicle's, and where it stood is not an obstacle).
        Needs the autopilot's position, which only a goal source asks for: with ``goal.source =
        "none"`` nothing is tracked and nothing is kept out
    """

    enabled: bool = True


@dataclass(frozen=True)
class CompanionConfig:
    """Everything ``avoid-companion run`` needs; one table per field."""

    lidar: LidarConfig = field(default_factory=LidarConfig)
    scan: ScanConfig = field(default_factory=ScanConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    shield: CompanionShieldConfig = field(default_factory=CompanionShieldConfig)
    supervisor: SupervisorConfig = field(default_factory=SupervisorConfig)
    autopilot: AutopilotConfig = field(default_factory=AutopilotConfig)
    params_check: ParamsCheckConfig = field(default_factory=ParamsCheckConfig)
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)
    recorder: RecorderConfig = field(default_factory=RecorderConfig)
    goal: GoalConfig = field(default_factory=GoalConfig)
    drift_hold: DriftHoldConfig = field(default_factory=DriftHoldConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)

    def __post_init__(self) -> None:
        if self.goal.source != "none" and self.policy.observation == "scan":
            raise ValueError(
                f"goal.source = {self.goal.source!r} needs a goal policy (policy.observation = \"goal\"); "
                "a scan-only policy cannot fly to a goal"
            )
        if self.policy.layout.movers and not self.tracking.enabled:
            raise ValueError("policy.movers are the tracker's: it needs tracking.enabled = true")
        if self.policy.layout.movers and self.goal.source == "none":
            raise ValueError(
                'policy.movers needs a goal source (goal.source = "none"): the tracker places the scans '
                "at the autopilot's position, which only a goal source asks for"
            )


def model_policy_settings(meta: Mapping[str, str]) -> dict[str, Any]:
    """The ``[policy]`` values that feed a model what its metadata says it was trained on: the
    observation (``scan`` or ``goal``, with its drift, command, firmware and mover features), the stack
    and the action scales. A tool that flies any exported model (``avoid-sim fly``, ``demo``)
    configures the companion with them; the companion still checks the model against them.

    :param meta: the model's ``lidar_avoid.*`` metadata
        (:func:`~companion.guidance.policy.read_model_metadata`)
    :raises UserError: a scale that is not a number, or a layout the companion cannot build
    """
    from companion.guidance.policy import LEGACY_VALUES, PREFIX

    meta = {**LEGACY_VALUES, **meta}
    settings: dict[str, Any] = {}
    for key, kind in (("stack", int), ("max_speed", float), ("max_yaw_rate", float),
                      ("max_sideways_speed", float)):  # fmt: skip
        if PREFIX + key in meta:
            try:
                settings[key] = kind(float(meta[PREFIX + key]))
            except ValueError:
                raw = meta[PREFIX + key]
                raise UserError(f"model metadata {PREFIX}{key} = {raw!r} is not a number") from None
    wanted = meta[PREFIX + "obs_layout"]
    goal_range = re.search(r"distance/([0-9.]+)m\b", wanted)  # the name spells the goal's scale out
    if goal_range:
        settings["goal_range"] = float(goal_range.group(1))
    parts = ("drift", "command", "firmware", "movers")
    for observation, *flags in itertools.product(("scan", "goal"), *[(False, True)] * len(parts)):
        choice = {"observation": observation, **dict(zip(parts, flags, strict=True))}
        if PolicyConfig(**settings, **choice).layout.name == wanted:
            return {**settings, **choice}
    raise UserError(f"model observation layout {wanted} is not one the companion can feed")


def default_recording_directory(environ: Mapping[str, str] = os.environ) -> Path:
    """Where flights are recorded when ``recorder.directory`` is empty: ``flights`` in the
    service's logs directory (systemd's ``LogsDirectory=``, handed over as ``$LOGS_DIRECTORY``:
    /var/log/lidar-avoid), else in the user's state directory (``$XDG_STATE_HOME``, by default
    ~/.local/state) under ``lidar-avoid``: a run on a workstation writes nowhere it should not.

    :param environ: the environment to read
    """
    logs = environ.get("LOGS_DIRECTORY", "").split(":")[0]
    if logs:
        return Path(logs) / "flights"
    state = environ.get("XDG_STATE_HOME", "")
    base = Path(state) if state and Path(state).is_absolute() else Path.home() / ".local" / "state"
    return base / "lidar-avoid" / "flights"


def load_config(path: str | Path, overrides: list[str] | None = None) -> CompanionConfig:
    """Read, override (``key.sub=value``), check and complete the companion config.

    Relative paths (the model, the TensorRT cache, the signing key, the parameter file, the
    recordings) written in the file are taken from the file's directory, those in ``overrides``
    from the working directory.

    :param path: the TOML file
    :param overrides: command-line ``dotted.key=value`` items (value parsed as TOML)
    :raises UserError: naming the key that is unknown, ill-typed, out of range or missing
    """
    path = Path(path)
    overrides = list(overrides or [])
    data = apply_overrides(load_toml(path), overrides)
    config = from_dict(CompanionConfig, data)
    if not config.policy.model:
        raise UserError("policy.model: required (path of the ONNX policy)")
    base = path.resolve().parent
    given = {item.split("=", 1)[0].strip() for item in overrides}

    def resolve(key: str, p: str) -> str:
        if not p:
            return p
        expanded = Path(p).expanduser()
        return str((Path.cwd() if key in given else base) / expanded)  # an absolute one stays

    signing_key = resolve("autopilot.signing_key", config.autopilot.signing_key)
    if signing_key:
        load_signing_key(signing_key)  # a bad key file stops start-up here, before the model loads
    recordings = resolve("recorder.directory", config.recorder.directory)
    if not recordings and config.recorder.enabled:
        recordings = str(default_recording_directory())
    return dataclasses.replace(
        config,
        autopilot=dataclasses.replace(config.autopilot, signing_key=signing_key),
        policy=dataclasses.replace(
            config.policy,
            model=resolve("policy.model", config.policy.model),
            trt_cache_dir=resolve("policy.trt_cache_dir", config.policy.trt_cache_dir),
        ),
        params_check=dataclasses.replace(
            config.params_check, file=resolve("params_check.file", config.params_check.file)
        ),
        recorder=dataclasses.replace(config.recorder, directory=recordings),
    )
