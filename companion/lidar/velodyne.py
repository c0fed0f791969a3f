"""Velodyne VLP-16: revolutions assembled from its packets, two decoder backends, and a UDP source.

The packet itself (layout, checks, decoding to points, encoding) is :mod:`companion.lidar.vlp16_packet`.
Here: :class:`RevolutionAssembler` gathers packets into whole turns and drops what is not one
(:func:`revolution_problem`), counting every drop; :class:`VelodyneUdpSource` reads the sensor's
datagrams off a non-blocking socket for the main loop.

Two decoder backends produce the same clouds (tests hold them to each other on a real recording):
``"numpy"`` (default: one vectorised pass over all packets waiting, measured 2.5–4× faster than the
binding, see bench/bench_velodyne.py) and ``"velodyne-decoder"`` (the maintained C++ decoder; it also
applies the manual's per-laser vertical offsets of up to ±11.2 mm in z, the numpy backend does not).
"""

from __future__ import annotations

import logging
import math
import operator
import socket
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal, NamedTuple

import numpy as np

from companion.common.errors import UserError
from companion.lidar.vlp16_packet import (
    DISTANCE_UNIT_M,
    FIRINGS_PER_PACKET,
    MALFORMED_REASONS,
    MAX_RANGE_M,
    PACKET_DTYPE,
    PACKET_DURATION_US,
    PACKET_SIZE,
    PACKETS_PER_SECOND,
    US_PER_HOUR,
    DecodedPackets,
    decode_packets_numpy,
    firing_azimuths,
    firing_azimuths_array,
    parse_header,
    points_per_firing,
    reason_codes,
)

log = logging.getLogger(__name__)

#: a forward jump of the sensor's timestamp longer than this (two revolutions at 600 rpm) means the
#: stream went silent: the revolution in progress is older than the gap and is dropped.
SILENCE_US = 200_000
#: The VLP-16 turns at 300–1200 rpm (manual §8.1); revolutions outside that, with 5 % slack for
#: motor jitter, are not whole turns of this sensor.
MIN_RPM = 300 * 0.95
MAX_RPM = 1200 * 1.05
#: A revolution must cover at least this much azimuth (a hole of a lost packet or two is tolerated).
MIN_COVERAGE_DEG = 350.0
#: No single hole in a revolution may be wider than this many packets' worth of firings.
MAX_HOLE_PACKETS = 3
#: Firing sequences in one whole revolution: from the fastest turn less the tolerated loss to the slowest.
MIN_FIRINGS_PER_REVOLUTION = math.floor(
    PACKETS_PER_SECOND * 60.0 / MAX_RPM * (MIN_COVERAGE_DEG / 360.0) * 24
)
MAX_FIRINGS_PER_REVOLUTION = math.ceil(PACKETS_PER_SECOND * 60.0 / MIN_RPM * 24)
#: The sensor makes at most 20 revolutions per second (1200 rpm); more whole revolutions than this
#: within any second are not the sensor's (a replayed or forged stream).
MAX_REVOLUTIONS_PER_SECOND = 22


class _ThrottledLog:
    """Logs at most one line per ``period`` seconds; the lines held back are counted into the next.

    Events a sender can trigger at will (silences, overflows, receive errors) must not become a log
    flood: writing thousands of lines a second to a slow journal would stall the main loop.
    """

    def __init__(self, level: int, period: float = 10.0) -> None:
        self.level = level
        self.period = period
        self._next = -math.inf
        self._held = 0

    def __call__(self, message: str, *args: object) -> None:
        now = time.monotonic()
        if now < self._next:
            self._held += 1
            return
        if self._held:
            message += " (and %d more in the last %g s)"
            args = (*args, self._held, self.period)
        log.log(self.level, message, *args)
        self._next = now + self.period
        self._held = 0


#: Why a completed revolution was dropped; the keys of the ``partial`` counter.
PARTIAL_REASONS = (
    "start_not_seen",
    "firing_count",
    "azimuth_backwards",
    "coverage",
    "hole",
)


