"""SITL harness: the real companion process flying a simulated (or external) autopilot.

One flight = a :class:`SitlFlight`: the simulated autopilot (real MAVLink over loopback UDP,
flying the JSBSim vehicle in real time), the lidar co-simulation (real VLP-16 packets to the
companion's port), the companion started as its own process (``python -m companion run``) with a
generated config, and a pymavlink ground station that does what the pilot does: GUIDED, arm,
take off to 1.5 m; on PX4 it streams zero setpoints as proof of life, switches to OFFBOARD and
stops streaming once the companion's own setpoints arrive. The companion then flies; the harness
watches (collision, clearance, setpoint rate, latency, the companion's STATUSTEXTs) and reports.
What it observes is :mod:`flightsim.sitl.flight_recorder`, the companion's config and ports
:mod:`flightsim.sitl.companion_setup`, the report itself (figures, printout, PNG)
:mod:`flightsim.sitl.flight_report`; the ``avoid-sim fly`` command line is :mod:`flightsim.sitl.fly_cli`.

With ``autopilot="external"`` a SITL flies its own physics; :mod:`flightsim.sitl.external_sitl` mirrors
its pose (ground truth where it sends it) into the world and the lidar is cast from there.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.common.errors import UserError
from companion.common.tomlconfig import to_dict, toml_dumps
from companion.perception.scan import ScanConfig
from flightsim.envs.raycast import LidarConfig
from flightsim.sitl import external_sitl
from flightsim.sitl.companion_setup import companion_config, free_udp_port
from flightsim.sitl.cosim import LidarCosim
from flightsim.sitl.flight_recorder import Recorder
from flightsim.sitl.flight_report import INTERRUPTED, FlightReport, latency_ms, plot_flight, waypoints_reached
from flightsim.sitl.ground_station import GroundStation, mission_items
from flightsim.sitl.recording import FlightRecording
from flightsim.worlds.world import World

log = logging.getLogger(__name__)

AUTOPILOTS = ("sim-ardupilot", "sim-px4", "external")
TAKEOFF_ALTITUDE = 1.5
#: the companion's STATUSTEXT when the last waypoint is reached (companion.guidance.goal.GoalTracker)
COMPLETE_MARK = "goal: complete"
#: a mission flight goes on this long after the companion announced completion (it holds), s
COMPLETE_HOLD_S = 1.0
#: the companion's STATUSTEXT on entering ACTIVE starts with this (supervisor state names)
ACTIVE_MARK = "->ACTIVE"


# ------------------------------------------------------------------------------------ records
@dataclass
class FlightOptions:
    """What to fly.

    :param autopilot: ``sim-ardupilot``, ``sim-px4`` or ``external``
    :param world: the room
    :param policy: ONNX policy file for the companion
    :param duration: seconds the companion flies after engaging (or after take-off if it never does)
    :param connect: external only: pymavlink string of the SITL's GCS port (e.g. ``tcp:127.0.0.1:5760``)
    :param lidar_step_deg: ray-caster azimuth step (0.2 = the real VLP-16)
    :param workdir: where the generated config, the companion's log and the plot go
    :param companion_overrides: section -> {field: value} applied to the generated companion config
    :param autopilot_params: parameter overrides for the simulated autopilot
    :param engage_timeout: seconds to wait for the companion to go ACTIVE
    :param signed: MAVLink 2 signing on every link (simulated autopilots): a fresh key in the
        workdir for the autopilot, the ground station and the companion's ``autopilot.signing_key``
    :param mission: upload the world's waypoints as a mission through the ground station and set
        the companion's ``goal.source = "mission"``
    :param ideal_response: simulated autopilots only: fly setpoints as given instead of through the
        firmware's calibrated response (:mod:`flightsim.vehicle.autopilot_response`)
    :param altitude_drift: simulated autopilots only: their altitude estimate's error after arming, m
    :param position_timeout: external only: seconds to wait for the autopilot's first position
        (its EKF origin; a fresh ArduPilot SITL needs 40-47 s)
    """

    autopilot: str
    world: World
    policy: Path
    duration: float = 30.0
    connect: str = ""
    lidar_step_deg: float = 0.2
    workdir: Path = Path(".")
    companion_overrides: dict[str, Any] = field(default_factory=dict)
    autopilot_params: dict[str, float] = field(default_factory=dict)
    engage_timeout: float = 20.0
    signed: bool = False
    mission: bool = False
    ideal_response: bool = False
    position_timeout: float = external_sitl.POSITION_TIMEOUT_S
    altitude_drift: float = 0.0


# ------------------------------------------------------------------------------------ the flight
class SitlFlight:
    """All the moving parts of one SITL flight; use as a context manager (it always cleans up).

    :param options: what to fly
    :param vehicle: a JSBSim vehicle to reuse across flights (loading one takes a moment)
    """

    def __init__(self, options: FlightOptions, vehicle: Any = None) -> None:
        if options.autopilot not in AUTOPILOTS:
            raise UserError(f"--autopilot must be one of {', '.join(AUTOPILOTS)}, not {options.autopilot!r}")
        if not Path(options.policy).is_file():
            raise UserError(f"policy file not found: {options.policy}")
        if options.signed and options.autopilot == "external":
            raise UserError("--signed needs a simulated autopilot (--autopilot sim-ardupilot or sim-px4)")
        self.options = options
        self.world = options.world
        self.workdir = Path(options.workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.vehicle = vehicle
        self.server: Any = None
        self.cosim: LidarCosim | None = None
        self.gcs: GroundStation | None = None
        self.companion: subprocess.Popen[bytes] | None = None
        self.external: external_sitl.ExternalPose | None = None
        self.ground_truth = "simulator"  # external: the SITL's truth message, or "estimate"
        self.position_wait_s = 0.0  # external: how long the autopilot took to report a position
        self.recorder = Recorder(t0=time.monotonic())
        self.recording = FlightRecording(self.workdir, self.world, options.lidar_step_deg)  # MCAP + truth
        self.recording.t0 = self.recorder.t0
        self.lidar_port = free_udp_port()
        self.companion_port = free_udp_port()
        self.config_path = self.workdir / "companion.toml"
        self.log_path = self.workdir / "companion.log"
        self.key_path = self.workdir / "mavlink-signing.key"
        self.engaged_at: float | None = None
        self._log_file: Any = None
        self._gcs_lock = threading.Lock()
        self._pump_thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.signing_key: bytes | None = None

    @property
    def personality(self) -> str:
        return {"sim-ardupilot": "ardupilot", "sim-px4": "px4"}.get(self.options.autopilot, "external")

    # ------------------------------------------------------------------ start / stop
    def __enter__(self) -> SitlFlight:
        try:
            self.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        """Start the autopilot (or connect to the external one), the lidar stream and the companion."""
        scan = ScanConfig()
        lidar = LidarConfig(azimuth_step_deg=self.options.lidar_step_deg, max_range=scan.max_range)
        self.cosim = LidarCosim(
            self.world, self._pose, ("127.0.0.1", self.lidar_port), lidar=lidar, scan=scan,
            world_time=self.world_time,
        )  # fmt: skip
        # cast once before anything runs in real time: the first cast compiles the numba kernel,
        # which holds the interpreter lock for seconds and would stall the autopilot's loop
        self.cosim.revolution_packets(self._start_state())
        if self.options.autopilot == "external":
            self._start_external()
            companion_type = "px4" if self.gcs.is_px4 else "ardupilot"  # type: ignore[union-attr]
        else:
            self._start_simulated()
            companion_type = self.personality
        self.cosim.start()
        connect = (
            f"udpin://127.0.0.1:{self.companion_port}"
            if companion_type == "px4"
            else f"udpin:127.0.0.1:{self.companion_port}"
        )
        overrides = dict(self.options.companion_overrides)
        if self.options.mission:
            overrides["goal"] = {**overrides.get("goal", {}), "source": "mission"}
        if self.signing_key is not None:
            overrides["autopilot"] = {**overrides.get("autopilot", {}), "signing_key": str(self.key_path)}
        cfg = companion_config(
            autopilot_type=companion_type,
            connect=connect,
            lidar_port=self.lidar_port,
            policy=Path(self.options.policy).resolve(),
            overrides=self.recording.companion_overrides(overrides),
        )
        self.config_path.write_text(toml_dumps(to_dict(cfg)))
        self.start_companion()

    def world_time(self) -> float:
        """Seconds since the flight's clock zero (the simulated autopilot's start): where the world's
        moving obstacles are, for the lidar and for judging collisions alike."""
        return time.monotonic() - self.recorder.t0

    def _pose(self) -> Any:
        """The vehicle state the lidar is cast from (simulated vehicle or mirrored external SITL)."""
        if self.external is not None:
            return self.external.state()
        return self.server.state

    def _start_state(self) -> Any:
        from flightsim.vehicle.quadrotor import VehicleState

        x, y, z = self.world.start_position
        return VehicleState(
            time=0.0,
            position=np.array([x, y, z]),
            velocity=np.zeros(3),
            roll=0.0,
            pitch=0.0,
            yaw=math.radians(self.world.start_yaw_deg),
            angular_rate=np.zeros(3),
            on_ground=False,
            armed=False,
        )

    def _start_simulated(self) -> None:
        from flightsim.sitl.sim_autopilot.server import SimAutopilotServer

        start = np.array([self.world.start_position[0], self.world.start_position[1], 0.0])
        if self.options.signed:
            from companion.autopilot.signing import write_signing_key

            self.key_path.unlink(missing_ok=True)
            self.signing_key = write_signing_key(self.key_path)
        self.server = SimAutopilotServer(
            self.personality,
            ["udpin:127.0.0.1:0", f"udpout:127.0.0.1:{self.companion_port}"],
            start_position=start,
            start_yaw=math.radians(self.world.start_yaw_deg),
            params=self.options.autopilot_params,
            vehicle=self.vehicle,
            signing_key=self.signing_key,
            response=not self.options.ideal_response,
            altitude_drift=self.options.altitude_drift,
        )
        self.recorder.t0 = self.recording.t0 = self.server.t0
        self.server.message_hooks.append(self._on_autopilot_message)
        self.server.step_hooks.append(self._on_step)
        self.server.start()
        gcs_port = self.server.endpoint.address(0)[1]
        self.gcs = GroundStation(f"udpout:127.0.0.1:{gcs_port}")
        if self.signing_key is not None:
            from companion.autopilot.signing import enable_signing

            enable_signing(self.gcs.mav.mav, self.signing_key)
        self.gcs.wait_heartbeat()

    def _start_external(self) -> None:
        """Connect the GCS to a running SITL, relay it to the companion (MAVLink router role) from
        now on, land and disarm it if a previous flight left it armed, anchor the world to its pose."""
        if not self.options.connect:
            raise UserError("--autopilot external needs --connect (e.g. tcp:127.0.0.1:5760)")
        self.external = external = external_sitl.ExternalPose(self.world)
        self.gcs = gcs = GroundStation(self.options.connect)
        gcs.wait_heartbeat(timeout=30.0)
        from pymavlink import mavutil

        relay = mavutil.mavlink_connection(f"udpout:127.0.0.1:{self.companion_port}", source_system=255)

        def forward_to_companion(msg: Any) -> None:
            changed = external.update(msg)
            # judge on truth once the SITL sends it, on the estimate only while it does not
            if changed == "truth" or (changed == "estimate" and external.truth_source is None):
                state = external.state()
                speed = float(np.linalg.norm(state.velocity[:2]))
                self.recorder.on_pose(time.monotonic(), state.position, state.yaw, speed, self.world)
                self.recording.on_state(time.monotonic(), state)
            relay.write(msg.get_msgbuf())

        gcs.on_message = forward_to_companion
        self._relay = relay
        self._relay_thread = threading.Thread(target=self._relay_back, daemon=True)
        self._relay_thread.start()
        external_sitl.request_streams(gcs)
        self.pump_gcs()  # from connect onwards: the companion must hear the autopilot before take-off
        self.position_wait_s = external_sitl.wait_for_position(external, self.options.position_timeout)
        self.pilot(external_sitl.land_and_disarm)
        self.ground_truth = self.pilot(lambda g: external_sitl.wait_for_truth(external, g.pump))
        if self.ground_truth == "estimate":
            log.warning("%s", external_sitl.ESTIMATE_WARNING)
        external.anchor()

    def _relay_back(self) -> None:
        """External SITL: companion → autopilot (setpoints, heartbeats, STATUSTEXT), recorded on the way."""
        while not self._stop.is_set():
            msg = self._relay.recv_match(blocking=True, timeout=0.1)
            if msg is None or msg.get_type() == "BAD_DATA":
                continue
            self.recorder.on_companion_message(msg, time.monotonic())
            self.gcs.mav.write(msg.get_msgbuf())  # type: ignore[union-attr]  (a socket send: no lock)

    def start_companion(self) -> None:
        """Start (or restart) the companion process with the generated config."""
        if self._log_file is None:
            self._log_file = open(self.log_path, "ab")  # noqa: SIM115 - lives as long as the flight
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.companion = subprocess.Popen(
            [sys.executable, "-m", "companion", "run", "--config", str(self.config_path)],
            stdout=self._log_file,
            stderr=subprocess.STDOUT,
            env=env,
        )
        log.info("companion started (pid %d), log %s", self.companion.pid, self.log_path)

    def kill_companion(self, sig: int = signal.SIGKILL) -> None:
        if self.companion is not None and self.companion.poll() is None:
            self.companion.send_signal(sig)
            self.companion.wait(timeout=10)

    def close(self) -> None:
        self._stop.set()
        if self.companion is not None and self.companion.poll() is None:
            self.companion.send_signal(signal.SIGINT)
            try:
                self.companion.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.companion.kill()
                self.companion.wait(timeout=5)
        if self._pump_thread is not None:
            self._pump_thread.join(timeout=2)
        if self.cosim is not None:
            self.cosim.stop()
        if self.server is not None:
            self.server.stop()
        if self.gcs is not None:
            self.gcs.close()
        if self._log_file is not None:
            self._log_file.close()
            self._log_file = None
        self.recording.close()

    # ------------------------------------------------------------------ observation hooks
    def now(self) -> float:
        return time.monotonic()

    def _on_autopilot_message(self, link: int, msg: Any, t: float) -> None:
        if link == 1:
            self.recorder.on_companion_message(msg, self.recorder.t0 + t)

    def _on_step(self, state: Any) -> None:
        self.recorder.on_pose(
            time.monotonic(), state.position, state.yaw, float(np.linalg.norm(state.velocity[:2])), self.world
        )
        self.recording.on_state(time.monotonic(), state)

    def companion_alive(self) -> bool:
        return self.companion is not None and self.companion.poll() is None

    def companion_exit(self) -> str:
        """Why the companion is gone: its exit status and the last line it logged."""
        assert self.companion is not None
        lines = self.companion_log().strip().splitlines()
        last = lines[-1] if lines else ""
        return f"the companion exited (status {self.companion.returncode}): {last}"

    def companion_log(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    # ------------------------------------------------------------------ the pilot
    def pump_gcs(self) -> None:
        """Keep the GCS link alive (heartbeats, telemetry) from a background thread (once)."""
        if self._pump_thread is not None:
            return

        def run() -> None:
            while not self._stop.is_set():
                with self._gcs_lock:
                    gcs = self.gcs
                    assert gcs is not None
                    gcs.pump(0.02)
                time.sleep(0.03)

        self._pump_thread = threading.Thread(target=run, name="gcs-pump", daemon=True)
        self._pump_thread.start()

    def pilot(self, action: Any) -> Any:
        """Run ``action(gcs)`` with the GCS to itself (the background pump pauses meanwhile)."""
        with self._gcs_lock:
            return action(self.gcs)

    def wait_companion_up(self, timeout: float = 20.0) -> None:
        """Wait for the companion's first HEARTBEAT (it is running); RuntimeError if it exited."""
        end = time.monotonic() + timeout
        while not self.recorder.companion_heartbeats:
            if not self.companion_alive():
                raise RuntimeError(self.companion_exit())
            if time.monotonic() > end:
                raise RuntimeError(f"no companion HEARTBEAT in {timeout:.0f} s (see {self.log_path})")
            time.sleep(0.05)

    def upload_mission(self) -> None:
        """Upload the world's waypoints as a mission, as a ground station does (before arming).

        The world's start is the autopilot's home, z m above it (MAV_FRAME_GLOBAL_RELATIVE_ALT_INT).
        A simulated autopilot's frame is the world's: waypoint (x, y, z) is (y − start y) m north and
        (x − start x) m east of home. An external SITL's frame is turned onto the world's
        (:class:`~flightsim.sitl.external_sitl.ExternalPose`): the offsets are turned back into it, from
        where the vehicle was anchored (:meth:`~flightsim.sitl.external_sitl.ExternalPose.mission_frame`).
        """
        if not self.world.waypoints:
            raise UserError(f"--mission: world {self.world.name!r} has no waypoints")

        def upload(gcs: GroundStation) -> None:
            if self.external is not None:
                origin, rotation = self.external.mission_frame()
                gcs.upload_mission(mission_items(self.world, origin, rotation))
            else:
                gcs.upload_mission(mission_items(self.world, gcs.home_position()))

        self.pilot(upload)

    def take_off(self) -> None:
        """GUIDED (ArduPilot) / Hold (PX4), arm, take off to 1.5 m; PX4: proof of life, then OFFBOARD."""
        gcs = self.gcs
        assert gcs is not None
        with self._gcs_lock:
            gcs.pump(0.3)
            if gcs.is_px4:
                # PX4 refuses to arm after a flight that ended in OFFBOARD: Hold first
                gcs.set_mode("HOLD")
                self._arm(gcs)
                gcs.takeoff(TAKEOFF_ALTITUDE)
            else:
                gcs.set_mode("GUIDED")
                self._arm(gcs)
                gcs.takeoff(TAKEOFF_ALTITUDE)
        self.pump_gcs()
        if gcs.is_px4:
            # PX4 accepts OFFBOARD only while setpoints stream: the companion streams zeros once the
            # vehicle is armed and it is ready (Px4Link.setpoints_before_offboard); retry until then.
            end = time.monotonic() + 15.0
            while True:
                try:
                    self.pilot(lambda g: g.set_mode("OFFBOARD", timeout=2.0))
                    break
                except RuntimeError:
                    if time.monotonic() > end:
                        raise
                    time.sleep(0.5)

    def _arm(self, gcs: GroundStation) -> None:
        """Arm; a real SITL refuses until its pre-arm checks pass (EKF, GPS), so keep trying a while."""
        end = time.monotonic() + (90.0 if self.external is not None else 0.0)
        while True:
            try:
                gcs.arm()
                return
            except RuntimeError:
                if time.monotonic() > end:
                    raise
                gcs.pump(2.0)

    def wait_engaged(self, timeout: float) -> bool:
        """Wait until the companion announces ACTIVE (True), exits or ``timeout`` s pass."""
        end = time.monotonic() + timeout
        start = time.monotonic()
        while time.monotonic() < end:
            if any(ACTIVE_MARK in t for t in self.recorder.texts(start - 60)):
                self.engaged_at = time.monotonic()
                return True
            if not self.companion_alive():
                return False
            time.sleep(0.05)
        return False

    def fly(self, duration: float) -> str:
        """Let the companion fly for ``duration`` s, or until a collision, the companion exits or
        (``--mission``) it announces the mission complete (then a moment more: it holds there).

        :return: why the flight ended early ("" when it ran its course, collided or completed)
        """
        end = time.monotonic() + duration
        while time.monotonic() < end and not self._stop.is_set():
            if self.recorder.collision_time is not None:
                return ""
            if self.options.mission and self.recorder.first_text(COMPLETE_MARK, 0.0) is not None:
                end = min(end, time.monotonic() + COMPLETE_HOLD_S)
            if not self.companion_alive():
                return self.companion_exit()
            if self.server is not None and self.server.error is not None:
                raise RuntimeError(f"simulated autopilot failed: {self.server.error}")
            time.sleep(0.05)
        return ""

    # ------------------------------------------------------------------ report
    def report(self, plot: Path | None = None, error: str = "") -> FlightReport:
        rec = self.recorder
        with rec.lock:
            traj = np.array(
                [row for row in rec.trajectory if self.engaged_at is None or row[0] >= self.engaged_at]
            )
            sp_times = [t for t in rec.setpoint_times if self.engaged_at is None or t >= self.engaged_at]
            texts = [text for _, text in rec.statustexts]
        end = rec.collision_time or (traj[-1, 0] if len(traj) else 0.0)
        if len(traj) and rec.collision_time is not None:
            traj = traj[traj[:, 0] <= rec.collision_time]
        distance = (
            float(np.sum(np.linalg.norm(np.diff(traj[:, 1:3], axis=0), axis=1))) if len(traj) > 1 else 0.0
        )
        flight_time = float(end - self.engaged_at) if self.engaged_at is not None and len(traj) else 0.0
        rate = 0.0
        if len(sp_times) > 1:
            rate = (len(sp_times) - 1) / (sp_times[-1] - sp_times[0])
        ends = (
            []
            if self.cosim is None
            else [e for e in self.cosim.stats.revolution_ends if e >= (self.engaged_at or 0)]
        )
        lat = latency_ms(ends, sp_times)
        malformed: dict[str, int] = {}
        if self.server is not None:
            malformed["autopilot_malformed"] = self.server.endpoint.counters.get("malformed", 0)
        result = FlightReport(
            world=self.world.name,
            autopilot=self.options.autopilot,
            engaged=self.engaged_at is not None,
            collision=rec.collision_time is not None,
            flight_time_s=round(flight_time, 2),
            distance_m=round(distance, 2),
            min_clearance_m=round(float(rec.min_clearance), 3) if math.isfinite(rec.min_clearance) else None,
            setpoint_rate_hz=round(rate, 2),
            latency_p50_ms=round(float(np.percentile(lat, 50)), 1) if lat else None,
            latency_p99_ms=round(float(np.percentile(lat, 99)), 1) if lat else None,
            transitions=[
                t for t in texts if any(s in t for s in ("ACTIVE", "HOLD", "STANDBY", "OVERRIDE", "WAIT"))
            ],
            malformed=malformed,
            error=error,
            recording=str(self.recording.path),
            ground_truth=self.ground_truth,
            position_wait_s=round(self.position_wait_s, 1),
            warnings=[external_sitl.ESTIMATE_WARNING] if self.ground_truth == "estimate" else [],
        )
        source = "simulator" if self.external is None else self.external.altitude_source
        engaged = len(traj) and self.engaged_at is not None
        result.judge_height(traj[:, 3] if engaged else np.zeros(0), self.world.room_height, source)
        if self.options.mission:
            reached = waypoints_reached(self.world, traj, self.engaged_at)
            result.waypoints_reached = reached
            result.waypoints_total = len(self.world.waypoints)
            with rec.lock:
                result.items_reached = list(rec.items_reached)
            result.mission_complete = len(reached) == len(self.world.waypoints)
            result.mission_time_s = reached[-1][1] if result.mission_complete else -1.0
            result.goal_events = [t for t in texts if "goal" in t or "mission" in t]
        if plot is not None:
            with rec.lock:
                full = np.array(rec.trajectory)
            plot_flight(
                self.world, full, self.engaged_at, rec.collision_time, plot,
                title=result.title(), world_t0=rec.t0,
            )  # fmt: skip
            result.plot = str(plot)
        return result


def run_flight(options: FlightOptions, plot: Path | None = None, vehicle: Any = None) -> FlightReport:
    """One complete flight: start everything, take off, let the companion fly, report, clean up."""
    with SitlFlight(options, vehicle=vehicle) as flight:
        error = ""
        try:
            flight.wait_companion_up()
            if options.mission:
                flight.upload_mission()
            flight.take_off()
            if flight.wait_engaged(options.engage_timeout):
                error = flight.fly(options.duration)
            elif not flight.companion_alive():
                error = flight.companion_exit()
            else:
                error = f"the companion never engaged (see {flight.log_path})"
        except KeyboardInterrupt:
            error = INTERRUPTED
        except RuntimeError as exc:
            error = str(exc)
        return flight.report(plot, error)
