"""The Velodyne VLP-16 data packet: its layout, its checks, and points from it and back.

The 1206-byte data packet (VLP-16 manual §9.3): 12 blocks of [0xFFEE flag, azimuth uint16 in 0.01°,
32 returns of (uint16 distance in 2 mm units, uint8 reflectivity)], then a uint32 timestamp (µs past
the hour, of the packet's first firing), a return-mode byte and a product-id byte. Each block holds two
firing sequences of the 16 lasers; only the first sequence's azimuth is sent, the second one lies
halfway to the next block's azimuth. Laser k of a sequence fires k × 2.304 µs after its start and a
sequence lasts 55.296 µs, so decoders advance each laser's azimuth accordingly (the manual's
"precision azimuth", as the ROS driver and velodyne-decoder do).

Points come out in the sensor's FLU frame of ARCHITECTURE.md (azimuth α clockwise from the front,
elevation ω): x = r·cosω·cosα, y = −r·cosω·sinα, z = r·sinω.

Pure numpy, no I/O: :func:`packet_error` / :func:`reason_codes` check packets,
:func:`decode_packets_numpy` turns them into points, :func:`encode_packets` writes them (the
simulator's sensor and the tests). :mod:`companion.lidar.velodyne` assembles revolutions from them
and reads them off UDP.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

#: Elevation ω of each laser in degrees, indexed by laser id (the order within a firing sequence).
#: From the VLP-16 manual: even ids point down (−15° … −1°), odd ids up (+1° … +15°), interleaved.
VLP16_ELEVATIONS_DEG: np.ndarray = np.array(
    [-15.0, 1.0, -13.0, 3.0, -11.0, 5.0, -9.0, 7.0, -7.0, 9.0, -5.0, 11.0, -3.0, 13.0, -1.0, 15.0],
    dtype=np.float64,
)
VLP16_ELEVATIONS_DEG.setflags(write=False)

PACKET_SIZE = 1206
BLOCKS_PER_PACKET = 12
LASERS = 16
FIRINGS_PER_PACKET = 2 * BLOCKS_PER_PACKET
DISTANCE_UNIT_M = 0.002
MAX_RANGE_M = 65535 * DISTANCE_UNIT_M
#: Duration of one firing sequence of all 16 lasers (16 × 2.304 µs + 18.43 µs recharge), µs.
FIRING_SEQUENCE_US = 55.296
#: Time between two lasers of a firing sequence, µs.
LASER_FIRING_US = 2.304
PACKET_DURATION_US = FIRINGS_PER_PACKET * FIRING_SEQUENCE_US
US_PER_HOUR = 3_600_000_000
PACKETS_PER_SECOND = 1e6 / PACKET_DURATION_US
RETURN_STRONGEST = 0x37
RETURN_LAST = 0x38
RETURN_DUAL = 0x39  # refused: two returns per firing
PRODUCT_ID_VLP16 = 0x22  # shared with the Puck LITE (same elevations); the Puck Hi-Res is 0x24

#: Why a packet was dropped, in the order they are checked; the keys of the ``malformed`` counter.
MALFORMED_REASONS = (
    "wrong_length",
    "bad_block_flag",
    "azimuth_out_of_range",
    "unsupported_return_mode",
    "unknown_product_id",
)
_RETURN_DTYPE = np.dtype([("distance", "<u2"), ("reflectivity", "u1")])
_BLOCK_DTYPE = np.dtype([("flag", "<u2"), ("azimuth", "<u2"), ("returns", _RETURN_DTYPE, (2 * LASERS,))])
#: numpy layout of one data packet, for reading and writing packets without copies.
PACKET_DTYPE = np.dtype(
    [
        ("blocks", _BLOCK_DTYPE, (BLOCKS_PER_PACKET,)),
        ("timestamp", "<u4"),
        ("return_mode", "u1"),
        ("product_id", "u1"),
    ]
)
assert PACKET_DTYPE.itemsize == PACKET_SIZE

# Per return slot of a block (2 firings × 16 lasers): the fraction of the block's azimuth step at
# which that laser fired (the precision-azimuth correction), and its elevation terms scaled to metres.
_SLOT_FIRING = np.repeat(np.arange(2), LASERS)
_SLOT_LASER = np.tile(np.arange(LASERS), 2)
_SLOT_STEP_FRACTION = (
    (_SLOT_FIRING * FIRING_SEQUENCE_US + _SLOT_LASER * LASER_FIRING_US) / (2 * FIRING_SEQUENCE_US)
).astype(np.float32)
_SLOT_COS_ELEVATION_M = (np.cos(np.radians(VLP16_ELEVATIONS_DEG)) * DISTANCE_UNIT_M)[_SLOT_LASER].astype(
    np.float32
)
_SLOT_SIN_ELEVATION_M = (np.sin(np.radians(VLP16_ELEVATIONS_DEG)) * DISTANCE_UNIT_M)[_SLOT_LASER].astype(
    np.float32
)
_CENTIDEG_TO_RAD = np.float32(math.pi / 18000.0)


def laser_azimuths_deg(firing_azimuth_deg: np.ndarray, step_deg: float) -> np.ndarray:
    """Where each laser of each firing really points, as decoders place its return.

    Laser k fires k × 2.304 µs into its 55.296 µs sequence while the head keeps turning, so its
    azimuth is the sequence's plus k × 2.304 / 55.296 of the step between sequences. A ray caster that
    casts laser k there gets back exactly the cloud it cast after encode → decode.

    :param firing_azimuth_deg: (A,) azimuth of each firing sequence, degrees clockwise from the front.
    :param step_deg: azimuth step between consecutive firing sequences, degrees.
    :return: (A, 16) azimuth of each laser in degrees, in [0, 360).
    """
    offsets = np.arange(LASERS) * (LASER_FIRING_US / FIRING_SEQUENCE_US) * step_deg
    return np.mod(np.asarray(firing_azimuth_deg, dtype=np.float64)[:, None] + offsets[None, :], 360.0)


# Header fields of a data packet: 12 × (flag, azimuth), then timestamp, return mode, product id.
_HEADER = struct.Struct("<" + "HH96x" * BLOCKS_PER_PACKET + "IBB")
_FLAGS = (0xEEFF,) * BLOCKS_PER_PACKET  # the bytes FF EE, read little-endian
assert _HEADER.size == PACKET_SIZE


def parse_header(packet: bytes) -> tuple[str | None, tuple[int, ...]]:
    """(why the packet is malformed or None, its unpacked header fields); a couple of µs per packet."""
    if len(packet) != PACKET_SIZE:
        return "wrong_length", ()
    fields = _HEADER.unpack_from(packet)
    if fields[0:24:2] != _FLAGS:
        return "bad_block_flag", fields
    if max(fields[1:24:2]) >= 36000:
        return "azimuth_out_of_range", fields
    if fields[25] not in (RETURN_STRONGEST, RETURN_LAST):
        return "unsupported_return_mode", fields
    if fields[26] != PRODUCT_ID_VLP16:
        return "unknown_product_id", fields
    return None, fields


def packet_error(packet: bytes) -> str | None:
    """Say why a datagram is not a VLP-16 data packet this module can decode.

    Dual-return packets (0x39) are refused: the scan wants one return per firing, so configure the
    sensor for strongest or last return.

    :param packet: the UDP payload.
    :return: one of MALFORMED_REASONS, or None when the packet is well formed.
    """
    return parse_header(packet)[0]


def reason_codes(packets: np.ndarray) -> np.ndarray:
    """parse_header's checks on (P, 1206) packets at once: 1 + index into MALFORMED_REASONS, or 0."""
    view = packets.view(PACKET_DTYPE)[:, 0]
    blocks = view["blocks"]
    codes = np.zeros(len(packets), dtype=np.int8)
    # Assigned last reason first, so that the first reason found wins as in parse_header.
    codes[view["product_id"] != PRODUCT_ID_VLP16] = 5
    mode = view["return_mode"]
    codes[(mode != RETURN_STRONGEST) & (mode != RETURN_LAST)] = 4
    codes[(blocks["azimuth"] >= 36000).any(axis=1)] = 3
    codes[(blocks["flag"] != _FLAGS[0]).any(axis=1)] = 2
    return codes


