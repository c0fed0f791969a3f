"""Goal tracking (pure): where the vehicle is, which waypoint is next, and that goal in the body frame.

:class:`NavInputs` keeps the navigation messages the autopilot streams (LOCAL_POSITION_NED for the
position, ATTITUDE or GLOBAL_POSITION_INT for the heading, GPS_GLOBAL_ORIGIN or GLOBAL_POSITION_INT
beside LOCAL_POSITION_NED for the origin). :class:`GoalTracker` walks a list of local-NED waypoints:
each is reached within its acceptance radius as the firmware judges it (3D on ArduPilot, horizontal
and vertical on PX4), a mission's starts and resumes at the autopilot's current item, progress is
reported as events, and every update says either where the current waypoint is in the body frame
or why the vehicle must hold.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from companion.guidance.goal_frames import GlobalOrigin, ned_to_body_flu, offset_global

#: LOCAL_POSITION_NED older than this is no position at all, seconds (then: HOLD).
POSITION_TIMEOUT_S = 1.0
#: GLOBAL_POSITION_INT and LOCAL_POSITION_NED this close in time describe the same instant, seconds.
ORIGIN_PAIRING_S = 0.2
#: Gain of the altitude loop: vertical speed per metre of height error, 1/s.
VERTICAL_GAIN = 1.0


@dataclass(frozen=True)
class Waypoint:
    """A goal in local NED metres.

    :param north: metres north of the origin
    :param east: metres east of the origin
    :param down: metres below the origin (negative: above)
    :param acceptance_radius: reached within this distance, metres (None: the configured one)
    :param label: how announcements name it (a mission item's sequence number, or "fixed 2")
    :param seq: the mission item it came from (MISSION_ITEM_REACHED names it); None: not a mission's
    :param altitude_radius: reached within ``acceptance_radius`` horizontally and this vertically,
        metres, as PX4 judges a mission item (NAV_MC_ALT_RAD); None: within ``acceptance_radius``
        in 3D, as ArduPilot's waypoint navigation does (WPNAV_RADIUS along its 3D track)
    """

    north: float
    east: float
    down: float
    acceptance_radius: float | None = None
    label: str = ""
    seq: int | None = None
    altitude_radius: float | None = None

    def distance(self, position: tuple[float, float, float]) -> float:
        return math.dist((self.north, self.east, self.down), position)

    def reached(self, position: tuple[float, float, float], radius: float) -> bool:
        """Within ``radius`` (and :attr:`altitude_radius`) of ``position``, as the firmware judges it."""
        if self.altitude_radius is None:
            return self.distance(position) <= radius
        horizontal = math.dist((self.north, self.east), position[:2])
        return horizontal <= radius and abs(self.down - position[2]) <= self.altitude_radius


@dataclass
class NavInputs:
    """The latest navigation messages from the autopilot, with the clock times they arrived."""

    position: tuple[float, float, float] | None = None
    position_time: float = -math.inf
    velocity: tuple[float, float] | None = None  # LOCAL_POSITION_NED's (north, east), m/s
    heading: float | None = None
    roll: float = 0.0  # ATTITUDE roll (FRD), rad
    pitch: float = 0.0  # ATTITUDE pitch (nose up), rad
    height: float | None = None  # GLOBAL_POSITION_INT relative_alt: the estimate's height above home, m
    origin: GlobalOrigin | None = None
    origin_from_gps_origin: bool = False
    home_amsl: float | None = None
    _global: tuple[float, Any] | None = field(default=None, repr=False)

    def on_message(self, msg: Any, now: float) -> None:
        """Take one decoded MAVLink message (others are ignored)."""
        kind = msg.get_type()
        if kind == "LOCAL_POSITION_NED":
            values = (float(msg.x), float(msg.y), float(msg.z))
            if all(math.isfinite(v) for v in values):
                self.position, self.position_time = values, now
                velocity = (float(msg.vx), float(msg.vy))
                self.velocity = velocity if all(math.isfinite(v) for v in velocity) else None
                self._pair_origin(now)
        elif kind == "ATTITUDE":
            if math.isfinite(msg.yaw):
                self.heading = float(msg.yaw)
            if math.isfinite(msg.roll) and math.isfinite(msg.pitch):
                self.roll, self.pitch = float(msg.roll), float(msg.pitch)
        elif kind == "GLOBAL_POSITION_INT":
            self.home_amsl = (msg.alt - msg.relative_alt) / 1000.0
            self.height = msg.relative_alt / 1000.0
            if msg.hdg != 65535:
                self.heading = math.radians(msg.hdg / 100.0)
            self._global = (now, msg)
            self._pair_origin(now)
        elif kind == "GPS_GLOBAL_ORIGIN":
            self.origin = GlobalOrigin(int(msg.latitude), int(msg.longitude), msg.altitude / 1000.0)
            self.origin_from_gps_origin = True
        elif kind == "HOME_POSITION":
            self.home_amsl = msg.altitude / 1000.0

    def _pair_origin(self, now: float) -> None:
        """Without GPS_GLOBAL_ORIGIN: origin = global position minus local position, same instant."""
        if self.origin_from_gps_origin or self._global is None or self.position is None:
            return
        t, g = self._global
        if abs(self.position_time - t) > ORIGIN_PAIRING_S or (g.lat == 0 and g.lon == 0):
            return
        n, e, d = self.position
        lat, lon = offset_global(g.lat, g.lon, -n, -e)
        self.origin = GlobalOrigin(round(lat), round(lon), g.alt / 1000.0 + d)

    def position_fresh(self, now: float) -> bool:
        return self.position is not None and now - self.position_time <= POSITION_TIMEOUT_S


@dataclass(frozen=True)
class GoalOutput:
    """One update's answer.

    :param hold_reason: why the vehicle must hold (None: fly toward ``goal_body``)
    :param goal_body: the current waypoint from the vehicle, body FLU metres (x forward, y left, z up)
    :param vertical_speed: climb rate toward the waypoint's height, up positive, bounded, m/s
    :param index: index of the current waypoint (== number of waypoints when complete)
    :param complete: every waypoint reached
    """

    hold_reason: str | None
    goal_body: tuple[float, float, float] | None = None
    vertical_speed: float = 0.0
    index: int = 0
    complete: bool = False


class GoalTracker:
    """Walk the waypoints in order; report each reached one and the end.

    :param acceptance_radius: the radius for waypoints that carry none, metres
    :param max_vertical_speed: bound of :attr:`GoalOutput.vertical_speed`, m/s
    """

    def __init__(self, acceptance_radius: float, max_vertical_speed: float) -> None:
        self._radius = acceptance_radius
        self._max_vz = max_vertical_speed
        self.waypoints: tuple[Waypoint, ...] = ()
        self.index = 0
        self.events: list[str] = []  # progress to announce, oldest first (drained by the caller)
        self.reached_items: list[int] = []  # mission items reached, for MISSION_ITEM_REACHED (drained)
        self._completed_announced = False

    def radius(self, wp: Waypoint) -> float:
        return wp.acceptance_radius if wp.acceptance_radius else self._radius

    def set_waypoints(self, waypoints: tuple[Waypoint, ...] | list[Waypoint],
                      current_seq: int | None = None) -> None:
        """A new list; the same list again changes nothing. A mission's starts, or resumes after a
        change, at the autopilot's current item (MISSION_CURRENT ``seq``), as the firmware would fly
        it: the first waypoint from that item on, else (none known, or past the end) the first.
        """
        if tuple(waypoints) == self.waypoints:
            return  # downloaded again but unchanged: carry on where we are
        self.waypoints = tuple(waypoints)
        self._completed_announced = False
        self.index = self._index_of(current_seq) or 0
        if self.waypoints:
            self.events.append(f"goal: {len(self.waypoints)} waypoints, next {self._name(self.index)}")

    def _index_of(self, seq: int | None) -> int | None:
        """The first waypoint from mission item ``seq`` on (None: no such waypoint, or no seq)."""
        if seq is None:
            return None
        return next((i for i, wp in enumerate(self.waypoints) if wp.seq is not None and wp.seq >= seq), None)

    @property
    def current_seq(self) -> int | None:
        """The mission item flown to now (None: not a mission's, or complete)."""
        return self.waypoints[self.index].seq if self.index < len(self.waypoints) else None

    def follow_current(self, seq: int) -> None:
        """The autopilot's current item changed to ``seq`` (a ground station set it): fly to it."""
        i = self._index_of(seq)
        if i is None or i == self.index or self.waypoints[i].seq != seq:
            return
        self.index = i
        self._completed_announced = False
        self.events.append(f"goal: autopilot's current item is {seq}, next {self._name(i)}")

    def autopilot_reached(self, seq: int) -> None:
        """The autopilot reports mission item ``seq`` reached (MISSION_ITEM_REACHED): past it."""
        while (current := self.current_seq) is not None and current <= seq:
            self.events.append(f"goal: autopilot reached {self._name(self.index)} "
                               f"({self.index + 1}/{len(self.waypoints)})")
            self.index += 1

    def _name(self, i: int) -> str:
        return self.waypoints[i].label or f"waypoint {i + 1}"

    def update(self, nav: NavInputs, now: float, height_correction: float = 0.0) -> GoalOutput:
        """Advance past reached waypoints; say where the current one is, or why to hold.

        :param height_correction: metres to add to the estimate's down coordinate for the true
            height (the lidar's measure of the estimate's drift; 0: the estimate is right)
        """
        if not self.waypoints:
            return GoalOutput("no waypoints")
        if not nav.position_fresh(now):
            return GoalOutput("no position", index=self.index)
        assert nav.position is not None
        pos = (nav.position[0], nav.position[1], nav.position[2] + height_correction)
        while self.index < len(self.waypoints):
            wp = self.waypoints[self.index]
            if not wp.reached(pos, self.radius(wp)):
                break
            if wp.seq is not None:
                self.reached_items.append(wp.seq)
            self.events.append(f"goal: reached {self._name(self.index)} "
                               f"({self.index + 1}/{len(self.waypoints)})")
            self.index += 1
        if self.index >= len(self.waypoints):
            if not self._completed_announced:
                self.events.append("goal: complete, holding")
                self._completed_announced = True
            return GoalOutput("goal complete", index=self.index, complete=True)
        if nav.heading is None:
            return GoalOutput("no heading", index=self.index)
        wp = self.waypoints[self.index]
        delta = (wp.north - pos[0], wp.east - pos[1], wp.down - pos[2])
        body = ned_to_body_flu(delta, nav.heading)
        vz = max(-self._max_vz, min(self._max_vz, VERTICAL_GAIN * body[2]))
        return GoalOutput(None, goal_body=body, vertical_speed=vz, index=self.index)

    def drain_events(self) -> list[str]:
        out, self.events = self.events, []
        return out

    def drain_reached_items(self) -> list[int]:
        out, self.reached_items = self.reached_items, []
        return out
