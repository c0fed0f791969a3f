"""N lidars at once: one compiled call casts every vehicle's VLP-16, one reduces all N clouds to scans.

The numbers are those of :meth:`flightsim.envs.raycast.VLP16Raycaster.cast_points` followed by
:func:`companion.perception.scan.scan_from_points`, per vehicle and bit for bit: the cast reuses the same
compiled kernels, the noise and dropout draw the same random numbers from each vehicle's own
generator in the same order (:func:`flightsim.envs.raycast._corrupt`), and the scan kernel repeats
``scan_from_points``' float32 arithmetic operation by operation (tests/flightsim/test_batch_lidar.py
proves it on the same clouds). In the env's path no cloud is materialised: each return goes from
the range grid straight into the scan bin its column fixes (:func:`column_bins`), through the same
float32 tests. What batching removes is the per-call cost (numpy's boolean masks,
``np.minimum.at``, some 20 small arrays per vehicle and step) and most atan2 calls.

The compiled scan covers the sensor mounted at the body origin, level (the project's mount);
any other mount reduces each cloud with ``scan_from_points`` itself.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from companion.perception.scan import N_BINS, ScanConfig, scan_from_points
from flightsim.envs.compiled_draws import draw, state_address
from flightsim.envs.raycast import (
    N_LASERS,
    LidarConfig,
    VLP16Raycaster,
    _band_floats,
    _cast_kernel,
    _points_kernel,
)
from flightsim.worlds.world import World

_BINS_PER_RAD = np.float32(N_BINS / (2.0 * math.pi))  # as companion.perception.scan's


class PackedWorlds:
    """The geometry of N worlds as flat arrays with offsets, for the batched cast kernel.

    Rebuilt only for the slots whose world changed (a reset), not every step.
    """

    def __init__(self, n: int) -> None:
        self.worlds: list[World | None] = [None] * n
        self.rooms = np.zeros((n, 3))
        self.boxes = np.zeros((0, 8))
        self.cylinders = np.zeros((0, 4))
        self.box_offsets = np.zeros(n + 1, dtype=np.int64)
        self.cylinder_offsets = np.zeros(n + 1, dtype=np.int64)

    def update(self, worlds: list[World]) -> None:
        """Take the current world of every slot (repacking only when one changed)."""
        if all(w is old for w, old in zip(worlds, self.worlds, strict=True)):
            return
        self.worlds = list(worlds)
        packed = [w.packed for w in worlds]
        self.rooms = np.array([room for room, _, _ in packed], dtype=np.float64)
        self.boxes = np.concatenate([boxes for _, boxes, _ in packed]).reshape(-1, 8)
        self.cylinders = np.concatenate([cyl for _, _, cyl in packed]).reshape(-1, 4)
        self.box_offsets = np.concatenate([[0], np.cumsum([len(b) for _, b, _ in packed])]).astype(np.int64)
        self.cylinder_offsets = np.concatenate([[0], np.cumsum([len(c) for _, _, c in packed])]).astype(
            np.int64
        )


class BatchLidar:
    """N vehicles' lidars and scans, one compiled call for each stage.

    :param n: number of vehicles
    :param lidar: the simulated sensor (one for all)
    :param scan: the scan geometry (one for all)
    :param keep_band: the points kept from the cloud (:func:`flightsim.envs.env.slice_band`)
    """

    def __init__(
        self, n: int, lidar: LidarConfig, scan: ScanConfig, keep_band: tuple[np.ndarray, float, float]
    ) -> None:
        self.n = n
        self.lidar = lidar
        self.scan = scan
        caster = self._caster = VLP16Raycaster(lidar)
        self._columns, self._cos_el, self._sin_el, self._unit = (
            caster._columns, caster._cos_el, caster._sin_el, caster._unit,
        )  # fmt: skip
        self._band = _band_floats(keep_band)
        self._ranges = np.empty((n, lidar.n_columns, N_LASERS), dtype=np.float32)
        self.worlds = PackedWorlds(n)
        self._identity = scan.mount_rpy_deg == (0.0, 0.0, 0.0) and scan.mount_xyz == (0.0, 0.0, 0.0)
        self._draws = CorruptionDraws(lidar, self._ranges.shape)
        self.column_bins = column_bins(caster.azimuth_deg, self._unit) if self._identity else None
        self._unit_xyz = tuple(np.ascontiguousarray(self._unit[:, :, c]) for c in range(3))

    def scans(
        self,
        worlds: list[World],
        origins: np.ndarray,
        rotations: np.ndarray,
        rngs: list[np.random.Generator],
        times: list[float] | None = None,
    ) -> np.ndarray:
        """``(N, 360)`` float32 scans: lidar ``i`` at ``origins[i]``, ``rotations[i]`` in ``worlds[i]``.

        :param worlds: each vehicle's world
        :param origins: ``(N, 3)`` sensor origins, world ENU, m
        :param rotations: ``(N, 3, 3)`` sensor-to-world rotations
        :param rngs: each vehicle's generator, for range noise and dropout (drawn as
            :func:`flightsim.envs.raycast._corrupt` draws them)
        :param times: each vehicle's time since its world's start, seconds: where a world's moving
            obstacles are (:meth:`~flightsim.envs.raycast.VLP16Raycaster.cast_moving`); None: 0
        """
        self.worlds.update(worlds)
        w, cfg = self.worlds, self.lidar
        hits = _cast_batch(
            origins, rotations, self._columns, self._cos_el, self._sin_el, w.rooms, w.boxes, w.box_offsets,
            w.cylinders, w.cylinder_offsets, cfg.min_range, cfg.max_range, self._ranges,
        )  # fmt: skip
        for v, world in enumerate(worlds):
            if world.moving:  # a second pass, then the count of returns the noise draws for again
                time = 0.0 if times is None else float(times[v])
                self._caster.cast_moving(world, origins[v], rotations[v], time, self._ranges[v])
                hits[v] = np.count_nonzero(self._ranges[v])
        noise_offsets = self._draws.draw(hits, rngs)
        corrupt = (
            self._draws.noise, noise_offsets, cfg.noise_std, self._draws.drop, cfg.noise_std > 0.0,
            cfg.dropout > 0.0, np.float32(cfg.min_range), np.float32(cfg.max_range), cfg.dropout,
        )  # fmt: skip
        if self.column_bins is not None:  # the cloud's points go straight into their column's bin
            out = np.empty((self.n, N_BINS), dtype=np.float32)
            _corrupt_and_scan(
                self._ranges, *corrupt, *self._unit_xyz, *self._band, self.column_bins,
                *_scan_floats(self.scan), out,
            )  # fmt: skip
            return out
        points, offsets = _corrupt_and_points(self._ranges, *corrupt, self._unit, *self._band)
        return scans_from_points(points.view(np.float32), offsets, self.scan, self._identity)


def column_bins(azimuth_deg: np.ndarray, unit: np.ndarray) -> np.ndarray | None:
    """The scan bin of every return of each column, ``(columns,)``, or None where that is not fixed.

    A return's direction in the sensor frame is its column's, whatever its range, noise or the
    vehicle's pose: ``scan_from_points`` bins it by the atan2 of its float32 x, y, which float32
    rounding moves by under 1e-4 bin. Columns at least 1e-3 bin from a bin edge (the 1° caster's
    sit mid-bin, 0.5 bin away) therefore always land in the bin that atan2 gives their unit
    vector, the same for all 16 lasers of the column; a caster with a column nearer an edge gets
    None (the scan then bins point by point).
    """
    angle = (-np.asarray(azimuth_deg, dtype=np.float64)) % 360.0  # azimuth runs clockwise
    if np.min(np.abs(angle - np.round(angle))) < 1e-3:
        return None
    bins = _unit_bins(unit, _BINS_PER_RAD)
    if np.any(bins != bins[:, :1]):  # cannot happen a 1e-3 bin from the edges; never assume it
        return None
    return bins[:, 0].copy()


def _scan_floats(config: ScanConfig) -> tuple[np.float32, np.float32, np.float32]:
    """The float32 bounds ``scan_from_points`` compares with: slice height, min range², max range."""
    return np.float32(config.slice_height), np.float32(config.min_range**2), np.float32(config.max_range)


class CorruptionDraws:
    """Each vehicle's range noise (a standard normal per return) and dropout draws (a uniform per
    ray), from its own generator in ``_corrupt``'s order, into reused buffers.

    ``rng.normal(0, σ, n)`` is ``0 + σ · rng.standard_normal()`` per value, the same stream: the
    kernels scale them (:func:`_corrupt_one`). The draws run compiled on the generators' own
    states (:mod:`flightsim.envs.compiled_draws`), or through numpy for a generator it does not cover.

    :param cfg: the sensor
    :param shape: ``(N, columns, lasers)``
    """

    def __init__(self, cfg: LidarConfig, shape: tuple[int, int, int]) -> None:
        self.cfg = cfg
        n = shape[0]
        self.noise = np.empty(math.prod(shape) if cfg.noise_std > 0.0 else 0)
        self.drop = np.empty(shape if cfg.dropout > 0.0 else (n, 0, 0))
        self._rngs: list[np.random.Generator | None] = [None] * n
        self._addresses = np.zeros(n, dtype=np.int64)
        self._compiled = np.zeros(n, dtype=np.bool_)

    def draw(self, hits: np.ndarray, rngs: list[np.random.Generator]) -> np.ndarray:
        """Draw for this step; returns where each vehicle's noise starts in ``noise``, ``(N + 1,)``.

        :param hits: ``(N,)`` returns per vehicle (one noise draw each)
        :param rngs: each vehicle's generator
        """
        cfg = self.cfg
        offsets = np.zeros(len(rngs) + 1, dtype=np.int64)
        if cfg.noise_std <= 0.0 and cfg.dropout <= 0.0:
            return offsets
        if cfg.noise_std > 0.0:
            np.cumsum(hits, out=offsets[1:])
        for i, rng in enumerate(rngs):
            if rng is not self._rngs[i]:  # a new generator (a seeded reset): find its state
                address = state_address(rng)
                self._rngs[i], self._addresses[i] = rng, address or 0
                self._compiled[i] = address is not None
        if self._compiled.all():
            draw(self._addresses, offsets[1:] - offsets[:-1], self.noise, offsets[:-1], self.drop)
            return offsets
        for i, rng in enumerate(rngs):
            if cfg.noise_std > 0.0:
                rng.standard_normal(out=self.noise[offsets[i] : offsets[i + 1]])
            if cfg.dropout > 0.0:
                rng.random(out=self.drop[i])  # the same draws as rng.random(shape), without the copy
        return offsets


def scans_from_points(
    points: np.ndarray, offsets: np.ndarray, config: ScanConfig, compiled: bool | None = None
) -> np.ndarray:
    """:func:`companion.perception.scan.scan_from_points` of N clouds stored back to back: ``(N,
    360)`` float32.

    :param points: ``(P, 3)`` float32 sensor-frame points, cloud ``i`` at ``offsets[i]:offsets[i+1]``
    :param offsets: ``(N + 1,)`` int64
    :param config: the scan geometry
    :param compiled: use the compiled kernel (default: when the mount is the identity, the only case
        it covers); otherwise ``scan_from_points`` per cloud
    """
    identity = config.mount_rpy_deg == (0.0, 0.0, 0.0) and config.mount_xyz == (0.0, 0.0, 0.0)
    if compiled is None:
        compiled = identity
    if compiled and not identity:
        raise ValueError("the compiled scan covers the identity mount only")
    n = len(offsets) - 1
    if not compiled:
        return np.stack([scan_from_points(points[offsets[i] : offsets[i + 1]], config) for i in range(n)])
    out = np.empty((n, N_BINS), dtype=np.float32)
    _scan_kernel(
        np.ascontiguousarray(points, dtype=np.float32), np.asarray(offsets, dtype=np.int64),
        *_scan_floats(config), _BINS_PER_RAD, out,
    )  # fmt: skip
    return out


# fmt: off
@njit(cache=True, error_model="numpy")
def _cast_batch(
    origins, rotations, columns, cos_el, sin_el, rooms, boxes, box_offsets, cylinders, cylinder_offsets,
    min_range, max_range, ranges,
):  # pragma: no cover - compiled
    """``_cast_kernel`` for every vehicle into ``ranges[i]``; returns each one's count of returns."""
    n = origins.shape[0]
    hits = np.zeros(n, dtype=np.int64)
    for v in range(n):
        _cast_kernel(
            origins[v], rotations[v], columns, cos_el, sin_el, rooms[v],
            boxes[box_offsets[v]:box_offsets[v + 1]], cylinders[cylinder_offsets[v]:cylinder_offsets[v + 1]],
            min_range, max_range, ranges[v],
        )
        count = 0
        r = ranges[v]
        for j in range(r.shape[0]):
            for i in range(r.shape[1]):
                if r[j, i] > 0.0:
                    count += 1
        hits[v] = count
    return hits