def firing_azimuths(block_azimuths: Sequence[int]) -> list[float]:
    """Azimuth of each of a packet's 24 firing sequences in 0.01°, in [0, 36000).

    The second firing of a block lies halfway to the next block; the last block reuses the step
    before it (within the packet only, as the ROS driver and velodyne-decoder do).

    :param block_azimuths: the 12 block azimuths of one packet, 0.01°.
    """
    out: list[float] = []
    step = 0
    for b, azimuth in enumerate(block_azimuths):
        if b + 1 < BLOCKS_PER_PACKET:
            step = (block_azimuths[b + 1] - azimuth) % 36000
        out.append(float(azimuth))
        out.append((azimuth + 0.5 * step) % 36000)
    return out


def firing_azimuths_array(block_azimuths: np.ndarray) -> np.ndarray:
    """firing_azimuths of (P, 12) packets at once, flattened to (P × 24,)."""
    step = np.empty_like(block_azimuths)
    np.subtract(block_azimuths[:, 1:], block_azimuths[:, :-1], out=step[:, :-1])
    np.mod(step[:, :-1], 36000.0, out=step[:, :-1])
    step[:, -1] = step[:, -2]
    firing = np.empty((len(block_azimuths), BLOCKS_PER_PACKET, 2), dtype=np.float64)
    firing[:, :, 0] = block_azimuths
    np.mod(block_azimuths + 0.5 * step, 36000.0, out=firing[:, :, 1])
    return firing.reshape(-1)


