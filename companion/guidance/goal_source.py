"""Where the companion's goal comes from, and what it is now: the glue between link and tracker.

A :class:`GoalSource` is fed every message the link received from the autopilot (from any thread:
they are queued) and stepped by the main loop. It keeps the navigation inputs, runs the mission
download (``source = "mission"``) or takes the configured waypoints (``"fixed"``), hands the
waypoints to the :class:`~companion.guidance.goal.GoalTracker`, and says what the policy's goal is, or why
the vehicle must hold.

A mission follows the autopilot, as the firmware's own mission would: it starts, and resumes after a
real change, at the autopilot's current item (MISSION_CURRENT); a ground station setting another
current item moves the goal there, and an item the autopilot reports reached (MISSION_ITEM_REACHED)
is passed. The companion's own progress goes back as MISSION_SET_CURRENT, so the autopilot's current
item is the one flown to (and AUTO, if the pilot switches to it, carries on from there). A download
whose items are the same as the mission flown is no change, whatever its plan id.

Height (``goal.height_hold``): each revolution's height above the floor
(:func:`~companion.perception.floor.floor_height`) is compared with the autopilot's estimate of its
height above home. When they differ by more than ``goal.height_tolerance`` the goal's vertical
speed and its reach are judged on the lidar's height (the estimate plus the difference), so the
vehicle holds the mission altitude over the floor it flies above; back within half the tolerance,
or with the floor out of sight, the autopilot's estimate is flown again, and the pilot is told.

Requests for the autopilot go out through the ``send`` callable the link provides; text for the
pilot collects in :attr:`GoalSource.announcements`.
"""

from __future__ import annotations

import collections
import logging
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from companion.autopilot.mavlink_adapter import mavlink
from companion.guidance.goal import GoalOutput, GoalTracker, NavInputs, Waypoint
from companion.guidance.mission import (
    MAV_MISSION_TYPE_MISSION,
    Mission,
    MissionDownloader,
    Phase,
    Request,
    mission_waypoints,
)
from companion.perception.floor import floor_height
from companion.perception.scan import ScanConfig

log = logging.getLogger(__name__)

#: Messages a goal source uses; the links pass these on.
GOAL_MESSAGES = frozenset({
    "LOCAL_POSITION_NED", "ATTITUDE", "GLOBAL_POSITION_INT", "GPS_GLOBAL_ORIGIN", "HOME_POSITION",
    "MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ACK", "MISSION_CURRENT", "MISSION_ITEM_REACHED",
})
#: Streams a goal source needs beyond the supervisor's (heading without GPS, the plan id).
GOAL_STREAMS = ("ATTITUDE", "MISSION_CURRENT")
#: The estimate's error is the median of this many revolutions' (a stray revolution moves it little).
HEIGHT_WINDOW = 5
#: This many revolutions in a row without the floor in sight: the autopilot's altitude is flown.
FLOOR_LOST_REVOLUTIONS = 5
#: Most queued messages kept (the loop drains them every iteration; a flood drops the oldest).
QUEUE_LIMIT = 1024