def revolution_problem(azimuth_centideg: np.ndarray) -> str | None:
    """Say why the firings of one revolution are not a whole turn of a VLP-16, or None when they are.

    A whole turn rises monotonically from the wrap to the next one, covers at least
    MIN_COVERAGE_DEG of azimuth, has no hole wider than MAX_HOLE_PACKETS packets and as many firing
    sequences as a VLP-16 makes in one turn at 300–1200 rpm. A single corrupt packet (every azimuth
    0.00°, say) cuts the turn around it into pieces that each fail one of these, where a check of the
    wrap alone would pass a "revolution" of 40° whose other 320° read as clear.

    :param azimuth_centideg: (F,) azimuth of each firing sequence, 0.01°, in firing order, cut at the
        wraps (as RevolutionAssembler cuts them).
    :return: one of PARTIAL_REASONS[1:], or None.
    """
    n = len(azimuth_centideg)
    if not MIN_FIRINGS_PER_REVOLUTION <= n <= MAX_FIRINGS_PER_REVOLUTION:
        return "firing_count"
    # the gap after each firing; the last one closes the turn back to the first firing
    gaps = np.empty(n, dtype=np.float64)
    np.subtract(azimuth_centideg[1:], azimuth_centideg[:-1], out=gaps[:-1])
    gaps[-1] = azimuth_centideg[0] + 36000.0 - azimuth_centideg[-1]
    if not gaps.min() > 0.0:
        return "azimuth_backwards"
    step = float(np.median(gaps))
    holes = gaps[gaps > 2.5 * step]
    if 36000.0 - float((holes - step).sum()) < MIN_COVERAGE_DEG * 100.0:
        return "coverage"
    if len(holes) and holes.max() > (MAX_HOLE_PACKETS * FIRINGS_PER_PACKET + 1) * step:
        return "hole"
    return None


def _decode_numpy(packets: np.ndarray, _payloads: Sequence[bytes]) -> DecodedPackets:
    return decode_packets_numpy(packets)


class _VelodyneDecoderBackend:
    """velodyne-decoder's C++ ScanDecoder on a run of packets.

    Its `column` field is not a firing index (it does not advance one for one over firings without a
    return), so where each firing's points start is taken from the packets themselves: the decoder
    emits every non-zero slot, in packet order.
    """

    def __init__(self) -> None:
        import velodyne_decoder as vd

        self._vd = vd
        config = vd.Config(model=vd.Model.VLP16, min_range=DISTANCE_UNIT_M / 2, max_range=MAX_RANGE_M)
        self._decoder = vd.ScanDecoder(config)

    def decode(self, packets: np.ndarray, payloads: Sequence[bytes]) -> DecodedPackets:
        vd = self._vd
        _, cloud = self._decoder.decode(vd.PacketVector([vd.VelodynePacket(0.0, p) for p in payloads]))
        returns = np.flatnonzero(packets.view(PACKET_DTYPE)[:, 0]["blocks"]["returns"]["distance"] != 0)
        if len(cloud) != len(returns):
            log.error("velodyne-decoder gave %d points for %d returns; using numpy", len(cloud), len(returns))
            return decode_packets_numpy(packets)
        points = np.ascontiguousarray(cloud[:, :3], dtype=np.float32)
        return DecodedPackets(points, points_per_firing(returns, len(packets)))


Backend = Literal["numpy", "velodyne-decoder"]

_NO_POINTS = np.zeros((0, 3), dtype=np.float32)
_NO_POINTS.setflags(write=False)

#: Batches at least this long are checked with numpy rather than packet by packet.
_VECTORISE_FROM = 4


@dataclass
class VelodyneCounters:
    """What the assembler saw; logged and exported by the companion."""

    #: datagrams fed, well formed or not.
    packets: int = 0
    #: dropped datagrams by reason (keys from MALFORMED_REASONS).
    malformed: dict[str, int] = field(default_factory=dict)
    #: revolutions completed and returned.
    revolutions: int = 0
    #: revolutions dropped because they were not one whole turn (see revolution_problem), or their
    #: start was not seen (before the first wrap, after an overflow or a silence).
    partial_revolutions: int = 0
    #: partial_revolutions by reason (keys from PARTIAL_REASONS).
    partial: dict[str, int] = field(default_factory=dict)
    #: revolutions abandoned because the azimuth never wrapped within max_packets_per_revolution.
    overflows: int = 0
    #: consecutive packets whose timestamps are more than 1.5 packet durations apart or go backwards
    #: (lost or reordered packets: that revolution is missing a sector).
    timestamp_gaps: int = 0
    #: silences (timestamp jumps over SILENCE_US): the revolution in progress was dropped, so the
    #: first revolution after a lidar outage holds no points from before it.
    silences: int = 0
    #: datagrams from an address other than the configured sensor_ip, dropped unread (UDP source).
    foreign_packets: int = 0
    #: whole revolutions withheld because more arrived within a second than the sensor can make
    #: (MAX_REVOLUTIONS_PER_SECOND): a forged or replayed stream (UDP source).
    implausible_revolutions: int = 0


