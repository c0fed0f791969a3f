"""VLP-16 decoding, revolution assembly, encoding and the UDP source.

Most tests run on packets the project makes itself (:func:`~tests.companion.vlp16_recording.room_recording`);
those of what only a real sensor shows run on its recording where it is available (its facts are in
tests/fixtures/README.md) and skip otherwise. Parsing done here for comparison uses `struct` and
plain Python, independently of the module's numpy code.
"""

from __future__ import annotations

import math
import os
import select
import socket
import struct
import time

import numpy as np
import pytest
import velodyne_decoder as vd
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.common.errors import UserError
from companion.lidar import vlp16_packet
from companion.lidar.velodyne import RevolutionAssembler, VelodyneUdpSource
from companion.lidar.vlp16_packet import (
    MALFORMED_REASONS,
    PACKET_SIZE,
    VLP16_ELEVATIONS_DEG,
    decode_packets_numpy,
    encode_packets,
    laser_azimuths_deg,
    packet_error,
)
from tests.companion.vlp16_recording import load_recording, needs_recording, room_recording


@pytest.fixture(scope="module")
def recording() -> list[bytes]:
    """The real sensor's packets (only for tests marked ``needs_recording``)."""
    return load_recording()


@pytest.fixture(scope="module")
def room() -> list[bytes]:
    """1,000 packets of a room, made with the project's encoder, laid out as the recording is."""
    return room_recording()


def parse_packet(packet: bytes) -> tuple[list[int], list[list[int]], list[list[int]], int, int, int]:
    """Plain-struct parse: block azimuths, distances and reflectivities by block, timestamp, mode, id."""
    azimuths, distances, reflectivities = [], [], []
    for b in range(12):
        flag, azimuth = struct.unpack_from("<HH", packet, 100 * b)
        assert flag == 0xEEFF
        azimuths.append(azimuth)
        returns = [struct.unpack_from("<HB", packet, 100 * b + 4 + 3 * j) for j in range(32)]
        distances.append([d for d, _ in returns])
        reflectivities.append([r for _, r in returns])
    timestamp, mode, product = struct.unpack_from("<IBB", packet, 1200)
    return azimuths, distances, reflectivities, timestamp, mode, product


def reference_firings(packets: list[bytes]) -> list[tuple[float, list[int]]]:
    """(azimuth in 0.01°, 16 distances) of every firing, second firing halfway to the next block."""
    firings = []
    for packet in packets:
        azimuths, distances, *_ = parse_packet(packet)
        for b in range(12):
            step = (
                (azimuths[b + 1] - azimuths[b]) % 36000 if b < 11 else (azimuths[11] - azimuths[10]) % 36000
            )
            firings.append((float(azimuths[b]), distances[b][:16]))
            firings.append(((azimuths[b] + step / 2) % 36000, distances[b][16:]))
    return firings


def clockwise_azimuth_deg(points: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(-points[:, 1], points[:, 0])) % 360.0


# --- elevations and packet validation ---------------------------------------------------------


def test_elevations_by_laser_id_follow_the_manual() -> None:
    assert VLP16_ELEVATIONS_DEG.shape == (16,)
    assert list(VLP16_ELEVATIONS_DEG[:4]) == [-15.0, 1.0, -13.0, 3.0]
    assert list(VLP16_ELEVATIONS_DEG[14:]) == [-1.0, 15.0]
    assert sorted(VLP16_ELEVATIONS_DEG) == list(range(-15, 16, 2))
    with pytest.raises(ValueError):
        VLP16_ELEVATIONS_DEG[0] = 0.0


@needs_recording
def test_every_recorded_packet_is_well_formed(recording: list[bytes]) -> None:
    assert [packet_error(p) for p in recording] == [None] * len(recording)


def test_every_made_packet_is_well_formed_and_the_room_turns_twelve_times(room: list[bytes]) -> None:
    assert [packet_error(p) for p in room] == [None] * len(room)
    assembler = RevolutionAssembler()
    revolutions = assembler.feed_batch(room)
    assert len(revolutions) == 12 and assembler.counters.partial == {"start_not_seen": 1}


