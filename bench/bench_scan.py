"""Figure: scan_from_points on one VLP-16 revolution (28,800 points), against two references.

Prints median and p99 wall time of the vectorised scan and, measured in the same run on the same
cloud, of
- a straightforward per-point Python loop, and
- the seed tutorial's ``PointCloudProcessor`` (docs/seed-tutorial.md, section 4): numpy masks and
  polar conversion, then a per-point Python loop for the per-bin minimum; timed on the N×3 array
  (its binning) and from a packed PointCloud2-style buffer (x, y, z, intensity float32, parsed
  point by point with ``struct`` as the tutorial does),
with the ratios first: the machine's speed and load move the absolute times several-fold, the
ratios much less. Target: <= 0.3 ms. Also the CPU time per call for the full revolution and for
the ~2,000-point cloud the training env hands it each step. The load average is printed.

    python bench/bench_scan.py
"""

from __future__ import annotations

import math
import os
import struct
import time

import numpy as np

from companion.perception.scan import N_BINS, ScanConfig, scan_from_points


def revolution(rng: np.random.Generator) -> np.ndarray:
    """A 0.2°-step, 16-laser revolution inside a 12 m x 8 m room with a floor 1.5 m below."""
    elev = np.radians(np.array([-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15], float))
    az = np.radians(
        np.arange(0.0, 360.0, 0.2) + 0.1
    )  # off the bin edges: float32 vs float64 would differ there
    a, w = np.meshgrid(az, elev, indexing="ij")
    d = np.stack([np.cos(w) * np.cos(a), -np.cos(w) * np.sin(a), np.sin(w)], axis=-1).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        t = np.min(
            np.stack(
                [
                    np.where(d[:, 0] != 0, 6.0 / np.abs(d[:, 0]), np.inf),
                    np.where(d[:, 1] != 0, 4.0 / np.abs(d[:, 1]), np.inf),
                    np.where(d[:, 2] < 0, 1.5 / -d[:, 2], np.inf),
                ]
            ),
            axis=0,
        )
    t = t + rng.normal(0.0, 0.01, t.shape)
    return (d * t[:, None]).astype(np.float32)


def python_loop(points: np.ndarray, cfg: ScanConfig) -> np.ndarray:
    scan = [1.0] * N_BINS
    for x, y, z in points.tolist():
        if x * x + y * y + z * z < cfg.min_range**2 or abs(z) >= cfg.slice_height:
            continue
        b = math.floor(math.degrees(math.atan2(y, x))) % N_BINS
        scan[b] = min(scan[b], math.hypot(x, y) / cfg.max_range)
    return np.clip(np.array(scan, np.float32), 0.0, 1.0)


def tutorial_processor(points: np.ndarray, cfg: ScanConfig) -> np.ndarray:
    """The seed tutorial's ``PointCloudProcessor.process_point_cloud`` after parsing (its section 4).

    Same steps, same order: height mask, polar conversion, ``int(angle * bins / 360)`` clipped,
    per-point Python loop keeping each bin's minimum, clip. (No minimum range, no mount
    transform: it does less than ``scan_from_points``.)
    """
    ranges = np.ones(N_BINS, dtype=np.float32)
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    keep = np.abs(z) < cfg.slice_height
    x, y = x[keep], y[keep]
    distances = np.sqrt(x**2 + y**2)
    angles_deg = np.degrees(np.arctan2(y, x)) % 360
    bins = np.clip((angles_deg * N_BINS / 360.0).astype(np.int32), 0, N_BINS - 1)
    for i in range(len(distances)):
        b = bins[i]
        if distances[i] < ranges[b] * cfg.max_range:
            ranges[b] = distances[i] / cfg.max_range
    return np.clip(ranges, 0.0, 1.0)


def pointcloud2_bytes(points: np.ndarray) -> bytes:
    """The cloud as a PointCloud2 ``data`` buffer: x, y, z, intensity float32 (point_step 16)."""
    packed = np.zeros((len(points), 4), np.float32)
    packed[:, :3] = points
    return packed.tobytes()


def tutorial_from_message(data: bytes, cfg: ScanConfig) -> np.ndarray:
    """The tutorial's whole ``process_point_cloud``: ``_parse_pointcloud2`` (struct, point by point) first."""
    points = []
    for i in range(len(data) // 16):
        points.append(struct.unpack("fff", data[i * 16 : i * 16 + 12]))
    return tutorial_processor(np.array(points, dtype=np.float32), cfg)


def timed(fn, reps: int) -> np.ndarray:
    out = np.empty(reps)
    for i in range(reps):
        t0 = time.perf_counter()
        fn()
        out[i] = time.perf_counter() - t0
    return out * 1e3


def cpu_per_call(fn, reps: int) -> float:
    """Best of 9 batches of CPU time per call, ms."""
    best = math.inf
    for _ in range(9):
        t0 = time.process_time()
        for _ in range(reps):
            fn()
        best = min(best, (time.process_time() - t0) / reps)
    return best * 1e3


def main() -> None:
    cfg = ScanConfig()
    pts = revolution(np.random.default_rng(0))
    assert pts.shape == (28_800, 3)
    np.testing.assert_allclose(scan_from_points(pts, cfg), python_loop(pts, cfg), atol=1e-6)
    # the tutorial bins with int(): bins agree except where a point sits exactly on a bin edge
    assert np.mean(np.isclose(tutorial_processor(pts, cfg), python_loop(pts, cfg), atol=1e-6)) > 0.99
    message = pointcloud2_bytes(pts)
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}, cpus: {os.cpu_count()}")
    fast = timed(lambda: scan_from_points(pts, cfg), 2000)
    references = {
        "per-point Python loop": timed(lambda: python_loop(pts, cfg), 20),
        "seed tutorial's processor, binning": timed(lambda: tutorial_processor(pts, cfg), 20),
        "seed tutorial's processor, parse + binning": timed(lambda: tutorial_from_message(message, cfg), 10),
    }
    p50, p99 = np.median(fast), np.percentile(fast, 99)
    print(f"scan_from_points, {len(pts)} points: p50 {p50:.3f} ms, p99 {p99:.3f} ms (target <= 0.3 ms)")
    print("same cloud, same run:                        speed-up    reference p50")
    for name, times in references.items():
        print(f"  vs {name:42s} {np.median(times) / p50:6.0f}x   {np.median(times):9.2f} ms")
    env_like = pts[::5][np.abs(pts[::5, 2]) < cfg.slice_height + 1e-3]  # 1° columns, slice pre-filtered
    print("CPU time per call (best of 9 batches):")
    for label, cloud, reps in (("one revolution", pts, 200), ("a training env step", env_like, 2000)):
        ms = cpu_per_call(lambda cloud=cloud: scan_from_points(cloud, cfg), reps)
        print(f"  {len(cloud):6d} points ({label}): {ms:.3f} ms")


if __name__ == "__main__":
    main()
