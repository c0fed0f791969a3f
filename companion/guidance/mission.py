"""Mission download (pure): the MAVLink mission protocol as a state machine, and items to waypoints.

Driven like a MAVProxy module: :meth:`MissionDownloader.on_message` takes decoded messages from the
autopilot, :meth:`MissionDownloader.tick` takes the time; both return the requests to send
(:class:`Request`), which the link encodes. The download is MISSION_REQUEST_LIST → MISSION_COUNT →
MISSION_REQUEST_INT / MISSION_ITEM_INT per item → MISSION_ACK, each request retried a bounded
number of times. A finished download is watched for changes: a new ``mission_id`` in
MISSION_CURRENT, a new ``total`` there, or a mission accepted from someone else (a ground
station's upload: the autopilot's MISSION_ACK, or a MISSION_COUNT to the autopilot) starts a new one.

pymavlink 2.4 predates the plan-id extension fields (MISSION_CURRENT ``mission_id``, MISSION_COUNT
and MISSION_ACK ``opaque_id``), so :func:`extension_u32` reads them from the frame's payload.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import Enum
from typing import Any

from companion.guidance.goal import Waypoint
from companion.guidance.goal_frames import GlobalOrigin, global_to_local_ne

MAV_CMD_NAV_WAYPOINT = 16
MAV_MISSION_TYPE_MISSION = 0
MAV_MISSION_ACCEPTED = 0
MAV_MISSION_ERROR = 1
MAV_FRAME_GLOBAL = 0
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_GLOBAL_RELATIVE_ALT = 3
MAV_FRAME_GLOBAL_INT = 5
MAV_FRAME_GLOBAL_RELATIVE_ALT_INT = 6
#: frames whose altitude is above mean sea level / above home; x, y are degrees × 1e7
ABSOLUTE_FRAMES = (MAV_FRAME_GLOBAL, MAV_FRAME_GLOBAL_INT)
RELATIVE_FRAMES = (MAV_FRAME_GLOBAL_RELATIVE_ALT, MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
#: MAV_FRAME_LOCAL_NED items carry x, y as metres × 1e4 in MISSION_ITEM_INT
LOCAL_FRAMES = (MAV_FRAME_LOCAL_NED,)

#: float32's relative precision: two encodings of one value differ by no more
FLOAT32_EPS = 2.0**-23

#: Payload offsets of the plan-id extension fields (MAVLink common.xml wire order).
MISSION_CURRENT_MISSION_ID_OFFSET = 6
MISSION_COUNT_OPAQUE_ID_OFFSET = 5
MISSION_ACK_OPAQUE_ID_OFFSET = 4
MAVLINK2_HEADER_LEN = 10

#: Names for the commands and frames an unsupported item may use (the rest are reported by number).
COMMAND_NAMES = {16: "NAV_WAYPOINT", 17: "NAV_LOITER_UNLIM", 18: "NAV_LOITER_TURNS", 19: "NAV_LOITER_TIME",
                 20: "NAV_RETURN_TO_LAUNCH", 21: "NAV_LAND", 22: "NAV_TAKEOFF", 82: "NAV_SPLINE_WAYPOINT",
                 93: "NAV_DELAY", 112: "CONDITION_DELAY", 177: "DO_JUMP", 178: "DO_CHANGE_SPEED",
                 183: "DO_SET_SERVO", 201: "DO_SET_ROI", 206: "DO_SET_CAM_TRIGG_DIST"}
FRAME_NAMES = {0: "GLOBAL", 1: "LOCAL_NED", 2: "MISSION", 3: "GLOBAL_RELATIVE_ALT", 4: "LOCAL_ENU",
               5: "GLOBAL_INT", 6: "GLOBAL_RELATIVE_ALT_INT", 10: "GLOBAL_TERRAIN_ALT",
               11: "GLOBAL_TERRAIN_ALT_INT"}


def extension_u32(msg: Any, offset: int) -> int:
    """A uint32 extension field at ``offset`` in the payload (0 when absent or truncated away)."""
    buf = bytes(msg.get_msgbuf())
    if not buf or buf[0] != 0xFD:  # MAVLink 1 frames carry no extensions
        return 0
    payload = buf[MAVLINK2_HEADER_LEN: MAVLINK2_HEADER_LEN + buf[1]]
    payload = payload + bytes(max(0, offset + 4 - len(payload)))  # MAVLink 2 trims trailing zeros
    return int(struct.unpack_from("<I", payload, offset)[0])


@dataclass(frozen=True)
class MissionItem:
    """One MISSION_ITEM_INT as downloaded."""

    seq: int
    frame: int
    command: int
    param1: float
    param2: float
    x: int
    y: int
    z: float

    def same_as(self, other: MissionItem) -> bool:
        """The same item, within MISSION_ITEM_INT's precision (x, y integers, the rest float32)."""
        return (
            (self.seq, self.frame, self.command, self.x, self.y)
            == (other.seq, other.frame, other.command, other.x, other.y)
            and all(math.isclose(a, b, rel_tol=FLOAT32_EPS, abs_tol=FLOAT32_EPS)
                    for a, b in ((self.param1, other.param1), (self.param2, other.param2), (self.z, other.z)))
        )

    @classmethod
    def of(cls, msg: Any) -> MissionItem:
        return cls(int(msg.seq), int(msg.frame), int(msg.command), float(msg.param1), float(msg.param2),
                   int(msg.x), int(msg.y), float(msg.z))

    def unsupported(self) -> str | None:
        """Why the companion cannot fly this item (None: it can)."""
        if self.command != MAV_CMD_NAV_WAYPOINT:
            name = COMMAND_NAMES.get(self.command, f"command {self.command}")
            return f"item {self.seq}: {name} not supported"
        if self.frame not in ABSOLUTE_FRAMES + RELATIVE_FRAMES + LOCAL_FRAMES:
            return f"item {self.seq}: frame {FRAME_NAMES.get(self.frame, self.frame)} not supported"
        if not math.isfinite(self.z) or not math.isfinite(self.param2):
            return f"item {self.seq}: not a number"
        on_earth = abs(self.x) <= 900_000_000 and abs(self.y) <= 1_800_000_000
        if self.frame not in LOCAL_FRAMES and not on_earth:
            return f"item {self.seq}: latitude/longitude out of range"
        return None


