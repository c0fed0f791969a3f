"""The scan convention of ARCHITECTURE.md, as properties that any point cloud must satisfy."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from companion.perception.scan import N_BINS, ScanConfig, scan_from_points

CFG = ScanConfig()
coords = st.floats(-15.0, 15.0, allow_nan=False, width=32)
clouds = arrays(np.float32, st.tuples(st.integers(0, 200), st.just(3)), elements=coords)


def point_at(angle_deg: float, dist: float, z: float = 0.0) -> np.ndarray:
    a = math.radians(angle_deg)
    return np.array([[dist * math.cos(a), dist * math.sin(a), z]], dtype=np.float32)


@settings(max_examples=200, deadline=None)
@given(clouds)
def test_values_in_unit_interval(points: np.ndarray) -> None:
    scan = scan_from_points(points, CFG)
    assert scan.shape == (N_BINS,)
    assert scan.dtype == np.float32
    assert np.all((scan >= 0.0) & (scan <= 1.0))


@settings(max_examples=100, deadline=None)
@given(clouds, st.randoms(use_true_random=False))
def test_invariant_under_point_permutation(points: np.ndarray, rnd) -> None:
    order = list(range(len(points)))
    rnd.shuffle(order)
    np.testing.assert_array_equal(scan_from_points(points, CFG), scan_from_points(points[order], CFG))


@settings(max_examples=200, deadline=None)
@given(clouds, arrays(np.float32, (1, 3), elements=coords))
def test_adding_a_point_never_raises_a_bin(points: np.ndarray, extra: np.ndarray) -> None:
    before = scan_from_points(points, CFG)
    after = scan_from_points(np.vstack([points, extra]), CFG)
    assert np.all(after <= before)


@pytest.mark.parametrize(
    ("angle", "expected_bin"), [(90.0, 90), (-90.0, 270), (0.5, 0), (-0.5, 359), (180.5, 180)]
)
def test_bins_run_counter_clockwise_from_forward(angle: float, expected_bin: int) -> None:
    scan = scan_from_points(point_at(angle, 5.0), CFG)
    assert scan[expected_bin] == pytest.approx(0.5)
    assert np.count_nonzero(scan < 1.0) == 1


def test_left_and_right_land_in_bins_90_and_270() -> None:
    scan = scan_from_points(np.vstack([point_at(90.0, 2.0), point_at(-90.0, 3.0)]), CFG)
    assert scan[90] == pytest.approx(0.2)
    assert scan[270] == pytest.approx(0.3)


@settings(max_examples=100, deadline=None)
@given(
    st.floats(0.0, 359.9),
    st.floats(0.2, 9.0),
    st.sampled_from([0.5, 0.6, 2.0, -0.5, -3.0]),
)
def test_points_outside_the_height_slice_are_ignored(angle: float, dist: float, z: float) -> None:
    scan = scan_from_points(point_at(angle, dist, z), CFG)
    assert np.all(scan == 1.0)


@settings(max_examples=100, deadline=None)
@given(st.floats(0.0, 359.9), st.floats(0.0, 0.099))
def test_points_under_min_range_are_ignored(angle: float, dist: float) -> None:
    scan = scan_from_points(point_at(angle, dist), CFG)
    assert np.all(scan == 1.0)


def test_empty_cloud_and_non_finite_points_give_an_empty_scan() -> None:
    assert np.all(scan_from_points(np.zeros((0, 3), np.float32), CFG) == 1.0)
    bad = np.array([[np.nan, 1.0, 0.0], [np.inf, 0.0, 0.0]], dtype=np.float32)
    assert np.all(scan_from_points(bad, CFG) == 1.0)


def test_min_per_bin_and_clip_beyond_max_range() -> None:
    pts = np.vstack([point_at(10.2, 4.0), point_at(10.7, 3.0), point_at(45.0, 25.0)])
    scan = scan_from_points(pts, CFG)
    assert scan[10] == pytest.approx(0.3)
    assert scan[45] == 1.0


def test_mount_transform_moves_points_into_the_body_frame() -> None:
    # Sensor yawed 90° left on the body: its "forward" is the body's left.
    cfg = ScanConfig(mount_rpy_deg=(0.0, 0.0, 90.0), mount_xyz=(0.0, 0.0, 0.0))
    scan = scan_from_points(point_at(0.0, 5.0), cfg)
    assert scan[90] == pytest.approx(0.5)
    # Sensor mounted 0.6 m above the body origin: a point level with the sensor is out of the slice.
    high = ScanConfig(mount_xyz=(0.0, 0.0, 0.6))
    assert np.all(scan_from_points(point_at(0.0, 5.0), high) == 1.0)
    assert scan_from_points(point_at(0.0, 5.0, -0.5), high)[0] == pytest.approx(0.5)


def test_config_rejects_min_range_above_max_range() -> None:
    with pytest.raises(ValueError, match="min_range"):
        ScanConfig(min_range=20.0, max_range=10.0)


def _reference_scan(points: np.ndarray, cfg: ScanConfig) -> np.ndarray:
    """The scan written the plain way (float32, mask, ``np.minimum.at``, modulo, clip): the oracle
    the optimised ``scan_from_points`` must match bit for bit."""
    scan = np.ones(N_BINS, dtype=np.float32)
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    body = pts
    with np.errstate(invalid="ignore", over="ignore"):
        if cfg.mount_rpy_deg != (0.0, 0.0, 0.0) or cfg.mount_xyz != (0.0, 0.0, 0.0):
            body = pts @ cfg.rotation().T.astype(np.float32) + np.asarray(cfg.mount_xyz, np.float32)
        r2 = pts[:, 0] * pts[:, 0] + pts[:, 1] * pts[:, 1] + pts[:, 2] * pts[:, 2]
    keep = (np.abs(body[:, 2]) < np.float32(cfg.slice_height)) & (r2 >= np.float32(cfg.min_range**2))
    x, y = body[keep, 0], body[keep, 1]
    rng = np.sqrt(x * x + y * y) / np.float32(cfg.max_range)
    bins = np.floor(np.arctan2(y, x) * np.float32(N_BINS / (2.0 * math.pi))).astype(np.int64) % N_BINS
    np.minimum.at(scan, bins, rng.astype(np.float32))
    return np.clip(scan, 0.0, 1.0)


ODD_CONFIGS = [
    CFG,
    ScanConfig(min_range=0.5, slice_height=0.3, max_range=5.0),
    ScanConfig(mount_rpy_deg=(1.0, -2.0, 30.0), mount_xyz=(0.1, 0.0, -0.05)),
]
wild = st.one_of(coords, st.sampled_from([0.0, -0.0, 0.1, -0.1, 0.5, -0.5, np.nan, np.inf, -np.inf]))


@settings(max_examples=300, deadline=None)
@given(
    arrays(np.float32, st.tuples(st.integers(0, 300), st.just(3)), elements=wild),
    st.sampled_from(ODD_CONFIGS),
)
def test_matches_the_plain_reference_bit_for_bit(points: np.ndarray, cfg: ScanConfig) -> None:
    np.testing.assert_array_equal(scan_from_points(points, cfg), _reference_scan(points, cfg))


def test_matches_the_reference_on_a_dense_ordered_revolution() -> None:
    # One 0.2° revolution in a room (the drone's case), forwards, backwards and shuffled.
    az, el = np.meshgrid(
        np.radians(np.arange(0.0, 360.0, 0.2) + 0.1), np.radians(np.arange(-15, 16, 2)), indexing="ij"
    )
    d = np.stack([np.cos(el) * np.cos(az), -np.cos(el) * np.sin(az), np.sin(el)], axis=-1).reshape(-1, 3)
    with np.errstate(divide="ignore"):
        t = np.min(np.abs(np.array([6.0, 4.0, 1.5]) / d), axis=1)
    cloud = (d * t[:, None]).astype(np.float32)
    for pts in (cloud, cloud[::-1], np.random.default_rng(0).permutation(cloud)):
        for cfg in ODD_CONFIGS:
            np.testing.assert_array_equal(scan_from_points(pts, cfg), _reference_scan(pts, cfg))


_EDGE_SCAN = """
import sys
import numpy as np
from companion.perception.scan import ScanConfig, scan_from_points
rng = np.random.default_rng(5)
# points a few float32 ulps either side of every bin edge, at ranges that tell the bins apart
edges = np.radians(np.repeat(np.arange(360.0), 40)) + rng.normal(0.0, 1e-6, 14400)
dist = rng.uniform(0.5, 9.0, edges.size)
pts = np.stack([dist * np.cos(edges), dist * np.sin(edges), np.zeros(edges.size)], 1).astype(np.float32)
sys.stdout.write(scan_from_points(pts, ScanConfig()).tobytes().hex())
"""


def test_the_scan_is_the_same_whichever_simd_loops_numpy_picks() -> None:
    """numpy picks its float32 ``arctan2`` loop by CPU, and its AVX-512 loop rounds differently from
    the scalar one: points at a bin edge moved bins, so the companion's scan, the single env's and
    the batched env's compiled scan differed on an AVX-512 machine. The same cloud, with numpy's
    AVX-512 loops on and off, must give the same scan (on a CPU without AVX-512 both runs take the
    same loops, and this checks nothing)."""
    import os
    import subprocess
    import sys

    def run(disable: str) -> str:
        env = {**os.environ, "NPY_DISABLE_CPU_FEATURES": disable}
        return subprocess.run([sys.executable, "-c", _EDGE_SCAN], env=env, capture_output=True, text=True,
                              check=True, timeout=60).stdout  # fmt: skip

    assert run("") == run("X86_V4 AVX512_ICL")