def _corrupt(packet: bytes, offset: int, value: bytes) -> bytes:
    return packet[:offset] + value + packet[offset + len(value) :]


def malformed_variants(packet: bytes) -> dict[str, bytes]:
    return {
        "wrong_length": packet[:1000],
        "bad_block_flag": _corrupt(packet, 700, b"\xff\xdd"),
        "azimuth_out_of_range": _corrupt(packet, 302, struct.pack("<H", 36000)),
        "unsupported_return_mode": _corrupt(packet, 1204, b"\x39"),
        "unknown_product_id": _corrupt(packet, 1205, b"\x24"),
    }


def test_packet_error_names_each_reason(room: list[bytes]) -> None:
    variants = malformed_variants(room[0])
    assert set(variants) == set(MALFORMED_REASONS)
    for reason, packet in variants.items():
        assert packet_error(packet) == reason
    assert packet_error(b"") == "wrong_length"
    assert packet_error(room[0] + b"\x00") == "wrong_length"
    # The first reason found wins: a bad flag and a bad product id is a bad flag.
    assert packet_error(_corrupt(variants["unknown_product_id"], 0, b"\x00\x00")) == "bad_block_flag"


def test_batch_checks_agree_with_the_per_packet_ones(room: list[bytes]) -> None:
    """Batches are checked with numpy, single packets in plain Python: same verdicts, same azimuths."""
    packets = [*malformed_variants(room[3]).values(), *room[:50]]
    packets = [p for p in packets if len(p) == PACKET_SIZE]
    data = np.frombuffer(b"".join(packets), dtype=np.uint8).reshape(-1, PACKET_SIZE)
    codes = vlp16_packet.reason_codes(data)
    assert [MALFORMED_REASONS[c - 1] if c else None for c in codes] == [packet_error(p) for p in packets]
    good = data[codes == 0]
    blocks = good.view(vlp16_packet.PACKET_DTYPE)[:, 0]["blocks"]["azimuth"]
    expected = [a for row in blocks.tolist() for a in vlp16_packet.firing_azimuths(row)]
    assert vlp16_packet.firing_azimuths_array(blocks.astype(np.float64)).tolist() == expected
    # and both agree with the plain-struct reference
    assert expected[: 24 * 50] == [az for az, _ in reference_firings(room[:50])]


@pytest.mark.parametrize("backend", ["numpy", "velodyne-decoder"])
def test_malformed_packets_are_counted_and_dropped_without_disturbing_assembly(
    room: list[bytes], backend: str
) -> None:
    clean = RevolutionAssembler(backend)
    expected = [rev.points for rev in clean.feed_batch(room[:300])]
    dirty = RevolutionAssembler(backend)
    got: list[np.ndarray] = []
    garbage = [*malformed_variants(room[0]).values(), b"", b"\x00" * PACKET_SIZE, os.urandom(1206)]
    for i, packet in enumerate(room[:300]):
        if i % 20 == 0:
            for bad in garbage:
                assert dirty.feed(bad) == []
        got += dirty.feed(packet)
    assert len(got) == len(expected) == 3
    for a, b in zip(got, expected, strict=True):
        np.testing.assert_array_equal(a, b)
    n = 15
    malformed = dirty.counters.malformed
    assert malformed["wrong_length"] == 2 * n
    assert malformed["bad_block_flag"] == 3 * n  # the corrupted flag, all zeros, random bytes
    assert malformed["azimuth_out_of_range"] == malformed["unsupported_return_mode"] == n
    assert malformed["unknown_product_id"] == n
    assert dirty.counters.packets == 300 + n * len(garbage)


# --- decoding the recording ---------------------------------------------------------------------


@pytest.fixture(scope="module", params=["numpy", "velodyne-decoder"])
def assembled(request: pytest.FixtureRequest, recording: list[bytes]) -> tuple[RevolutionAssembler, list]:
    assembler = RevolutionAssembler(request.param)
    revolutions: list[np.ndarray] = []
    for packet in recording:
        revolutions += assembler.feed(packet)
    return assembler, revolutions


