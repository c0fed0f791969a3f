"""The real VLP-16 recording of tests/fixtures, as packets, for the tests and benches that replay it."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from companion.lidar.vlp16_packet import PACKET_DTYPE, PACKET_DURATION_US, PACKET_SIZE, US_PER_HOUR

#: The packets from the first wrap to just before the last one: played in a loop, the azimuth runs on
#: across the seam (355.5° → 356.7°) and every lap holds 12 whole revolutions.
LOOP = slice(53, 957)
REVOLUTIONS_PER_LOOP = 12


def fixture_dir() -> Path:
    override = os.environ.get("LIDAR_AVOID_FIXTURES")
    return Path(override) if override else Path(__file__).resolve().parents[1] / "fixtures"


def load_recording() -> list[bytes]:
    """The 1,000 recorded data packets, 1206 bytes each."""
    raw = (fixture_dir() / "vlp16-recording.bin").read_bytes()
    assert len(raw) == 1000 * PACKET_SIZE
    return [raw[i : i + PACKET_SIZE] for i in range(0, len(raw), PACKET_SIZE)]


def looped_recording(laps: int, recording: list[bytes] | None = None) -> list[bytes]:
    """``laps`` laps of the recording's LOOP, timestamps rewritten to run on as the sensor's would.

    Only the timestamps change: azimuths and returns are the real sensor's.
    """
    packets = (recording or load_recording())[LOOP] * laps
    data = np.frombuffer(b"".join(packets), dtype=PACKET_DTYPE).copy()
    start = int(data["timestamp"][0])
    data["timestamp"] = np.mod(start + np.floor(np.arange(len(data)) * PACKET_DURATION_US), US_PER_HOUR)
    raw = data.tobytes()
    return [raw[i : i + PACKET_SIZE] for i in range(0, len(raw), PACKET_SIZE)]
