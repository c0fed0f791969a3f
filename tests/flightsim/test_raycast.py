"""VLP-16 ray caster: analytic ranges, conventions, limits, noise, and a brute-force cross-check."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.common.errors import UserError
from companion.common.tomlconfig import from_dict
from companion.lidar.vlp16_packet import VLP16_ELEVATIONS_DEG
from companion.perception.scan import ScanConfig, scan_from_points
from flightsim.envs.raycast import LidarConfig, RangeGrid, VLP16Raycaster, grid_to_points
from flightsim.worlds.world import Box, Cylinder, World, generate_world

EL = np.radians(VLP16_ELEVATIONS_DEG)
FLAT = [1, 14]  # laser ids at +1 and -1 degrees


def _room(obstacles=(), size=(12.0, 8.0), height=3.0) -> World:
    return World("t", size, height, tuple(obstacles), (0.0, 0.0, 1.5), 0.0)


def _rz(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _ry(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rx(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _cast(world, position=(0.0, 0.0, 1.5), rotation=None, **cfg) -> RangeGrid:
    caster = VLP16Raycaster(LidarConfig(**cfg))
    return caster.cast(world, np.asarray(position, float), np.eye(3) if rotation is None else rotation)


# -- analytic ranges -------------------------------------------------------------------------
# Columns sit at (j + 0.5) * step degrees clockwise; with step 1, column j points -(j + 0.5) deg
# counter-clockwise from the sensor's nose. Yawing the sensor by +0.5 deg (HALF) makes column j
# point exactly -j deg.

HALF = _rz(0.5)


def _wall_distance(x0: float, y0: float, hx: float, hy: float, ccw_deg: float) -> float:
    """Horizontal distance from (x0, y0) to the room walls along a world heading."""
    c, s = math.cos(math.radians(ccw_deg)), math.sin(math.radians(ccw_deg))
    tx = ((hx if c > 0 else -hx) - x0) / c if abs(c) > 1e-12 else math.inf
    ty = ((hy if s > 0 else -hy) - y0) / s if abs(s) > 1e-12 else math.inf
    return min(tx, ty)


def test_columns_are_half_a_step_off_whole_degrees() -> None:
    grid = _cast(_room(), azimuth_step_deg=0.2)
    assert grid.azimuth_deg.shape == (1800,)
    assert grid.azimuth_deg[0] == pytest.approx(0.1) and grid.azimuth_deg[-1] == pytest.approx(359.9)


def test_range_to_walls_by_azimuth() -> None:
    grid = _cast(_room(), position=(1.0, 0.5, 1.5))
    assert grid.ranges.shape == (360, 16) and grid.ranges.dtype == np.float32
    for column in (0, 89, 90, 179, 270, 300):
        horizontal = _wall_distance(1.0, 0.5, 6.0, 4.0, -grid.azimuth_deg[column])  # azimuth is clockwise
        for laser in FLAT:
            assert grid.ranges[column, laser] == pytest.approx(horizontal / math.cos(EL[laser]), abs=1e-3)
    # the convention itself: clockwise 90 is the right-hand wall (y = -4), 270 the left (y = +4)
    assert grid.ranges[90, 1] == pytest.approx(4.5 / math.cos(math.radians(0.5)) / math.cos(EL[1]), abs=1e-3)
    assert grid.ranges[270, 1] == pytest.approx(3.5 / math.cos(math.radians(0.5)) / math.cos(EL[1]), abs=1e-3)


def test_range_to_floor() -> None:
    grid = _cast(_room(size=(40.0, 40.0)), position=(0.0, 0.0, 1.5), max_range=30.0)
    for laser in (0, 2, 4, 6):  # -15, -13, -11, -9 degrees
        assert grid.ranges[17, laser] == pytest.approx(1.5 / math.sin(-EL[laser]), abs=1e-3)


def test_range_to_rotated_box_face() -> None:
    # box centred 3 m away along 30 deg and yawed 30 deg: its -x face is 2.5 m along that line
    c30, s30 = math.cos(math.radians(30)), math.sin(math.radians(30))
    box = Box((3.0 * c30, 3.0 * s30, 1.5), (1.0, 2.0, 3.0), 30.0)
    # the sensor yawed 30.5 deg: column 0 points along 30 deg, column 355 (5 deg left) obliquely
    grid = _cast(_room([box]), rotation=_rz(30.5))
    for laser in FLAT:
        assert grid.ranges[0, laser] == pytest.approx(2.5 / math.cos(EL[laser]), abs=1e-3)
        horizontal = 2.5 / math.cos(math.radians(5.0))
        assert grid.ranges[355, laser] == pytest.approx(horizontal / math.cos(EL[laser]), abs=1e-3)
    # unrotated, 30 deg counter-clockwise is clockwise azimuth 330: column 329 (329.5 deg) is just
    # right of the box's centre line, at 0.5 deg incidence
    grid = _cast(_room([box]))
    horizontal = 2.5 / math.cos(math.radians(0.5))
    assert grid.ranges[329, 1] == pytest.approx(horizontal / math.cos(EL[1]), abs=1e-3)


def test_range_to_cylinder() -> None:
    cyl = Cylinder((4.0, 0.0), 0.5, 3.0)
    grid = _cast(_room([cyl]), rotation=HALF)
    for laser in FLAT:
        assert grid.ranges[0, laser] == pytest.approx(3.5 / math.cos(EL[laser]), abs=1e-3)
        a = math.radians(5.0)  # column 5: 5 deg right, grazing the cylinder's right-hand side
        horizontal = 4.0 * math.cos(a) - math.sqrt(0.25 - (4.0 * math.sin(a)) ** 2)
        assert grid.ranges[5, laser] == pytest.approx(horizontal / math.cos(EL[laser]), abs=1e-3)
    # 8 deg right misses it and hits the end wall x = +6
    assert grid.ranges[8, 1] == pytest.approx(6.0 / math.cos(math.radians(8)) / math.cos(EL[1]), abs=1e-3)


def test_rays_pass_over_short_obstacles_and_walls() -> None:
    low = Box((3.0, 0.0, 0.6), (1.0, 1.0, 1.2))  # x from 2.5 to 3.5, top at z = 1.2
    grid = _cast(_room([low], height=1.7), max_range=20.0, rotation=HALF)
    # +15 deg at 1.5 m altitude rises above the 1.7 m wall top long before x = 6: no return
    assert grid.ranges[0, 15] == 0.0
    # -15 deg hits the box's front face (x = 2.5 at z = 0.83)
    assert grid.ranges[0, 0] == pytest.approx(2.5 / math.cos(math.radians(15)), abs=1e-3)
    # -5 deg clears the front edge (z = 1.28 at x = 2.5) and lands on the top face 0.3 m down
    assert grid.ranges[0, 10] == pytest.approx(0.3 / math.sin(math.radians(5)), abs=1e-3)
    # +1 deg passes over the box and hits the wall at x = 6, z = 1.5 + 6 tan 1deg < 1.7
    assert grid.ranges[0, 1] == pytest.approx(6.0 / math.cos(EL[1]), abs=1e-3)


def test_tilted_sensor_sees_floor_closer() -> None:
    """Pitched 10 deg nose down (FLU: positive pitch about y tips the nose down)."""
    grid = _cast(_room(size=(60.0, 60.0)), rotation=HALF @ _ry(10.0), max_range=30.0)
    theta = math.radians(10.0)
    for laser in (0, 14):  # -15 and -1 deg become about -25 and -11 deg in front
        x = math.cos(EL[laser]) * math.cos(math.radians(0.5))
        down = math.sin(theta) * x - math.cos(theta) * math.sin(EL[laser])  # -(world z of the ray)
        assert grid.ranges[0, laser] == pytest.approx(1.5 / down, abs=1e-3)


# -- limits ----------------------------------------------------------------------------------


def test_nothing_beyond_max_range() -> None:
    grid = _cast(_room(size=(40.0, 40.0)), max_range=10.0)
    assert grid.ranges.max() <= 10.0
    # walls are 20 m away, only the steep downward lasers reach the floor within 10 m
    hits = grid.ranges > 0.0
    assert hits[:, [0, 2, 4, 6]].all()  # -15 … -9 deg: floor at 5.8 … 9.6 m
    assert not hits[:, [8, 10, 12, 14]].any()  # -7 … -1 deg: floor at 12.3 … 86 m
    assert not hits[:, 1::2].any()  # upward lasers see nothing


def test_nothing_under_min_range() -> None:
    near = Cylinder((0.3, 0.0), 0.25, 3.0)  # its face is 0.05 m in front of the sensor
    grid = _cast(_room([near]), min_range=0.1, rotation=HALF)
    assert (grid.ranges[0] == 0.0).all()
    assert grid.ranges[180, 1] == pytest.approx(6.0 / math.cos(EL[1]), abs=1e-3)


# -- the brute force cross-check (the kernel culls obstacles per column; this tests them all) ----


def _reference(world: World, origin: np.ndarray, rot: np.ndarray, azimuth_deg: np.ndarray, cfg) -> np.ndarray:
    a = np.radians(azimuth_deg)[:, None]
    d = np.stack(np.broadcast_arrays(np.cos(EL) * np.cos(a), -np.cos(EL) * np.sin(a), np.sin(EL)), -1)
    d = d.reshape(-1, 3) @ rot.T
    o = origin
    best = np.full(d.shape[0], np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        best = np.where(d[:, 2] < 0, -o[2] / d[:, 2], best)
        for axis, half in ((0, world.room_size[0] / 2), (1, world.room_size[1] / 2)):
            t = (np.sign(d[:, axis]) * half - o[axis]) / d[:, axis]
            z = o[2] + t * d[:, 2]
            best = np.where((z >= 0) & (z <= world.room_height) & (t > 0), np.minimum(best, t), best)
        for ob in world.obstacles:
            if isinstance(ob, Box):
                yaw = math.radians(ob.yaw_deg)
                r_inv = _rz(-math.degrees(yaw))
                lo = r_inv @ (o - np.asarray(ob.center))
                ld = d @ r_inv.T
                h = np.asarray(ob.size) / 2
                t1, t2 = (-h - lo) / ld, (h - lo) / ld
                near = np.nanmax(np.minimum(t1, t2), axis=1)
                far = np.nanmin(np.maximum(t1, t2), axis=1)
                t = np.where((near > 0) & (near <= far), near, np.inf)
            else:
                px, py = o[0] - ob.center[0], o[1] - ob.center[1]
                aa = d[:, 0] ** 2 + d[:, 1] ** 2
                bb = px * d[:, 0] + py * d[:, 1]
                disc = bb**2 - aa * (px**2 + py**2 - ob.radius**2)
                ts = (-bb - np.sqrt(np.maximum(disc, 0))) / aa
                zs = o[2] + ts * d[:, 2]
                t = np.where((disc >= 0) & (ts > 0) & (zs >= 0) & (zs <= ob.height), ts, np.inf)
                tc = (ob.height - o[2]) / d[:, 2]
                qx, qy = px + tc * d[:, 0], py + tc * d[:, 1]
                cap = (d[:, 2] < 0) & (o[2] > ob.height) & (qx**2 + qy**2 <= ob.radius**2)
                t = np.where(cap, np.minimum(t, tc), t)
            best = np.minimum(best, t)
    best = np.where((best >= cfg.min_range) & (best <= cfg.max_range), best, 0.0)
    return best.reshape(len(azimuth_deg), 16)


@pytest.mark.parametrize("seed", range(6))
def test_matches_brute_force_on_random_poses(seed: int) -> None:
    rng = np.random.default_rng(seed)
    world = generate_world(seed, 1.0)
    caster = VLP16Raycaster(LidarConfig(azimuth_step_deg=0.5))
    checked = 0
    while checked < 4:
        hx, hy = world.room_size[0] / 2, world.room_size[1] / 2
        origin = rng.uniform([-hx + 0.3, -hy + 0.3, 0.3], [hx - 0.3, hy - 0.3, 3.5])
        if world.clearance(origin) < 0.2:
            continue
        tilt = 35.0 if checked == 3 else 12.0
        rot = _rz(rng.uniform(0, 360)) @ _ry(rng.uniform(-tilt, tilt)) @ _rx(rng.uniform(-tilt, tilt))
        grid = caster.cast(world, origin, rot)
        expected = _reference(world, origin, rot, grid.azimuth_deg, caster.config)
        np.testing.assert_allclose(grid.ranges, expected, atol=1e-4)
        checked += 1


@pytest.mark.parametrize(
    "lidar", [LidarConfig(), LidarConfig(azimuth_step_deg=0.2), LidarConfig(noise_std=0.02, dropout=0.1)]
)
def test_cast_points_is_grid_to_points_of_cast(lidar: LidarConfig) -> None:
    # The env's one-call path must give the very same cloud, band or not, step after step.
    world = generate_world(3, 1.0)
    caster = VLP16Raycaster(lidar)
    band = (np.array([0.0, 0.05, 0.998]), 0.01, 0.4)
    rng = np.random.default_rng(0)
    for k in range(4):
        origin = np.array([*world.start_position[:2], 0.8 + 0.3 * k])
        rot = _rz(rng.uniform(0, 360)) @ _ry(rng.uniform(-15, 15))
        for keep_band in (None, band):
            expected = grid_to_points(caster.cast(world, origin, rot, np.random.default_rng(k)), keep_band)
            got = caster.cast_points(world, origin, rot, np.random.default_rng(k), keep_band)
            assert got.dtype == np.float32 and got.shape[0] > 100
            np.testing.assert_array_equal(got, expected)


# -- noise and dropout -----------------------------------------------------------------------


def test_noise_statistics() -> None:
    world = _room()
    exact = _cast(world).ranges
    noisy = _cast(world, noise_std=0.05).ranges  # rng=None: a fresh unseeded generator
    both = (exact > 0) & (noisy > 0)
    err = (noisy - exact)[both]
    assert abs(err.mean()) < 0.005
    assert err.std() == pytest.approx(0.05, rel=0.1)


def test_dropout_fraction_and_seeded_determinism() -> None:
    world = _room()
    caster = VLP16Raycaster(LidarConfig(dropout=0.3))
    exact = _cast(world).ranges
    a = caster.cast(world, np.array([0.0, 0.0, 1.5]), np.eye(3), np.random.default_rng(5)).ranges
    b = caster.cast(world, np.array([0.0, 0.0, 1.5]), np.eye(3), np.random.default_rng(5)).ranges
    np.testing.assert_array_equal(a, b)
    lost = ((a == 0) & (exact > 0)).sum() / (exact > 0).sum()
    assert lost == pytest.approx(0.3, abs=0.03)
    kept = a > 0
    np.testing.assert_array_equal(a[kept], exact[kept])


# -- points and config -----------------------------------------------------------------------


def test_grid_to_points_follows_the_velodyne_convention() -> None:
    az = np.array([0.0, 90.0, 180.0, 270.0])
    ranges = np.zeros((4, 16), np.float32)
    ranges[:, 1] = 2.0  # +1 deg laser
    ranges[1, 0] = 3.0  # -15 deg laser at azimuth 90 (right)
    pts = grid_to_points(RangeGrid(az, ranges))
    assert pts.dtype == np.float32 and pts.shape == (5, 3)
    c1, s1 = 2.0 * math.cos(EL[1]), 2.0 * math.sin(EL[1])
    expected = [
        [c1, 0.0, s1],  # front
        [0.0, -3.0 * math.cos(EL[0]), 3.0 * math.sin(EL[0])],  # right, laser 0 comes first
        [0.0, -c1, s1],  # right
        [-c1, 0.0, s1],  # back
        [0.0, c1, s1],  # left
    ]
    np.testing.assert_allclose(pts, expected, atol=1e-5)


def test_scan_of_a_cast_sees_the_walls_where_they_are() -> None:
    """The caster's cloud through the companion's scan: bin 0 front, bin 90 left."""
    scan = scan_from_points(grid_to_points(_cast(_room(), position=(1.0, 0.5, 1.5))), ScanConfig())
    assert scan[0] == pytest.approx(0.5, abs=1e-3)  # 5 m of 10
    assert scan[90] == pytest.approx(0.35, abs=1e-3)  # left wall y = +4
    assert scan[270] == pytest.approx(0.45, abs=1e-3)  # right wall y = -4
    assert scan[180] == pytest.approx(0.7, abs=1e-3)


def test_config_checks() -> None:
    assert LidarConfig(azimuth_step_deg=0.2).n_columns == 1800
    with pytest.raises(ValueError, match="does not divide 360"):
        LidarConfig(azimuth_step_deg=0.7)
    with pytest.raises(UserError, match=r"lidar: azimuth_step_deg 0.7 does not divide 360"):
        from_dict(LidarConfig, {"azimuth_step_deg": 0.7}, prefix="lidar.")
    with pytest.raises(UserError, match=r"lidar.dropout: 1.5 is above the maximum"):
        from_dict(LidarConfig, {"dropout": 1.5}, prefix="lidar.")