@njit(cache=True, inline="always")
def _corrupt_one(r, noise, k, std, d, noisy, dropping, min_range32, max_range32, dropout):  # pragma: no cover
    """``_corrupt`` on one grid: the same float32 arithmetic on the same draws (standard normals
    from ``k``, scaled as ``rng.normal(0, std)`` scales them and cast to float32 as ``_corrupt`` does)."""
    n_cols, n_el = r.shape
    if noisy:
        for j in range(n_cols):
            for i in range(n_el):
                if r[j, i] > 0.0:
                    value = r[j, i] + np.float32(0.0 + std * noise[k])  # float32 + float32, as numpy
                    k += 1
                    # numpy compares a float32 array with a Python float in float32 (NEP 50)
                    r[j, i] = np.float32(0.0) if (value < min_range32) | (value > max_range32) else value
    if dropping:
        for j in range(n_cols):
            for i in range(n_el):
                if d[j, i] < dropout:
                    r[j, i] = 0.0


@njit(cache=True)
def _corrupt_and_points(
    ranges, noise, noise_offsets, std, drop, noisy, dropping, min_range32, max_range32, dropout, unit,
    nx, ny, nz, offset, half,
):  # pragma: no cover - compiled
    """``_corrupt`` then ``_points_kernel``, all vehicles; clouds back to back, ``(N + 1,)`` offsets."""
    n, n_cols, n_el = ranges.shape
    points = np.empty((n * n_cols * n_el, 3), dtype=np.float32)
    offsets = np.zeros(n + 1, dtype=np.int64)
    total = 0
    for v in range(n):
        d = drop[v] if dropping else drop[0]
        r = ranges[v]
        _corrupt_one(r, noise, noise_offsets[v], std, d, noisy, dropping, min_range32, max_range32, dropout)
        cloud = _points_kernel(ranges[v], unit, nx, ny, nz, offset, half)
        m = cloud.shape[0]
        points[total:total + m] = cloud
        total += m
        offsets[v + 1] = total
    return points[:total], offsets


