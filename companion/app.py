"""``avoid-companion run``: the companion process. Wiring and the main loop, nothing else.

Start-up: load the config, the policy (refusing a model that does not match), the lidar source,
the optional autopilot parameter check, then the autopilot link; READY=1 to systemd.

The loop (one thread, ``select()`` on the lidar socket with a short timeout so the link is
serviced even when the lidar is silent):

- the newest finished revolution of the iteration: scan → tracker (``[tracking]``: what moves, at
  the autopilot's pose) → frame (the scan; for a goal policy also the goal and the measured
  velocity, none while the goal holds or the velocity is stale; the moving returns kept out of the
  drift estimate and the route's map) → frame stack → policy → supervisor.on_scan
  (older ones that arrived in the same read are counted as skipped: the work per iteration stays
  one scan, however much arrived; the lidar source bounds its own reading in time and count). A
  source that saw more revolutions than the sensor can make reports ``implausible``: a fault for
  the supervisor ("lidar implausible" → HOLD).
- the link's vehicle status → supervisor.on_vehicle; supervisor.tick() says what to send:
  POLICY → the shielded policy setpoint (every scan; the last one again when no scan came for
  LATE_SCAN_AFTER, so the stream never pauses while a scan is late: the autopilot would keep
  flying it anyway, and the lidar-stale timeout still holds), ZERO → zero velocity (every scan,
  and at 10 Hz without scans), NONE → no setpoint; then OBSTACLE_DISTANCE for the newest scan
- HEARTBEAT at 1 Hz; every supervisor transition: one log line, one STATUSTEXT
- WATCHDOG=1 after every iteration that completed; a periodic counters log line

Nothing a packet or the autopilot sends may end the process in the air: each iteration's faults
are caught, counted and logged. SIGTERM/SIGINT only wake the loop (``signal.set_wakeup_fd``); the
loop then sends a zero-velocity setpoint if it was commanding, and exits 0.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import select
import signal
import time
from collections import Counter
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from companion.autopilot.connection import ensure_port_free
from companion.autopilot.link import AutopilotLink, VehicleStatus
from companion.autopilot.obstacle_distance import obstacle_distance_allowed, obstacle_distance_from_scan
from companion.common.errors import UserError
from companion.common.tomlconfig import to_dict
from companion.config import CompanionConfig, load_config
from companion.guidance.goal import GoalOutput, NavInputs
from companion.guidance.goal_source import (
    GOAL_STREAMS,
    GoalSource,
    completion_mode_command,
    reached_message,
    request_message,
)
from companion.guidance.policy import InferenceFault, OnnxPolicy, PolicySpec
from companion.guidance.route import RoutePlanner, enu_pose
from companion.notify import SystemdNotifier
from companion.perception.drift import DriftConfig, DriftEstimator, held_drift
from companion.perception.framestack import FrameStack
from companion.perception.observation import (
    build_frame,
    command_features,
    drift_features,
    firmware_features,
    goal_features,
    mover_features,
)
from companion.perception.scan import BIN_CONVENTION, N_BINS, scan_from_points
from companion.perception.tracking import ScanTracker, TrackerOutput, without_movers
from companion.recording.recorder import FlightRecorder, open_recorder
from companion.recording.taps import tap_parts
from companion.safety.shield import Command, SafetyShield, command_from_action
from companion.safety.supervisor import CommandKind, Supervisor, SupervisorState, Transition

log = logging.getLogger(__name__)

#: Zero setpoints (HOLD, and PX4's pre-OFFBOARD stream) go out at least this often without scans, s.
ZERO_SETPOINT_PERIOD = 0.1
#: While ACTIVE and no scan came for this long after the last setpoint (the scan is lost, partial or
#: withheld), the last setpoint goes out again rather than none, s. Not a new decision on an old
#: picture: the autopilot keeps flying the last setpoint it got, and supervisor.lidar_timeout (0.3 s)
#: still ends it with HOLD.
LATE_SCAN_AFTER = 0.12
#: while no autopilot has been heard, a line saying so, with the address listened on, this often (s)
WAITING_LOG_INTERVAL = 5.0

#: After an iteration whose lidar read stopped at its bounds with datagrams still waiting (a flood),
#: the loop pauses this long, s: it reads at most about half the time instead of spinning, so a
#: flood cannot take the whole processor (run SCHED_FIFO, the companion would starve the kernel's
#: own threads, ksoftirqd among them, and its own datagrams with them). The kernel drops the excess.
BACKLOG_PAUSE = 0.005
#: The supervisor's HOLD reason when a goal frame cannot be built for want of a measured velocity.
VELOCITY_STALE = "velocity stale"
#: Watchdog ping period when systemd does not say (WATCHDOG_USEC unset), s.
DEFAULT_WATCHDOG_PERIOD = 1.0
#: With ``goal.source = "none"``, a goal policy flies toward a goal this far ahead along the current
#: heading, m: it moves with the vehicle, so the vehicle flies forward and avoids, as a scan-only
#: policy does (20 m: well inside the distance feature's range, far beyond the lidar's).
GOAL_AHEAD_M = 20.0

# MAV_SEVERITY of the STATUSTEXT for a transition into each state.
_SEVERITY = {
    SupervisorState.HOLD: 4,  # WARNING
    SupervisorState.PILOT_OVERRIDE: 4,
    SupervisorState.WAITING_FOR_AUTOPILOT: 4,
    SupervisorState.ACTIVE: 5,  # NOTICE
}
_INFO = 6
_COMMANDING = (CommandKind.POLICY, CommandKind.ZERO)


class LidarSource(Protocol):
    """What the loop needs from a lidar adapter (VLP-16 over UDP, CAN rangefinder ring)."""

    def fileno(self) -> int | None: ...

    def read_available(self) -> list[np.ndarray]: ...

    def close(self) -> None: ...


# ---- start-up --------------------------------------------------------------------------------


def policy_spec(config: CompanionConfig) -> PolicySpec:
    """What the companion feeds the model; the model's metadata must agree with every field."""
    return PolicySpec(
        stack=config.policy.stack,
        n_bins=N_BINS,
        max_range=config.scan.max_range,
        bin_convention=BIN_CONVENTION,
        max_speed=config.policy.max_speed,
        max_yaw_rate=config.policy.max_yaw_rate,
        max_sideways_speed=config.policy.sideways_speed,
        layout=config.policy.layout,
    )


