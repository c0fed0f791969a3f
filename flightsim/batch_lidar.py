"""N lidars at once: one compiled call casts every vehicle's VLP-16, one reduces all N clouds to scans.

The numbers are those of :meth:`flightsim.raycast.VLP16Raycaster.cast_points` followed by
:func:`companion.scan.scan_from_points`, per vehicle and bit for bit: the cast reuses the same
compiled kernels, the noise and dropout draw the same random numbers from each vehicle's own
generator in the same order (:func:`flightsim.raycast._corrupt`), and the scan kernel repeats
``scan_from_points``' float32 arithmetic operation by operation (tests/flightsim/test_batch_lidar.py
proves it on the same clouds). What batching removes is the per-call cost: numpy's boolean
masks, ``np.minimum.at`` and some 20 small array allocations per vehicle and step.

The compiled scan covers the sensor mounted at the body origin, level (the project's mount);
any other mount reduces each cloud with ``scan_from_points`` itself.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from companion.scan import N_BINS, ScanConfig, scan_from_points
from flightsim.raycast import (
    N_LASERS,
    LidarConfig,
    VLP16Raycaster,
    _band_floats,
    _cast_kernel,
    _points_kernel,
)
from flightsim.world import World

_BINS_PER_RAD = np.float32(N_BINS / (2.0 * math.pi))  # as companion.scan's


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
    :param keep_band: the points kept from the cloud (:func:`flightsim.env.slice_band`)
    """

    def __init__(
        self, n: int, lidar: LidarConfig, scan: ScanConfig, keep_band: tuple[np.ndarray, float, float]
    ) -> None:
        self.n = n
        self.lidar = lidar
        self.scan = scan
        caster = VLP16Raycaster(lidar)
        self._columns, self._cos_el, self._sin_el, self._unit = (
            caster._columns, caster._cos_el, caster._sin_el, caster._unit,
        )  # fmt: skip
        self._band = _band_floats(keep_band)
        self._ranges = np.empty((n, lidar.n_columns, N_LASERS), dtype=np.float32)
        self.worlds = PackedWorlds(n)
        self._identity = scan.mount_rpy_deg == (0.0, 0.0, 0.0) and scan.mount_xyz == (0.0, 0.0, 0.0)
        self._no_drop = np.zeros((n, 0, 0))

    def scans(
        self, worlds: list[World], origins: np.ndarray, rotations: np.ndarray, rngs: list[np.random.Generator]
    ) -> np.ndarray:
        """``(N, 360)`` float32 scans: lidar ``i`` at ``origins[i]``, ``rotations[i]`` in ``worlds[i]``.

        :param worlds: each vehicle's world
        :param origins: ``(N, 3)`` sensor origins, world ENU, m
        :param rotations: ``(N, 3, 3)`` sensor-to-world rotations
        :param rngs: each vehicle's generator, for range noise and dropout (drawn as
            :func:`flightsim.raycast._corrupt` draws them)
        """
        self.worlds.update(worlds)
        w, cfg = self.worlds, self.lidar
        hits = _cast_batch(
            origins, rotations, self._columns, self._cos_el, self._sin_el, w.rooms, w.boxes, w.box_offsets,
            w.cylinders, w.cylinder_offsets, cfg.min_range, cfg.max_range, self._ranges,
        )  # fmt: skip
        noise, noise_offsets, drop = _draw_corruption(cfg, hits, self._ranges.shape, rngs)
        if drop is None:
            drop = self._no_drop
        points, offsets = _corrupt_and_points(
            self._ranges, noise, noise_offsets, drop, cfg.noise_std > 0.0, cfg.dropout > 0.0,
            np.float32(cfg.min_range), np.float32(cfg.max_range), cfg.dropout, self._unit, *self._band,
        )  # fmt: skip
        return scans_from_points(points.view(np.float32), offsets, self.scan, self._identity)


