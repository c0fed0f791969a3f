"""Hostile VLP-16 input. Only whole revolutions leave the assembler: corrupt, replayed, lost or
forged packets cut the turn into pieces, and a piece of a turn must never reach the scan (its missing
sectors would read as clear).

The defect this guards against (issue 14): one packet of the real recording with every azimuth set to
0.00° closed a "revolution" of 1,955 points covering 40°, so 320 of 360 bins read as clear. And the
UDP source takes packets only from the sensor, reads a bounded amount per call and withholds turns
that come faster than the sensor can make them. The packets are a room the project makes, laid out
as that recording is (:func:`~tests.companion.vlp16_recording.room_recording`).
"""

from __future__ import annotations

import select
import socket
import struct
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.lidar.velodyne import (
    MAX_FIRINGS_PER_REVOLUTION,
    MAX_REVOLUTIONS_PER_SECOND,
    MIN_FIRINGS_PER_REVOLUTION,
    RevolutionAssembler,
    VelodyneUdpSource,
    revolution_problem,
)
from companion.lidar.vlp16_packet import PACKET_SIZE, encode_packets
from companion.perception.scan import ScanConfig, scan_from_points
from tests.companion.vlp16_recording import room_recording


@pytest.fixture(scope="module")
def recording() -> list[bytes]:
    return room_recording()


@pytest.fixture(scope="module")
def reference(recording: list[bytes]) -> list[np.ndarray]:
    return [rev.points for rev in RevolutionAssembler().feed_batch(recording)]


def with_block_azimuths(packet: bytes, azimuths: list[int]) -> bytes:
    """The packet with its 12 block azimuth fields replaced (header and returns untouched)."""
    out = bytearray(packet)
    for b, azimuth in enumerate(azimuths):
        struct.pack_into("<H", out, 100 * b + 2, azimuth)
    return bytes(out)


def assemble(packets: list[bytes], batched: bool) -> tuple[RevolutionAssembler, list[np.ndarray]]:
    assembler = RevolutionAssembler()
    if batched:
        return assembler, [rev.points for rev in assembler.feed_batch(packets)]
    return assembler, [cloud for p in packets for cloud in assembler.feed(p)]


def sectors_with_returns(points: np.ndarray) -> int:
    azimuth = np.degrees(np.arctan2(-points[:, 1], points[:, 0])) % 360.0
    return len(np.unique(np.floor(azimuth)))


def is_one_of(cloud: np.ndarray, clouds: list[np.ndarray]) -> bool:
    return any(c.shape == cloud.shape and np.array_equal(c, cloud) for c in clouds)


@pytest.mark.parametrize("batched", [False, True])
def test_a_packet_with_every_azimuth_zeroed_clears_no_sector(
    recording: list[bytes], reference: list[np.ndarray], batched: bool
) -> None:
    packets = list(recording)
    packets[120] = with_block_azimuths(recording[120], [0] * 12)  # at about 317°, inside the 1st whole turn
    assembler, clouds = assemble(packets, batched)
    # The turn holding packet 120 is cut in two (0–317° and 0°+317–360°): neither comes out.
    assert len(clouds) == len(reference) - 1
    assert all(is_one_of(cloud, reference[1:]) for cloud in clouds)
    assert assembler.counters.partial_revolutions == 1 + 2
    assert assembler.counters.partial == {"start_not_seen": 1, "coverage": 1, "firing_count": 1}
    # and what reaches the scan is a room, never an almost empty scan
    for cloud in clouds:
        assert np.count_nonzero(scan_from_points(cloud, ScanConfig(slice_height=2.0)) == 1.0) < 60


@pytest.mark.parametrize(("again", "at", "partial"), [(199, 200, {"azimuth_backwards": 1}),
                                                      (150, 200, {"coverage": 1, "firing_count": 1})])
