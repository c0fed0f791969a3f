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
import os
import time

import numpy as np

from companion.lidar.velodyne import RevolutionAssembler, encode_packets

BACKENDS = ("numpy", "velodyne-decoder")


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
    return f"min {us.min():6.0f}   p50 {np.percentile(us, 50):6.0f}   p99 {np.percentile(us, 99):6.0f} µs"


def bench_burst(revolutions: list[list[bytes]]) -> dict[str, list[float]]:
    """Per backend, the time to take in one revolution's 75 packets at once and return its cloud.

    The backends take turns revolution by revolution, so background load hits both alike.
    """
    assemblers = {backend: RevolutionAssembler(backend) for backend in BACKENDS}
    times: dict[str, list[float]] = {backend: [] for backend in BACKENDS}
    for k, packets in enumerate(revolutions):
        for backend, assembler in assemblers.items():
            start = time.perf_counter()
            done = assembler.feed_batch(packets)
            elapsed = time.perf_counter() - start
            if k == 0:
                assert done == []  # first wrap: the partial revolution before it is dropped
                continue
            assert len(done) == 1 and len(done[0].points) == 28_800
            times[backend].append(elapsed)
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
    bench_burst(revolutions[:5])  # warm up
    burst = bench_burst(revolutions)
    for backend in BACKENDS:
        print(f"  burst  {backend:17s} {percentiles(burst[backend])}")
    ratio = np.median(burst["velodyne-decoder"]) / np.median(burst["numpy"])
    print(f"  burst  velodyne-decoder / numpy, p50: {ratio:.2f}×")
    for backend in BACKENDS:
        wrap, total = bench_stream(backend, revolutions)
        print(f"  stream {backend:17s} completing packet: {percentiles(wrap)}")
        print(f"  stream {backend:17s} all 75 packets:    {percentiles(total)}")
    print("  budget: companion end to end p99 ≤ 2000 µs (decode should be well under 1000 µs)")
    load = os.getloadavg()[0]
    print(f"  (load average {load:.1f} on {os.cpu_count()} CPUs while measuring)")


if __name__ == "__main__":
    main()