def companion_shield(config: CompanionConfig, autopilot_yaw_rate: float | None) -> SafetyShield:
    """The loop's shield: the braking and yaw limits of this autopilot (measured), its yaw cap as read
    from it when known (None: the firmware default). ``avoid-companion replay`` builds its shield
    here too, from the recording, so a replay runs the very limits the flight ran."""
    return SafetyShield(config.shield, config.scan.max_range, config.autopilot.type, autopilot_yaw_rate)


def tracking_pose(nav: NavInputs, now: float) -> tuple[float, float, float] | None:
    """Where the tracker places a scan taken ``now``: the autopilot's local position, carried on to
    ``now`` at its velocity, and heading, as the route's ENU pose (:func:`enu_pose`), the frame
    LidarNav-v0 tracks in; None while either is unknown or the position is stale (without a goal
    source no position is asked for), and then nothing is tracked.

    Carried on, because the position streams at about the scans' rate but not in step with them:
    its age at a scan wanders over a period, and a pose that jumps back by that period's travel
    (0.15 m at 1.5 m/s) would move every static object at once."""
    if nav.heading is None or nav.position is None or not nav.position_fresh(now):
        return None
    north, east = nav.position[0], nav.position[1]
    if nav.velocity is not None:
        age = max(now - nav.position_time, 0.0)
        north, east = north + nav.velocity[0] * age, east + nav.velocity[1] * age
    return enu_pose(north, east, nav.heading)


def open_lidar(config: CompanionConfig, clock: Callable[[], float]) -> LidarSource:
    """The configured lidar source, opened (a bad port or bus is a :class:`UserError`)."""
    lidar = config.lidar
    if lidar.source == "velodyne":
        from companion.lidar.velodyne import VelodyneUdpSource

        v = lidar.velodyne
        if not v.sensor_ip:
            log.warning("lidar.velodyne.sensor_ip is not set: VLP-16 packets from any sender are decoded")
        return VelodyneUdpSource(v.host, v.port, backend=v.decoder, clock=clock, sensor_ip=v.sensor_ip)
    from companion.lidar.can_ring import open_can_ring

    return open_can_ring(lidar.can, clock)


def obstacle_distance_limits(config: CompanionConfig) -> tuple[int, int]:
    """OBSTACLE_DISTANCE (min_distance, max_distance) in cm, from the scan's range limits."""
    return max(1, round(config.scan.min_range * 100)), round(config.scan.max_range * 100)


