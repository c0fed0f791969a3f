"""Hostile lidar traffic from a separate process: the room packets at the sensor's pace, and floods.

Run as ``python -m tests.companion.lidar_flood`` by the flood test and bench/bench_flood.py, so that
sending 10,000 datagrams a second shares no interpreter (and no GIL) with the measurement:

- ``--play SPEED:SECONDS,...``: the room packets (tests/companion/vlp16_recording.py), looped, from
  the sensor's address, at SPEED times the sensor's 754 packets/s for SECONDS, phase after phase (2.5 replays
  25 whole turns a second, more than a VLP-16 can make);
- ``--flood KIND --rate N --seconds S``: N hostile datagrams a second of one of FLOOD_KINDS.

Prints one JSON line when done: datagrams sent and the monotonic start and end (CLOCK_MONOTONIC is
shared by every process on Linux).
"""

from __future__ import annotations

import argparse
import json
import socket
import sys
import time

import numpy as np

from companion.lidar.vlp16_packet import PACKET_DTYPE, PACKETS_PER_SECOND, PRODUCT_ID_VLP16, RETURN_STRONGEST
from tests.companion.vlp16_recording import looped_recording

#: garbage: datagrams of random length and bytes, and 1206-byte packets with one header field wrong;
#: foreign: well-formed packets with random azimuths (a wrap in almost every one) and returns, from
#: another address; forged: the same from the sensor's own address (a spoofed source);
#: replay: the room's packets again (tests/companion/vlp16_recording.py), from the sensor's address,
#: at the flood's rate.
FLOOD_KINDS = ("garbage", "foreign", "forged", "replay")
SENSOR_HOST = "127.0.0.1"
FOREIGN_HOST = "127.0.0.2"


def forged_packets(n: int, rng: np.random.Generator) -> list[bytes]:
    """Well-formed VLP-16 data packets with random azimuths and returns: every check passes, decoding
    costs in full, and the azimuth wraps in almost every packet."""
    packets = np.zeros(n, dtype=PACKET_DTYPE)
    packets["blocks"]["flag"] = 0xEEFF
    packets["blocks"]["azimuth"] = rng.integers(0, 36000, size=(n, 12))
    packets["blocks"]["returns"]["distance"] = rng.integers(0, 65536, size=(n, 12, 32))
    packets["timestamp"] = rng.integers(0, 3_600_000_000, size=n)
    packets["return_mode"] = RETURN_STRONGEST
    packets["product_id"] = PRODUCT_ID_VLP16
    raw = packets.tobytes()
    return [raw[i * 1206 : (i + 1) * 1206] for i in range(n)]


def garbage_packets(n: int, rng: np.random.Generator) -> list[bytes]:
    out = []
    good = forged_packets(1, rng)[0]
    for i in range(n):
        if i % 2:
            out.append(rng.integers(0, 256, int(rng.integers(0, 1500)), dtype=np.uint8).tobytes())
        else:
            offset = int(rng.choice([0, 700, 1204, 1205]))  # block flag, another flag, mode, product id
            out.append(good[:offset] + bytes([int(rng.integers(0, 256)) ^ 0x5A]) + good[offset + 1 :])
    return out


def _pace(sock: socket.socket, target: tuple[str, int], packets: list[bytes], rate: float, seconds: float,
          first: int = 0) -> int:
    """Send ``packets`` in a loop from index ``first`` at ``rate``/s for ``seconds``; return the count."""
    start = time.monotonic()
    sent = 0
    n = len(packets)
    while (elapsed := time.monotonic() - start) < seconds:
        due = int(elapsed * rate) - sent
        for _ in range(due):  # a full receive queue drops the datagram, as a wire would
            sock.sendto(packets[(first + sent) % n], target)
            sent += 1
        time.sleep(0.0005)
    return sent


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--play", default="", help="SPEED:SECONDS,... of the room packets")
    parser.add_argument("--flood", choices=FLOOD_KINDS)
    parser.add_argument("--rate", type=float, default=10_000.0)
    parser.add_argument("--seconds", type=float, default=3.0)
    args = parser.parse_args(argv)
    target = (SENSOR_HOST, args.port)
    rng = np.random.default_rng(14)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
    sock.bind((FOREIGN_HOST if args.flood == "foreign" else SENSOR_HOST, 0))
    report: dict[str, float] = {"start": time.monotonic(), "sent": 0}
    if args.play:
        recording = looped_recording(10)
        for phase in args.play.split(","):
            speed, seconds = (float(x) for x in phase.split(":"))
            if speed > 0:
                report["sent"] += _pace(sock, target, recording, PACKETS_PER_SECOND * speed, seconds,
                                        first=int(report["sent"]))
            else:
                time.sleep(seconds)
    elif args.flood:
        if args.flood == "garbage":
            pool = garbage_packets(512, rng)
        elif args.flood == "replay":
            pool = looped_recording(1)
        else:
            pool = forged_packets(512, rng)
        report["sent"] = _pace(sock, target, pool, args.rate, args.seconds)
    report["end"] = time.monotonic()
    sock.close()
    print(json.dumps(report), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