@needs_recording
def test_recording_yields_twelve_revolutions_cut_at_the_wrap(assembled: tuple) -> None:
    assembler, revolutions = assembled
    assert len(revolutions) == 12
    assert assembler.counters.revolutions == 12
    assert assembler.counters.partial_revolutions == 1  # before the first of the 13 wraps
    assert assembler.counters.packets == 1000
    assert assembler.counters.malformed == {}
    assert assembler.counters.timestamp_gaps == 0
    for cloud in revolutions:
        assert cloud.dtype == np.float32 and cloud.shape[1] == 3
        assert 15_150 <= len(cloud) <= 15_450
        assert np.isfinite(cloud).all()
        azimuth = clockwise_azimuth_deg(cloud)
        # Starts just after 0°, ends just before 360°, and sweeps clockwise in between.
        assert azimuth[:20].min() < 1.0 and azimuth[-20:].max() > 359.0
        assert np.all(np.diff(np.unwrap(np.radians(azimuth[::200]))) > -0.1)


@needs_recording
def test_recording_revolutions_hold_exactly_the_returns_between_the_wraps(
    assembled: tuple, recording: list[bytes]
) -> None:
    _, revolutions = assembled
    firings = reference_firings(recording)
    wraps = [i for i in range(1, len(firings)) if firings[i][0] < firings[i - 1][0] - 18000]
    assert len(wraps) == 13
    for k, cloud in enumerate(revolutions):
        returns = sum(d != 0 for _, distances in firings[wraps[k] : wraps[k + 1]] for d in distances)
        assert len(cloud) == returns


@needs_recording
def test_recording_looks_like_a_room(assembled: tuple) -> None:
    _, revolutions = assembled
    ranges = np.linalg.norm(np.concatenate(revolutions), axis=1)
    assert 0.49 <= ranges.min() <= 0.51
    assert 12.32 <= ranges.max() <= 12.36
    assert abs(np.median(ranges) - 2.1) < 0.05
    # Consecutive revolutions of a static scene look alike: same count within 1 %, same median.
    counts = [len(c) for c in revolutions]
    assert max(counts) - min(counts) < 0.01 * np.mean(counts)


def test_decoded_points_follow_the_flu_formula(room: list[bytes]) -> None:
    """Points computed by hand from raw bytes with x = r cosω cosα, y = −r cosω sinα, z = r sinω."""
    packet = room[0]
    azimuths, distances, *_ = parse_packet(packet)
    decoded = decode_packets_numpy(np.frombuffer(packet, dtype=np.uint8).reshape(1, -1))
    expected = []
    for b in range(12):
        step = (azimuths[min(b + 1, 11)] - azimuths[min(b, 10)]) % 36000
        for j in range(32):
            if distances[b][j] == 0:
                continue
            firing, laser = divmod(j, 16)
            alpha = math.radians((azimuths[b] + step * (firing * 55.296 + laser * 2.304) / 110.592) / 100)
            omega = math.radians(VLP16_ELEVATIONS_DEG[laser])
            r = distances[b][j] * 0.002
            expected.append(
                (
                    r * math.cos(omega) * math.cos(alpha),
                    -r * math.cos(omega) * math.sin(alpha),
                    r * math.sin(omega),
                )
            )
    np.testing.assert_allclose(decoded.points, np.array(expected), atol=2e-5)


