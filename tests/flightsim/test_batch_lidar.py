"""The batched lidar: N scans in one compiled call are ``scan_from_points`` of the same clouds, exactly."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.perception.scan import ScanConfig, scan_from_points
from flightsim.envs.batch_lidar import BatchLidar, scans_from_points
from flightsim.envs.env import EnvConfig, LidarAvoidEnv, slice_band
from flightsim.envs.raycast import LidarConfig


def _pack(clouds: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in clouds])]).astype(np.int64)
    return np.concatenate(clouds).astype(np.float32).reshape(-1, 3), offsets


def _awkward_clouds(rng: np.random.Generator) -> list[np.ndarray]:
    """Clouds that probe every test of the scan: bin edges, the slice and min-range bounds, NaN/inf."""
    edges = np.radians(np.arange(-180.0, 181.0, 1.0))  # points exactly on (float32-rounded) bin edges
    r = rng.uniform(0.05, 12.0, edges.size)
    on_edges = np.stack([r * np.cos(edges), r * np.sin(edges), rng.uniform(-0.6, 0.6, edges.size)], axis=1)
    slice_z = np.float32(0.5)
    at_slice = np.array([[1.0, 0.0, slice_z], [0.0, 1.0, -slice_z], [2.0, 2.0, np.nextafter(slice_z, 0)]])
    near_min = np.array([[0.1, 0.0, 0.0], [0.0, 0.0999999, 0.0], [0.06, 0.08, 0.0], [0.0, 0.0, 0.1]])
    broken = np.array([[np.nan, 1.0, 0.0], [1.0, np.inf, 0.0], [-np.inf, 0.0, 0.0], [1.0, 1.0, np.nan]])
    behind = np.array([[-3.0, 0.0, 0.0], [-3.0, -1e-7, 0.0], [-3.0, 1e-7, 0.0]])  # around bin 180
    clouds = [on_edges, at_slice, near_min, broken, behind, np.zeros((0, 3))]
    clouds += [rng.normal(0.0, 4.0, (int(n), 3)) for n in rng.integers(1, 5000, 20)]
    return [c.astype(np.float32) for c in clouds]


def test_batched_scans_equal_scan_from_points_on_the_same_clouds() -> None:
    rng = np.random.default_rng(16)
    clouds = _awkward_clouds(rng)
    config = ScanConfig()
    points, offsets = _pack(clouds)
    batched = scans_from_points(points, offsets, config)
    assert batched.dtype == np.float32 and batched.shape == (len(clouds), 360)
    for i, cloud in enumerate(clouds):
        np.testing.assert_array_equal(batched[i], scan_from_points(cloud, config), err_msg=f"cloud {i}")
    assert (batched < 1.0).sum() > 1000  # the clouds fill bins: the comparison is not of empty scans


@pytest.mark.filterwarnings("ignore:invalid value encountered in matmul")  # the NaN points
@pytest.mark.parametrize(
    "config",
    [ScanConfig(max_range=7.5, min_range=0.3, slice_height=0.2), ScanConfig(mount_rpy_deg=(0.0, 0.0, 30.0))],
)
def test_other_scan_geometries_equal_scan_from_points(config: ScanConfig) -> None:
    clouds = _awkward_clouds(np.random.default_rng(3))
    batched = scans_from_points(*_pack(clouds), config)  # a rotated mount reduces cloud by cloud
    for i, cloud in enumerate(clouds):
        np.testing.assert_array_equal(batched[i], scan_from_points(cloud, config), err_msg=f"cloud {i}")


def test_the_compiled_scan_refuses_a_mount_it_does_not_cover() -> None:
    with pytest.raises(ValueError, match="identity mount"):
        scans_from_points(*_pack([np.ones((3, 3))]), ScanConfig(mount_xyz=(0.1, 0.0, 0.0)), compiled=True)


@pytest.mark.parametrize(
    "lidar",
    [
        LidarConfig(),
        LidarConfig(noise_std=0.02, dropout=0.02),
        LidarConfig(noise_std=0.3, dropout=0.5),
        LidarConfig(azimuth_step_deg=0.2, noise_std=0.02),  # the real sensor's columns
        LidarConfig(azimuth_step_deg=2.0, dropout=0.1),  # columns on bin edges: binned point by point
    ],
)
@pytest.mark.parametrize("bit_generator", [np.random.PCG64, np.random.Philox])  # compiled draws; numpy's
def test_batched_lidar_equals_each_env_cast_and_scan(lidar: LidarConfig, bit_generator) -> None:
    """Cast, noise, dropout, cloud and scan of N poses in N worlds: each one's, from its own generator,
    which is left where the env's own draws leave it."""
    n = 5
    config = EnvConfig(lidar=lidar, difficulty=0.9)
    envs = [LidarAvoidEnv(config) for _ in range(n)]
    for i, env in enumerate(envs):
        env.reset(seed=100 + i)
    batch = BatchLidar(n, lidar, config.scan, slice_band(config.scan))
    assert (batch.column_bins is None) == (lidar.azimuth_step_deg == 2.0)  # which path is tested
    rng = np.random.default_rng(0)
    for _ in range(3):
        poses = []
        for env in envs:  # tilted and turned a little, as in flight
            roll, pitch, yaw = rng.uniform(-0.3, 0.3, 3)
            env._state.roll, env._state.pitch, env._state.yaw = roll, pitch, yaw + math.pi * rng.uniform()
            poses.append(env._sensor_pose())
        seeds = rng.integers(0, 2**31, n)
        generators = [np.random.Generator(bit_generator(s)) for s in seeds]
        origins, rotations = np.array([p[0] for p in poses]), np.array([p[1] for p in poses])
        batched = batch.scans([env.world for env in envs], origins, rotations, generators)
        for i, env in enumerate(envs):
            env._np_random = np.random.Generator(bit_generator(seeds[i]))
            np.testing.assert_array_equal(batched[i], env._fresh_scan(), err_msg=f"env {i}")
            after = generators[i].integers(2**62, size=4)  # both generators carry on from the same place
            np.testing.assert_array_equal(after, env.np_random.integers(2**62, size=4))
        assert (batched < 1.0).sum() > 500  # real clouds were compared, not empty scans
