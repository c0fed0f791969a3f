"""A ring of single-beam CAN rangefinders (Benewake TF series) as a point-cloud source.

Each sensor sends one CAN frame per measurement on its own id. Frame layout (TFmini-i-CAN, TF02-Pro
and TFmini Plus CAN manuals; ArduPilot's AP_RangeFinder_Benewake_CAN reads the same bytes):

    byte 0–1  distance, uint16 little-endian, centimetres (0 = no valid measurement)
    byte 2–3  signal strength, uint16 little-endian
    byte 4–7  sensor timestamp, uint32 little-endian, milliseconds (unused here)

DLC 8, standard 11-bit id by default (0x003 from the factory; give each sensor its own id with
Benewake's configuration tool), 250 kbit/s by default. An id up to 0x7FF is taken only from standard
frames, a larger one only from extended frames. Each sensor becomes one point at its mounting
yaw in the FLU sensor frame (x forward, y left, z = 0), so the scan code treats the ring like a lidar.
"""

from __future__ import annotations

import logging
import math
import struct
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from companion.common.errors import UserError


@dataclass(frozen=True)
class CanSensorConfig:
    """One rangefinder of the CAN ring.

    :param can_id: arbitration id its distance frames arrive with
    :param yaw_deg: direction it points, degrees counter-clockwise from forward (body FLU)
    """

    can_id: int = field(default=0, metadata={"min": 0, "max": 0x1FFFFFFF})
    yaw_deg: float = field(default=0.0, metadata={"min": -360.0, "max": 360.0})


@dataclass(frozen=True)
class CanConfig:
    """A ring of CAN rangefinders read through python-can.

    :param interface: python-can interface (``socketcan`` on the Jetson, ``virtual`` for tests)
    :param channel: python-can channel (``can0``)
    :param bitrate: bus bit rate (Benewake's default 250 kbit/s; ignored by interfaces that do not set
        it, e.g. socketcan)
    :param max_range: readings beyond this are "no return", metres
    :param stale_after: a reading older than this is not used, s (a silent sensor stops the clouds)
    :param sensors: one entry per rangefinder
    """

    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: int = field(default=250_000, metadata={"min": 10_000, "max": 8_000_000})
    max_range: float = field(default=12.0, metadata={"min": 0.5, "max": 200.0})
    stale_after: float = field(default=0.3, metadata={"min": 0.01, "max": 10.0})
    sensors: tuple[CanSensorConfig, ...] = ()

    def __post_init__(self) -> None:
        ids = [s.can_id for s in self.sensors]
        duplicates = sorted({i for i in ids if ids.count(i) > 1})
        if duplicates:
            raise ValueError(f"sensors: CAN id {duplicates[0]:#x} is used more than once")


log = logging.getLogger(__name__)

FRAME_DLC = 8
_FRAME = struct.Struct("<HHI")
MAX_CAN_ID = 0x1FFFFFFF

#: Highest standard (11-bit) id: a sensor's id up to this arrives in standard frames, above it in
#: extended (29-bit) ones, as benewake_frame sends them.
MAX_STANDARD_ID = 0x7FF

#: Why a frame was dropped; the keys of the ``malformed`` counter. ``wrong_id_format``: a sensor's
#: id in the other frame format (extended 0x10 is not standard 0x10, whoever sent it).
MALFORMED_REASONS = ("error_frame", "remote_frame", "unknown_id", "wrong_id_format", "wrong_dlc")


@dataclass(frozen=True)
class CanRangefinder:
    """One rangefinder of the ring.

    :param can_id: the CAN id its frames arrive on.
    :param yaw_deg: its mounting yaw in degrees, counter-clockwise from forward (90 = left).
    """

    can_id: int
    yaw_deg: float


