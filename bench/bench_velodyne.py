"""VLP-16 decode + revolution assembly time per revolution (75 packets, 28,800 slots at 0.2°).

Prints min/p50/p99 in microseconds, for the numpy backend and the velodyne-decoder backend (its C++
core, called through its Python binding), taking turns revolution by revolution so background load
hits both alike:
  burst      all packets of a revolution handed over at once (what a main loop that was busy sees):
             synthetic revolutions with a return in every slot (28,800 points, a closed room), and
             the real recording in ../shared/fixtures beside the repository, when there (about
             15,300 returns per revolution);
  stream     packets fed one by one as they arrive; "completing packet" is the work done on the
             packet that closes the revolution (the latency added after the revolution ends).
The companion's end-to-end budget is p99 ≤ 2 ms from packets in to setpoint out.

    /work/venv/bin/python bench/bench_velodyne.py [--revolutions 300] [--fixtures DIR]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from companion.lidar.velodyne import RevolutionAssembler
from companion.lidar.vlp16_packet import PACKET_SIZE, encode_packets

BACKENDS = ("numpy", "velodyne-decoder")


def synthetic_revolutions(revolutions: int, seed: int = 0) -> list[list[bytes]]:
    """Packets of consecutive revolutions, every return non-zero (28,800 points each).

    Grouped 75 packets at a time so that each group's last packet holds the wrap (at its 13th
    firing), as when a whole revolution arrives at once.
    """
    rng = np.random.default_rng(seed)
    firings = 1800
    start = 360.0 - 0.2 * (74 * 24 + 12) + 0.1
    azimuth = np.mod(start + 0.2 * np.arange((revolutions + 1) * firings), 360.0)
    ranges = rng.uniform(0.5, 30.0, size=(len(azimuth), 16))
    packets = encode_packets(azimuth, ranges)
    return [packets[i : i + 75] for i in range(0, len(packets), 75)]


def recorded_revolutions(path: Path) -> list[list[bytes]]:
    """The recording split after each packet holding a wrap: the first group holds the first wrap."""
    raw = path.read_bytes()
    packets = [raw[i : i + PACKET_SIZE] for i in range(0, len(raw), PACKET_SIZE)]
    assembler = RevolutionAssembler()
    groups: list[list[bytes]] = [[]]
    for packet in packets:
        groups[-1].append(packet)
        before = assembler.counters.revolutions + assembler.counters.partial_revolutions
        assembler.feed(packet)
        if assembler.counters.revolutions + assembler.counters.partial_revolutions > before:
            groups.append([])
    return groups[:-1]  # the tail after the last wrap completes nothing


def percentiles(samples: list[float]) -> str:
    us = np.array(samples) * 1e6
    return f"min {us.min():6.0f}   p50 {np.percentile(us, 50):6.0f}   p99 {np.percentile(us, 99):6.0f} µs"


def bench_burst(groups: list[list[bytes]], passes: int = 1) -> dict[str, list[float]]:
    """Per backend, the time to take in each group of packets at once (one revolution each)."""
    times: dict[str, list[float]] = {backend: [] for backend in BACKENDS}
    for _ in range(passes):
        assemblers = {backend: RevolutionAssembler(backend) for backend in BACKENDS}
        for k, packets in enumerate(groups):
            for backend, assembler in assemblers.items():
                start = time.perf_counter()
                done = assembler.feed_batch(packets)
                elapsed = time.perf_counter() - start
                assert len(done) == (k > 0)  # the first wrap closes a partial revolution: dropped
                if k > 0:
                    times[backend].append(elapsed)
    return times


def bench_stream(backend: str, groups: list[list[bytes]]) -> tuple[list[float], list[float]]:
    """Fed packet by packet: (time on the packet completing a revolution, total time per revolution)."""
    assembler = RevolutionAssembler(backend)
    completing, totals = [], []
    spent = 0.0
    for packet in (p for packets in groups for p in packets):
        start = time.perf_counter()
        done = assembler.feed(packet)
        elapsed = time.perf_counter() - start
        spent += elapsed
        if done:
            completing.append(elapsed)
            totals.append(spent)
            spent = 0.0
    return completing[1:], totals[1:]  # the first one also paid for the partial revolution


def report_burst(title: str, times: dict[str, list[float]]) -> None:
    print(title)
    for backend in BACKENDS:
        print(f"  burst  {backend:17s} {percentiles(times[backend])}")
    ratio = np.median(times["velodyne-decoder"]) / np.median(times["numpy"])
    print(f"  burst  velodyne-decoder / numpy, p50: {ratio:.2f}×")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--revolutions", type=int, default=300)
    default_fixtures = (  # fetched data lives beside the repository, never in it
        os.environ.get("LIDAR_AVOID_FIXTURES") or Path(__file__).resolve().parents[2] / "shared/fixtures"
    )
    parser.add_argument("--fixtures", type=Path, default=default_fixtures)
    args = parser.parse_args()

    synthetic = synthetic_revolutions(args.revolutions)
    bench_burst(synthetic[:5])  # warm up
    report_burst(
        f"VLP-16 decode + assemble, {args.revolutions} synthetic revolutions of 28,800 returns (75 packets)",
        bench_burst(synthetic),
    )
    for backend in BACKENDS:
        completing, total = bench_stream(backend, synthetic)
        print(f"  stream {backend:17s} completing packet: {percentiles(completing)}")
        print(f"  stream {backend:17s} all packets:       {percentiles(total)}")

    recording = args.fixtures / "vlp16-recording.bin"
    if recording.exists():
        groups = recorded_revolutions(recording)
        passes = max(1, args.revolutions // (len(groups) - 1))
        report_burst(
            f"real recording: {len(groups) - 1} revolutions × {passes} passes, about 15,300 returns each",
            bench_burst(groups, passes),
        )
    else:
        print(f"(no recording at {recording}: real-data figures skipped)")
    print("budget: companion end to end p99 ≤ 2000 µs (decode should be well under 1000 µs)")
    print(f"(load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs while measuring)")


if __name__ == "__main__":
    main()