def open_link(config: CompanionConfig, clock: Callable[[], float]) -> AutopilotLink:
    """The configured autopilot link (ArduPilot via pymavlink, PX4 via MAVSDK).

    :raises UserError: the link's listening port is held by another process (a second companion)
    """
    ap = config.autopilot
    link = ap.link
    ensure_port_free(link)
    min_cm, max_cm = obstacle_distance_limits(config)
    common: dict[str, Any] = {
        "clock": clock,
        "source_system": ap.source_system,
        "source_component": ap.source_component,
        "stream_rate_hz": ap.stream_rate_hz,
        "min_distance_cm": min_cm,
        "max_distance_cm": max_cm,
    }
    from companion.autopilot.signing import load_signing_key

    common["autopilot"] = (ap.system_id, ap.component_id)
    common["signing_key"] = load_signing_key(ap.signing_key) if ap.signing_key else None
    if ap.type == "px4":
        try:
            from companion.autopilot.px4 import Px4Link
        except ModuleNotFoundError as exc:
            if (exc.name or "").split(".")[0] != "mavsdk":
                raise
            raise UserError(
                "autopilot.type = px4 needs mavsdk >= 4, which is not installed: pip install 'mavsdk>=4' "
                "(it comes with the base install: pip install -e . or systemd/install.sh)"
            ) from None

        return Px4Link(link.mavsdk, **common)
    from companion.autopilot.ardupilot import ArduPilotLink

    return ArduPilotLink(link.pymavlink, baud=link.baud or ap.baud, **common)


def open_goal(config: CompanionConfig, link: Any, clock: Callable[[], float]) -> GoalSource | None:
    """The configured goal source, listening to the link (None: ``goal.source = "none"``)."""
    if config.goal.source == "none":
        return None
    ap = config.autopilot
    target = (ap.system_id, ap.component_id)
    goal = GoalSource(config.goal, (ap.source_system, ap.source_component), ap.type == "ardupilot", clock,
                      lambda request: link.send_message(request_message(request, target)))
    link.add_message_listener(goal.on_message, GOAL_STREAMS)
    return goal


def check_parameters(config: CompanionConfig) -> tuple[list[str], float | None]:
    """Run the configured autopilot parameter check before the link takes the port.

    :return: one line per mismatch (``warn``: the caller logs and STATUSTEXTs them), and the
        autopilot's yaw-rate cap as read (rad/s; None: not read, the shield assumes the firmware's
        default)
    :raises UserError: ``refuse`` and something differs, or the check could not run
    """
    pc = config.params_check
    if pc.mode == "off":
        return [], None
    from companion.params import check as params
    from companion.params.client import open_connection
    from companion.params.files import default_param_file, load_param_file

    wanted = load_param_file(pc.file or default_param_file(config.autopilot.type), config.autopilot.type)
    link = config.autopilot.link
    try:
        ensure_port_free(link)
        conn = open_connection(link.pymavlink, link.baud or config.autopilot.baud)
        try:
            if config.autopilot.signing_key:  # a signing autopilot ignores unsigned parameter requests
                from companion.autopilot.signing import enable_signing, load_signing_key

                enable_signing(conn.mav, load_signing_key(config.autopilot.signing_key))
            report = params.run_params(
                conn,
                config.autopilot.type,
                wanted,
                heartbeat_timeout=pc.timeout,
                allow_missing=frozenset(pc.allow_missing),
            )
        finally:
            conn.close()
    except UserError as exc:
        if pc.mode == "refuse":
            raise UserError(f"params_check: {exc}") from None
        log.warning("parameter check could not run: %s", exc)
        return [f"param check failed: {exc}"], None
    bad = [r for r in report.results if not r.ok]
    lines = [
        f"param {r.name}: wanted {params.format_value(r.wanted.value, r.wanted.param_type)}, "
        f"autopilot {params.format_value(r.actual, r.actual_type)} ({r.status.value})"
        for r in bad
    ]
    if bad and pc.mode == "refuse":
        raise UserError(f"params_check: {len(bad)} autopilot parameter(s) differ from {pc.file}: "
                        + "; ".join(lines))
    yaw_cap = params.yaw_rate_limit(report, config.autopilot.type)
    if yaw_cap is not None and yaw_cap < config.policy.max_yaw_rate - 1e-3:
        trained = math.degrees(config.policy.max_yaw_rate)
        lines.append(
            f"yaw limit {params.YAW_RATE_LIMIT_PARAMS[config.autopilot.type]} "
            f"{math.degrees(yaw_cap):.0f} deg/s < the policy's {trained:.0f}: "
            f"shield caps yaw at {yaw_cap:.2f} rad/s"
        )
    for line in lines:
        log.warning("%s", line)
    log.info("parameter check: %d/%d as wanted", len(report.results) - len(bad), len(report.results))
    return lines, yaw_cap