@dataclass(frozen=True)
class Mission:
    """A complete, downloaded mission (ArduPilot's item 0, home, already left out)."""

    items: tuple[MissionItem, ...]
    mission_id: int = 0

    def problems(self) -> list[str]:
        return [p for p in (item.unsupported() for item in self.items) if p is not None]

    def same_items(self, other: Mission | None) -> bool:
        """Downloaded again with nothing changed (the plan id may differ: it is not an item)."""
        return other is not None and len(self.items) == len(other.items) and all(
            a.same_as(b) for a, b in zip(self.items, other.items, strict=True))

    @property
    def needs_origin(self) -> bool:
        return any(item.frame not in LOCAL_FRAMES for item in self.items)


def mission_waypoints(mission: Mission, origin: GlobalOrigin | None, home_amsl: float | None,
                      item_radius: bool = True, altitude_radius: float | None = None) -> list[Waypoint]:
    """The mission's items as local-NED waypoints, each reached as the firmware judges it.

    :param origin: where local NED (0, 0, 0) is (needed for global frames)
    :param home_amsl: home's altitude above sea level (needed for relative-altitude frames)
    :param item_radius: an item's own acceptance radius (param2 > 0) counts, as on PX4; False: the
        configured one for every item, as on ArduPilot Copter (its WPNAV_RADIUS; param2 unused)
    :param altitude_radius: reached within this vertically and the radius horizontally (PX4's
        NAV_MC_ALT_RAD), metres; None: within the radius in 3D (ArduPilot)
    :raises ValueError: an item is unsupported, or the origin / home it needs is unknown
    """
    problems = mission.problems()
    if problems:
        raise ValueError(problems[0])
    out = []
    for item in mission.items:
        radius = item.param2 if item_radius and item.param2 > 0 else None
        label = f"item {item.seq}"
        if item.frame in LOCAL_FRAMES:
            out.append(Waypoint(item.x / 1e4, item.y / 1e4, item.z, radius, label, item.seq, altitude_radius))
            continue
        if origin is None:
            raise ValueError("no origin")
        north, east = global_to_local_ne(item.x, item.y, origin)
        if item.frame in RELATIVE_FRAMES:
            if home_amsl is None:
                raise ValueError("no home altitude")
            amsl = home_amsl + item.z
        else:
            amsl = item.z
        out.append(Waypoint(north, east, -(amsl - origin.alt_amsl), radius, label, item.seq, altitude_radius))
    return out