@njit(cache=True)
def _corrupt_and_scan(
    ranges, noise, noise_offsets, std, drop, noisy, dropping, min_range32, max_range32, dropout, ux, uy, uz,
    nx, ny, nz, offset, half, bins, slice_height, min_r2, max_range, out,
):  # pragma: no cover - compiled
    """``_corrupt``, ``_points_kernel`` and ``_scan_kernel`` fused, all vehicles: each return that
    the cloud would hold (the same float32 point, the same keep test) counts in the scan as that
    point would, in the bin of its column (:func:`column_bins`); no cloud is materialised.

    A bin keeps the least ``f(xy2) = sqrt(xy2) / max_range`` (float32) of its points, and ``f`` never
    decreases as ``xy2`` grows (each float32 operation rounds monotonically), so the least of a
    column's ``f`` is ``f`` of its least ``xy2``: one square root and division per column, for the
    same bits. The lasers of a column go through a branch-free loop (which vectorises: the unit
    vectors come as three arrays ``ux, uy, uz``) into a buffer, and the least is taken after.
    Dropout acts on each return alone, so it is applied in that loop rather than in a pass of its own.
    """
    n, n_cols, n_el = ranges.shape
    nothing = np.float32(np.inf)
    zero = np.float32(0.0)
    kept_xy2 = np.empty(n_el, dtype=np.float32)
    for v in range(n):
        r = ranges[v]
        d = drop[v] if dropping else drop[0]
        _corrupt_one(r, noise, noise_offsets[v], std, d, noisy, False, min_range32, max_range32, dropout)
        scan = out[v]
        scan[:] = np.float32(1.0)
        for j in range(n_cols):
            for i in range(n_el):
                rr = r[j, i]
                if dropping:
                    rr = zero if d[j, i] < dropout else rr
                x, y, z = rr * ux[j, i], rr * uy[j, i], rr * uz[j, i]
                # scan_from_points' float32 arithmetic and tests, after _points_kernel's keep test
                xy2 = np.float32(x * x)
                xy2 = np.float32(xy2 + np.float32(y * y))
                r2 = np.float32(np.float32(z * z) + xy2)
                kept = (rr > 0.0) & (abs(nx * x + ny * y + nz * z + offset) < half)
                kept = kept & (abs(z) < slice_height) & (r2 >= min_r2)
                kept_xy2[i] = xy2 if kept else nothing
            least = nothing
            for i in range(n_el):
                least = min(least, kept_xy2[i])
            if least < nothing:
                value = np.float32(np.float32(math.sqrt(least)) / max_range)
                if value < scan[bins[j]]:
                    scan[bins[j]] = value