def test_a_replayed_packet_drops_the_turn_it_lands_in(
    recording: list[bytes], reference: list[np.ndarray], again: int, at: int, partial: dict[str, int]
) -> None:
    """Packet ``again`` arrives a second time before packet ``at``: right after itself (its azimuths
    repeat) or 50 packets late (its azimuth falls by more than half a turn, which cuts the turn)."""
    packets = [*recording[:at], recording[again], *recording[at:]]
    assembler, clouds = assemble(packets, batched=True)
    assert len(clouds) == len(reference) - 1 and all(is_one_of(c, reference) for c in clouds)
    assert assembler.counters.partial == {"start_not_seen": 1, **partial}


def _turns(step: float, turns: int = 3, start: float = 90.0) -> tuple[np.ndarray, list[bytes]]:
    firings = round(360 / step) * turns
    firings += -firings % 24
    azimuth = np.mod(start + step * np.arange(firings), 360.0)
    return azimuth, encode_packets(azimuth, np.full((firings, 16), 5.0), start_timestamp_us=1e6)


@pytest.mark.parametrize(
    ("step", "lost", "reason", "dropped"),
    [
        (0.2, [], None, 0),  # 600 rpm, nothing lost: whole
        (0.2, [100, 101], None, 0),  # two packets lost (9.6°) in the first whole turn: still whole
        (0.2, [100, 101, 102], "coverage", 1),  # 14.4° missing
        (0.1, [200, 201, 202, 203], "hole", 1),  # 300 rpm: 9.6° missing in one hole of four packets
        (1.0, [], "firing_count", 2),  # 15 packets a turn: 2,400 rpm, no VLP-16 turns that fast
    ],
)
def test_only_whole_turns_of_a_vlp16_are_revolutions(
    step: float, lost: list[int], reason: str | None, dropped: int
) -> None:
    _, packets = _turns(step)  # from 90°, three turns wrap three times: a piece, then two whole turns
    packets = [p for i, p in enumerate(packets) if i not in lost]
    assembler, clouds = assemble(packets, batched=False)
    assert len(clouds) == 2 - dropped
    assert assembler.counters.partial == {"start_not_seen": 1, **({reason: dropped} if reason else {})}


def test_revolution_problem_on_firing_azimuths() -> None:
    whole = np.arange(0.0, 36000.0, 20.0)  # 1,800 firings at 0.2°
    assert revolution_problem(whole) is None
    assert revolution_problem(whole[:-24 * 3]) == "coverage"  # the last three packets never came
    assert revolution_problem(np.delete(whole, range(900, 948))) is None  # two packets mid-turn
    backwards = whole.copy()
    backwards[500] = backwards[499]
    assert revolution_problem(backwards) == "azimuth_backwards"
    assert revolution_problem(whole[::4]) == "firing_count"  # 450 firings: 2,400 rpm
    assert revolution_problem(np.arange(0.0, 36000.0, 5.0)) == "firing_count"  # 7,200: 150 rpm
    assert MIN_FIRINGS_PER_REVOLUTION < 905 and MAX_FIRINGS_PER_REVOLUTION > 3617  # 1200 and 300 rpm


@settings(max_examples=60, deadline=None)
@given(
    index=st.integers(60, 900),
    azimuths=st.lists(st.integers(0, 35999), min_size=12, max_size=12),
    batched=st.booleans(),
)
def test_no_single_forged_azimuth_packet_makes_a_scan_with_a_missing_sector(
    recording: list[bytes], index: int, azimuths: list[int], batched: bool
) -> None:
    packets = list(recording)
    packets[index] = with_block_azimuths(recording[index], azimuths)
    assert len(packets[index]) == PACKET_SIZE
    _, clouds = assemble(packets, batched)
    assert len(clouds) >= 12 - 2  # at most the turns around the forged packet are lost
    for cloud in clouds:  # the room has returns in every one-degree sector of a turn
        assert sectors_with_returns(cloud) >= 300