def test_backends_agree_on_the_room(room: list[bytes]) -> None:
    """Same points in the same order; velodyne-decoder adds the manual's ±11.2 mm vertical offsets."""
    data = np.frombuffer(b"".join(room[:200]), dtype=np.uint8).reshape(-1, PACKET_SIZE)
    ours = RevolutionAssembler("numpy")._decode(data, room[:200])
    theirs = RevolutionAssembler("velodyne-decoder")._decode(data, room[:200])
    np.testing.assert_array_equal(ours.points_per_firing, theirs.points_per_firing)
    assert ours.points_per_firing.sum() == len(ours.points) == len(theirs.points)
    horizontal = np.hypot(ours.points[:, 0], ours.points[:, 1])
    np.testing.assert_allclose(np.hypot(theirs.points[:, 0], theirs.points[:, 1]), horizontal, atol=1e-5)
    # velodyne-decoder 3.1 rounds each laser's azimuth to 0.01° and advances it at the mean rotation
    # rate rather than by each block's own step (a real sensor's steps jitter 0.38–0.42°).
    difference = (clockwise_azimuth_deg(theirs.points) - clockwise_azimuth_deg(ours.points) + 180) % 360 - 180
    assert np.abs(difference).max() < 0.03
    assert np.median(np.abs(difference)) < 0.004
    dz = theirs.points[:, 2] - ours.points[:, 2]
    assert 0.010 < np.abs(dz).max() < 0.0115
    # Up-looking lasers are offset down and vice versa (VLP-16 manual, table 9-1).
    assert np.all(dz[ours.points[:, 2] > 0.05] < 0) and np.all(dz[ours.points[:, 2] < -0.05] > 0)


@needs_recording
def test_velodyne_decoder_stream_cuts_at_packet_boundaries_with_more_points(
    recording: list[bytes], assembled: tuple
) -> None:
    """The library's own stream splitter keeps whole packets, so its revolutions are a bit larger."""
    _, ours = assembled
    decoder = vd.StreamDecoder(vd.Config(model=vd.Model.VLP16))
    theirs = [r for p in recording if (r := decoder.decode(0.0, p)) is not None]
    sizes = [len(cloud) for _, cloud in theirs]
    inner = sizes[1:13]  # full revolutions, as ours
    assert len(inner) == 12
    assert 0 < np.mean(inner) - np.mean([len(c) for c in ours]) < 600


# --- encoder ------------------------------------------------------------------------------------


@needs_recording
def test_encoder_reproduces_the_recording_bit_for_bit(recording: list[bytes]) -> None:
    for packet in recording[::37]:
        azimuths, distances, reflectivities, timestamp, mode, product = parse_packet(packet)
        firing_azimuth = np.repeat(np.array(azimuths) / 100.0, 2)  # odd firings are not sent
        ranges = np.array(distances, dtype=np.float64).reshape(24, 16) * 0.002
        encoded = encode_packets(
            firing_azimuth,
            ranges,
            reflectivity=np.array(reflectivities).reshape(24, 16),
            start_timestamp_us=timestamp,
            return_mode=mode,
            product_id=product,
        )
        assert encoded == [packet]