@njit(cache=True)
def _unit_bins(unit, bins_per_rad):  # pragma: no cover - compiled
    """The scan bin ``scan_from_points`` gives each (column, laser) unit vector."""
    n_cols, n_el = unit.shape[0], unit.shape[1]
    bins = np.empty((n_cols, n_el), dtype=np.int64)
    for j in range(n_cols):
        for i in range(n_el):
            bins[j, i] = _bin(unit[j, i, 0], unit[j, i, 1], bins_per_rad, N_BINS)
    return bins


@njit(cache=True, inline="always")
def _bin(x, y, bins_per_rad, n_bins):  # pragma: no cover - compiled
    """``floor(atan2(y, x) · 360/2π)``, the angle in float64 rounded to float32 and the product in
    float32, negative wrapped: ``scan_from_points``' bin."""
    index = math.floor(np.float32(np.float32(math.atan2(np.float64(y), np.float64(x))) * bins_per_rad))
    return index + n_bins if index < 0 else index


@njit(cache=True, inline="always")
def _scan_point(scan, x, y, z, index, slice_height, min_r2, max_range):  # pragma: no cover - compiled
    """One point through ``scan_from_points``' tests and float32 arithmetic, into bin ``index``.

    ``|z| < slice``; ``xy2 = x*x + y*y``; ``r2 = z*z + xy2 >= min_range²``; the bin keeps the least
    ``sqrt(xy2) / max_range``.
    """
    if not abs(z) < slice_height:
        return
    xy2 = np.float32(x * x)
    xy2 = np.float32(xy2 + np.float32(y * y))
    r2 = np.float32(np.float32(z * z) + xy2)
    if not r2 >= min_r2:
        return
    rng = np.float32(np.float32(math.sqrt(xy2)) / max_range)
    if rng < scan[index]:
        scan[index] = rng


@njit(cache=True)
def _scan_kernel(points, offsets, slice_height, min_r2, max_range, bins_per_rad, out):  # pragma: no cover
    """``scan_from_points`` with the identity mount, per cloud, point by point in its float32 order."""
    for v in range(offsets.shape[0] - 1):
        scan = out[v]
        scan[:] = np.float32(1.0)
        for k in range(offsets[v], offsets[v + 1]):
            x, y, z = points[k, 0], points[k, 1], points[k, 2]
            if abs(z) < slice_height:  # (NaN/inf x, y fall out in _scan_point before the bin matters)
                _scan_point(scan, x, y, z, _bin(x, y, bins_per_rad, N_BINS), slice_height, min_r2, max_range)
# fmt: on