# --- the UDP source: one sensor, bounded reads, no more turns than the sensor makes --------------


def _drain(source: VelodyneUdpSource, until: float = 0.3) -> list[np.ndarray]:
    clouds: list[np.ndarray] = []
    deadline = time.monotonic() + until
    while time.monotonic() < deadline:
        if select.select([source], [], [], 0.02)[0]:
            clouds += source.read_available()
    return clouds


def _sender(host: str) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((host, 0))
    return sock


def test_udp_source_takes_packets_only_from_the_sensor_ip(recording: list[bytes]) -> None:
    """A spoofer on 127.0.0.2 sends all-clear turns with their wraps, two for each real packet."""
    _, forged = _turns(0.2, turns=1, start=0.0)  # a whole turn of 5 m returns
    with VelodyneUdpSource("127.0.0.1", 0, sensor_ip="127.0.0.1") as source:
        sensor, spoofer = _sender("127.0.0.1"), _sender("127.0.0.2")
        clouds: list[np.ndarray] = []
        for start in range(0, 400, 25):  # in chunks, so the loopback queue never overflows
            for i, packet in enumerate(recording[start : start + 25]):
                sensor.sendto(packet, source.address)
                for k in range(2):
                    spoofer.sendto(forged[(2 * (start + i) + k) % len(forged)], source.address)
            clouds += _drain(source, 0.05)
        clouds += _drain(source)
        sensor.close()
        spoofer.close()
        counters = source.counters
    expected = [rev.points for rev in RevolutionAssembler().feed_batch(recording[:400])]
    assert len(clouds) == len(expected) == 4
    assert all(np.array_equal(a, b) for a, b in zip(clouds, expected, strict=True))
    assert counters.foreign_packets == 800 and counters.packets == 400


def test_udp_source_reads_are_bounded_in_time_and_count() -> None:
    _, packets = _turns(0.2, turns=4)
    with VelodyneUdpSource("127.0.0.1", 0, max_read_seconds=0.0) as hurried, VelodyneUdpSource(
        "127.0.0.1", 0, max_datagrams_per_read=100, max_read_seconds=60.0
    ) as counted:
        sender = _sender("127.0.0.1")
        for packet in packets[:200]:
            sender.sendto(packet, hurried.address)
            sender.sendto(packet, counted.address)
        sender.close()
        hurried.read_available()
        counted.read_available()
        assert hurried.counters.packets == 64  # one chunk, then the time was up
        assert counted.counters.packets == 100
        hurried.read_available()
        assert hurried.counters.packets == 128  # the rest waits in the socket for the next reads


def test_more_turns_a_second_than_the_sensor_makes_are_withheld() -> None:
    now = [0.0]
    _, turns = _turns(0.375, turns=40, start=0.0)  # 40 packets a turn: 1,125 rpm, plausible
    with VelodyneUdpSource("127.0.0.1", 0, clock=lambda: now[0]) as source:
        sender = _sender("127.0.0.1")

        def play(first: int, n: int) -> list[np.ndarray]:
            clouds: list[np.ndarray] = []
            for t in range(first, first + n):
                for packet in turns[40 * t : 40 * (t + 1)]:
                    sender.sendto(packet, source.address)
                clouds += _drain(source, 0.03)
                now[0] += 1.0 / 30  # 30 turns a second: a replay, or a forger
            return clouds

        fast = play(0, 30)  # 28 whole turns (the first wrap only starts one)
        assert len(fast) == MAX_REVOLUTIONS_PER_SECOND  # then a second holds more than the sensor makes
        assert source.implausible and source.counters.implausible_revolutions == 28 - len(fast)
        now[0] += 1.0  # the sensor at its own pace again: a second later the turns come through
        slow: list[np.ndarray] = []
        for first in range(30, 38):
            slow += play(first, 1)
            now[0] += 0.1 - 1.0 / 30
        sender.close()
    assert not source.implausible and len(slow) == 8