def test_encoder_layout_and_timestamps() -> None:
    azimuth = np.arange(48) * 0.2 + 359.0
    ranges = np.zeros((48, 16))
    ranges[0, 0] = 1.234
    ranges[1, 15] = 200.0  # beyond 131.07 m: no return
    ranges[2, 3] = np.nan
    ranges[3, 5] = 131.07
    packets = encode_packets(azimuth, ranges, start_timestamp_us=3_599_999_000.0, return_mode=0x38)
    assert [len(p) for p in packets] == [PACKET_SIZE, PACKET_SIZE]
    first = packets[0]
    assert all(first[100 * b : 100 * b + 2] == b"\xff\xee" for b in range(12))
    block_azimuths = [struct.unpack_from("<H", first, 100 * b + 2)[0] for b in range(12)]
    assert block_azimuths[:6] == [35900, 35940, 35980, 20, 60, 100]  # wraps modulo 360°
    assert struct.unpack_from("<H", first, 4)[0] == 617  # 1.234 m in 2 mm units
    assert struct.unpack_from("<H", first, 4 + 3 * 31)[0] == 0
    assert struct.unpack_from("<H", first, 104 + 3 * 16 + 3 * 5)[0] == 65535
    assert first[1204:] == b"\x38\x22"
    stamps = [struct.unpack_from("<I", p, 1200)[0] for p in packets]
    assert stamps == [3_599_999_000, (3_599_999_000 + 1327) % 3_600_000_000]
    assert [packet_error(p) for p in packets] == [None, None]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"azimuth_deg": np.zeros(25), "ranges": np.zeros((25, 16))}, "multiple of 24"),
        ({"azimuth_deg": np.zeros(24), "ranges": np.zeros((24, 15))}, "ranges"),
        ({"azimuth_deg": np.full(24, np.nan), "ranges": np.zeros((24, 16))}, "non-finite"),
        ({"azimuth_deg": np.zeros(24), "ranges": np.zeros((24, 16)), "return_mode": 0x39}, "return_mode"),
        ({"azimuth_deg": np.zeros(24), "ranges": np.zeros((24, 16)), "product_id": 256}, "product_id"),
        (
            {
                "azimuth_deg": np.zeros(24),
                "ranges": np.zeros((24, 16)),
                "reflectivity": np.full((24, 16), 300),
            },
            "reflectivity",
        ),
    ],
)
def test_encoder_rejects_what_it_cannot_send(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        encode_packets(**kwargs)


def expected_points(azimuth_deg: np.ndarray, ranges: np.ndarray, step_deg: float) -> np.ndarray:
    """Where decoders must put the returns: each laser at its precision azimuth, quantised range."""
    alpha = np.radians(laser_azimuths_deg(azimuth_deg, step_deg))
    omega = np.radians(VLP16_ELEVATIONS_DEG)[None, :]
    r = np.rint(ranges / 0.002) * 0.002
    points = np.stack(
        [r * np.cos(omega) * np.cos(alpha), -r * np.cos(omega) * np.sin(alpha), r * np.sin(omega)],
        axis=-1,
    )
    return points[r > 0]


def assert_round_trip(decoded: np.ndarray, expected: np.ndarray, *, z_slack: float = 0.0) -> None:
    assert decoded.shape == expected.shape
    r = np.linalg.norm(expected, axis=1)
    error = np.abs(decoded - expected)
    # 1 mm range rounding is already in `expected`; 0.02° of azimuth (0.01° block quantisation
    # through the interpolation, plus velodyne-decoder's own 0.01° rounding), float32.
    tolerance = r * math.radians(0.02) + 1e-5 + 1e-6 * r
    assert np.all(error[:, :2] <= tolerance[:, None])
    assert np.all(error[:, 2] <= 1e-5 + 1e-6 * r + z_slack)


@settings(max_examples=40, deadline=None)
@given(
    start=st.floats(0.0, 359.99),
    step_centideg=st.integers(4, 200),
    n_packets=st.integers(1, 3),
    max_range=st.floats(0.01, 131.0),
    dropout=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**32 - 1),
)
def test_encode_decode_round_trip(
    start: float, step_centideg: int, n_packets: int, max_range: float, dropout: float, seed: int
) -> None:
    step = step_centideg / 100.0
    azimuth = np.mod(start + step * np.arange(n_packets * 24), 360.0)
    rng = np.random.default_rng(seed)
    ranges = rng.uniform(0.0, max_range, size=(len(azimuth), 16))
    ranges[rng.random(ranges.shape) < dropout] = 0.0
    packets = encode_packets(azimuth, ranges)
    expected = expected_points(azimuth, ranges, step)
    data = np.frombuffer(b"".join(packets), dtype=np.uint8).reshape(-1, PACKET_SIZE)
    assert_round_trip(decode_packets_numpy(data).points, expected)
    _, cloud = vd.ScanDecoder(vd.Config(model=vd.Model.VLP16, min_range=0.001, max_range=131.07)).decode(
        vd.PacketVector([vd.VelodynePacket(0.0, p) for p in packets])
    )
    assert_round_trip(cloud[:, :3], expected, z_slack=0.0115)