@dataclass(frozen=True)
class Request:
    """A message for the link to send to the autopilot.

    :param kind: ``MISSION_REQUEST_LIST``, ``MISSION_REQUEST_INT``, ``MISSION_ACK`` or
        ``MISSION_SET_CURRENT``
    :param seq: item asked for (MISSION_REQUEST_INT) or made current (MISSION_SET_CURRENT)
    :param result: MAV_MISSION_RESULT (MISSION_ACK)
    """

    kind: str
    seq: int = 0
    result: int = 0


class Phase(Enum):
    IDLE = "idle"  # nothing asked yet
    LISTING = "listing"  # MISSION_REQUEST_LIST sent, waiting for MISSION_COUNT
    ITEMS = "items"  # MISSION_REQUEST_INT sent, waiting for the item
    DONE = "done"  # a mission is held; watching for changes
    FAILED = "failed"  # retries exhausted; a new attempt after ``retry_after``


class MissionDownloader:
    """Download the autopilot's mission and keep it current.

    :param own: (system, component) the companion sends as: replies addressed elsewhere are not ours
    :param skip_home: leave out item 0 (ArduPilot stores home there)
    :param timeout: wait for each reply, seconds
    :param retries: times a request is repeated before the download fails
    :param retry_after: wait before a failed download starts over, seconds
    :param change_settle: wait after a sign of a new mission before downloading it, seconds
    """

    def __init__(self, own: tuple[int, int], skip_home: bool, timeout: float = 1.0, retries: int = 5,
                 retry_after: float = 5.0, change_settle: float = 0.5) -> None:
        self._own = own
        self._skip_home = skip_home
        self._timeout = timeout
        self._retries = retries
        self._retry_after = retry_after
        self._settle = change_settle
        self.phase = Phase.IDLE
        self.mission: Mission | None = None
        self.events: list[str] = []  # to announce, oldest first
        self.counters: dict[str, int] = {"downloads": 0, "timeouts": 0, "failures": 0, "changes": 0}
        self._count = 0
        self._items: dict[int, MissionItem] = {}
        self._next = 0
        self._deadline = math.inf
        self._tries = 0
        self._opaque_id = 0
        self._latest_current: tuple[int, int] | None = None  # (plan id, total) of the last MISSION_CURRENT
        self.current_seq: int | None = None  # the autopilot's current item (the last MISSION_CURRENT)
        self._current_at_start: tuple[int, int] | None = None  # ... when the download began
        self._reference: tuple[int, int] | None = None  # ... of the mission held
        self._start_at: float | None = None  # a (re)download is due at this time

    # ---- inputs ------------------------------------------------------------------------------

    def start(self, now: float) -> list[Request]:
        """Begin a download now (again, if one is running)."""
        self._start_at = None
        self._current_at_start = self._latest_current
        self._items = {}
        self._tries = 0
        self.phase = Phase.LISTING
        return self._ask(Request("MISSION_REQUEST_LIST"), now)

    def _ask(self, request: Request, now: float) -> list[Request]:
        self._deadline = now + self._timeout
        return [request]

    def _schedule(self, now: float, why: str) -> None:
        if self._start_at is None:
            self.counters["changes"] += 1
            self.events.append(f"mission changed ({why}), downloading again")
            self._start_at = now + self._settle

    def _ours(self, msg: Any) -> bool:
        return (msg.target_system, msg.target_component) == self._own

    def on_message(self, msg: Any, now: float) -> list[Request]:
        """One message from the autopilot (the link has checked the sender)."""
        kind = msg.get_type()
        if kind == "MISSION_CURRENT":
            return self._on_current(msg, now)
        if getattr(msg, "mission_type", MAV_MISSION_TYPE_MISSION) != MAV_MISSION_TYPE_MISSION:
            return []
        if kind == "MISSION_COUNT":
            if not self._ours(msg):
                self._schedule(now, "uploaded by another system")
                return []
            if self.phase is not Phase.LISTING:
                return []
            return self._on_count(msg, now)
        if kind == "MISSION_ITEM_INT" and self._ours(msg) and self.phase is Phase.ITEMS:
            return self._on_item(msg, now)
        if kind == "MISSION_ACK":
            if not self._ours(msg):
                if msg.type == MAV_MISSION_ACCEPTED:
                    self._schedule(now, "upload accepted")
                return []
            if self.phase in (Phase.LISTING, Phase.ITEMS):
                self._fail(f"autopilot refused the download (MAV_MISSION_RESULT {msg.type})", now)
        return []

    def _on_current(self, msg: Any, now: float) -> list[Request]:
        """Compare MISSION_CURRENT's (plan id, total) with those the mission held was downloaded under.

        The reference is the last MISSION_CURRENT before the download began, so an upload that lands
        while downloading shows as a change (at worst one download too many, never one too few).
        Without one (the first download), the first MISSION_CURRENT after it is the reference, checked
        against the items downloaded.
        """
        seen = (extension_u32(msg, MISSION_CURRENT_MISSION_ID_OFFSET), int(msg.total))
        self._latest_current = seen
        self.current_seq = int(msg.seq)
        if self.phase is not Phase.DONE or self.mission is None:
            return []
        if self._reference is None:
            self._reference = seen
            if seen[1] != len(self.mission.items):
                self._schedule(now, f"{seen[1]} items")
        elif seen[0] != self._reference[0]:
            self._schedule(now, f"mission id {seen[0]}")
        elif seen[1] != self._reference[1]:
            self._schedule(now, f"{seen[1]} items")
        return []

    def _on_count(self, msg: Any, now: float) -> list[Request]:
        self._count = int(msg.count)
        self._opaque_id = extension_u32(msg, MISSION_COUNT_OPAQUE_ID_OFFSET)
        self._next = 1 if self._skip_home else 0
        self._tries = 0
        if self._next >= self._count:
            return self._finish(now)
        self.phase = Phase.ITEMS
        return self._ask(Request("MISSION_REQUEST_INT", self._next), now)

    def _on_item(self, msg: Any, now: float) -> list[Request]:
        if msg.seq != self._next:
            return []  # a late duplicate of an earlier item: the request for the right one stands
        self._items[self._next] = MissionItem.of(msg)
        self._next += 1
        self._tries = 0
        if self._next >= self._count:
            return self._finish(now)
        return self._ask(Request("MISSION_REQUEST_INT", self._next), now)

    def _finish(self, now: float) -> list[Request]:
        first = 1 if self._skip_home else 0
        items = tuple(self._items[i] for i in range(first, self._count))
        self.mission = Mission(items, self._opaque_id)
        self.phase = Phase.DONE
        self._deadline = math.inf
        self._reference = self._current_at_start
        self.counters["downloads"] += 1
        self.events.append(f"mission downloaded: {len(items)} items")
        self.events += [f"mission {p}" for p in self.mission.problems()]
        return [Request("MISSION_ACK", result=MAV_MISSION_ACCEPTED)]

    def _fail(self, why: str, now: float) -> None:
        self.phase = Phase.FAILED
        self._deadline = math.inf
        self._start_at = now + self._retry_after
        self.counters["failures"] += 1
        self.events.append(f"mission download failed: {why}")

    def tick(self, now: float) -> list[Request]:
        """Time passes: repeat an unanswered request, give up after the retries, start due downloads."""
        if self._start_at is not None and now >= self._start_at:
            return self.start(now)
        if self.phase not in (Phase.LISTING, Phase.ITEMS) or now < self._deadline:
            return []
        self.counters["timeouts"] += 1
        self._tries += 1
        if self._tries > self._retries:
            what = "MISSION_COUNT" if self.phase is Phase.LISTING else f"item {self._next}"
            self._fail(f"no {what} after {self._retries} retries", now)
            return []
        if self.phase is Phase.LISTING:
            return self._ask(Request("MISSION_REQUEST_LIST"), now)
        return self._ask(Request("MISSION_REQUEST_INT", self._next), now)

    def current_is_of_held(self) -> bool:
        """The last MISSION_CURRENT speaks of the mission held (same plan id, where both carry one),
        not of a new one still to download."""
        if self.phase is not Phase.DONE or self.mission is None or self._latest_current is None:
            return False
        if self._start_at is not None:
            return False  # a change is known and its download due
        plan_id = self._latest_current[0]
        return plan_id == 0 or self.mission.mission_id == 0 or plan_id == self.mission.mission_id

    def drain_events(self) -> list[str]:
        out, self.events = self.events, []
        return out
