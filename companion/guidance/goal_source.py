"""Where the companion's goal comes from, and what it is now: the glue between link and tracker.

A :class:`GoalSource` is fed every message the link received from the autopilot (from any thread:
they are queued) and stepped by the main loop. It keeps the navigation inputs, runs the mission
download (``source = "mission"``) or takes the configured waypoints (``"fixed"``), hands the
waypoints to the :class:`~companion.guidance.goal.GoalTracker`, and says what the policy's goal is, or why
the vehicle must hold. Requests for the autopilot go out through the ``send`` callable the link
provides; text for the pilot collects in :attr:`GoalSource.announcements`.
"""

from __future__ import annotations

import collections
import logging
import threading
from collections.abc import Callable
from typing import Any

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

log = logging.getLogger(__name__)

#: Messages a goal source uses; the links pass these on.
GOAL_MESSAGES = frozenset({
    "LOCAL_POSITION_NED", "ATTITUDE", "GLOBAL_POSITION_INT", "GPS_GLOBAL_ORIGIN", "HOME_POSITION",
    "MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ACK", "MISSION_CURRENT",
})
#: Streams a goal source needs beyond the supervisor's (heading without GPS, the plan id).
GOAL_STREAMS = ("ATTITUDE", "MISSION_CURRENT")
#: Most queued messages kept (the loop drains them every iteration; a flood drops the oldest).
QUEUE_LIMIT = 1024


class GoalSource:
    """The goal for the policy, from the configured source.

    :param config: the ``[goal]`` table (:class:`companion.config.GoalConfig`)
    :param own: (system, component) the companion sends as
    :param skip_home: the autopilot keeps home as mission item 0 (ArduPilot)
    :param clock: the loop's monotonic clock, seconds
    :param send: sends one :class:`~companion.guidance.mission.Request` to the autopilot
    """

    def __init__(self, config: Any, own: tuple[int, int], skip_home: bool, clock: Callable[[], float],
                 send: Callable[[Request], None]) -> None:
        self.config = config
        self._clock = clock
        self._send = send
        self.nav = NavInputs()
        self.tracker = GoalTracker(config.acceptance_radius, config.max_vertical_speed)
        self.downloader = MissionDownloader(own, skip_home, config.download_timeout, config.download_retries)
        self.announcements: list[str] = []
        self._queue: collections.deque[Any] = collections.deque(maxlen=QUEUE_LIMIT)
        self._lock = threading.Lock()
        self._mission_used: Mission | None = None
        self._mission_problem: str | None = None
        self._started = False
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

    def _goal(self, now: float) -> GoalOutput:
        if self.config.source == "mission":
            problem = self._use_mission()
            if problem is not None:
                return GoalOutput(problem, index=self.tracker.index)
        return self.tracker.update(self.nav, now)

    def _use_mission(self) -> str | None:
        """Give the tracker the downloaded mission once it can be placed; else why not."""
        d = self.downloader
        if d.phase is not Phase.DONE or d.mission is None:
            return "mission download failed" if d.phase is Phase.FAILED else "mission downloading"
        if d.mission is not self._mission_used:
            try:
                waypoints = mission_waypoints(d.mission, self.nav.origin, self.nav.home_amsl)
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
            self.tracker.set_waypoints(waypoints, self.nav.position)
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
