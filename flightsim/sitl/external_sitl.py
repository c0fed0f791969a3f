"""``avoid-sim fly --autopilot external``: a SITL that flies its own physics, mirrored into the world.

The SITL is a real ArduPilot or PX4 build, or ``avoid-sim autopilot`` run as its own process (which
is how CI tests this path). The harness is its ground station and the MAVLink router between it and
the companion; this module is the part that differs from the simulated autopilots:

- **Link**: the ground-station link is pumped from connect onwards (heartbeats out, everything in,
  relayed to the companion), so the companion hears the autopilot before anything is armed.
- **Frame**: the SITL's pose when the harness anchors it (on the ground, before take-off) is put at
  the world's start position, and the SITL's frame is rotated so that its heading then is the
  world's start yaw. The world is rotated into the SITL's heading rather than the vehicle yawed
  after take-off: no extra manoeuvre, and the companion starts facing what the world says.
- **Ground truth**: collisions, clearance, height and the lidar use the simulator's truth where the
  SITL sends it: SIMSTATE from ArduPilot SITL (lat/lng, attitude) with its SIM_STATE for the
  altitude (SIMSTATE carries none; SIM_STATE's lat/lon are float32 degrees, decimetres, so only its
  altitude is taken), HIL_STATE_QUATERNION from PX4 SIH (lat/lon/alt, quaternion, velocity), all
  asked for with MAV_CMD_SET_MESSAGE_INTERVAL. Without
  them the autopilot's estimate (LOCAL_POSITION_NED + ATTITUDE) is used and the report says so:
  PX4's estimate was measured 0.2-0.4 m/s off the truth, and one flight's true clearance fell
  below the vehicle radius 11 s before the estimate's did.
- **Mission** (``--mission``): the world's waypoints are placed from the anchored vehicle's
  GLOBAL_POSITION_INT and turned back into the SITL's frame (:meth:`ExternalPose.mission_frame`);
  the ground station uploads them as it does to the simulated autopilots.
- **Before arming**: a vehicle still armed from a previous flight is landed (LAND) and disarmed,
  or the flight is refused with a message saying what to do; PX4 is switched to Hold first (it
  refuses to arm after a flight that ended in OFFBOARD).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from pymavlink.quaternion import QuaternionBase

from companion.guidance.goal_frames import GlobalOrigin, global_to_local_ne
from flightsim.worlds.world import World

log = logging.getLogger(__name__)

#: ground-truth messages of the SITLs (ArduPilot's SIMSTATE has no altitude: its SIM_STATE does), and
#: the rate asked for them
TRUTH_MESSAGES = ("SIMSTATE", "SIM_STATE", "HIL_STATE_QUATERNION")
TRUTH_RATE_HZ = 50.0
#: estimate streams the mirror needs, and their rate
ESTIMATE_MESSAGES = ("LOCAL_POSITION_NED", "ATTITUDE", "GLOBAL_POSITION_INT")
ESTIMATE_RATE_HZ = 20.0
#: how long to wait by default for the autopilot's first position (a fresh ArduPilot SITL needs 40-47 s), s
POSITION_TIMEOUT_S = 120.0
#: how often the wait for a position says how long it has waited, s
POSITION_PROGRESS_S = 5.0
#: how long to wait for a truth message before judging on the estimate, s
TRUTH_WAIT_S = 3.0
#: a vehicle armed at connect must have landed and disarmed within this, s
LAND_TIMEOUT_S = 60.0

PoseCallback = Callable[[float, np.ndarray, float, float], None]


def _wrap(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))


class ExternalPose:
    """The SITL's pose in the world frame, from its truth where it sends one, else its estimate.

    Thread-safe: the ground-station pump updates it, the lidar co-simulation reads it.

    :param world: the room; its start position and yaw are where the anchored pose goes
    """

    def __init__(self, world: World) -> None:
        self.start_xy = np.array(world.start_position[:2], dtype=np.float64)
        self.start_yaw = math.radians(world.start_yaw_deg)
        self.truth_source: str | None = None  # the truth message seen, None: none yet
        self._lock = threading.Lock()
        self._est_ned: np.ndarray | None = None
        self._est_vel_ned = np.zeros(3)
        self._est_rpy = (0.0, 0.0, math.nan)  # roll, pitch (FRD), yaw (NED)
        self._est_ll: tuple[int, int] | None = None  # GLOBAL_POSITION_INT lat, lon, degrees × 1e7
        self._truth_ll: tuple[int, int] | None = None  # lat, lon, degrees × 1e7
        self._truth_alt: float | None = None  # m AMSL (HIL_STATE_QUATERNION, SIM_STATE)
        self._alt_source: str | None = None  # the message the true altitude comes from
        self._truth_rpy = (0.0, 0.0, math.nan)
        self._truth_vel_ned: np.ndarray | None = None
        self._anchor: dict[str, Any] | None = None

    # ------------------------------------------------------------------ input
    def update(self, msg: Any) -> str | None:
        """Take one message; returns ``"truth"`` or ``"estimate"`` when the pose it gives changed."""
        kind = msg.get_type()
        with self._lock:
            if kind == "LOCAL_POSITION_NED":
                self._est_ned = np.array([msg.x, msg.y, msg.z], dtype=np.float64)
                self._est_vel_ned = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64)
                return "estimate"
            if kind == "ATTITUDE":
                self._est_rpy = (float(msg.roll), float(msg.pitch), float(msg.yaw))
                return None
            if kind == "GLOBAL_POSITION_INT":
                if msg.lat != 0 or msg.lon != 0:  # 0, 0: sent before the GPS fix, no position yet
                    self._est_ll = (int(msg.lat), int(msg.lon))
                return None
            if kind == "SIMSTATE":
                self.truth_source = kind
                self._truth_ll = (msg.lat, msg.lng)
                self._truth_rpy = (float(msg.roll), float(msg.pitch), float(msg.yaw))
                return "truth"
            if kind == "SIM_STATE":
                if not math.isfinite(msg.alt):
                    return None
                self._truth_alt = float(msg.alt)
                self._alt_source = kind
                return "truth" if self.truth_source is not None else None
            if kind == "HIL_STATE_QUATERNION":
                q = np.array(msg.attitude_quaternion, dtype=np.float64)
                if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 0.5:
                    return None  # no attitude in it: not a truth to judge on
                self.truth_source = kind
                roll, pitch, yaw = QuaternionBase(q / np.linalg.norm(q)).euler
                self._truth_ll = (msg.lat, msg.lon)
                self._truth_alt = msg.alt / 1000.0
                self._alt_source = kind
                self._truth_rpy = (float(roll), float(pitch), float(yaw))
                self._truth_vel_ned = np.array([msg.vx, msg.vy, msg.vz], dtype=np.float64) / 100.0
                return "truth"
        return None

    @property
    def altitude_source(self) -> str:
        """What the height is judged on: the truth message giving it, or ``"estimate"``."""
        with self._lock:
            if self._anchor is not None and self._anchor.get("truth_alt") is None:
                return "estimate"  # no true altitude when anchored: the estimate's, throughout
            return self._alt_source or "estimate"

    def missing_estimate(self) -> list[str]:
        """The estimate messages not heard yet (empty: the world can be anchored)."""
        with self._lock:
            return [name for name, seen in (
                ("LOCAL_POSITION_NED", self._est_ned is not None),
                ("ATTITUDE", math.isfinite(self._est_rpy[2])),
                ("GLOBAL_POSITION_INT", self._est_ll is not None),
            ) if not seen]  # fmt: skip

    def anchor(self) -> None:
        """Fix the mapping: the pose now (vehicle on the ground) is the world's start pose."""
        with self._lock:
            if self._est_ned is None or not math.isfinite(self._est_rpy[2]):
                raise RuntimeError("external SITL: no LOCAL_POSITION_NED and ATTITUDE to anchor the world to")
            anchor: dict[str, Any] = {"est_ned": self._est_ned.copy(), "est_ll": self._est_ll}
            if self.truth_source is not None and self._truth_ll is not None:
                anchor["truth_ll"] = self._truth_ll
                anchor["truth_alt"] = self._truth_alt
                yaw_ned = self._truth_rpy[2]
            else:
                yaw_ned = self._est_rpy[2]
            # rotation from the SITL's ENU frame into the world's: its heading now → start yaw
            anchor["theta"] = _wrap(self.start_yaw - (math.pi / 2 - yaw_ned))
            self._anchor = anchor
        log.info("external SITL anchored: heading rotated by %.1f deg onto the world's start yaw",
                 math.degrees(anchor["theta"]))

    # ------------------------------------------------------------------ output
    def mission_frame(self) -> tuple[tuple[int, int], float]:
        """Where the world's start is on Earth and how the world is turned, for a mission upload:
        ((lat, lon) × 1e7 of the anchored vehicle, the world's rotation from the SITL's ENU, rad).

        The origin is the autopilot's own GLOBAL_POSITION_INT where the world was anchored, not its
        HOME_POSITION: both firmwares move home there when the vehicle arms, and until then home may
        still be where a previous flight took off (the companion then judges the waypoints in the
        same estimate the autopilot flies by).

        :raises RuntimeError: not anchored, or the SITL sent no GLOBAL_POSITION_INT by then
        """
        with self._lock:
            if self._anchor is None or self._anchor["est_ll"] is None:
                raise RuntimeError("external SITL: no GLOBAL_POSITION_INT when the world was anchored, "
                                   "so the mission has no place on Earth")
            return self._anchor["est_ll"], float(self._anchor["theta"])

    def state(self) -> Any:
        """A :class:`~flightsim.vehicle.quadrotor.VehicleState` in the world frame (start pose
        until anchored)."""
        from flightsim.vehicle.quadrotor import VehicleState

        with self._lock:
            anchor = self._anchor
            if anchor is None or self._est_ned is None:
                return VehicleState(
                    time=0.0, position=np.array([*self.start_xy, 0.0]), velocity=np.zeros(3),
                    roll=0.0, pitch=0.0, yaw=self.start_yaw, angular_rate=np.zeros(3),
                    on_ground=True, armed=False,
                )  # fmt: skip
            d_ned = self._est_ned - anchor["est_ned"]
            up = -float(d_ned[2])
            vel_ned = self._est_vel_ned
            roll, pitch, yaw_ned = self._est_rpy
            if "truth_ll" in anchor and self._truth_ll is not None:
                north, east = global_to_local_ne(*self._truth_ll, GlobalOrigin(*anchor["truth_ll"], 0.0))
                d_ned = np.array([north, east, d_ned[2]])
                if self._truth_alt is not None and anchor["truth_alt"] is not None:
                    up = self._truth_alt - anchor["truth_alt"]  # none (SIMSTATE alone): the estimate's
                if self._truth_vel_ned is not None:
                    vel_ned = self._truth_vel_ned
                roll, pitch, yaw_ned = self._truth_rpy
            theta = anchor["theta"]
            c, s = math.cos(theta), math.sin(theta)
            rot = np.array([[c, -s], [s, c]])
            xy = self.start_xy + rot @ np.array([d_ned[1], d_ned[0]])
            vxy = rot @ np.array([vel_ned[1], vel_ned[0]])
        return VehicleState(
            time=0.0,
            position=np.array([xy[0], xy[1], up]),
            velocity=np.array([vxy[0], vxy[1], -float(vel_ned[2])]),
            roll=roll,
            pitch=-pitch,
            yaw=_wrap(math.pi / 2 - yaw_ned + theta),
            angular_rate=np.zeros(3),
            on_ground=up < 0.1,
            armed=True,
        )


