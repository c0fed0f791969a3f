"""Fuzz targets for hostile input, run by hand for as long as you like (hypothesis):

    python -m tests.companion.fuzz_inputs vlp16 --examples 100000
    python -m tests.companion.fuzz_inputs config --examples 20000

``vlp16``: streams made of the room packets (tests/companion/vlp16_recording.py) with packets corrupted
(bytes flipped, azimuth fields overwritten, truncated, extended), duplicated, dropped, reordered or
replaced by noise, fed to the RevolutionAssembler in random batch sizes. Nothing may raise; every
revolution that comes out is a finite (N, 3) float32 cloud within the sensor's range and its firings pass
``revolution_problem`` (one whole turn), and the counters add up.

``config``: companion config files built from the real keys with hostile values (NaN, ±inf, huge,
negative, wrong types, deep nesting) and raw bytes. ``load_config`` either raises a one-line
UserError or returns a config whose every float is finite and within its declared range.

tests/companion/test_fuzz_inputs.py runs both with a few examples in CI so they do not rot. A failure
prints the smallest input hypothesis found (and stores it in .hypothesis/ to replay first next time).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import logging
import math
import struct
import sys
import tempfile
import typing
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from companion.common.errors import UserError
from companion.config import CompanionConfig, load_config
from companion.lidar.velodyne import RevolutionAssembler, revolution_problem
from companion.lidar.vlp16_packet import (
    MAX_RANGE_M,
    PACKET_DTYPE,
    PACKET_SIZE,
    firing_azimuths_array,
    packet_error,
)
from tests.companion.vlp16_recording import room_recording

RECORDING = room_recording()

# --- VLP-16 packets ----------------------------------------------------------------------------


@st.composite
def corrupted(draw: st.DrawFn, packet: bytes) -> bytes:
    kind = draw(st.sampled_from(["flip", "azimuths", "truncate", "extend", "noise", "timestamp", "same"]))
    if len(packet) != PACKET_SIZE:  # corrupted already: corrupt it further
        return packet + draw(st.binary(max_size=8)) if kind == "extend" else packet[: len(packet) // 2]
    if kind == "flip":
        data = bytearray(packet)
        for _ in range(draw(st.integers(1, 8))):
            data[draw(st.integers(0, PACKET_SIZE - 1))] ^= 1 << draw(st.integers(0, 7))
        return bytes(data)
    if kind == "azimuths":
        data = bytearray(packet)
        for block in draw(st.lists(st.integers(0, 11), min_size=1, max_size=12)):
            struct.pack_into("<H", data, 100 * block + 2, draw(st.integers(0, 0xFFFF)))
        return bytes(data)
    if kind == "truncate":
        return packet[: draw(st.integers(0, PACKET_SIZE - 1))]
    if kind == "extend":
        return packet + draw(st.binary(min_size=1, max_size=64))
    if kind == "noise":
        return draw(st.binary(min_size=0, max_size=2 * PACKET_SIZE))
    if kind == "timestamp":
        return packet[:1200] + struct.pack("<I", draw(st.integers(0, 2**32 - 1))) + packet[1204:]
    return packet


@st.composite
def hostile_streams(draw: st.DrawFn) -> list[bytes]:
    start = draw(st.integers(0, len(RECORDING) - 400))
    stream = list(RECORDING[start : start + draw(st.integers(80, 400))])
    for _ in range(draw(st.integers(0, 12))):
        i = draw(st.integers(0, len(stream) - 1))
        action = draw(st.sampled_from(["corrupt", "duplicate", "drop", "swap", "insert"]))
        if action == "corrupt":
            stream[i] = draw(corrupted(stream[i]))
        elif action == "duplicate":
            stream.insert(draw(st.integers(0, len(stream))), stream[i])
        elif action == "drop" and len(stream) > 1:
            del stream[i]
        elif action == "swap":
            j = draw(st.integers(0, len(stream) - 1))
            stream[i], stream[j] = stream[j], stream[i]
        else:
            stream.insert(i, draw(corrupted(RECORDING[draw(st.integers(0, len(RECORDING) - 1))])))
    return stream


def firing_azimuths(packets: list[bytes]) -> np.ndarray:
    good = [p for p in packets if packet_error(p) is None]
    view = np.frombuffer(b"".join(good), dtype=PACKET_DTYPE)
    return firing_azimuths_array(view["blocks"]["azimuth"].astype(np.float64))


def check_vlp16_stream(stream: list[bytes], cuts: list[int]) -> None:
    """Feed ``stream`` in batches ending at ``cuts``; check every revolution and the counters."""
    assembler = RevolutionAssembler()
    revolutions = []
    fed = 0
    for cut in [*sorted(set(cuts)), len(stream)]:
        if cut > fed:
            revolutions += [(fed + r.completed_by, r.points) for r in assembler.feed_batch(stream[fed:cut])]
            fed = cut
    counters = assembler.counters
    assert counters.packets == len(stream)
    assert counters.revolutions == len(revolutions)
    assert counters.partial_revolutions == sum(counters.partial.values())
    # every revolution is one whole turn: the firings between the wraps around it pass the check
    azimuth = firing_azimuths(stream)
    wraps = np.flatnonzero(azimuth[1:] < azimuth[:-1] - 18000.0) + 1
    for _, points in revolutions:
        assert points.dtype == np.float32 and points.ndim == 2 and points.shape[1] == 3
        assert np.isfinite(points).all()
        assert float(np.abs(points).max(initial=0.0)) <= MAX_RANGE_M
    whole = [azimuth[a:b] for a, b in itertools.pairwise(wraps)]
    assert len(revolutions) <= sum(revolution_problem(w) is None for w in whole)


def fuzz_vlp16(examples: int) -> typing.Callable[[], None]:
    """The vlp16 target: call the result to run ``examples`` streams."""

    @settings(max_examples=examples, deadline=None, suppress_health_check=list(HealthCheck))
    @given(stream=hostile_streams(), cuts=st.lists(st.integers(0, 500), max_size=8))
    def run(stream: list[bytes], cuts: list[int]) -> None:
        check_vlp16_stream(stream, cuts)

    return run


# --- config --------------------------------------------------------------------------------------


def _leaf_keys(cls: type, prefix: str = "") -> list[tuple[str, typing.Any]]:
    out = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            out += _leaf_keys(tp, f"{prefix}{f.name}.")
        else:
            out.append((prefix + f.name, tp))
    return out


KEYS = _leaf_keys(CompanionConfig)
HOSTILE_FLOATS = st.sampled_from([math.nan, math.inf, -math.inf, 1e300, -1e300, 0.0, -0.0, 1e-300, 5e-324])
VALUES = st.one_of(
    HOSTILE_FLOATS, st.floats(allow_nan=True, allow_infinity=True), st.integers(-(2**63), 2**63 - 1),
    st.booleans(), st.text(max_size=20), st.lists(HOSTILE_FLOATS | st.floats(-10, 10), max_size=4),
)


def _toml_value(value: typing.Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"').encode("unicode_escape").decode() + '"'
    return "[" + ", ".join(_toml_value(v) for v in value) + "]"


@st.composite
def config_files(draw: st.DrawFn) -> bytes:
    if draw(st.integers(0, 9)) == 0:  # raw bytes now and then
        return draw(st.binary(max_size=400))
    lines = ['policy.model = "m.onnx"']
    for key, _ in draw(st.lists(st.sampled_from(KEYS), max_size=6, unique=True)):
        if key != "policy.model":
            lines.append(f"{key} = {_toml_value(draw(VALUES))}")
    if draw(st.booleans()):
        depth = draw(st.sampled_from([10, 1000, 100_000]))
        lines.append("deep = " + "[" * depth + "]" * depth)
    return ("\n".join(lines) + "\n").encode()


def _floats(obj: typing.Any, prefix: str = "") -> list[tuple[str, float, typing.Any]]:
    """(key, value, field metadata) of every float in the config."""
    out = []
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            out += _floats(value, f"{prefix}{f.name}.")
        elif isinstance(value, tuple):
            for i, item in enumerate(value):
                if dataclasses.is_dataclass(item):
                    out += _floats(item, f"{prefix}{f.name}[{i}].")
                elif isinstance(item, float):
                    out.append((f"{prefix}{f.name}[{i}]", item, f.metadata))
        elif isinstance(value, float):
            out.append((prefix + f.name, value, f.metadata))
    return out


def check_config_file(content: bytes, directory: Path) -> None:
    path = directory / "fuzz.toml"
    path.write_bytes(content)
    try:
        config = load_config(path)
    except UserError as exc:
        message = str(exc)
        assert message and "\n" not in message and ": " in message, message  # "what: problem", one line
        return
    for key, value, meta in _floats(config):
        assert math.isfinite(value), key
        assert meta.get("min", -math.inf) <= value <= meta.get("max", math.inf), key


def fuzz_config(examples: int, directory: Path) -> typing.Callable[[], None]:
    """The config target: call the result to run ``examples`` files (written into ``directory``)."""

    @settings(max_examples=examples, deadline=None, suppress_health_check=list(HealthCheck))
    @given(content=config_files())
    def run(content: bytes) -> None:
        check_config_file(content, directory)

    return run


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="fuzz the companion's hostile-input paths (hypothesis)")
    parser.add_argument("target", choices=("vlp16", "config"))
    parser.add_argument("--examples", type=int, default=10_000)
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)  # every fresh assembler logs its first drop of each kind
    with tempfile.TemporaryDirectory() as tmp:
        if args.target == "vlp16":
            fuzz_vlp16(args.examples)()
        else:
            fuzz_config(args.examples, Path(tmp))()
    print(f"{args.target}: {args.examples} examples, no failure")
    return 0


if __name__ == "__main__":
    sys.exit(main())
