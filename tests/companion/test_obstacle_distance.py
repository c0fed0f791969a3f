"""OBSTACLE_DISTANCE pooling: sector geometry as ArduPilot reads it, units and edge values."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from companion.autopilot.obstacle_distance import (
    N_SECTORS,
    UNKNOWN_CM,
    obstacle_distance_from_scan,
    sector_distances,
)
from companion.perception.scan import ScanConfig, scan_from_points

EMPTY = 1001  # max_distance + 1


def _one_return(bin_index: int, value: float = 0.2) -> np.ndarray:
    scan = np.ones(360, dtype=np.float32)
    scan[bin_index] = value
    return scan


@functools.cache
def _sectors_hit(bin_index: int) -> frozenset[int]:
    out = obstacle_distance_from_scan(_one_return(bin_index), max_range=10.0)
    return frozenset(int(j) for j in np.flatnonzero(out != EMPTY))


@functools.cache
def _expected_sectors(bin_index: int) -> frozenset[int]:
    """Sectors whose clockwise span [5j-2.5, 5j+2.5) overlaps the bin's clockwise span (-i-1, -i]."""
    lo, hi = -bin_index - 1.0, -float(bin_index)
    hit = set()
    for j in range(N_SECTORS):
        for shift in (-360.0, 0.0, 360.0):
            s_lo, s_hi = 5 * j - 2.5 + shift, 5 * j + 2.5 + shift
            if min(hi, s_hi) - max(lo, s_lo) > 0:
                hit.add(j)
    return frozenset(hit)


@pytest.mark.parametrize(
    ("bin_index", "sectors"),
    [
        (0, {0}),  # just left of forward
        (359, {0}),  # just right of forward
        (2, {0, 71}),  # [2°, 3°) left straddles the 2.5° edge
        (3, {71}),  # 3-4° left: sector 71 is 355° clockwise = 5° left
        (357, {0, 1}),  # [-3°, -2°) straddles the edge to sector 1 (5° right)
        (356, {1}),
        (90, {54}),  # left = 270° clockwise
        (270, {18}),  # right = 90° clockwise
        (180, {36}),  # behind
        (272, {17, 18}),  # 88° clockwise (on the 87.5° edge)
    ],
)
def test_known_bins_land_in_known_sectors(bin_index: int, sectors: set[int]) -> None:
    assert _sectors_hit(bin_index) == sectors


def test_every_bin_maps_to_the_overlapping_sectors() -> None:
    for i in range(360):
        assert _sectors_hit(i) == _expected_sectors(i), f"bin {i}"


def test_every_sector_takes_six_bins_centred_on_its_angle() -> None:
    for j in range(N_SECTORS):
        bins = [i for i in range(360) if j in _sectors_hit(i)]
        # centre of those bins, counter-clockwise, must be -5j degrees (= 5j clockwise)
        angles = np.radians(np.array(bins) + 0.5)
        centre = math.degrees(math.atan2(np.sin(angles).sum(), np.cos(angles).sum()))
        assert len(bins) == 6
        assert (centre + 5 * j + 180) % 360 - 180 == pytest.approx(0.0, abs=1e-9)


def test_point_cloud_to_sector_end_to_end() -> None:
    """A point 3 m away, 40° to the right of forward, is reported in sector 8 (40° clockwise)."""
    ang = math.radians(-40.0)
    scan = scan_from_points(np.array([[3 * math.cos(ang), 3 * math.sin(ang), 0.0]]), ScanConfig())
    out = obstacle_distance_from_scan(scan, max_range=10.0)
    assert out[8] == 300
    assert np.count_nonzero(out != EMPTY) == 1


def test_units_are_centimetres_floored() -> None:
    out = obstacle_distance_from_scan(_one_return(0, 0.12345), max_range=10.0)
    assert out.dtype == np.uint16 and out.shape == (72,)
    assert out[0] == 123  # 1.2345 m → 123 cm, never rounded up


def test_minimum_over_the_sector() -> None:
    scan = np.ones(360, dtype=np.float32)
    scan[[358, 359, 0, 1]] = [0.5, 0.4, 0.3, 0.6]
    assert obstacle_distance_from_scan(scan, max_range=10.0)[0] == 300