# ---- the loop ----------------------------------------------------------------------------------


class Companion:
    """The running companion: owns the policy, the lidar source, the link and the pure parts.

    :param config: the loaded configuration
    :param clock: monotonic clock shared by the supervisor, the links and the lidar source
    :param notifier: systemd notification (default: from the environment)
    """

    def __init__(
        self,
        config: CompanionConfig,
        clock: Callable[[], float] = time.monotonic,
        notifier: SystemdNotifier | None = None,
    ) -> None:
        self.config = config
        self._clock = clock
        self.notifier = notifier if notifier is not None else SystemdNotifier()
        self.policy = OnnxPolicy(
            config.policy.model,
            policy_spec(config),
            config.policy.providers or None,
            trt_cache_dir=config.policy.trt_cache_dir or None,
            sha256=config.policy.sha256 or None,
        )
        self._param_messages, autopilot_yaw_rate = check_parameters(config)
        self.lidar = open_lidar(config, clock)
        try:
            self.link = open_link(config, clock)
        except BaseException:
            self.lidar.close()
            raise
        self.supervisor = Supervisor(config.supervisor, clock)
        self.shield = companion_shield(config, autopilot_yaw_rate)
        self.layout = config.policy.layout
        self.stack = FrameStack(config.policy.stack, self.layout.frame_size)
        # the velocity estimate's error, from consecutive scans (drift layouts); kept across holds
        self._drift = DriftEstimator(DriftConfig(max_range=config.scan.max_range))
        self._drift_time = -math.inf
        self._od_limits = obstacle_distance_limits(config)
        # PX4 only accepts a switch to OFFBOARD while setpoints already stream.
        self._stream_before_mode = bool(getattr(self.link, "setpoints_before_offboard", False))
        self.counters: Counter[str] = Counter()
        self._status = VehicleStatus()
        self._kind = CommandKind.NONE
        self._reset_stack = True
        self._latest: tuple[np.ndarray, Command] | None = None  # newest scan and its requested command
        self._unsent_scan: np.ndarray | None = None  # newest scan not yet sent as OBSTACLE_DISTANCE
        self._last_filter: float | None = None
        self._last_zero = -math.inf
        self._last_setpoint = -math.inf
        self._last_command = Command(0.0, 0.0)  # the last setpoint sent, repeated while a scan is late
        self._last_held = (0.0, 0.0)  # the drift estimate it carried on top (drift_hold)
        self._last_heartbeat = -math.inf
        self._last_watchdog = -math.inf
        self._last_log = clock()
        self._last_waiting_log = clock()  # the start-up line names the address; this repeats it
        self._stopping = False
        self.goal = open_goal(config, self.link, clock)
        # with a goal source: hold until the goal is first evaluated, and announce what it says then
        self._goal_output = GoalOutput(None if self.goal is None else "starting")
        # goal.route: a map of the scans and a route on it (needs the goal source's position)
        route = config.goal.route and self.goal is not None and self.layout.goal
        self._route = RoutePlanner(config.goal.route_planner, config.scan.max_range) if route else None
        # [tracking]: what moves, each scan; its output stays here for the shield
        self.tracker = ScanTracker(max_range=config.scan.max_range) if config.tracking.enabled else None
        self.tracked: TrackerOutput | None = None
        if self.tracker is not None and self.goal is None:
            log.info("tracking: no goal source, so no position from the autopilot: nothing is tracked")
        self._completion_requested = False
        self.recorder = self._start_recorder(autopilot_yaw_rate)

    def _start_recorder(self, autopilot_yaw_rate: float | None) -> FlightRecorder | None:
        """The flight recorder (``[recorder]``): its taps wrap the parts, so the loop stays as it is.
        The yaw cap read from the autopilot and the shield's stopping model go into its metadata:
        replay builds the same shield."""
        stopping = (self.shield.max_decel, self.shield.reaction_time)
        recorder = open_recorder(self.config, to_dict(self.config), self._clock, autopilot_yaw_rate, stopping)
        if recorder is not None:
            recorder.watch_counters(companion=self.counters, supervisor=self.supervisor.counters,
                                    shield=self.shield.interventions, link=self.link.counters)
            parts = tap_parts(recorder, lidar=self.lidar, stack=self.stack, policy=self.policy,
                              shield=self.shield, link=self.link, supervisor=self.supervisor,
                              **({"tracker": self.tracker} if self.tracker is not None else {}))
            for name, tapped in parts.items():
                setattr(self, name, tapped)
        return recorder

    # ---- one iteration ---------------------------------------------------------------------

    def step(self, timeout: float) -> None:
        """Wait up to ``timeout`` for lidar data, then do everything one iteration does."""
        fds = [fd for fd in (self.lidar.fileno(), self._link_fileno()) if fd is not None]
        if fds:
            select.select(fds, [], [], timeout)
        elif timeout > 0:
            time.sleep(timeout)
        clouds = self.lidar.read_available()
        self._status = self.link.poll()
        self.supervisor.on_vehicle(self._status)
        self._step_goal()
        if getattr(self.lidar, "implausible", False):
            self.counters["reads_implausible"] += 1
            self.supervisor.on_scan(False, "lidar implausible")
        elif clouds:
            self.counters["revolutions_skipped"] += len(clouds) - 1
            self._on_cloud(clouds[-1])
        kind = self.supervisor.tick()
        self._send(kind, new_scan=bool(clouds))  # the setpoint first: it is the time-critical message
        self._kind = kind
        self._send_obstacle_distance()
        for transition in self.supervisor.drain_transitions():
            self._announce(transition)
        self._periodic()
        if getattr(self.lidar, "backlogged", False):
            self.counters["backlog_pauses"] += 1
            time.sleep(BACKLOG_PAUSE)

    def _step_goal(self) -> None:
        """Goal: progress announced; a goal that says hold gates the policy (see :meth:`_send`)."""
        if self.goal is None:
            return
        out = self.goal.step(self._status.heartbeat_time is not None)
        for text in self.goal.drain_announcements():
            log.info("%s", text)
            self.link.send_statustext(f"avoid {text}", _INFO)
        for seq in self.goal.tracker.drain_reached_items():
            self.link.send_message(reached_message(seq))
            self.counters["mission_items_reached"] += 1
        if out.hold_reason != self._goal_output.hold_reason:
            text = f"goal: hold ({out.hold_reason})" if out.hold_reason else "goal: tracking"
            log.info("%s", text)
            self.link.send_statustext(f"avoid {text}", 4 if out.hold_reason else _INFO)
            self.counters["goal_changes"] += 1
        self._goal_output = out
        g = self.config.goal
        if (out.complete and g.on_complete != "hold" and not self._completion_requested
                and self.supervisor.state in (SupervisorState.ACTIVE, SupervisorState.HOLD)):
            self._completion_requested = True
            ap = self.config.autopilot
            target = (ap.system_id, ap.component_id)
            self.link.send_message(completion_mode_command(ap.type, g.on_complete, target))
            self.link.send_statustext(f"avoid goal complete: requesting {g.on_complete.upper()}", _INFO)

    def _link_fileno(self) -> int | None:
        fileno = getattr(self.link, "fileno", None)
        return fileno() if fileno is not None else None

    def _on_cloud(self, cloud: np.ndarray) -> None:
        scan = scan_from_points(cloud, self.config.scan)
        if self.goal is not None:
            self.goal.observe_cloud(cloud, self.config.scan)
        self.counters["scans"] += 1
        self._unsent_scan = scan
        self._track(scan)
        frame = self._frame(scan)
        if isinstance(frame, str):  # no frame: the policy does not run, the stack starts over
            self._latest = (scan, Command(0.0, 0.0))
            self._reset_stack = True
            if frame == VELOCITY_STALE:
                self.counters["frames_without_velocity"] += 1
                self.supervisor.on_scan(False, VELOCITY_STALE)
            else:  # the goal says hold: the scan is good, the goal gates the setpoint (see _send)
                self.supervisor.on_scan(True)
            return
        scan = frame[: self.layout.n_bins]  # the frame's own scan (a view): the recorder pairs them
        obs = self.stack.reset(frame) if self._reset_stack else self.stack.push(frame)
        self._reset_stack = False
        try:
            action = self.policy.act(obs)
        except InferenceFault as exc:
            self.counters["inference_faults"] += 1
            if self.counters["inference_faults"] == 1 or self.counters["inference_faults"] % 100 == 0:
                log.warning("inference fault (%d so far): %s", self.counters["inference_faults"], exc)
            self.supervisor.on_scan(False)
            self._latest = (scan, Command(0.0, 0.0))
            return
        self.supervisor.on_scan(True)
        cfg = self.config.policy
        self._latest = (scan, command_from_action(action, cfg.max_speed, cfg.max_yaw_rate,
                                                            cfg.sideways_speed))

    def _track(self, scan: np.ndarray) -> None:
        """What moves in ``scan``, at the autopilot's pose now (:func:`tracking_pose`), as LidarNav-v0
        tracks it; kept in :attr:`tracked`."""
        if self.tracker is None:
            return
        now = self._clock()
        pose = tracking_pose(self.goal.nav, now) if self.goal is not None else None
        self.tracked = self.tracker.update(scan, pose, now)

    def _shield_movers(self) -> dict[str, Any]:
        """What moves in the newest scan, for the shield (its ``moving_bins`` and ``movers``): the
        tracker's output; nothing with tracking off."""
        return {} if self.tracked is None else self.tracked.shield_inputs()

    @property
    def moving_bins(self) -> np.ndarray | None:
        """``(360,)`` bool: the newest scan's bins whose return moves (None: tracking off)."""
        return None if self.tracked is None else self.tracked.moving_bins

    def _frame(self, scan: np.ndarray) -> np.ndarray | str:
        """The policy's frame for ``scan`` (LidarNav-v0's, built by the same functions), or why
        there is none: the goal says hold, or the measured velocity is stale (a false picture)."""
        if not self.layout.goal:
            return scan
        goal = self._goal_output
        if goal.hold_reason is not None:
            return goal.hold_reason
        status = self._status
        age = self._clock() - status.velocity_time if status.velocity_time is not None else math.inf
        if status.velocity_body is None or not age <= self.config.supervisor.velocity_timeout:
            return VELOCITY_STALE
        # no goal source: a goal GOAL_AHEAD_M ahead on the current heading, wherever the vehicle is
        forward, left = goal.goal_body[:2] if goal.goal_body is not None else (GOAL_AHEAD_M, 0.0)
        features = goal_features(*self._toward(scan, forward, left), *status.velocity_body, self.layout)
        if self.layout.drift:
            now = self._clock()
            dt, self._drift_time = now - self._drift_time, now
            moving = self.moving_bins
            static = scan if moving is None else without_movers(scan, moving)
            bias = self._drift.observe(static, np.asarray(status.velocity_body), forward, left, dt)
            features = np.concatenate([features, drift_features(bias, self.layout)])
        if self.layout.command:  # what the autopilot is still answering (LidarNav-v0's command)
            sent = self._last_command
            features = np.concatenate([features, command_features(sent.forward, sent.yaw_rate, self.layout)])
        if self.layout.firmware:  # which firmware answers (LidarNav-v0's firmware)
            ardupilot = self.config.autopilot.type == "ardupilot"
            features = np.concatenate([features, firmware_features(ardupilot, self.layout)])
        if self.layout.movers:  # what moves in this scan (LidarNav-v0's movers); the config makes
            assert self.tracked is not None  # sure the tracker runs, and _track ran on this scan
            features = np.concatenate([features, mover_features(self.tracked.movers(), self.layout)])
        return build_frame(scan, features, self.layout)

    def _toward(self, scan: np.ndarray, forward: float, left: float) -> tuple[float, float]:
        """Where the goal features point, body FLU metres: along the route on the map of the scans
        (``goal.route``, LidarNav-v0's ``route``), else at the goal (``forward``, ``left``)."""
        if self._route is None or self.goal is None:
            return forward, left
        nav, tracker = self.goal.nav, self.goal.tracker
        if nav.position is None or nav.heading is None or tracker.index >= len(tracker.waypoints):
            return forward, left
        x, y, heading = enu_pose(nav.position[0], nav.position[1], nav.heading)
        self._route.observe(scan, x, y, heading, self.moving_bins)
        waypoint = tracker.waypoints[tracker.index]
        goal_x, goal_y, _ = enu_pose(waypoint.north, waypoint.east, 0.0)
        subgoal = self._route.subgoal(x, y, heading, goal_x, goal_y)
        return subgoal.forward, subgoal.left

    def _send_obstacle_distance(self) -> None:
        """OBSTACLE_DISTANCE for the newest scan (the autopilot's own avoidance layer).

        Sent after the setpoint, which is the time-critical message; when a backlog brought several
        scans in one iteration, the older ones are stale and not sent.
        """
        scan, self._unsent_scan = self._unsent_scan, None
        if scan is None or not self.config.autopilot.obstacle_distance:
            return
        if not obstacle_distance_allowed(self._status, self.config.supervisor.min_engage_altitude):
            self.counters["obstacle_distance_on_ground"] += 1  # floor returns: never sent
            return
        sectors = obstacle_distance_from_scan(scan, self.config.scan.max_range, *self._od_limits)
        self.link.send_obstacle_distance(sectors)

    def _send(self, kind: CommandKind, new_scan: bool) -> None:
        now = self._clock()
        if kind is CommandKind.POLICY and self._goal_output.hold_reason is not None:
            self.counters["goal_holds"] += 1  # the goal says hold (complete, no position, ...)
            kind = CommandKind.ZERO
        if kind is CommandKind.POLICY:
            if new_scan and self._latest is not None:
                scan, requested = self._latest
                last = self._last_filter
                dt = min(max(now - last, 1e-3), 0.5) if last is not None else 0.1
                # the supervisor only commands while the measured velocity is fresh
                velocity, drift, held = self._shield_motion()
                moving = self._shield_movers()
                command = self.shield.filter(requested, scan, dt, velocity, drift=drift, **moving)
                self._last_filter = now
                self._send_policy_setpoint(command, held)
                self._last_setpoint, self._last_command, self._last_held = now, command, held
                self.counters["setpoints_policy"] += 1
            elif now - self._last_setpoint > LATE_SCAN_AFTER:
                self._send_policy_setpoint(self._last_command, self._last_held)
                self._last_setpoint = now
                self.counters["setpoints_late_scan"] += 1
        else:
            # Leaving ACTIVE: the next engagement ramps up from standstill, with a fresh stack.
            self.shield.reset()
            self._last_filter = None
            stream = kind is CommandKind.ZERO or (
                self._stream_before_mode
                and self._status.armed
                and self.supervisor.state in (SupervisorState.STANDBY, SupervisorState.PILOT_OVERRIDE)
            )
            if stream and (new_scan or now - self._last_zero >= ZERO_SETPOINT_PERIOD):
                self.link.send_velocity(0.0, 0.0)
                self._last_zero = self._last_setpoint = now
                self._last_command = Command(0.0, 0.0)
                self.counters["setpoints_zero"] += 1
        if self.supervisor.state is not SupervisorState.ACTIVE:
            self._reset_stack = True

    def _shield_motion(
        self,
    ) -> tuple[tuple[float, float] | None, tuple[float, float] | None, tuple[float, float]]:
        """What the shield judges the motion by, and what the setpoint carries on top of its command.

        The drift estimate (drift layouts only) is held by the setpoint as far as ``[drift_hold]``
        says (:func:`companion.perception.drift.held_drift`); the vehicle then truly flies the setpoint less
        the rest of the error, so the shield is given the rest of the estimate (for
        ``shield.drift_compensation``). It judges the motion by the measured velocity less the
        whole estimate, the true motion as the scans show it: on the estimate alone it braked for
        a motion the scans did not show, and missed one the estimate hid (PX4's drifts 0.2-0.4 m/s
        off the truth; docs/goal-policy.md, "The shield judges the true motion").

        :returns: the velocity and the drift estimate for the shield (body forward, left, m/s;
            None where unknown), and the held part (forward, left, m/s)
        """
        velocity = self._status.velocity_body
        if not self.layout.drift:
            return velocity, None, (0.0, 0.0)
        bias = self._drift.bias
        held = held_drift(bias, self.config.drift_hold)
        drift = (float(bias[0]) - held[0], float(bias[1]) - held[1])
        if velocity is not None and np.isfinite(bias).all():
            velocity = (float(velocity[0]) - float(bias[0]), float(velocity[1]) - float(bias[1]))
        return velocity, drift, held

    def _send_policy_setpoint(self, command: Command, held: tuple[float, float]) -> None:
        """Send the shield's ``command`` with the ``held`` drift on top. The climb toward the
        waypoint's height goes beside the shield, which judges the horizontal motion the scan
        slice can see (bounded by goal.max_vertical_speed)."""
        self.link.send_velocity(command.forward + held[0], command.yaw_rate, command.lateral + held[1],
                                self._goal_output.vertical_speed)

    def _announce(self, transition: Transition) -> None:
        self.counters["transitions"] += 1
        log.info("supervisor %s", transition)
        self.link.send_statustext(f"avoid {transition}", _SEVERITY.get(transition.new, _INFO))
        self.notifier.status(transition.new.value)

    def _periodic(self) -> None:
        now = self._clock()
        if now - self._last_heartbeat >= self.config.runtime.heartbeat_interval:
            self.link.send_heartbeat()
            self._last_heartbeat = now
        if self._param_messages and self._status.heartbeat_time is not None:
            for line in self._param_messages:  # warn mode: the pilot sees them once the link is up
                self.link.send_statustext(line, 4)
            self._param_messages = []
        if now - self._last_log >= self.config.runtime.log_interval:
            self._last_log = now
            log.info("%s", self.summary())
        waiting = self.supervisor.state == SupervisorState.WAITING_FOR_AUTOPILOT
        if waiting and now - self._last_waiting_log >= WAITING_LOG_INTERVAL:
            self._last_waiting_log = now
            log.info("waiting for the autopilot (%s) on %s: no heartbeat yet", self.config.autopilot.type,
                     self.config.autopilot.connection)

    def summary(self) -> str:
        """One line of counters for the periodic log."""
        parts = [f"state={self.supervisor.state.value}"]
        parts += [f"{k}={v}" for k, v in sorted(self.counters.items())]
        parts += [f"link.{k}={v}" for k, v in sorted(self.link.counters.items()) if v]
        lidar_counters = getattr(self.lidar, "counters", None)
        if lidar_counters is not None:
            parts += [f"lidar.{k}={v}" for k, v in sorted(vars(lidar_counters).items()) if v]
        parts += [f"shield.{k}={v}" for k, v in sorted(self.shield.interventions.items())]
        sup = self.supervisor.counters
        parts += [f"supervisor.{k.replace(' ', '_')}={v}" for k, v in sorted(sup.items())]
        return " ".join(parts)

    # ---- the whole run ---------------------------------------------------------------------

    def run(self) -> int:
        """Loop until SIGTERM/SIGINT; return the exit status (0)."""
        wake_r, wake_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        previous_handlers = {s: signal.signal(s, _wake_only) for s in (signal.SIGTERM, signal.SIGINT)}
        previous_wakeup = signal.set_wakeup_fd(wake_w, warn_on_full_buffer=False)
        try:
            self.supervisor.start()
            for transition in self.supervisor.drain_transitions():
                self._announce(transition)
            self.notifier.ready("model loaded, links open")
            log.info("companion running: lidar %s, autopilot %s %s", self.config.lidar.source,
                     self.config.autopilot.type, self.config.autopilot.connection)
            watchdog_period = self.notifier.watchdog_period or DEFAULT_WATCHDOG_PERIOD
            while not self._stopping:
                ok = self._guarded_step(wake_r)
                now = self._clock()
                if ok and now - self._last_watchdog >= watchdog_period:
                    self.notifier.watchdog()
                    self._last_watchdog = now
            return 0
        finally:
            signal.set_wakeup_fd(previous_wakeup)
            for s, handler in previous_handlers.items():
                signal.signal(s, handler)
            os.close(wake_r)
            os.close(wake_w)

    def _guarded_step(self, wake_r: int) -> bool:
        """One iteration; True when it completed. A fault is counted and logged, never raised."""
        try:
            ready, _, _ = select.select([wake_r], [], [], 0)
            if ready:
                signals = os.read(wake_r, 64)
                log.info("signal %s: stopping", ", ".join(signal.Signals(s).name for s in signals))
                self._stopping = True
                return True
            self.step(self.config.runtime.poll_interval)
            return True
        except Exception as exc:  # the process must survive whatever one iteration met
            self.counters["loop_faults"] += 1
            n = self.counters["loop_faults"]
            if n <= 5 or n % 100 == 0:
                log.exception("fault in the main loop (%d so far): %s", n, exc)
            time.sleep(min(self.config.runtime.poll_interval, 0.01))  # never spin on a persistent fault
            return False

    def close(self) -> None:
        """Zero setpoint if the companion was commanding, then release everything."""
        self.notifier.stopping()
        try:
            if self._kind in _COMMANDING:
                self.link.send_velocity(0.0, 0.0)
                self.counters["setpoints_zero"] += 1
                log.info("sent a zero-velocity setpoint on the way out")
            log.info("%s", self.summary())
        finally:
            self.link.close()
            self.lidar.close()
            if self.recorder is not None:
                self.recorder.close()
            self.notifier.close()


def _wake_only(signum: int, frame: Any) -> None:
    """Signal handler: nothing. ``set_wakeup_fd`` already put the signal number in the loop's pipe."""


# ---- CLI ----------------------------------------------------------------------------------------


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """``run --config FILE [key=value ...]``."""
    parser.add_argument("--config", required=True, metavar="FILE.toml",
                        help="companion configuration (see config/companion.example.toml)")
    parser.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                        help="override config keys, e.g. shield.max_speed=1.0 (relative paths: from the "
                        "working directory)")
    parser.add_argument("--set", dest="set_overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config key, as KEY=VALUE after the options does")


def command(args: argparse.Namespace) -> int:
    """Run the companion until SIGTERM/SIGINT."""
    config = load_config(args.config, [*args.set_overrides, *args.overrides])
    companion = Companion(config)
    try:
        return companion.run()
    finally:
        companion.close()