class GoalSource:
    """The goal for the policy, from the configured source.

    :param config: the ``[goal]`` table (:class:`companion.config.GoalConfig`)
    :param own: (system, component) the companion sends as
    :param skip_home: the autopilot keeps home as mission item 0 (ArduPilot); it also says how an
        item is judged reached: ArduPilot in 3D within ``acceptance_radius``, PX4 within the item's own
        radius (else ``acceptance_radius``) horizontally and ``acceptance_altitude`` vertically
    :param clock: the loop's monotonic clock, seconds
    :param send: sends one :class:`~companion.guidance.mission.Request` to the autopilot
    """

    def __init__(self, config: Any, own: tuple[int, int], skip_home: bool, clock: Callable[[], float],
                 send: Callable[[Request], None]) -> None:
        self.config = config
        self._clock = clock
        self._send = send
        self._skip_home = skip_home
        self.nav = NavInputs()
        self.tracker = GoalTracker(config.acceptance_radius, config.max_vertical_speed)
        self.downloader = MissionDownloader(own, skip_home, config.download_timeout, config.download_retries)
        self.announcements: list[str] = []
        self._queue: collections.deque[Any] = collections.deque(maxlen=QUEUE_LIMIT)
        self._lock = threading.Lock()
        self._mission_used: Mission | None = None
        self._mission_problem: str | None = None
        self._current_seen: int | None = None  # the autopilot's current item, as last followed
        self._current_sent: set[int] = set()  # MISSION_SET_CURRENTs sent and not yet echoed
        self._started = False
        self._floor: collections.deque[float] = collections.deque(maxlen=HEIGHT_WINDOW)  # estimate - lidar
        self._floor_missed = 0
        self._floor_seen: bool | None = None  # as last announced
        self.height_correction = 0.0  # m added to the estimate's down coordinate (lidar - estimate)
        self.output = GoalOutput("starting")
        if config.source == "fixed":
            self.tracker.set_waypoints(
                [Waypoint(w.north, w.east, w.down, w.acceptance_radius or None, f"fixed {i + 1}")
                 for i, w in enumerate(config.waypoints)], None)

    def on_message(self, msg: Any) -> None:
        """A message from the autopilot (any thread)."""
        if msg.get_type() in GOAL_MESSAGES:
            with self._lock:
                self._queue.append(msg)

    def step(self, autopilot_found: bool) -> GoalOutput:
        """Process queued messages, run the download, update the tracker; return the goal."""
        now = self._clock()
        with self._lock:
            messages, self._queue = list(self._queue), collections.deque(maxlen=QUEUE_LIMIT)
        requests: list[Request] = []
        for msg in messages:
            self.nav.on_message(msg, now)
            if self.config.source == "mission":
                requests += self.downloader.on_message(msg, now)
                if msg.get_type() == "MISSION_ITEM_REACHED" and self._mission_used is self.downloader.mission:
                    self.tracker.autopilot_reached(int(msg.seq))
        if self.config.source == "mission" and autopilot_found:
            if not self._started:
                self._started = True
                requests += self.downloader.start(now)
            requests += self.downloader.tick(now)
        for request in requests:
            self._send(request)
        self.announcements += self.downloader.drain_events()
        self.output = self._goal(now)
        self.announcements += self.tracker.drain_events()
        return self.output

    def observe_cloud(self, points: np.ndarray, scan: ScanConfig) -> None:
        """One revolution's returns (sensor frame): the height above the floor, and from it how far
        the autopilot's altitude estimate is off (``goal.height_hold``)."""
        if not self.config.height_hold:
            return
        height = floor_height(points, scan, self.nav.roll, self.nav.pitch)
        if height is None:
            self._floor_missed += 1
            if self._floor_missed >= FLOOR_LOST_REVOLUTIONS:
                self._floor.clear()
                self._set_height_correction(0.0, "floor not in sight: flying the autopilot's altitude")
                self._announce_floor(False)
            return
        self._floor_missed = 0
        self._announce_floor(True)
        if self.nav.height is None:
            return
        # the estimate's error at each revolution, paired as measured (a climb moves both alike)
        self._floor.append(self.nav.height - height)
        drift = float(np.median(self._floor))  # > 0: the estimate says higher than the vehicle is
        tolerance = self.config.height_tolerance
        said = f"autopilot altitude {self.nav.height:.2f} m, lidar {height:.2f} m over the floor"
        if abs(drift) > tolerance or (self.height_correction and abs(drift) > tolerance / 2):
            self._set_height_correction(drift, f"{said}: holding the lidar's")
        else:
            self._set_height_correction(0.0, f"{said}: the autopilot's agrees again")

    def _set_height_correction(self, value: float, why: str) -> None:
        if (value == 0.0) != (self.height_correction == 0.0):
            self.announcements.append(f"height: {why}")
        self.height_correction = value

    def _announce_floor(self, seen: bool) -> None:
        if seen != self._floor_seen:
            if seen or self._floor_seen is not None:
                self.announcements.append("height: floor in sight" if seen else "height: floor not in sight")
            self._floor_seen = seen

    def _goal(self, now: float) -> GoalOutput:
        if self.config.source != "mission":
            return self.tracker.update(self.nav, now, self.height_correction)
        problem = self._use_mission()
        if problem is not None:
            return GoalOutput(problem, index=self.tracker.index)
        self._follow_current()
        before = self.tracker.current_seq
        output = self.tracker.update(self.nav, now, self.height_correction)
        after = self.tracker.current_seq
        if after is not None and after != before:  # our own progress: the autopilot's current item too
            self._current_sent.add(after)
            self._send(Request("MISSION_SET_CURRENT", after))
        return output

    def _follow_current(self) -> None:
        """A new current item from the autopilot (a ground station set it) moves the goal there;
        the echo of the companion's own MISSION_SET_CURRENT does not."""
        seq = self.downloader.current_seq
        if seq is None or seq == self._current_seen or not self.downloader.current_is_of_held():
            return
        self._current_seen = seq
        if seq in self._current_sent:
            self._current_sent.clear()
            return
        self.tracker.follow_current(seq)

    def _use_mission(self) -> str | None:
        """Give the tracker the downloaded mission once it can be placed; else why not."""
        d = self.downloader
        if d.phase is not Phase.DONE or d.mission is None:
            return "mission download failed" if d.phase is Phase.FAILED else "mission downloading"
        if d.mission is not self._mission_used and d.mission.same_items(self._mission_used):
            self._mission_used = d.mission  # downloaded again, nothing changed: carry on
            self.announcements.append(f"mission unchanged, carrying on to item {self.tracker.current_seq}")
        if d.mission is not self._mission_used:
            try:
                waypoints = mission_waypoints(d.mission, self.nav.origin, self.nav.home_amsl,
                                              item_radius=not self._skip_home,
                                              altitude_radius=None if self._skip_home
                                              else self.config.acceptance_altitude)
            except ValueError as exc:
                problem = str(exc)
                if problem != self._mission_problem:
                    self._mission_problem = problem
                    log.warning("mission not usable yet: %s", problem)
                if d.mission.problems():
                    return "mission has unsupported items"
                return problem
            if not waypoints:
                return "mission empty"
            self._mission_used = d.mission
            self._mission_problem = None
            self.tracker.set_waypoints(waypoints, d.current_seq)
            self._current_seen = d.current_seq
        return None

    def drain_announcements(self) -> list[str]:
        out, self.announcements = self.announcements, []
        return out