class DecodedPackets(NamedTuple):
    """Points of a run of consecutive packets."""

    #: (N, 3) float32 FLU points in metres, in packet order; no-return slots dropped.
    points: np.ndarray
    #: (P × 24,) number of points each firing sequence contributed, to cut between firings.
    points_per_firing: np.ndarray


def decode_packets_numpy(packets: np.ndarray) -> DecodedPackets:
    """Decode well-formed VLP-16 packets in one vectorised pass (see packet_error).

    Every slot is computed and the returns picked out once at the end: boolean masks over the
    ragged pattern of real returns cost more in branch mispredictions than the extra arithmetic.

    :param packets: (P, 1206) uint8, consecutive packets of one sensor.
    """
    blocks = packets.view(PACKET_DTYPE)[:, 0]["blocks"]
    azimuth = blocks["azimuth"].astype(np.float32)
    step = np.empty_like(azimuth)
    np.subtract(azimuth[:, 1:], azimuth[:, :-1], out=step[:, :-1])
    np.mod(step[:, :-1], 36000.0, out=step[:, :-1])
    step[:, -1] = step[:, -2]
    raw = blocks["returns"]["distance"]
    distance = raw.astype(np.float32)
    alpha = step[:, :, None] * _SLOT_STEP_FRACTION
    alpha += azimuth[:, :, None]
    alpha *= _CENTIDEG_TO_RAD
    horizontal = distance * _SLOT_COS_ELEVATION_M
    slots = np.empty((*distance.shape, 3), dtype=np.float32)
    np.multiply(horizontal, np.cos(alpha), out=slots[..., 0])
    np.multiply(horizontal, np.sin(alpha), out=slots[..., 1])
    np.negative(slots[..., 1], out=slots[..., 1])
    np.multiply(distance, _SLOT_SIN_ELEVATION_M, out=slots[..., 2])
    returns = np.flatnonzero(distance != 0)  # a contiguous bool array: the fast case of flatnonzero
    points = slots.reshape(-1, 3).take(returns, axis=0)
    return DecodedPackets(points, points_per_firing(returns, len(packets)))


def points_per_firing(returns: np.ndarray, n_packets: int) -> np.ndarray:
    """Points per firing sequence, from the flat slot indices of the returns (32 slots per block)."""
    return np.bincount(returns >> 4, minlength=n_packets * FIRINGS_PER_PACKET)  # 16 slots per firing


def _decode_numpy(packets: np.ndarray, _payloads: Sequence[bytes]) -> DecodedPackets:
    return decode_packets_numpy(packets)