def benewake_frame(
    can_id: int, distance_m: float, strength: int = 1000, timestamp_ms: int = 0
) -> can.Message:
    """A TF-series measurement frame, as the sensor sends it (for simulators and tests).

    :param can_id: the sensor's id (standard frame when ≤ 0x7FF).
    :param distance_m: distance in metres, rounded to centimetres; 0 = no valid measurement.
    """
    centimetres = round(distance_m * 100)
    if not 0 <= centimetres <= 0xFFFF:
        raise ValueError(f"distance {distance_m} m does not fit the frame's uint16 centimetres")
    return can.Message(
        arbitration_id=can_id,
        is_extended_id=can_id > MAX_STANDARD_ID,
        data=_FRAME.pack(centimetres, strength, timestamp_ms & 0xFFFFFFFF),
    )


@dataclass
class CanRingCounters:
    """What the ring saw; logged and exported by the companion."""

    #: frames received, good or not.
    frames: int = 0
    #: dropped frames by reason (keys from MALFORMED_REASONS).
    malformed: dict[str, int] = field(default_factory=dict)
    #: measurements without a usable return (0 cm, beyond max_range, or weaker than min_strength).
    no_return: int = 0
    #: readings discarded because they were older than stale_after when a cloud was due.
    stale: int = 0
    #: clouds emitted.
    clouds: int = 0