class Revolution(NamedTuple):
    """One full turn of the sensor."""

    #: (N, 3) float32 FLU points in metres.
    points: np.ndarray
    #: index (into the batch fed) of the packet whose wrap completed this revolution.
    completed_by: int


class RevolutionAssembler:
    """Validates VLP-16 packets, decodes them and cuts revolutions exactly where the azimuth wraps.

    Each packet's header is checked as it arrives (malformed packets are counted per reason and
    dropped, never raised) and its firings' azimuths are scanned for the wrap: the azimuth falling by
    more than half a turn from one firing sequence to the next, usually inside a packet. Packets are
    decoded in vectorised runs: at every wrap (so a revolution is ready as soon as its last packet
    is in) and whenever ``decode_every`` packets wait (so that run stays short). The firings before
    the wrap close the revolution, the rest start the next one; the part before the first wrap is
    dropped (its start was not seen), and so is every revolution that is not one whole turn of the
    sensor (revolution_problem: coverage, holes, firing count): a piece of a turn would read as clear
    wherever its missing sectors are.

    :param backend: "numpy" (default) or "velodyne-decoder"; see the module docstring.
    :param decode_every: decode waiting packets once this many have arrived without a wrap.
    :param max_packets_per_revolution: abandon a revolution that never wraps after this many packets
        (the VLP-16's slowest 300 rpm needs about 151; longer ones would be dropped anyway).
    """

    def __init__(
        self,
        backend: Backend = "numpy",
        *,
        decode_every: int = 8,
        max_packets_per_revolution: int = MAX_FIRINGS_PER_REVOLUTION // FIRINGS_PER_PACKET + 2,
    ) -> None:
        if backend not in ("numpy", "velodyne-decoder"):
            raise ValueError(f"unknown VLP-16 decoder backend {backend!r} (numpy or velodyne-decoder)")
        self.backend = backend
        self._decode: Callable[[np.ndarray, Sequence[bytes]], DecodedPackets] = (
            _VelodyneDecoderBackend().decode if backend == "velodyne-decoder" else _decode_numpy
        )
        self.decode_every = decode_every
        self.max_packets_per_revolution = max_packets_per_revolution
        self.counters = VelodyneCounters()
        self._pending: list[bytes] = []  # well-formed packets not decoded yet
        self._pending_wraps: list[int] = []  # firing index (within _pending) where a revolution starts
        self._parts: list[np.ndarray] = []  # decoded points of the revolution being built
        self._azimuths: list[np.ndarray] = []  # its firings' azimuths, 0.01°
        self._packets_in_revolution = 0
        self._started = False  # a wrap has been seen: the revolution being built is whole
        self._last_azimuth: float | None = None
        self._last_timestamp: int | None = None
        self._log_overflow = _ThrottledLog(logging.WARNING)
        self._log_silence = _ThrottledLog(logging.INFO)

    def feed(self, packet: bytes) -> list[np.ndarray]:
        """Add one packet; return the revolutions it completed (usually none, sometimes one).

        :param packet: a UDP payload from the sensor.
        :return: completed revolutions as (N, 3) float32 FLU clouds.
        """
        return [rev.points for rev in self.feed_batch((packet,))]

    def feed_batch(self, packets: Sequence[bytes]) -> list[Revolution]:
        """Add consecutive packets; return the revolutions they completed, oldest first.

        A few packets are checked one by one in plain Python (cheapest per packet); from
        ``_VECTORISE_FROM`` packets on, headers and wraps are checked in one numpy pass.

        :param packets: UDP payloads in arrival order.
        """
        if len(packets) >= _VECTORISE_FROM:
            return self._feed_vectorised(packets)
        revolutions: list[Revolution] = []
        for index, packet in enumerate(packets):
            self.counters.packets += 1
            reason, fields = parse_header(packet)
            if reason is not None:
                self._count_malformed(reason)
                continue
            self._check_timestamps(fields[24:25])
            first_firing = FIRINGS_PER_PACKET * len(self._pending)
            self._pending.append(packet)
            self._packets_in_revolution += 1
            wraps = self._find_wraps(fields[1:24:2])
            if wraps:
                self._pending_wraps += [first_firing + w for w in wraps]
                revolutions += [Revolution(points, index) for points, _ in self._decode_pending()]
                self._packets_in_revolution = 1
            elif self._packets_in_revolution > self.max_packets_per_revolution:
                self._overflow()
        if len(self._pending) >= self.decode_every:
            self._decode_pending()  # no wrap waiting, so this completes nothing
        return revolutions

    def _feed_vectorised(self, packets: Sequence[bytes]) -> list[Revolution]:
        self.counters.packets += len(packets)
        index = [i for i, packet in enumerate(packets) if len(packet) == PACKET_SIZE]
        for _ in range(len(packets) - len(index)):
            self._count_malformed("wrong_length")
        if not index:
            return []
        payloads = [packets[i] for i in index]
        data = np.frombuffer(b"".join(payloads), dtype=np.uint8).reshape(-1, PACKET_SIZE)
        codes = reason_codes(data)
        if codes.any():
            for code in codes[codes > 0].tolist():
                self._count_malformed(MALFORMED_REASONS[code - 1])
            keep = np.flatnonzero(codes == 0).tolist()
            if not keep:
                return []
            index = [index[k] for k in keep]
            payloads = [payloads[k] for k in keep]
        view = np.frombuffer(b"".join(payloads), dtype=PACKET_DTYPE)
        self._check_timestamps(view["timestamp"].tolist())
        azimuth = firing_azimuths_array(view["blocks"]["azimuth"].astype(np.float64))
        previous = np.empty_like(azimuth)
        previous[1:] = azimuth[:-1]
        previous[0] = azimuth[0] if self._last_azimuth is None else self._last_azimuth
        self._last_azimuth = float(azimuth[-1])
        wraps = np.flatnonzero(azimuth < previous - 18000.0)
        first_packet = len(self._pending)
        self._pending += payloads
        self._pending_wraps += (wraps + FIRINGS_PER_PACKET * first_packet).tolist()
        if len(wraps):
            self._packets_in_revolution = len(payloads) - int(wraps[-1]) // FIRINGS_PER_PACKET
        else:
            self._packets_in_revolution += len(payloads)
            if self._packets_in_revolution > self.max_packets_per_revolution:
                self._overflow()
                return []
        if not len(wraps) and len(self._pending) < self.decode_every:
            return []
        return [
            Revolution(points, index[wrap // FIRINGS_PER_PACKET - first_packet])
            for points, wrap in self._decode_pending()
        ]

    def _find_wraps(self, block_azimuths: Sequence[int]) -> list[int]:
        """Firings of this packet where the azimuth falls by more than half a turn."""
        previous = self._last_azimuth
        last = block_azimuths[-1] + 0.5 * ((block_azimuths[-1] - block_azimuths[-2]) % 36000)
        if (
            last < 36000
            and (previous is None or block_azimuths[0] >= previous - 18000.0)
            and all(map(operator.le, block_azimuths, block_azimuths[1:]))
        ):  # the common case, cheaply: azimuths only rise within the packet and from the last one
            self._last_azimuth = last
            return []
        wraps = []
        for i, azimuth in enumerate(firing_azimuths(block_azimuths)):
            if previous is not None and azimuth < previous - 18000.0:
                wraps.append(i)
            previous = azimuth
        self._last_azimuth = previous
        return wraps

    def _decode_pending(self) -> list[tuple[np.ndarray, int]]:
        """Decode the waiting packets; return each revolution completed with its wrap's firing index.

        The wraps cut the waiting firings into pieces: the first closes the revolution carried over
        from earlier packets, the last starts the next one, those between stand alone. Only the
        packets of pieces that can still be part of a whole turn are decoded; the others (start not
        seen, a firing count no VLP-16 makes: what a flood of wraps brings) are judged and counted
        from their azimuths alone, so such a flood costs header checks, not decoding.
        """
        data = np.frombuffer(b"".join(self._pending), dtype=np.uint8).reshape(-1, PACKET_SIZE)
        block_azimuths = data.view(PACKET_DTYPE)[:, 0]["blocks"]["azimuth"]
        azimuth = firing_azimuths_array(block_azimuths.astype(np.float64))
        wraps = self._pending_wraps
        edges = [0, *wraps, len(azimuth)]  # piece k: firings edges[k] .. edges[k + 1]
        counts = np.diff(edges)
        plausible = (counts >= MIN_FIRINGS_PER_REVOLUTION) & (counts <= MAX_FIRINGS_PER_REVOLUTION)
        wanted = plausible.copy()
        carried = sum(map(len, self._azimuths))
        first_total = carried + edges[1]
        wanted[0] = self._started and (  # closes (or extends) the carried revolution
            MIN_FIRINGS_PER_REVOLUTION <= first_total <= MAX_FIRINGS_PER_REVOLUTION
            if wraps
            else first_total <= MAX_FIRINGS_PER_REVOLUTION
        )
        if wraps:
            wanted[-1] = True  # starts the next revolution: its end is not here yet
        points, bounds = self._decode_pieces(data, edges, wanted)
        revolutions: list[tuple[np.ndarray, int]] = []
        if wraps:
            self._parts.append(points[: bounds[wraps[0]]])
            self._azimuths.append(azimuth[: wraps[0]])
            self._close(wraps[0], revolutions)
            middle = plausible[1:-1]
            if len(middle) and not middle.all():
                self._count_partial("firing_count", len(middle) - int(np.count_nonzero(middle)))
            for k in np.flatnonzero(middle).tolist():
                first, wrap = wraps[k], wraps[k + 1]
                self._parts = [points[bounds[first] : bounds[wrap]]]
                self._azimuths = [azimuth[first:wrap]]
                self._close(wrap, revolutions)
            self._parts = [points[bounds[wraps[-1]] :]]
            self._azimuths = [azimuth[wraps[-1] :]]
        else:
            self._parts.append(points)
            self._azimuths.append(azimuth)
        self._pending = []
        self._pending_wraps = []
        return revolutions

    def _decode_pieces(
        self, data: np.ndarray, edges: list[int], wanted: np.ndarray
    ) -> tuple[np.ndarray, list[int]]:
        """Decode the packets holding a firing of a wanted piece.

        :return: the points, and for each firing index f of the waiting packets where its points
            start in them (firings of packets not decoded have none).
        """
        n_packets = len(data)
        need = np.zeros(n_packets, dtype=bool)
        for k in np.flatnonzero(wanted).tolist():
            first, end = edges[k], edges[k + 1]
            if end > first:
                need[first // FIRINGS_PER_PACKET : (end - 1) // FIRINGS_PER_PACKET + 1] = True
        if need.all():
            decoded = self._decode(data, self._pending)
            per_firing = decoded.points_per_firing
        elif not need.any():
            return _NO_POINTS, [0] * (n_packets * FIRINGS_PER_PACKET + 1)
        else:
            index = np.flatnonzero(need)
            decoded = self._decode(data[index], [self._pending[i] for i in index.tolist()])
            per_firing = np.zeros(n_packets * FIRINGS_PER_PACKET, dtype=np.int64)
            per_firing[np.repeat(need, FIRINGS_PER_PACKET)] = decoded.points_per_firing
        return decoded.points, np.concatenate(([0], np.cumsum(per_firing))).tolist()

    def _close(self, wrap: int, revolutions: list[tuple[np.ndarray, int]]) -> None:
        """The revolution in _parts ended at firing ``wrap``: keep it when whole, count it when not."""
        problem = self._judge()
        if problem is None:
            revolutions.append((np.concatenate(self._parts), wrap))
            self.counters.revolutions += 1
        else:
            self._count_partial(problem)
        self._started = True
        self._parts = []
        self._azimuths = []

    def _judge(self) -> str | None:
        """Why the revolution just closed is not whole (revolution_problem), or None."""
        if not self._started:
            return "start_not_seen"
        n = sum(map(len, self._azimuths))
        if not MIN_FIRINGS_PER_REVOLUTION <= n <= MAX_FIRINGS_PER_REVOLUTION:
            return "firing_count"  # cheaply, without joining the pieces: what a flood of wraps makes
        return revolution_problem(np.concatenate(self._azimuths))

    def _overflow(self) -> None:
        self._log_overflow("VLP-16: no wrap in %d packets; dropping them", self._packets_in_revolution)
        self.counters.overflows += 1
        self._restart()

    def _restart(self) -> None:
        """Forget everything queued: the next revolution starts at the next wrap."""
        self._last_azimuth = None
        self._pending = []
        self._pending_wraps = []
        self._parts = []
        self._azimuths = []
        self._packets_in_revolution = 0
        self._started = False

    def _check_timestamps(self, stamps: Sequence[int]) -> None:
        """Count lost or reordered packets; after a silence, start over (called before queueing)."""
        previous = self._last_timestamp
        if (
            previous is not None
            and stamps
            and SILENCE_US < (stamps[0] - previous) % US_PER_HOUR < US_PER_HOUR / 2
        ):
            self.counters.silences += 1
            self._log_silence(
                "VLP-16: stream silent for %.2f s; dropping the revolution in progress",
                ((stamps[0] - previous) % US_PER_HOUR) / 1e6,
            )
            self._restart()
        for stamp in stamps:
            if previous is not None and (stamp - previous) % US_PER_HOUR > 1.5 * PACKET_DURATION_US:
                self.counters.timestamp_gaps += 1
                log.debug("VLP-16: timestamp gap %d → %d µs, packets lost or reordered", previous, stamp)
            previous = stamp
        self._last_timestamp = previous

    def _count_partial(self, reason: str, n: int = 1) -> None:
        self.counters.partial_revolutions += n
        partial = self.counters.partial
        if reason not in partial and reason != "start_not_seen":
            log.warning("VLP-16: dropping a revolution that is not one whole turn (%s); further ones are "
                        "only counted", reason)
        partial[reason] = partial.get(reason, 0) + n

    def _count_malformed(self, reason: str) -> None:
        malformed = self.counters.malformed
        if reason not in malformed:
            log.warning("VLP-16: dropping malformed packet (%s); further ones are only counted", reason)
        malformed[reason] = malformed.get(reason, 0) + 1


#: Datagrams read per assembler feed while draining the socket: small enough that the read budget is
#: checked often, large enough for the vectorised checks.
_READ_CHUNK = 64


class VelodyneUdpSource:
    """A VLP-16 on UDP: a non-blocking socket for the main loop's select, feeding a RevolutionAssembler.

    Hostile input is bounded here. Only datagrams from ``sensor_ip`` are decoded (as the ROS velodyne
    driver's ``device_ip``); others are counted and dropped. One read drains at most
    ``max_datagrams_per_read`` datagrams and stops once ``max_read_seconds`` are spent reading and
    decoding, so a flood cannot starve the main loop (the kernel drops what the socket cannot hold).
    More whole revolutions within a second than the sensor can make are withheld and flagged
    (``implausible``), for the companion to hold.

    :param host: address to bind (0.0.0.0 = all interfaces).
    :param port: the sensor's data port (2368 by default).
    :param backend: decoder backend, see RevolutionAssembler.
    :param clock: time source for ``last_revolution_end`` and the revolution rate (monotonic by
        default, to compare with the companion's own clock).
    :param receive_buffer_bytes: socket receive buffer; a revolution is about 90 KiB.
    :param sensor_ip: the sensor's IPv4 address; None or "" accepts datagrams from anyone.
    :param max_datagrams_per_read: drain at most this many datagrams per read_available call.
    :param max_read_seconds: stop draining once a read_available call has taken this long.
    :raises UserError: when the socket cannot be bound (address in use, bad host).
    """

    def __init__(
        self,
        host: str = "0.0.0.0",
        port: int = 2368,
        *,
        backend: Backend = "numpy",
        clock: Callable[[], float] = time.monotonic,
        receive_buffer_bytes: int = 1 << 21,
        sensor_ip: str | None = None,
        max_datagrams_per_read: int = 1024,
        max_read_seconds: float = 0.005,
    ) -> None:
        self.assembler = RevolutionAssembler(backend)
        self._clock = clock
        self._sensor_ip = sensor_ip or None
        self._max_datagrams = max_datagrams_per_read
        self._max_read_seconds = max_read_seconds
        self._recent: deque[float] = deque()  # clock() of the whole revolutions of the last second
        #: clock() when the packet completing the last returned revolution was read; None before.
        self.last_revolution_end: float | None = None
        #: the last read_available withheld revolutions: they came faster than the sensor turns.
        self.implausible = False
        #: the last read_available stopped at its bounds with datagrams still waiting (a flood).
        self.backlogged = False
        self._log_receive_error = _ThrottledLog(logging.WARNING)
        self._log_implausible = _ThrottledLog(logging.WARNING)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer_bytes)
            sock.bind((host, port))
        except (OSError, OverflowError) as exc:
            sock.close()
            raise UserError(f"cannot listen for VLP-16 packets on {host}:{port}: {exc}") from exc
        sock.setblocking(False)
        self._sock = sock
        # Linux caps the buffer at net.core.rmem_max; say what we got (a revolution is ~90 KiB).
        log.info(
            "VLP-16: listening on %s:%d for %s (decoder %s, receive buffer %d bytes)",
            *sock.getsockname()[:2],
            self._sensor_ip or "any sender",
            backend,
            sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF),
        )

    @property
    def address(self) -> tuple[str, int]:
        """The bound (host, port); the port is the real one when 0 was asked for."""
        host, port = self._sock.getsockname()[:2]
        return host, port

    @property
    def counters(self) -> VelodyneCounters:
        """Packet and revolution counters of the assembler."""
        return self.assembler.counters

    def fileno(self) -> int:
        """The socket's descriptor, for select/poll."""
        return self._sock.fileno()

    def read_available(self) -> list[np.ndarray]:
        """Drain the datagrams waiting (never blocks, bounded in count and time) and return the
        revolutions they completed.

        :return: (N, 3) float32 FLU clouds, oldest first; usually none or one; none while the
            revolutions come faster than the sensor can make them (then ``implausible`` is set).
        """
        deadline = time.perf_counter() + self._max_read_seconds
        budget = self._max_datagrams
        revolutions: list[Revolution] = []
        stamps: list[float] = []
        drained = False
        while budget > 0 and not drained:
            payloads, chunk_stamps, received, drained = self._receive(min(_READ_CHUNK, budget))
            budget -= received
            if payloads:
                for rev in self.assembler.feed_batch(payloads):
                    revolutions.append(rev)
                    stamps.append(chunk_stamps[rev.completed_by])
            if time.perf_counter() >= deadline:
                break
        self.backlogged = not drained
        self.implausible = self._too_fast(stamps)
        if self.implausible:
            self.counters.implausible_revolutions += len(revolutions)
            return []
        if revolutions:
            self.last_revolution_end = stamps[-1]
        return [rev.points for rev in revolutions]

    def _receive(self, limit: int) -> tuple[list[bytes], list[float], int, bool]:
        """Up to ``limit`` datagrams: (the sensor's payloads, their clock() stamps, datagrams read,
        whether the socket ran empty)."""
        payloads: list[bytes] = []
        stamps: list[float] = []
        sensor = self._sensor_ip
        for received in range(limit):
            try:
                payload, sender = self._sock.recvfrom(2048)
            except (BlockingIOError, InterruptedError):
                return payloads, stamps, received, True
            except OSError as exc:  # e.g. ICMP errors surfacing on a UDP socket: not ours to die of
                self._log_receive_error("VLP-16: receive error %s", exc)
                return payloads, stamps, received, True
            if sensor is not None and sender[0] != sensor:
                self._count_foreign(sender[0])
                continue
            payloads.append(payload)
            stamps.append(self._clock())
        return payloads, stamps, limit, False

    def _count_foreign(self, address: str) -> None:
        counters = self.counters
        if not counters.foreign_packets:
            log.warning("VLP-16: dropping a datagram from %s (not sensor_ip %s); further ones are only "
                        "counted", address, self._sensor_ip)
        counters.foreign_packets += 1

    def _too_fast(self, stamps: list[float]) -> bool:
        """Record whole revolutions completed at ``stamps``; True when the last second held more than
        the sensor can make."""
        recent = self._recent
        recent.extend(stamps)
        if not recent:
            return False
        while recent[0] < recent[-1] - 1.0:
            recent.popleft()
        too_fast = bool(stamps) and len(recent) > MAX_REVOLUTIONS_PER_SECOND
        if too_fast:
            self._log_implausible("VLP-16: %d whole revolutions within a second, more than the sensor "
                                  "makes; withholding them", len(recent))
        return too_fast

    def close(self) -> None:
        """Close the socket."""
        self._sock.close()

    def __enter__(self) -> VelodyneUdpSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