@pytest.mark.parametrize(
    ("step", "start", "packets_per_revolution"),
    [
        (0.25, 90.5, 60),  # wrap at the first firing of a block, inside a packet (960 rpm)
        (0.2, 90.0, 75),
        (0.2, 90.3, 75),  # wrap at the interpolated second firing of a block
        (0.2, 0.0, 75),  # wrap at a packet boundary
    ],
)
@pytest.mark.parametrize("backend", ["numpy", "velodyne-decoder"])
@pytest.mark.parametrize("batched", [False, True])
def test_encoded_revolutions_assemble_to_the_cloud_that_went_in(
    step: float, start: float, packets_per_revolution: int, backend: str, batched: bool
) -> None:
    """Three turns: a partial revolution, then whole ones, each cut where the azimuth wraps."""
    rng = np.random.default_rng(7)
    firings = round(360 / step)
    assert firings == packets_per_revolution * 24
    azimuth = np.mod(start + step * np.arange(3 * firings + 24), 360.0)
    ranges = rng.uniform(0.5, 30.0, size=(len(azimuth), 16))
    ranges[rng.random(ranges.shape) < 0.3] = 0.0
    packets = encode_packets(azimuth, ranges, start_timestamp_us=1e6)
    assembler = RevolutionAssembler(backend)
    wraps = np.flatnonzero(np.diff(azimuth) < -180) + 1
    if batched:
        revolutions = assembler.feed_batch(packets)
        # Each revolution names the packet holding the wrap that closed it.
        assert [rev.completed_by for rev in revolutions] == [w // 24 for w in wraps[1:]]
        clouds = [rev.points for rev in revolutions]
    else:
        clouds = [c for p in packets for c in assembler.feed(p)]
    assert len(clouds) == len(wraps) - 1 >= 2
    assert assembler.counters.partial_revolutions == 1
    assert assembler.counters.timestamp_gaps == 0
    for k, cloud in enumerate(clouds):
        whole = slice(wraps[k], wraps[k + 1])
        expected = expected_points(azimuth[whole], ranges[whole], step)
        assert_round_trip(cloud, expected, z_slack=0.0115 if backend == "velodyne-decoder" else 0.0)


def test_lost_packets_show_as_timestamp_gaps() -> None:
    azimuth = np.mod(0.2 * np.arange(3 * 1800), 360.0)
    packets = encode_packets(azimuth, np.full((3 * 1800, 16), 5.0))
    assembler = RevolutionAssembler()
    clouds = [c for i, p in enumerate(packets) if i not in (100, 101, 160) for c in assembler.feed(p)]
    assert assembler.counters.timestamp_gaps == 2
    assert len(clouds) == 1  # the revolution from packet 75 to 149, with 100 and 101 lost
    assert len(clouds[0]) == 1800 * 16 - 2 * 24 * 16  # the lost packets' firings are missing


@pytest.mark.parametrize("batched", [False, True])
def test_after_a_silence_no_revolution_holds_points_from_before_it(batched: bool) -> None:
    """The sensor goes quiet mid-turn for 1.5 s: the turn it was in is dropped, not completed later."""
    azimuth = np.mod(0.2 * np.arange(6 * 1800), 360.0)
    # a partial turn (start not seen), a whole one, about half of the next; after it two more turns
    before, after = 2 * 1800 + 912, 4 * 1800 + 912
    packets = encode_packets(azimuth[:before], np.full((before, 16), 2.0), start_timestamp_us=1e6)
    packets += encode_packets(
        azimuth[before:after], np.full((after - before, 16), 7.0), start_timestamp_us=2.6e6
    )
    assembler = RevolutionAssembler()
    if batched:
        # the main loop reads what arrived before the silence, then what came after it
        clouds = [r.points for r in assembler.feed_batch(packets[: before // 24])]
        clouds += [r.points for r in assembler.feed_batch(packets[before // 24 :])]
    else:
        clouds = [c for p in packets for c in assembler.feed(p)]
    ranges = [np.linalg.norm(c, axis=1) for c in clouds]
    assert len(ranges) == 2 and assembler.counters.silences == 1
    assert np.allclose(ranges[0], 2.0, atol=0.01)  # the whole turn before the silence
    assert np.allclose(ranges[1], 7.0, atol=0.01)  # and only then a turn of fresh returns
    assert len(ranges[1]) == 1800 * 16


def test_a_sensor_that_never_wraps_does_not_grow_without_bound() -> None:
    stuck = encode_packets(np.full(24, 123.0), np.full((24, 16), 3.0))[0]
    assembler = RevolutionAssembler(max_packets_per_revolution=50)
    for _ in range(120):
        assert assembler.feed(stuck) == []
    assert assembler.counters.overflows == 2
    assert sum(len(p) for p in assembler._parts) <= 50 * 24 * 16


# --- UDP ----------------------------------------------------------------------------------------


def _drain(source: VelodyneUdpSource, until: float = 0.2) -> list[np.ndarray]:
    clouds: list[np.ndarray] = []
    deadline = time.monotonic() + until
    while time.monotonic() < deadline:
        ready, _, _ = select.select([source], [], [], 0.02)
        if ready:
            clouds += source.read_available()
    return clouds


def test_udp_source_assembles_revolutions_from_datagrams(room: list[bytes]) -> None:
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    with VelodyneUdpSource("127.0.0.1", 0) as source:
        assert source.read_available() == []  # non-blocking when nothing waits
        address = source.address
        garbage = [*malformed_variants(room[5]).values(), b"x", os.urandom(3000)]
        clouds: list[np.ndarray] = []
        for start in range(0, 400, 25):  # in chunks, so the loopback queue never overflows
            for packet in room[start : start + 25]:
                sender.sendto(packet, address)
            for bad in garbage:
                sender.sendto(bad, address)
            clouds += _drain(source, 0.05)
        sender.close()
        clouds += _drain(source)
        counters = source.counters
    reference = RevolutionAssembler()
    expected = [c for p in room[:400] for c in reference.feed(p)]
    assert len(clouds) == len(expected) == 4
    for got, want in zip(clouds, expected, strict=True):
        np.testing.assert_array_equal(got, want)
    chunks = 16
    assert counters.packets == 400 + chunks * len(garbage)
    assert counters.malformed["wrong_length"] == 3 * chunks  # short, 1 byte, 3000 bytes truncated
    for reason in MALFORMED_REASONS[1:]:
        assert counters.malformed[reason] == chunks
    assert source.last_revolution_end is not None and source.last_revolution_end <= time.monotonic()


def test_udp_source_sends_encoded_revolutions_and_stamps_their_end() -> None:
    ticks = iter(range(10_000))
    step = 0.2
    azimuth = np.mod(step * np.arange(2 * 1800 + 24), 360.0)
    packets = encode_packets(azimuth, np.full((len(azimuth), 16), 4.0))
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    with VelodyneUdpSource("127.0.0.1", 0, clock=lambda: float(next(ticks))) as source:
        clouds: list[np.ndarray] = []
        for packet in packets:
            sender.sendto(packet, source.address)
            ready, _, _ = select.select([source], [], [], 1.0)
            assert ready
            clouds += source.read_available()
            if clouds and source.last_revolution_end is not None:
                break
        sender.close()
        # One datagram per read: the stamp is that of the packet holding the second wrap (the 151st).
        assert len(clouds) == 1 and len(clouds[0]) == 1800 * 16
        assert source.last_revolution_end == 150.0
        ranges = np.linalg.norm(clouds[0], axis=1)
        np.testing.assert_allclose(ranges, 4.0, atol=1e-5)


def test_udp_source_reports_a_port_in_use_as_a_user_error() -> None:
    with VelodyneUdpSource("127.0.0.1", 0) as first, pytest.raises(UserError, match=r"127\.0\.0\.1:\d+"):
        VelodyneUdpSource("127.0.0.1", first.address[1])
    with pytest.raises(UserError, match="cannot listen"):
        VelodyneUdpSource("not-a-host.invalid", 2368)