def request_message(request: Request, target: tuple[int, int]) -> Any:
    """``request`` as a pymavlink message addressed to the autopilot ``target``."""
    if request.kind == "MISSION_REQUEST_LIST":
        return mavlink.MAVLink_mission_request_list_message(*target, MAV_MISSION_TYPE_MISSION)
    if request.kind == "MISSION_REQUEST_INT":
        return mavlink.MAVLink_mission_request_int_message(*target, request.seq, MAV_MISSION_TYPE_MISSION)
    if request.kind == "MISSION_ACK":
        return mavlink.MAVLink_mission_ack_message(*target, request.result, MAV_MISSION_TYPE_MISSION)
    if request.kind == "MISSION_SET_CURRENT":
        return mavlink.MAVLink_mission_set_current_message(*target, request.seq)
    raise ValueError(f"unknown mission request {request.kind!r}")


def reached_message(seq: int) -> Any:
    """MISSION_ITEM_REACHED for mission item ``seq``, sent beside the STATUSTEXT: in GUIDED/OFFBOARD
    the autopilot is not flying the mission and reports no progress of its own, and scripts on the
    vehicle's link (MAVSDK's mission progress, MAVROS ``mission/reached``) read this message."""
    return mavlink.MAVLink_mission_item_reached_message(seq)


#: DO_SET_MODE (param1 flags, param2, param3) asking for LAND or RTL: ArduCopter custom modes,
#: PX4 main mode AUTO (4) with its sub-mode.
_COMPLETION_MODES = {
    ("ardupilot", "land"): (9, 0),
    ("ardupilot", "rtl"): (6, 0),
    ("px4", "land"): (4, 6),
    ("px4", "rtl"): (4, 5),
}


def completion_mode_command(autopilot_type: str, on_complete: str, target: tuple[int, int]) -> Any:
    """The COMMAND_LONG (MAV_CMD_DO_SET_MODE) requesting ``on_complete``'s mode, once, at the end."""
    mode, sub = _COMPLETION_MODES[(autopilot_type, on_complete)]
    return mavlink.MAVLink_command_long_message(
        *target, mavlink.MAV_CMD_DO_SET_MODE, 0, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode, sub,
        0, 0, 0, 0)
