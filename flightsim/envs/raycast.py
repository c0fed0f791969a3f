"""Ray-cast VLP-16: what the real sensor would return in a :class:`~flightsim.worlds.world.World`.

The output is the sensor's own data layout (a range per azimuth column and laser id) and, through
:func:`grid_to_points`, the same sensor-frame point cloud the ROS velodyne driver produces, so the
companion's scan code sees in simulation exactly the kind of input it sees on the drone.

Speed matters (the environment casts 16 × 360 rays every 0.1 s step and trains at thousands of
steps per second), so the kernel is a numba function that culls obstacles per azimuth column:
an obstacle is only tested by the columns whose horizontal direction passes near its footprint
circle, widened by how far the vehicle's tilt can swing a ±15° laser's heading away from its
column's. Floor and walls are closed-form and cheap.

Moving obstacles (:mod:`flightsim.worlds.moving`) are cast as the real sensor sees them: the
revolution ends at the time asked for and takes :data:`REVOLUTION_S`, and each azimuth column
fires at its own moment within it (column 0, just right of the nose, first, as the sensor spins
clockwise), with every moving obstacle where it is at that moment. An object moving across the
sweep comes out skewed, as on a real VLP-16. A world without moving obstacles casts exactly as
before (the second pass never runs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from companion.lidar.vlp16_packet import VLP16_ELEVATIONS_DEG
from flightsim.worlds.moving import pack_moving
from flightsim.worlds.world import World

N_LASERS = 16
REVOLUTION_S = 0.1  # one turn of the sensor at 600 rpm (10 Hz), seconds
_MAX_ABS_ELEVATION_RAD = math.radians(float(np.max(np.abs(VLP16_ELEVATIONS_DEG))))


@dataclass(frozen=True)
class LidarConfig:
    """Simulated sensor settings.

    :param azimuth_step_deg: column spacing; 0.2 is the real VLP-16 at 10 Hz, 1.0 is 5× cheaper.
        360 must be a whole multiple of it. Columns are at ``(j + 0.5) · step``.
    :param min_range: returns closer than this are lost, metres
    :param max_range: nothing is returned beyond this, metres
    :param noise_std: Gaussian range noise, metres (0 = exact)
    :param dropout: probability that any one return is lost
    """

    azimuth_step_deg: float = field(default=1.0, metadata={"min": 0.05, "max": 10.0})
    min_range: float = field(default=0.1, metadata={"min": 0.0, "max": 5.0})
    max_range: float = field(default=10.0, metadata={"min": 0.5, "max": 200.0})
    noise_std: float = field(default=0.0, metadata={"min": 0.0, "max": 1.0})
    dropout: float = field(default=0.0, metadata={"min": 0.0, "max": 1.0})

    def __post_init__(self) -> None:
        columns = 360.0 / self.azimuth_step_deg
        if abs(columns - round(columns)) > 1e-6:
            raise ValueError(f"azimuth_step_deg {self.azimuth_step_deg} does not divide 360")
        if self.min_range >= self.max_range:
            raise ValueError(f"min_range {self.min_range} must be below max_range {self.max_range}")

    @property
    def n_columns(self) -> int:
        """Azimuth columns per revolution."""
        return round(360.0 / self.azimuth_step_deg)


@dataclass
class RangeGrid:
    """One revolution as the sensor reports it.

    :param azimuth_deg: ``(A,)`` column azimuths, VLP-16 convention: clockwise seen from above,
        0 = the sensor's front, in ``[0, 360)``
    :param ranges: ``(A, 16)`` float32 metres by laser id; 0.0 = no return
    """

    azimuth_deg: np.ndarray
    ranges: np.ndarray


def grid_to_points(grid: RangeGrid, keep_band: tuple[np.ndarray, float, float] | None = None) -> np.ndarray:
    """The ``(N, 3)`` float32 sensor-frame (FLU) point cloud of a grid, no-returns dropped.

    ``x = r cosω cosα, y = −r cosω sinα, z = r sinω`` (ω laser elevation, α azimuth), as the ROS
    velodyne driver does. Points come column by column, laser id order within a column.

    :param grid: one revolution
    :param keep_band: ``(normal (3,), offset, half_width)``: keep only points with
        ``|normal · p + offset| < half_width``. Lets a caller skip points that a later height
        slice drops anyway (the environment passes the scan's slice widened by a millimetre, so
        the scan comes out identical from about half the points)
    """
    ranges = np.ascontiguousarray(grid.ranges, dtype=np.float32)
    unit = _unit_vectors(np.asarray(grid.azimuth_deg, dtype=np.float64))
    if ranges.shape != unit.shape[:2]:
        raise ValueError(f"ranges shape {ranges.shape} does not match {unit.shape[0]} azimuths x {N_LASERS}")
    points = _points_kernel(ranges, unit, *_band_floats(keep_band))
    # numba hands back a float32 dtype that is not numpy's canonical instance; numpy then misses its
    # fast paths downstream (np.minimum.at in the scan ran 25x slower), so re-view it as plain float32
    return points.view(np.float32)


def _band_floats(keep_band: tuple[np.ndarray, float, float] | None) -> tuple[float, ...]:
    """``(nx, ny, nz, offset, half_width)`` of a keep band as the kernels take it (None: keep all)."""
    if keep_band is None:
        return 0.0, 0.0, 0.0, 0.0, math.inf
    normal, offset, half = keep_band
    nx, ny, nz = normal
    return float(nx), float(ny), float(nz), float(offset), float(half)


_UNIT_CACHE: dict[bytes, np.ndarray] = {}
_LAST_UNIT: list = [None, None]  # (azimuth array, its unit vectors): the caster reuses one array


def _unit_vectors(azimuth_deg: np.ndarray) -> np.ndarray:
    """``(A, 16, 3)`` unit ray directions in the sensor frame, cached per azimuth table."""
    if _LAST_UNIT[0] is azimuth_deg:
        return _LAST_UNIT[1]
    key = azimuth_deg.tobytes()
    unit = _UNIT_CACHE.get(key)
    if unit is None:
        alpha = np.radians(azimuth_deg)[:, None]
        omega = np.radians(VLP16_ELEVATIONS_DEG.astype(np.float64))[None, :]
        unit = np.stack(
            np.broadcast_arrays(np.cos(omega) * np.cos(alpha), -np.cos(omega) * np.sin(alpha), np.sin(omega)),
            axis=-1,
        ).astype(np.float32)
        if len(_UNIT_CACHE) > 16:
            _UNIT_CACHE.clear()
        _UNIT_CACHE[key] = unit
    if not azimuth_deg.flags.writeable:  # only a read-only table can't change behind the cache's back
        _LAST_UNIT[:] = [azimuth_deg, unit]
    return unit


@njit(cache=True)
def _points_kernel(ranges, unit, nx, ny, nz, offset, half):  # pragma: no cover - compiled
    n_cols, n_el = ranges.shape
    points = np.empty((n_cols * n_el, 3), dtype=np.float32)
    n = 0
    for j in range(n_cols):
        for i in range(n_el):
            r = ranges[j, i]
            x, y, z = r * unit[j, i, 0], r * unit[j, i, 1], r * unit[j, i, 2]
            if r > 0.0 and abs(nx * x + ny * y + nz * z + offset) < half:
                points[n, 0] = x
                points[n, 1] = y
                points[n, 2] = z
                n += 1
    return points[:n]


# fmt: off
@njit(cache=True)
def _cast_points_kernel(
    origin, rot, columns, cos_el, sin_el, room, boxes, cylinders, min_range, max_range, ranges, unit,
    nx, ny, nz, offset, half,
):  # pragma: no cover - compiled
    """:func:`_cast_kernel` into ``ranges``, then :func:`_points_kernel`: one call from Python."""
    _cast_kernel(origin, rot, columns, cos_el, sin_el, room, boxes, cylinders, min_range, max_range, ranges)
    return _points_kernel(ranges, unit, nx, ny, nz, offset, half)
# fmt: on


class VLP16Raycaster:
    """Casts one VLP-16 revolution into a world.

    :param config: sensor settings
    """

    def __init__(self, config: LidarConfig | None = None) -> None:
        self.config = config or LidarConfig()
        # Columns sit half a step off the whole degrees: a column exactly on a 1-degree scan bin edge
        # would land in either neighbour by rounding, leaving holes (empty bins read as free space).
        step = self.config.azimuth_step_deg
        self.azimuth_deg = (np.arange(self.config.n_columns, dtype=np.float64) + 0.5) * step
        self.azimuth_deg.setflags(write=False)
        alpha = np.radians(self.azimuth_deg)
        # column directions in the sensor frame: azimuth runs clockwise, so y = -sin(alpha)
        self._columns = np.stack([np.cos(alpha), -np.sin(alpha), np.zeros_like(alpha)], axis=1)
        omega = np.radians(VLP16_ELEVATIONS_DEG.astype(np.float64))
        self._cos_el, self._sin_el = np.cos(omega), np.sin(omega)
        self._unit = _unit_vectors(self.azimuth_deg)
        self._scratch = np.empty((self.config.n_columns, N_LASERS), dtype=np.float32)  # cast_points' grid

    def cast(
        self,
        world: World,
        position: np.ndarray,
        rotation: np.ndarray,
        rng: np.random.Generator | None = None,
        time: float = 0.0,
    ) -> RangeGrid:
        """One revolution from a sensor pose.

        :param world: the geometry to hit (floor, walls, boxes, cylinders, moving obstacles)
        :param position: ``(3,)`` sensor origin in the world frame (ENU), metres
        :param rotation: ``(3, 3)`` sensor (FLU) to world rotation
        :param rng: random source for noise and dropout (a fresh unseeded one if None and needed)
        :param time: when the revolution ends, seconds since the world's start (moves the moving
            obstacles; a static world ignores it)
        """
        room, boxes, cylinders = world.packed
        cfg = self.config
        ranges = np.empty((self.config.n_columns, N_LASERS), dtype=np.float32)
        _cast_kernel(
            np.ascontiguousarray(position, dtype=np.float64),
            np.ascontiguousarray(rotation, dtype=np.float64),
            self._columns,
            self._cos_el,
            self._sin_el,
            room,
            boxes,
            cylinders,
            cfg.min_range,
            cfg.max_range,
            ranges,
        )
        if world.moving:
            self.cast_moving(world, position, rotation, time, ranges)
        if cfg.noise_std > 0.0 or cfg.dropout > 0.0:
            _corrupt(ranges, cfg, rng if rng is not None else np.random.default_rng())
        return RangeGrid(self.azimuth_deg, ranges)

    def cast_points(
        self,
        world: World,
        position: np.ndarray,
        rotation: np.ndarray,
        rng: np.random.Generator | None = None,
        keep_band: tuple[np.ndarray, float, float] | None = None,
        time: float = 0.0,
    ) -> np.ndarray:
        """One revolution straight to its point cloud: ``grid_to_points(cast(...), keep_band)``.

        The same numbers, but without noise or dropout to apply in between it is one compiled
        call with a reused grid buffer: the training env does this every step.

        :param world: the geometry to hit
        :param position: ``(3,)`` sensor origin in the world frame (ENU), metres
        :param rotation: ``(3, 3)`` sensor (FLU) to world rotation
        :param rng: random source for noise and dropout (see :meth:`cast`)
        :param keep_band: see :func:`grid_to_points`
        :param time: see :meth:`cast`
        :return: ``(N, 3)`` float32 sensor-frame points
        """
        cfg = self.config
        if cfg.noise_std > 0.0 or cfg.dropout > 0.0 or world.moving:
            return grid_to_points(self.cast(world, position, rotation, rng, time), keep_band)
        room, boxes, cylinders = world.packed
        points = _cast_points_kernel(
            np.ascontiguousarray(position, dtype=np.float64),
            np.ascontiguousarray(rotation, dtype=np.float64),
            self._columns, self._cos_el, self._sin_el, room, boxes, cylinders,
            cfg.min_range, cfg.max_range, self._scratch, self._unit, *_band_floats(keep_band),
        )  # fmt: skip
        return points.view(np.float32)  # numba's float32 dtype instance is not numpy's (see grid_to_points)

    def firing_times(self, time: float) -> np.ndarray:
        """``(A,)`` when each azimuth column fires in the revolution that ends at ``time``, seconds."""
        n = self.config.n_columns
        return time - REVOLUTION_S + (np.arange(n) + 0.5) * (REVOLUTION_S / n)

    def cast_moving(
        self, world: World, position: np.ndarray, rotation: np.ndarray, time: float, ranges: np.ndarray
    ) -> None:
        """Add the moving obstacles to a cast revolution's ``ranges`` ``(A, 16)`` in place: a return
        from one, where it is when its column fires, replaces a farther static return or none."""
        boxes, cylinders = pack_moving(world.moving, self.firing_times(time))
        _cast_moving_kernel(
            np.ascontiguousarray(position, dtype=np.float64),
            np.ascontiguousarray(rotation, dtype=np.float64),
            self._columns, self._cos_el, self._sin_el, boxes, cylinders,
            self.config.min_range, self.config.max_range, ranges,
        )  # fmt: skip


def _corrupt(ranges: np.ndarray, cfg: LidarConfig, rng: np.random.Generator) -> None:
    """Gaussian range noise and random lost returns, in place; noisy ranges out of limits are lost."""
    hit = ranges > 0.0
    if cfg.noise_std > 0.0:
        noisy = ranges[hit] + rng.normal(0.0, cfg.noise_std, int(hit.sum())).astype(np.float32)
        noisy[(noisy < cfg.min_range) | (noisy > cfg.max_range)] = 0.0
        ranges[hit] = noisy
    if cfg.dropout > 0.0:
        ranges[rng.random(ranges.shape) < cfg.dropout] = 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _hit_box(px, py, pz, dx, dy, dz, b):  # pragma: no cover - compiled
    """Entry distance of a ray (origin relative to the box centre) into a z-rotated box.

    Branch-free slab test so the loop over lasers vectorises: a zero direction component gives
    ±inf slab bounds (IEEE), a miss or a start inside gives inf.
    """
    c, s = b[6], b[7]
    lx, ly = c * px + s * py, -s * px + c * py
    ldx, ldy = c * dx + s * dy, -s * dx + c * dy
    ix, iy, iz = 1.0 / ldx, 1.0 / ldy, 1.0 / dz
    ax, bx = (-b[3] - lx) * ix, (b[3] - lx) * ix
    ay, by = (-b[4] - ly) * iy, (b[4] - ly) * iy
    az, bz = (-b[5] - pz) * iz, (b[5] - pz) * iz
    t_near = max(min(ax, bx), min(ay, by), min(az, bz))
    t_far = min(max(ax, bx), max(ay, by), max(az, bz))
    return t_near if (t_near > 0.0) & (t_near <= t_far) else np.inf


@njit(cache=True, error_model="numpy", inline="always")
def _hit_cylinder(px, py, oz, dx, dy, dz, r, h):  # pragma: no cover - compiled
    """Entry distance of a ray (origin relative to the axis) into a vertical cylinder on the floor.

    The side (z within [0, h]) or the top cap; branch-free like :func:`_hit_box`.
    """
    a = dx * dx + dy * dy
    b = px * dx + py * dy
    disc = b * b - a * (px * px + py * py - r * r)
    t_side = (-b - math.sqrt(max(disc, 0.0))) / a
    z = oz + t_side * dz
    t = t_side if (disc >= 0.0) & (t_side > 0.0) & (z >= 0.0) & (z <= h) else np.inf
    t_cap = (h - oz) / dz
    qx, qy = px + t_cap * dx, py + t_cap * dy
    cap = (dz < 0.0) & (oz > h) & (qx * qx + qy * qy <= r * r) & (t_cap < t)
    return t_cap if cap else t


@njit(cache=True, error_model="numpy")
def _cast_kernel(
    origin, rot, columns, cos_el, sin_el, room, boxes, cylinders, min_range, max_range, out
):  # pragma: no cover - compiled
    ox, oy, oz = origin[0], origin[1], origin[2]
    hx, hy, height = room[0], room[1], room[2]
    zx, zy, zz = rot[0, 2], rot[1, 2], rot[2, 2]
    n_box, n_cyl = boxes.shape[0], cylinders.shape[0]
    n_obs = n_box + n_cyl

    # how far tilt can swing a laser's heading from its column's (see module docstring)
    sin_tilt = math.sqrt(max(0.0, 1.0 - zz * zz))
    cos_tilt = abs(zz)
    spread_s = math.sin(0.2618) * sin_tilt  # 15 degrees, the steepest VLP-16 laser
    spread_c = math.cos(0.2618) * cos_tilt - spread_s
    spread = math.atan2(spread_s, spread_c) if spread_c > 0.0 else math.pi

    # per obstacle: unit direction of its footprint centre and the cosine of the half-angle it spans
    cx = np.empty(n_obs)
    cy = np.empty(n_obs)
    cos_half = np.empty(n_obs)
    for k in range(n_obs):
        if k < n_box:
            b = boxes[k]
            fx, fy, fr = b[0], b[1], math.sqrt(b[3] * b[3] + b[4] * b[4])
        else:
            cl = cylinders[k - n_box]
            fx, fy, fr = cl[0], cl[1], cl[2]
        vx, vy = fx - ox, fy - oy
        dist = math.sqrt(vx * vx + vy * vy)
        fr += 1e-6
        if dist - fr > max_range:
            cos_half[k] = 2.0  # out of reach: no column tests it
            cx[k], cy[k] = 1.0, 0.0
        elif dist <= fr:
            cos_half[k] = -2.0  # around us: every column tests it
            cx[k], cy[k] = 1.0, 0.0
        else:
            half = math.asin(fr / dist) + spread + 1e-6
            cos_half[k] = math.cos(half) if half < math.pi else -2.0
            cx[k], cy[k] = vx / dist, vy / dist

    candidates = np.empty(n_obs, dtype=np.int64)
    n_el = cos_el.shape[0]
    t_col = np.empty(n_el)
    dxs, dys, dzs = np.empty(n_el), np.empty(n_el), np.empty(n_el)
    for j in range(columns.shape[0]):
        sx, sy = columns[j, 0], columns[j, 1]
        ux = rot[0, 0] * sx + rot[0, 1] * sy
        uy = rot[1, 0] * sx + rot[1, 1] * sy
        uz = rot[2, 0] * sx + rot[2, 1] * sy
        # floor and walls, branch-free so the laser loop vectorises (IEEE inf/nan fall out as misses)
        for i in range(n_el):
            dx = cos_el[i] * ux + sin_el[i] * zx
            dy = cos_el[i] * uy + sin_el[i] * zy
            dz = cos_el[i] * uz + sin_el[i] * zz
            dxs[i], dys[i], dzs[i] = dx, dy, dz
            t = -oz / dz if dz < 0.0 else np.inf
            tw = (math.copysign(hx, dx) - ox) / dx
            zw = oz + tw * dz
            t = tw if (zw >= 0.0) & (zw <= height) & (tw < t) else t
            tw = (math.copysign(hy, dy) - oy) / dy
            zw = oz + tw * dz
            t = tw if (zw >= 0.0) & (zw <= height) & (tw < t) else t
            t_col[i] = t
        uh = math.sqrt(ux * ux + uy * uy)
        n_cand = 0
        for k in range(n_obs):
            near = (ux * cx[k] + uy * cy[k]) >= cos_half[k] * uh if uh > 1e-9 else cos_half[k] < 1.5
            if near:
                candidates[n_cand] = k
                n_cand += 1
        for m in range(n_cand):
            k = candidates[m]
            if k < n_box:
                b = boxes[k]
                px, py, pz = ox - b[0], oy - b[1], oz - b[2]
                for i in range(n_el):
                    t_col[i] = min(t_col[i], _hit_box(px, py, pz, dxs[i], dys[i], dzs[i], b))
            else:
                cl = cylinders[k - n_box]
                px, py, r, h = ox - cl[0], oy - cl[1], cl[2], cl[3]
                for i in range(n_el):
                    t_col[i] = min(t_col[i], _hit_cylinder(px, py, oz, dxs[i], dys[i], dzs[i], r, h))
        for i in range(n_el):
            t = t_col[i]
            out[j, i] = t if (t >= min_range) & (t <= max_range) else 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _hit_lifted_cylinder(px, py, pz, dx, dy, dz, r, h):  # pragma: no cover - compiled
    """Entry distance of a ray (origin relative to the axis at the bottom) into a vertical cylinder
    from its bottom up ``h``: :func:`_hit_cylinder` and the bottom cap, seen from below."""
    t = _hit_cylinder(px, py, pz, dx, dy, dz, r, h)
    t_bottom = -pz / dz
    qx, qy = px + t_bottom * dx, py + t_bottom * dy
    bottom = (dz > 0.0) & (pz < 0.0) & (qx * qx + qy * qy <= r * r) & (t_bottom < t)
    return t_bottom if bottom else t


@njit(cache=True, error_model="numpy")
def _cast_moving_kernel(
    origin, rot, columns, cos_el, sin_el, boxes, cylinders, min_range, max_range, out
):  # pragma: no cover - compiled
    """The moving obstacles into ``out``: ``boxes`` ``(A, B, 8)`` and ``cylinders`` ``(A, C, 5)``
    (centre xy, radius, bottom z, top z) hold each one's pose when column ``j`` fires. A return
    from one within the range limits replaces a farther return or none. (A static surface nearer
    than ``min_range`` reads as none, so a moving one behind it would show: the vehicle has
    collided long before anything is that near.)"""
    ox, oy, oz = origin[0], origin[1], origin[2]
    zx, zy, zz = rot[0, 2], rot[1, 2], rot[2, 2]
    n_el = cos_el.shape[0]
    n_box, n_cyl = boxes.shape[1], cylinders.shape[1]
    # as _cast_kernel culls: a column tests only the obstacles its lasers' headings can reach
    sin_tilt = math.sqrt(max(0.0, 1.0 - zz * zz))
    spread_s = math.sin(0.2618) * sin_tilt
    spread_c = math.cos(0.2618) * abs(zz) - spread_s
    spread = math.atan2(spread_s, spread_c) if spread_c > 0.0 else math.pi
    near = np.empty(n_box + n_cyl, dtype=np.bool_)
    for j in range(columns.shape[0]):
        sx, sy = columns[j, 0], columns[j, 1]
        ux = rot[0, 0] * sx + rot[0, 1] * sy
        uy = rot[1, 0] * sx + rot[1, 1] * sy
        uz = rot[2, 0] * sx + rot[2, 1] * sy
        uh = math.sqrt(ux * ux + uy * uy)
        any_near = False
        for k in range(n_box + n_cyl):
            if k < n_box:
                b = boxes[j, k]
                fx, fy, fr = b[0], b[1], math.sqrt(b[3] * b[3] + b[4] * b[4]) + 1e-6
            else:
                c = cylinders[j, k - n_box]
                fx, fy, fr = c[0], c[1], c[2] + 1e-6
            vx, vy = fx - ox, fy - oy
            dist = math.sqrt(vx * vx + vy * vy)
            if dist - fr > max_range:
                near[k] = False
            elif dist <= fr or uh <= 1e-9:
                near[k] = True
            else:
                half = math.asin(fr / dist) + spread + 1e-6
                near[k] = half >= math.pi or (ux * vx + uy * vy) >= math.cos(half) * uh * dist
            any_near = any_near or near[k]
        if not any_near:
            continue
        for i in range(n_el):
            dx = cos_el[i] * ux + sin_el[i] * zx
            dy = cos_el[i] * uy + sin_el[i] * zy
            dz = cos_el[i] * uz + sin_el[i] * zz
            t = np.inf
            for k in range(n_box):
                if near[k]:
                    b = boxes[j, k]
                    t = min(t, _hit_box(ox - b[0], oy - b[1], oz - b[2], dx, dy, dz, b))
            for k in range(n_cyl):
                if near[n_box + k]:
                    c = cylinders[j, k]
                    h = c[4] - c[3]
                    t = min(t, _hit_lifted_cylinder(ox - c[0], oy - c[1], oz - c[3], dx, dy, dz, c[2], h))
            if (t >= min_range) & (t <= max_range):
                r = out[j, i]
                if (r == 0.0) | (t < r):
                    out[j, i] = t
