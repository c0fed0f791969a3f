"""Figure: scan_from_points on one VLP-16 revolution (28,800 points).

Prints median and p99 wall time of the vectorised scan and of a straightforward per-point Python
loop on the same cloud (the tutorial's approach), and their ratio. Target: <= 0.3 ms. Also the
CPU time per call (less sensitive to other load on a shared machine) for the full revolution and
for the ~2,000-point cloud the training env hands it each step (the revolution's points within
the height slice, 1° columns).

    python bench/bench_scan.py
"""

from __future__ import annotations

import math
import os
import time

import numpy as np

from companion.scan import N_BINS, ScanConfig, scan_from_points


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
    print(f"load average: {' '.join(f'{x:.2f}' for x in os.getloadavg())}, cpus: {os.cpu_count()}")
    fast = timed(lambda: scan_from_points(pts, cfg), 2000)
    slow = timed(lambda: python_loop(pts, cfg), 20)
    p50, p99 = np.median(fast), np.percentile(fast, 99)
    print(f"scan_from_points, {len(pts)} points: p50 {p50:.3f} ms, p99 {p99:.3f} ms (target <= 0.3 ms)")
    print(f"per-point Python loop:            p50 {np.median(slow):.3f} ms")
    print(f"speed-up: {np.median(slow) / np.median(fast):.0f}x")
    env_like = pts[::5][np.abs(pts[::5, 2]) < cfg.slice_height + 1e-3]  # 1° columns, slice pre-filtered
    print("CPU time per call (best of 9 batches):")
    for label, cloud, reps in (("one revolution", pts, 200), ("a training env step", env_like, 2000)):
        ms = cpu_per_call(lambda cloud=cloud: scan_from_points(cloud, cfg), reps)
        print(f"  {len(cloud):6d} points ({label}): {ms:.3f} ms")


if __name__ == "__main__":
    main()