def request_streams(gcs: Any) -> None:
    """Ask the SITL for what the mirror needs: every data stream at 10 Hz (ArduPilot's SRx_ rates
    may be zero), the estimate at 20 Hz and the truth messages at 50 Hz (an autopilot that does not
    know one refuses it, which is how a SITL without truth shows)."""
    from pymavlink import mavutil

    mav = gcs.mav.mav
    mav.request_data_stream_send(gcs.target_system, 1, 0, 10, 1)
    for names, rate in ((ESTIMATE_MESSAGES, ESTIMATE_RATE_HZ), (TRUTH_MESSAGES, TRUTH_RATE_HZ)):
        for name in names:
            msg_id = getattr(mavutil.mavlink, f"MAVLINK_MSG_ID_{name}")
            mav.command_long_send(gcs.target_system, 1, mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                  msg_id, 1e6 / rate, 0, 0, 0, 0, 0)


def land_and_disarm(gcs: Any, timeout: float = LAND_TIMEOUT_S) -> bool:
    """A vehicle left armed by a previous flight: land it (LAND) and wait for its disarm.

    :return: True when something had to be done
    :raises RuntimeError: it did not disarm within ``timeout``, naming what the user should do
    """
    from pymavlink import mavutil

    if not gcs.armed:
        return False
    log.warning("the external SITL is armed (%s, %.1f m): landing and disarming it before this flight",
                gcs.mode, gcs.altitude)
    try:
        if gcs.altitude > 0.3 or not math.isfinite(gcs.altitude):
            gcs.set_mode("LAND")
        else:
            gcs.command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0)
        gcs.wait(lambda: not gcs.armed, timeout, "the vehicle to land and disarm")
    except RuntimeError as exc:
        raise RuntimeError(
            f"the external SITL is armed (left flying by a previous flight?) and could not be landed "
            f"and disarmed ({exc}): land and disarm it from a ground station, or restart the SITL"
        ) from None
    return True


