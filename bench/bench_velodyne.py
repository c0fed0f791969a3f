"""VLP-16 decode + revolution assembly time per 28,800-point revolution (75 packets, 0.2° steps).

Prints p50/p99 in microseconds for:
  burst    all 75 packets of a revolution handed over at once (what a main loop that was busy sees),
           numpy backend vs velodyne-decoder backend (its C++ core, called through its Python binding);
  stream   packets fed one by one as they arrive; the figure is the work done on the packet that
           completes the revolution (the latency the companion adds after the revolution ends).
The companion's end-to-end budget is p99 ≤ 2 ms from packets in to setpoint out.

    /work/venv/bin/python bench/bench_velodyne.py [--revolutions 300]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from companion.lidar.velodyne import RevolutionAssembler, encode_packets


def revolution_packets(revolutions: int, seed: int = 0) -> list[list[bytes]]:
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


def percentiles(samples: list[float]) -> str:
    us = np.array(samples) * 1e6
    return f"p50 {np.percentile(us, 50):7.0f} µs   p99 {np.percentile(us, 99):7.0f} µs"


def bench_burst(backend: str, revolutions: list[list[bytes]]) -> list[float]:
    assembler = RevolutionAssembler(backend)
    assert assembler.feed_batch(revolutions[0]) == []  # first wrap: partial revolution
    times = []
    for packets in revolutions[1:]:
        start = time.perf_counter()
        done = assembler.feed_batch(packets)
        times.append(time.perf_counter() - start)
        assert len(done) == 1 and len(done[0].points) == 28_800
    return times


def bench_stream(backend: str, revolutions: list[list[bytes]]) -> tuple[list[float], list[float]]:
    """Fed packet by packet: (time on the packet completing a revolution, total time per revolution)."""
    assembler = RevolutionAssembler(backend)
    completing, totals = [], []
    spent = 0.0
    for packet in (p for packets in revolutions for p in packets):
        start = time.perf_counter()
        done = assembler.feed(packet)
        elapsed = time.perf_counter() - start
        spent += elapsed
        if done:
            completing.append(elapsed)
            totals.append(spent)
            spent = 0.0
    return completing[1:], totals[1:]  # the first one also paid for the partial revolution


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--revolutions", type=int, default=300)
    args = parser.parse_args()
    revolutions = revolution_packets(args.revolutions)
    print(f"VLP-16 decode + assemble, {args.revolutions} revolutions of 28,800 points (75 packets)")
    burst = {}
    for backend in ("numpy", "velodyne-decoder"):
        bench_burst(backend, revolutions[:5])  # warm up
        burst[backend] = bench_burst(backend, revolutions)
        print(f"  burst  {backend:17s} {percentiles(burst[backend])}")
    ratio = np.median(burst["velodyne-decoder"]) / np.median(burst["numpy"])
    print(f"  burst  velodyne-decoder / numpy, p50: {ratio:.2f}×")
    for backend in ("numpy", "velodyne-decoder"):
        wrap, total = bench_stream(backend, revolutions)
        print(f"  stream {backend:17s} completing packet: {percentiles(wrap)}")
        print(f"  stream {backend:17s} all 75 packets:    {percentiles(total)}")
    print("  budget: companion end to end p99 ≤ 2000 µs (decode should be well under 1000 µs)")


if __name__ == "__main__":
    main()