def test_too_close_is_min_distance_not_dropped() -> None:
    out = obstacle_distance_from_scan(_one_return(0, 0.0), max_range=10.0)
    assert out[0] == 10
    out = obstacle_distance_from_scan(_one_return(0, 0.005), max_range=10.0, min_cm=20)
    assert out[0] == 20


def test_empty_and_beyond_max_distance_read_as_no_obstacle() -> None:
    assert (obstacle_distance_from_scan(np.ones(360), max_range=10.0) == EMPTY).all()
    # a 20 m lidar: a return at 15 m is beyond max_distance 1000 cm → no obstacle
    out = obstacle_distance_from_scan(_one_return(0, 0.75), max_range=20.0)
    assert out[0] == EMPTY
    out = obstacle_distance_from_scan(_one_return(0, 0.5), max_range=20.0)
    assert out[0] == 1000


def test_non_finite_bin_is_unknown() -> None:
    out = obstacle_distance_from_scan(_one_return(0, float("nan")), max_range=10.0)
    assert out[0] == UNKNOWN_CM
    assert (np.delete(out, 0) == EMPTY).all()


def test_wrong_length_rejected() -> None:
    with pytest.raises(ValueError, match="360 bins, got 72"):
        obstacle_distance_from_scan(np.ones(72), max_range=10.0)


@settings(max_examples=60)
@given(hnp.arrays(np.float32, 360, elements=st.floats(0.0, 1.0, width=32)))
def test_every_sector_is_valid_and_conservative(scan: np.ndarray) -> None:
    out = obstacle_distance_from_scan(scan, max_range=10.0)
    assert ((out >= 10) & (out <= EMPTY)).all()
    # no sector reports more than the nearest return of any bin it covers (within 1 cm)
    for i in range(360):
        if scan[i] < 1.0:
            for j in _expected_sectors(i):
                assert out[j] <= max(10, scan[i] * 1000.0) + 1e-3


def test_sector_distances_are_72_plain_ints_and_a_wrong_count_is_refused() -> None:
    out = sector_distances(obstacle_distance_from_scan(np.ones(360), 10.0))
    assert len(out) == 72 and all(type(v) is int and v == 1001 for v in out)
    with pytest.raises(ValueError, match="72 sectors, got 71"):
        sector_distances(np.zeros(71, np.uint16))


def test_sent_only_while_airborne():
    from companion.autopilot.link import LandedState, VehicleStatus
    from companion.autopilot.obstacle_distance import obstacle_distance_allowed

    def status(landed, altitude):
        return VehicleStatus(landed_state=landed, altitude=altitude)

    assert obstacle_distance_allowed(status(LandedState.IN_AIR, 1.5), 1.0)
    assert not obstacle_distance_allowed(status(LandedState.ON_GROUND, 0.0), 1.0)
    assert not obstacle_distance_allowed(status(LandedState.TAKEOFF, 1.2), 1.0)  # still climbing
    assert not obstacle_distance_allowed(status(LandedState.IN_AIR, 0.6), 1.0)  # the slice cuts the floor
    assert not obstacle_distance_allowed(status(LandedState.IN_AIR, None), 1.0)
    assert obstacle_distance_allowed(status(None, 1.5), 1.0)  # no EXTENDED_SYS_STATE: altitude alone
    assert not obstacle_distance_allowed(status(None, 0.2), 1.0)


def test_floor_below_the_slice_never_reaches_the_sectors():
    """Airborne at 1.5 m, the floor returns of the low lasers are outside the slice: no sector
    reports them; only the wall 2 m ahead is there."""
    azimuths = np.radians(np.arange(0.0, 360.0, 1.0))
    floor = np.stack([1.4 * np.cos(azimuths), 1.4 * np.sin(azimuths), np.full_like(azimuths, -1.5)], axis=1)
    wall = np.array([[2.0, 0.0, 0.0]])
    scan = scan_from_points(np.vstack([floor, wall]), ScanConfig())
    sectors = obstacle_distance_from_scan(scan, 10.0)
    assert sectors[0] == 200 and np.count_nonzero(sectors <= 1000) == 1
