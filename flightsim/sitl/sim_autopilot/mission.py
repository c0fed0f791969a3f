"""The mission protocol of the simulated autopilots (pure): upload, download, MISSION_CURRENT.

As the firmwares do it:

- upload (a GCS sends MISSION_COUNT): the autopilot asks for each item with MISSION_REQUEST_INT,
  re-asks an unanswered one (1 s, 5 times, then MISSION_ACK ``OPERATION_CANCELLED``), checks
  each item (command known, frame supported: global frames only, ``MAV_MISSION_UNSUPPORTED_FRAME``
  otherwise) and answers MISSION_ACK ``ACCEPTED`` with the new plan id (``opaque_id``);
- download (MISSION_REQUEST_LIST): MISSION_COUNT with the plan id, then each item asked for;
- ArduPilot keeps home as item 0: a download returns home there (and counts it), an upload's item 0
  is replaced by home; PX4's items start at 0;
- MISSION_CURRENT (streamed) carries the current item, the total and the plan id ``mission_id``;
  MISSION_SET_CURRENT makes an item current in any mode (answered with MISSION_CURRENT; an item
  that does not exist is refused with a STATUSTEXT on the firmware, ignored here).

pymavlink 2.4 predates the plan-id extension fields, so the three messages that carry one are sent
through small subclasses that append it to the payload (wire order of common.xml).
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

#: Re-ask an item not received within this, seconds, this many times, then cancel the upload.
UPLOAD_ITEM_TIMEOUT = 1.0
UPLOAD_RETRIES = 5
#: Global frames both firmwares take for mission items (local frames are refused).
SUPPORTED_FRAMES = frozenset((
    mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
    mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink.MAV_FRAME_MISSION,
))


class MissionCurrentWithId(mavlink.MAVLink_mission_current_message):
    """MISSION_CURRENT with its ``mission_id`` extension (fence and rally ids are 0: none kept)."""

    def __init__(self, seq: int, total: int, mission_state: int, mission_mode: int, mission_id: int) -> None:
        super().__init__(seq, total, mission_state, mission_mode)
        self.mission_id = mission_id

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        payload = self.unpacker.pack(self.seq, self.total, self.mission_state, self.mission_mode)
        return self._pack(mav, self.crc_extra, payload + struct.pack("<III", self.mission_id, 0, 0),
                          force_mavlink1=force_mavlink1)


class MissionCountWithId(mavlink.MAVLink_mission_count_message):
    """MISSION_COUNT with its ``opaque_id`` extension (the plan id, on download)."""

    def __init__(self, target_system: int, target_component: int, count: int, opaque_id: int) -> None:
        super().__init__(target_system, target_component, count, mavlink.MAV_MISSION_TYPE_MISSION)
        self.opaque_id = opaque_id

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        payload = self.unpacker.pack(self.count, self.target_system, self.target_component, self.mission_type)
        return self._pack(mav, self.crc_extra, payload + struct.pack("<I", self.opaque_id),
                          force_mavlink1=force_mavlink1)


class MissionAckWithId(mavlink.MAVLink_mission_ack_message):
    """MISSION_ACK with its ``opaque_id`` extension (the new plan id, after an upload)."""

    def __init__(self, target_system: int, target_component: int, result: int, opaque_id: int) -> None:
        super().__init__(target_system, target_component, result, mavlink.MAV_MISSION_TYPE_MISSION)
        self.opaque_id = opaque_id

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        payload = self.unpacker.pack(self.target_system, self.target_component, self.type, self.mission_type)
        return self._pack(mav, self.crc_extra, payload + struct.pack("<I", self.opaque_id),
                          force_mavlink1=force_mavlink1)


@dataclass(frozen=True)
class StoredItem:
    """One mission item as the autopilot keeps it (MISSION_ITEM_INT's fields)."""

    frame: int
    command: int
    params: tuple[float, float, float, float]
    x: int
    y: int
    z: float
    autocontinue: int = 1

    @classmethod
    def of(cls, msg: Any) -> StoredItem:
        x, y = msg.x, msg.y
        if msg.get_type() == "MISSION_ITEM":  # float lat/lon in the legacy message
            x, y = round(msg.x * 1e7), round(msg.y * 1e7)
        return cls(int(msg.frame), int(msg.command), (msg.param1, msg.param2, msg.param3, msg.param4),
                   int(x), int(y), float(msg.z), int(msg.autocontinue))

    def message(self, seq: int, target: tuple[int, int], current: bool) -> Any:
        return mavlink.MAVLink_mission_item_int_message(
            target[0], target[1], seq, self.frame, self.command, int(current), self.autocontinue,
            *self.params, self.x, self.y, self.z, mavlink.MAV_MISSION_TYPE_MISSION)


@dataclass
class _Upload:
    link: int
    peer: tuple[int, int]
    count: int
    items: list[StoredItem]
    deadline: float
    tries: int = 0


class MissionStore:
    """One autopilot's mission and its protocol.

    :param home_item: a function returning home as an item (ArduPilot: item 0 is home), or None (PX4)
    """

    def __init__(self, home_item: Callable[[], StoredItem] | None) -> None:
        self._home_item = home_item
        self.items: list[StoredItem] = []  # without ArduPilot's home
        self.mission_id = 0
        self.current = 0  # index into the items as the firmware numbers them
        self._upload: _Upload | None = None
        self.counters: dict[str, int] = {}

    def _count(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1

    @property
    def offset(self) -> int:
        """Sequence number of the first stored item (1 on ArduPilot, after home)."""
        return 1 if self._home_item is not None else 0

    @property
    def total(self) -> int:
        """Items a download reports (with ArduPilot's home)."""
        return len(self.items) + self.offset

    def item(self, seq: int) -> StoredItem | None:
        if self._home_item is not None and seq == 0:
            return self._home_item()
        i = seq - self.offset
        return self.items[i] if 0 <= i < len(self.items) else None

    def current_message(self) -> Any:
        state = mavlink.MISSION_STATE_NO_MISSION if not self.items else mavlink.MISSION_STATE_NOT_STARTED
        seq = max(self.current, self.offset) if self.items else 0
        return MissionCurrentWithId(seq, len(self.items), state, 0, self.mission_id)

    def handle(self, msg: Any, link: int, now: float) -> list[tuple[Any, int]]:
        """One mission-protocol message from ``link``; returns (reply, link) pairs."""
        kind = msg.get_type()
        if getattr(msg, "mission_type", 0) != mavlink.MAV_MISSION_TYPE_MISSION:
            peer = (msg.get_srcSystem(), msg.get_srcComponent())
            return [(MissionAckWithId(*peer, mavlink.MAV_MISSION_UNSUPPORTED, 0), link)]
        self._count(f"rx_{kind}")
        peer = (msg.get_srcSystem(), msg.get_srcComponent())
        if kind == "MISSION_REQUEST_LIST":
            return [(MissionCountWithId(*peer, self.total, self.mission_id), link)]
        if kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            item = self.item(msg.seq)
            if item is None:
                return [(MissionAckWithId(*peer, mavlink.MAV_MISSION_INVALID_SEQUENCE, 0), link)]
            return [(item.message(msg.seq, peer, msg.seq == self.current), link)]
        if kind == "MISSION_COUNT":
            return self._start_upload(msg, peer, link, now)
        if kind in ("MISSION_ITEM_INT", "MISSION_ITEM"):
            return self._on_item(msg, peer, link, now)
        if kind == "MISSION_SET_CURRENT":
            if self.items and self.offset <= msg.seq < self.total:
                self.current = int(msg.seq)
                return [(self.current_message(), link)]
            return []
        if kind == "MISSION_CLEAR_ALL":
            self._replace([])
            return [(MissionAckWithId(*peer, mavlink.MAV_MISSION_ACCEPTED, self.mission_id), link)]
        return []  # MISSION_ACK closing a download: nothing to do

    def _start_upload(self, msg: Any, peer: tuple[int, int], link: int, now: float) -> list[tuple[Any, int]]:
        if msg.count == 0:
            self._replace([])
            return [(MissionAckWithId(*peer, mavlink.MAV_MISSION_ACCEPTED, self.mission_id), link)]
        self._upload = _Upload(link, peer, int(msg.count), [], now + UPLOAD_ITEM_TIMEOUT)
        return [(self._request(0), link)]

    def _request(self, seq: int) -> Any:
        assert self._upload is not None
        return mavlink.MAVLink_mission_request_int_message(*self._upload.peer, seq,
                                                           mavlink.MAV_MISSION_TYPE_MISSION)

    def _on_item(self, msg: Any, peer: tuple[int, int], link: int, now: float) -> list[tuple[Any, int]]:
        up = self._upload
        if up is None or peer != up.peer or msg.seq != len(up.items):
            return []  # not uploading, someone else, or a duplicate: the firmware ignores it
        result = self._check(msg)
        if result != mavlink.MAV_MISSION_ACCEPTED:
            self._upload = None
            self._count("uploads_refused")
            return [(MissionAckWithId(*peer, result, 0), link)]
        up.items.append(StoredItem.of(msg))
        up.tries, up.deadline = 0, now + UPLOAD_ITEM_TIMEOUT
        if len(up.items) < up.count:
            return [(self._request(len(up.items)), link)]
        self._upload = None
        self._replace(up.items[self.offset:])  # ArduPilot: item 0 is home, whatever was sent
        self._count("uploads")
        return [(MissionAckWithId(*peer, mavlink.MAV_MISSION_ACCEPTED, self.mission_id), link)]

    def _check(self, msg: Any) -> int:
        if msg.seq < self.offset:
            return mavlink.MAV_MISSION_ACCEPTED  # ArduPilot's home slot: accepted, then replaced
        if msg.command not in mavlink.enums["MAV_CMD"]:
            return mavlink.MAV_MISSION_UNSUPPORTED
        if msg.frame not in SUPPORTED_FRAMES:
            return mavlink.MAV_MISSION_UNSUPPORTED_FRAME
        return mavlink.MAV_MISSION_ACCEPTED

    def _replace(self, items: list[StoredItem]) -> None:
        self.items = list(items)
        self.current = self.offset
        blob = repr([(i.frame, i.command, i.params, i.x, i.y, i.z) for i in items]).encode()
        self.mission_id = zlib.crc32(blob) or 1 if items else 0

    def tick(self, now: float) -> list[tuple[Any, int]]:
        """Re-ask an unanswered upload item; cancel the upload after the retries."""
        up = self._upload
        if up is None or now < up.deadline:
            return []
        up.tries += 1
        if up.tries > UPLOAD_RETRIES:
            self._upload = None
            self._count("uploads_timed_out")
            return [(MissionAckWithId(*up.peer, mavlink.MAV_MISSION_OPERATION_CANCELLED, 0), up.link)]
        up.deadline = now + UPLOAD_ITEM_TIMEOUT
        return [(self._request(len(up.items)), up.link)]