def _draw_corruption(
    cfg: LidarConfig, hits: np.ndarray, shape: tuple[int, ...], rngs: list[np.random.Generator]
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Each vehicle's range noise (one per return) and dropout draws, in ``_corrupt``'s order."""
    n = len(rngs)
    offsets = np.zeros(n + 1, dtype=np.int64)
    if cfg.noise_std <= 0.0 and cfg.dropout <= 0.0:
        return np.zeros(0, dtype=np.float32), offsets, None
    noise_parts = []
    drop = np.empty(shape) if cfg.dropout > 0.0 else None
    for i, rng in enumerate(rngs):
        if cfg.noise_std > 0.0:
            noise_parts.append(rng.normal(0.0, cfg.noise_std, int(hits[i])).astype(np.float32))
        if drop is not None:
            rng.random(out=drop[i])  # the same draws as rng.random(shape), without the copy
    if noise_parts:
        offsets[1:] = np.cumsum(hits)
        return np.concatenate(noise_parts), offsets, drop
    return np.zeros(0, dtype=np.float32), offsets, drop


def scans_from_points(
    points: np.ndarray, offsets: np.ndarray, config: ScanConfig, compiled: bool | None = None
) -> np.ndarray:
    """:func:`companion.scan.scan_from_points` of N clouds stored back to back: ``(N, 360)`` float32.

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
        np.float32(config.slice_height), np.float32(config.min_range**2), np.float32(config.max_range),
        _BINS_PER_RAD, out,
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


@njit(cache=True)
def _corrupt_and_points(
    ranges, noise, noise_offsets, drop, noisy, dropping, min_range32, max_range32, dropout, unit,
    nx, ny, nz, offset, half,
):  # pragma: no cover - compiled
    """``_corrupt`` (the same float32 arithmetic, the same draws) then ``_points_kernel``, all vehicles.

    The clouds come back to back with ``(N + 1,)`` offsets.
    """
    n, n_cols, n_el = ranges.shape
    points = np.empty((n * n_cols * n_el, 3), dtype=np.float32)
    offsets = np.zeros(n + 1, dtype=np.int64)
    total = 0
    for v in range(n):
        r = ranges[v]
        if noisy:
            k = noise_offsets[v]
            for j in range(n_cols):
                for i in range(n_el):
                    if r[j, i] > 0.0:
                        value = r[j, i] + noise[k]  # float32 + float32, as numpy adds them
                        k += 1
                        # numpy compares a float32 array with a Python float in float32 (NEP 50)
                        r[j, i] = np.float32(0.0) if (value < min_range32) | (value > max_range32) else value
        if dropping:
            d = drop[v]
            for j in range(n_cols):
                for i in range(n_el):
                    if d[j, i] < dropout:
                        r[j, i] = 0.0
        cloud = _points_kernel(r, unit, nx, ny, nz, offset, half)
        m = cloud.shape[0]
        points[total:total + m] = cloud
        total += m
        offsets[v + 1] = total
    return points[:total], offsets


@njit(cache=True)
def _scan_kernel(points, offsets, slice_height, min_r2, max_range, bins_per_rad, out):  # pragma: no cover
    """``scan_from_points`` with the identity mount, per cloud, in its float32 operation order.

    Per point: ``|z| < slice``; ``xy2 = x*x + y*y``; ``r2 = z*z + xy2 >= min_range²``; the range
    ``sqrt(xy2) / max_range`` goes to bin ``floor(atan2(y, x) · 360/2π)`` (negative wraps), min.
    """
    one = np.float32(1.0)
    for v in range(offsets.shape[0] - 1):
        scan = out[v]
        scan[:] = one
        for k in range(offsets[v], offsets[v + 1]):
            x, y, z = points[k, 0], points[k, 1], points[k, 2]
            if not abs(z) < slice_height:
                continue
            xy2 = np.float32(x * x)
            xy2 = np.float32(xy2 + np.float32(y * y))
            r2 = np.float32(np.float32(z * z) + xy2)
            if not r2 >= min_r2:
                continue
            rng = np.float32(np.float32(math.sqrt(xy2)) / max_range)
            index = math.floor(np.float32(np.float32(math.atan2(y, x)) * bins_per_rad))
            if index < 0:
                index += scan.shape[0]
            if rng < scan[index]:
                scan[index] = rng
# fmt: on