class CanRangefinderRing:
    """Turns Benewake TF frames from a python-can bus into (N, 3) FLU point clouds.

    A cloud is emitted once every sensor has reported since the last cloud, with one point per
    sensor that saw something within ``max_range``. A reading older than ``stale_after`` seconds is
    discarded rather than used, so a sensor that stops talking stops the clouds: the companion then
    sees the lidar go stale and holds, instead of flying into a sector it cannot see.

    :param bus: an open python-can bus (see :meth:`open`).
    :param sensors: the rangefinders; ids must be distinct.
    :param max_range: returns beyond this many metres count as no return.
    :param stale_after: seconds after which a reading is too old to use.
    :param min_strength: readings with a weaker signal count as no return (0 accepts all, as
        ArduPilot's RNGFNDx_SNR_MIN).
    :param clock: time source for staleness (monotonic by default).
    :raises UserError: on duplicate or out-of-range ids or non-finite yaws.
    """

    def __init__(
        self,
        bus: can.BusABC,
        sensors: Sequence[CanRangefinder],
        *,
        max_range: float = 12.0,
        stale_after: float = 0.3,
        min_strength: int = 0,
        clock: Callable[[], float] = time.monotonic,
        max_frames_per_read: int = 1024,
    ) -> None:
        if not sensors:
            raise UserError("the CAN rangefinder ring needs at least one sensor")
        self._index: dict[int, int] = {}
        for i, sensor in enumerate(sensors):
            if not 0 <= sensor.can_id <= MAX_CAN_ID:
                raise UserError(f"CAN rangefinder id {sensor.can_id:#x} is outside 0..0x1FFFFFFF")
            if sensor.can_id in self._index:
                raise UserError(f"two CAN rangefinders share the id {sensor.can_id:#x}")
            if not math.isfinite(sensor.yaw_deg):
                raise UserError(f"CAN rangefinder {sensor.can_id:#x} has a non-finite yaw")
            self._index[sensor.can_id] = i
        self.bus = bus
        self.sensors = tuple(sensors)
        self.max_range = max_range
        self.stale_after = stale_after
        self.min_strength = min_strength
        self.counters = CanRingCounters()
        self._clock = clock
        self._max_frames = max_frames_per_read
        yaw = np.radians([s.yaw_deg for s in sensors])
        self._directions = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=1).astype(np.float32)
        n = len(sensors)
        self._distance = np.zeros(n, dtype=np.float32)  # metres, 0 = no return
        self._stamp = np.full(n, -math.inf)  # clock() when the reading arrived
        self._fresh = np.zeros(n, dtype=bool)  # reported since the last cloud

    @classmethod
    def open(
        cls,
        interface: str,
        channel: str,
        sensors: Sequence[CanRangefinder],
        bitrate: int | None = None,
        **kwargs: Any,
    ) -> CanRangefinderRing:
        """Open a python-can bus and build the ring on it.

        :param interface: python-can interface name ("socketcan", "virtual", …).
        :param channel: the channel ("can0", …).
        :param bitrate: bus bitrate where the interface sets it (Benewake's default is 250000).
        :param kwargs: passed to CanRangefinderRing.
        :raises UserError: when the bus cannot be opened.
        """
        bus_args: dict[str, Any] = {"interface": interface, "channel": channel}
        if bitrate is not None:
            bus_args["bitrate"] = bitrate
        try:
            bus = can.Bus(**bus_args)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise UserError(f"cannot open CAN bus {interface}:{channel}: {exc}") from exc
        try:
            return cls(bus, sensors, **kwargs)
        except Exception:
            bus.shutdown()
            raise

    def fileno(self) -> int | None:
        """The bus's descriptor for select where the interface has one (socketcan does), else None.

        Without one (the virtual interface), poll read_available from the loop's timeout.
        """
        try:
            return self.bus.fileno()
        except NotImplementedError:
            return None

    def read_available(self, now: float | None = None) -> list[np.ndarray]:
        """Drain the frames waiting (never blocks) and return the clouds they completed.

        :param now: the time to stamp this batch with; clock() when omitted.
        :return: (N, 3) float32 FLU clouds, N ≤ number of sensors; usually none or one.
        """
        now = self._clock() if now is None else now
        clouds: list[np.ndarray] = []
        for _ in range(self._max_frames):
            try:
                message = self.bus.recv(timeout=0.0)
            except can.CanOperationError as exc:
                log.warning("CAN rangefinders: receive error %s", exc)
                break
            if message is None:
                break
            self.counters.frames += 1
            if self._accept(message, now) and self._fresh.all():
                cloud = self._cloud(now)
                if cloud is not None:
                    clouds.append(cloud)
        return clouds

    def _accept(self, message: can.Message, now: float) -> bool:
        if message.is_error_frame:
            return self._drop("error_frame")
        if message.is_remote_frame:
            return self._drop("remote_frame")
        index = self._index.get(message.arbitration_id)
        if index is None:
            return self._drop("unknown_id")
        if message.is_extended_id != (message.arbitration_id > MAX_STANDARD_ID):
            return self._drop("wrong_id_format")
        if message.dlc != FRAME_DLC or len(message.data) != FRAME_DLC:
            return self._drop("wrong_dlc")
        centimetres, strength, _ = _FRAME.unpack_from(message.data)
        distance = centimetres / 100.0
        if centimetres == 0 or distance > self.max_range or strength < self.min_strength:
            self.counters.no_return += 1
            distance = 0.0
        self._distance[index] = distance
        self._stamp[index] = now
        self._fresh[index] = True
        return True

    def _cloud(self, now: float) -> np.ndarray | None:
        stale = now - self._stamp > self.stale_after
        if stale.any():
            self.counters.stale += int(stale.sum())
            self._fresh[stale] = False
            return None
        self._fresh[:] = False
        self.counters.clouds += 1
        hit = self._distance > 0
        return self._directions[hit] * self._distance[hit, None]

    def _drop(self, reason: str) -> bool:
        malformed = self.counters.malformed
        if reason not in malformed:
            log.warning("CAN rangefinders: dropping frame (%s); further ones are only counted", reason)
        malformed[reason] = malformed.get(reason, 0) + 1
        return False

    def close(self) -> None:
        """Shut the bus down."""
        self.bus.shutdown()

    def __enter__(self) -> CanRangefinderRing:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_can_ring(config: CanConfig, clock: Callable[[], float] = time.monotonic) -> CanRangefinderRing:
    """Open the ring described by the companion's ``[lidar.can]`` config.

    :param config: interface, channel, bitrate, max_range, stale_after and the sensors.
    :param clock: time source for staleness.
    :raises UserError: when the bus cannot be opened or the sensor list is wrong.
    """
    return CanRangefinderRing.open(
        config.interface,
        config.channel,
        [CanRangefinder(s.can_id, s.yaw_deg) for s in config.sensors],
        bitrate=config.bitrate,
        max_range=config.max_range,
        stale_after=config.stale_after,
        clock=clock,
    )