def wait_for_position(
    pose: ExternalPose,
    timeout: float = POSITION_TIMEOUT_S,
    progress_every: float = POSITION_PROGRESS_S,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> float:
    """Wait as a pilot does for the autopilot's position (its EKF origin), saying every
    ``progress_every`` s how long it has waited; the pump fills ``pose`` meanwhile.

    :return: the seconds waited
    :raises RuntimeError: ``timeout`` s passed, naming what never arrived
    """
    start = clock()
    next_note = start + progress_every
    while missing := pose.missing_estimate():
        now = clock()
        if now - start >= timeout:
            raise RuntimeError(
                f"external SITL: no {' / '.join(missing)} within {timeout:.0f} s: the autopilot never "
                "reported a position (no GPS fix or EKF origin?); raise --position-timeout or check the SITL"
            )
        if now >= next_note:
            log.info("waiting for EKF origin: %.0f s (no %s yet)", now - start, " / ".join(missing))
            next_note += progress_every
        sleep(0.05)
    return clock() - start


def wait_for_truth(pose: ExternalPose, pump: Callable[[float], None], timeout: float = TRUTH_WAIT_S) -> str:
    """Pump until a truth message arrives or ``timeout`` s pass; the source the report names."""
    end = time.monotonic() + timeout
    while pose.truth_source is None and time.monotonic() < end:
        pump(0.05)
    return pose.truth_source or "estimate"


ESTIMATE_WARNING = (
    "the SITL sends no ground truth (SIMSTATE / HIL_STATE_QUATERNION): collisions and clearance "
    "were judged on the autopilot's estimate, which can be off by decimetres"
)
