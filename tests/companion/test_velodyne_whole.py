"""Only whole revolutions leave the assembler: corrupt, replayed, lost or forged packets cut the turn
into pieces, and a piece of a turn must never reach the scan (its missing sectors would read as clear).

The defect this guards against (issue 14): one packet of the real recording with every azimuth set to
0.00° closed a "revolution" of 1,955 points covering 40°, so 320 of 360 bins read as clear.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.lidar.velodyne import (
    MAX_FIRINGS_PER_REVOLUTION,
    MIN_FIRINGS_PER_REVOLUTION,
    PACKET_SIZE,
    RevolutionAssembler,
    encode_packets,
    revolution_problem,
)
from companion.scan import ScanConfig, scan_from_points
from tests.companion.vlp16_recording import load_recording


@pytest.fixture(scope="module")
def recording() -> list[bytes]:
    return load_recording()


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
    for cloud in clouds:  # the recorded room has returns in 322–326 one-degree sectors per turn
        assert sectors_with_returns(cloud) >= 300