def encode_packets(
    azimuth_deg: np.ndarray,
    ranges: np.ndarray,
    *,
    reflectivity: np.ndarray | None = None,
    start_timestamp_us: float = 0,
    return_mode: int = RETURN_STRONGEST,
    product_id: int = PRODUCT_ID_VLP16,
) -> list[bytes]:
    """Pack firing sequences into VLP-16 data packets, as the sensor sends them.

    Two firings per block, 12 blocks per packet. Only the even firings' azimuths are sent (rounded to
    0.01°); decoders put the odd ones halfway to the next block, so the azimuths should advance
    evenly (as the sensor's do). Ranges are rounded to 2 mm; NaN, ≤ 0 and > 131.07 m are sent as no
    return (0). Packet p's timestamp is floor(start + p × 24 × 55.296 µs) modulo one hour.

    :param azimuth_deg: (A,) azimuth of each firing sequence, degrees clockwise from the front
        (taken modulo 360); A must be a multiple of 24 (1° step: 360 = 15 packets, 0.2°: 1800 = 75).
    :param ranges: (A, 16) metres by laser id (VLP16_ELEVATIONS_DEG order), 0 = no return.
    :param reflectivity: (A, 16) 0–255 per return; 0 when omitted.
    :param start_timestamp_us: time of the first firing, µs past the hour.
    :param return_mode: 0x37 strongest or 0x38 last (dual needs two returns per firing).
    :param product_id: product-id byte, 0x22 for the VLP-16.
    :return: the packets, 1206 bytes each.
    """
    azimuth_deg = np.asarray(azimuth_deg, dtype=np.float64)
    ranges = np.asarray(ranges, dtype=np.float64)
    n_firings = len(azimuth_deg)
    if azimuth_deg.ndim != 1 or ranges.shape != (n_firings, LASERS):
        raise ValueError(f"need azimuth_deg (A,) and ranges (A, 16), not {azimuth_deg.shape}, {ranges.shape}")
    if n_firings % FIRINGS_PER_PACKET:
        raise ValueError(f"the number of firings ({n_firings}) must be a multiple of {FIRINGS_PER_PACKET}")
    if not np.isfinite(azimuth_deg).all():
        raise ValueError("azimuth_deg has a non-finite value")
    if return_mode not in (RETURN_STRONGEST, RETURN_LAST):
        raise ValueError(f"return_mode must be 0x37 or 0x38, got {return_mode:#x}")
    if not 0 <= product_id <= 255:
        raise ValueError(f"product_id must be a byte, got {product_id}")
    n_packets = n_firings // FIRINGS_PER_PACKET

    with np.errstate(invalid="ignore"):
        units = np.rint(ranges / DISTANCE_UNIT_M)
        units[~((units > 0) & (units <= 65535))] = 0  # also catches NaN
    packets = np.zeros(n_packets, dtype=PACKET_DTYPE)
    blocks = packets["blocks"]
    blocks["flag"] = 0xEEFF
    block_azimuth = azimuth_deg[0::2].reshape(n_packets, BLOCKS_PER_PACKET)
    blocks["azimuth"] = np.mod(np.rint(np.mod(block_azimuth, 360.0) * 100.0), 36000).astype(np.uint16)
    # Firings 2k and 2k+1 share block k: (P, 12, 2, 16) → (P, 12, 32) return slots.
    blocks["returns"]["distance"] = units.astype(np.uint16).reshape(n_packets, BLOCKS_PER_PACKET, 2 * LASERS)
    if reflectivity is not None:
        reflectivity = np.asarray(reflectivity)
        if reflectivity.shape != ranges.shape:
            raise ValueError(f"reflectivity must have the shape {ranges.shape}, not {reflectivity.shape}")
        if reflectivity.min(initial=0) < 0 or reflectivity.max(initial=0) > 255:
            raise ValueError("reflectivity must be within 0–255")
        blocks["returns"]["reflectivity"] = reflectivity.astype(np.uint8).reshape(
            n_packets, BLOCKS_PER_PACKET, 2 * LASERS
        )
    stamps = np.floor(start_timestamp_us + np.arange(n_packets) * PACKET_DURATION_US)
    packets["timestamp"] = np.mod(stamps, US_PER_HOUR).astype(np.uint32)
    packets["return_mode"] = return_mode
    packets["product_id"] = product_id
    raw = packets.tobytes()
    return [raw[i : i + PACKET_SIZE] for i in range(0, len(raw), PACKET_SIZE)]
