"""VLP-16 packet streams for the tests and benches: a room the project makes itself, and the real
sensor's recording where it is available.

The real recording is fetched data (1,000 packets of a VLP-16 from einride/vlp16-go, MIT): it lives
outside the repository, in ``../shared/fixtures/vlp16-recording.bin`` beside the checkout (CI and
every developer have it; ``LIDAR_AVOID_FIXTURES`` names another directory). The tests of what only
real data can show (the recording's own facts, the encoder bit for bit, velodyne-decoder's stream
on it) skip without it, saying where it was looked for. Every other test of the decoder and the
assembler uses :func:`room_recording`: the project's own encoder writing a room as the simulator's
lidar does (:mod:`companion.lidar.vlp16_packet`), laid out as the recording is.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from companion.lidar.vlp16_packet import (
    FIRINGS_PER_PACKET,
    PACKET_DTYPE,
    PACKET_DURATION_US,
    PACKET_SIZE,
    US_PER_HOUR,
    VLP16_ELEVATIONS_DEG,
    encode_packets,
)

REPO = Path(__file__).resolve().parents[2]

#: the room's layout: 1,000 packets, 0.2° a firing sequence (600 rpm: 75 packets a turn), the
#: azimuth wrapping halfway through packet 53, as in the recording
ROOM_PACKETS = 1000
ROOM_STEP_DEG = 0.2
ROOM_FIRST_WRAP = 53
#: 12 whole turns of the room from its first wrap: played in a loop, the azimuth runs on across the seam
LOOP = slice(ROOM_FIRST_WRAP, ROOM_FIRST_WRAP + 12 * 75)


def recording_path() -> Path:
    """Where the real recording is looked for: ``$LIDAR_AVOID_FIXTURES``, else ``../shared/fixtures``
    beside the repository."""
    override = os.environ.get("LIDAR_AVOID_FIXTURES")
    return (Path(override) if override else REPO.parent / "shared" / "fixtures") / "vlp16-recording.bin"


#: a test of what only the real sensor's data shows: skipped, saying where it looked, without it
needs_recording = pytest.mark.skipif(
    not recording_path().is_file(),
    reason=f"the real VLP-16 recording is not at {recording_path()} (fetched data, kept beside the "
    "repository in ../shared/fixtures/; LIDAR_AVOID_FIXTURES names another directory)",
)


def load_recording() -> list[bytes]:
    """The 1,000 recorded data packets, 1206 bytes each (mark the test :data:`needs_recording`)."""
    raw = recording_path().read_bytes()
    assert len(raw) == 1000 * PACKET_SIZE
    return [raw[i : i + PACKET_SIZE] for i in range(0, len(raw), PACKET_SIZE)]


def room_ranges(azimuth_deg: np.ndarray) -> np.ndarray:
    """(A, 16) ranges of each laser in an 8 m × 5 m room, the sensor 0.7 m right of and 0.4 m
    behind its centre, 1.5 m above the floor, under an open roof (the lasers above 4° see no
    return, as about half of a real indoor turn's slots hold none), with a doorway 1 m wide (10°
    around 100°: no return); metres.

    :param azimuth_deg: (A,) degrees clockwise from the front
    """
    alpha = np.radians(azimuth_deg)
    dx, dy = np.cos(alpha), -np.sin(alpha)  # FLU: clockwise azimuth is a negative y
    x0, y0, half_x, half_y = -0.4, -0.7, 4.0, 2.5
    with np.errstate(divide="ignore"):
        tx = np.where(dx > 0, (half_x - x0) / dx, (-half_x - x0) / dx)
        ty = np.where(dy > 0, (half_y - y0) / dy, (-half_y - y0) / dy)
    horizontal = np.minimum(np.abs(tx), np.abs(ty))
    omega = np.radians(VLP16_ELEVATIONS_DEG)[None, :]
    to_wall = horizontal[:, None] / np.cos(omega)
    to_floor = np.where(omega < 0, 1.5 / np.maximum(np.abs(np.sin(omega)), 1e-9), np.inf)
    ranges = np.minimum(to_wall, to_floor)
    ranges[:, VLP16_ELEVATIONS_DEG > 4] = 0.0
    doorway = np.abs((azimuth_deg - 100.0 + 180.0) % 360.0 - 180.0) < 5.0
    ranges[doorway[:, None] & (np.abs(VLP16_ELEVATIONS_DEG) < 10)[None, :]] = 0.0
    return ranges


def room_recording(packets: int = ROOM_PACKETS) -> list[bytes]:
    """``packets`` VLP-16 data packets of :func:`room_ranges`, made with the project's encoder and laid
    out as the real recording is (its first wrap halfway through packet 53, a turn every 75)."""
    firings = packets * FIRINGS_PER_PACKET
    first_wrap = ROOM_FIRST_WRAP * FIRINGS_PER_PACKET + FIRINGS_PER_PACKET // 2
    azimuth = (ROOM_STEP_DEG * (np.arange(firings) - first_wrap)) % 360.0
    return encode_packets(azimuth, room_ranges(azimuth), start_timestamp_us=1_000_000.0)


def looped_recording(laps: int) -> list[bytes]:
    """``laps`` laps of the room's :data:`LOOP`, timestamps rewritten to run on as the sensor's would."""
    packets = room_recording()[LOOP] * laps
    data = np.frombuffer(b"".join(packets), dtype=PACKET_DTYPE).copy()
    start = int(data["timestamp"][0])
    data["timestamp"] = np.mod(start + np.floor(np.arange(len(data)) * PACKET_DURATION_US), US_PER_HOUR)
    raw = data.tobytes()
    return [raw[i : i + PACKET_SIZE] for i in range(0, len(raw), PACKET_SIZE)]
