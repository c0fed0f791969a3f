"""The CAN rangefinder ring on a real python-can virtual bus."""

from __future__ import annotations

import itertools
import struct

import can
import numpy as np
import pytest

from companion.common.errors import UserError
from companion.lidar.can_ring import (
    CanConfig,
    CanRangefinder,
    CanRangefinderRing,
    CanSensorConfig,
    benewake_frame,
    open_can_ring,
)
from companion.perception.scan import ScanConfig, scan_from_points

_channels = itertools.count()

RING = [
    CanRangefinder(0x10, 0.0),
    CanRangefinder(0x11, 90.0),
    CanRangefinder(0x12, 180.0),
    CanRangefinder(0x13, -90.0),
]


@pytest.fixture
def buses():
    """A sensor-side bus and the companion's ring on the same fresh virtual channel."""
    channel = f"can-ring-test-{next(_channels)}"
    sensor_bus = can.Bus(interface="virtual", channel=channel)
    ring = CanRangefinderRing(can.Bus(interface="virtual", channel=channel), RING, max_range=12.0)
    yield sensor_bus, ring
    ring.close()
    sensor_bus.shutdown()


def send(bus: can.BusABC, readings: dict[int, float], strength: int = 1000) -> None:
    for can_id, distance in readings.items():
        bus.send(benewake_frame(can_id, distance, strength))


def test_benewake_frame_layout() -> None:
    frame = benewake_frame(0x10, 1.23, strength=500, timestamp_ms=7)
    assert frame.arbitration_id == 0x10 and not frame.is_extended_id and frame.dlc == 8
    assert bytes(frame.data) == bytes([0x7B, 0x00, 0xF4, 0x01, 7, 0, 0, 0])
    assert benewake_frame(0x18FF0001, 655.35).is_extended_id
    assert struct.unpack_from("<H", benewake_frame(3, 655.35).data)[0] == 0xFFFF
    with pytest.raises(ValueError, match="uint16"):
        benewake_frame(3, 655.36)


def test_cloud_once_every_sensor_reported_with_points_at_their_yaws(buses) -> None:
    sensor_bus, ring = buses
    send(sensor_bus, {0x10: 1.0, 0x11: 2.0, 0x12: 3.0})
    assert ring.read_available(now=0.0) == []  # 0x13 has not reported yet
    send(sensor_bus, {0x13: 4.5})
    [cloud] = ring.read_available(now=0.01)
    assert cloud.dtype == np.float32 and cloud.shape == (4, 3)
    np.testing.assert_allclose(cloud, [[1, 0, 0], [0, 2, 0], [-3, 0, 0], [0, -4.5, 0]], atol=1e-6)
    # The next cloud needs every sensor again; a sensor reporting twice just updates its reading.
    send(sensor_bus, {0x10: 1.5, 0x11: 2.5, 0x12: 3.5})
    send(sensor_bus, {0x10: 0.7})
    assert ring.read_available(now=0.02) == []
    send(sensor_bus, {0x13: 5.0})
    [cloud] = ring.read_available(now=0.03)
    np.testing.assert_allclose(cloud[:, 0], [0.7, 0, -3.5, 0], atol=1e-6)
    assert ring.counters.clouds == 2 and ring.counters.frames == 9


def test_several_rounds_in_one_read_give_several_clouds(buses) -> None:
    sensor_bus, ring = buses
    for distance in (1.0, 2.0, 3.0):
        send(sensor_bus, dict.fromkeys((0x10, 0x11, 0x12, 0x13), distance))
    clouds = ring.read_available(now=1.0)
    assert [float(c[0, 0]) for c in clouds] == [1.0, 2.0, 3.0]


def test_no_return_leaves_its_direction_empty(buses) -> None:
    sensor_bus, ring = buses
    ring.min_strength = 100
    send(sensor_bus, {0x10: 0.0, 0x11: 12.01, 0x12: 3.0})  # no measurement, beyond max_range, good
    send(sensor_bus, {0x13: 2.0}, strength=99)  # too weak
    [cloud] = ring.read_available(now=0.0)
    np.testing.assert_allclose(cloud, [[-3, 0, 0]], atol=1e-6)
    assert ring.counters.no_return == 3


def test_malformed_frames_are_counted_and_dropped(buses) -> None:
    sensor_bus, ring = buses
    send(sensor_bus, {0x10: 1.0, 0x11: 1.0})
    sensor_bus.send(can.Message(arbitration_id=0x12, data=b"\x10\x00", is_extended_id=False))  # DLC 2
    sensor_bus.send(
        can.Message(arbitration_id=0x12, data=bytes(12), is_fd=True, is_extended_id=False)
    )  # DLC 12
    sensor_bus.send(can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False))  # unknown id
    sensor_bus.send(can.Message(arbitration_id=0x12, is_remote_frame=True, dlc=8, is_extended_id=False))
    sensor_bus.send(can.Message(arbitration_id=0x12, is_error_frame=True, is_extended_id=False))
    assert ring.read_available(now=0.0) == []
    assert ring.counters.malformed == {"wrong_dlc": 2, "unknown_id": 1, "remote_frame": 1, "error_frame": 1}
    send(sensor_bus, {0x12: 2.0, 0x13: 2.0})
    [cloud] = ring.read_available(now=0.01)
    assert len(cloud) == 4
    assert ring.counters.frames == 9


def test_an_extended_frame_is_not_the_standard_id_it_shares_a_number_with(buses) -> None:
    """Issue 14: extended frame 0x10 was read as sensor 0x10 (standard)."""
    sensor_bus, ring = buses
    send(sensor_bus, {0x11: 1.0, 0x12: 1.0, 0x13: 1.0})
    forged = benewake_frame(0x10, 0.2).data
    sensor_bus.send(can.Message(arbitration_id=0x10, data=forged, is_extended_id=True))
    assert ring.read_available(now=0.0) == []  # 0x10 never reported: no cloud, no 0.2 m return
    assert ring.counters.malformed == {"wrong_id_format": 1}
    send(sensor_bus, {0x10: 4.0})
    [cloud] = ring.read_available(now=0.01)
    assert float(cloud[0, 0]) == pytest.approx(4.0)


def test_a_silent_sensor_stops_the_clouds_instead_of_leaving_a_blind_sector(buses) -> None:
    sensor_bus, ring = buses
    send(sensor_bus, {0x10: 1.0})
    assert ring.read_available(now=0.0) == []
    send(sensor_bus, {0x11: 1.0, 0x12: 1.0, 0x13: 1.0})
    assert ring.read_available(now=0.5) == []  # 0x10's reading is 0.5 s old
    assert ring.counters.stale == 1
    send(sensor_bus, {0x10: 2.0})
    [cloud] = ring.read_available(now=0.55)
    assert float(cloud[0, 0]) == 2.0


def test_extended_ids_and_the_scan_code_apply_unchanged() -> None:
    sensors = [CanRangefinder(0x18FF0000 + k, yaw) for k, yaw in enumerate((0.0, 45.0, 135.5, 270.0))]
    with (
        can.Bus(interface="virtual", channel="can-ring-scan") as sensor_bus,
        CanRangefinderRing.open("virtual", "can-ring-scan", sensors, max_range=10.0) as ring,
    ):
        assert ring.fileno() is None  # the virtual interface has no descriptor: poll instead
        for k, distance in enumerate((2.0, 5.0, 8.0, 1.0)):
            sensor_bus.send(benewake_frame(0x18FF0000 + k, distance))
        [cloud] = ring.read_available()
    scan = scan_from_points(cloud, ScanConfig(max_range=10.0))
    expected = np.ones(360, dtype=np.float32)
    expected[[0, 45, 135, 270]] = [0.2, 0.5, 0.8, 0.1]
    np.testing.assert_allclose(scan, expected, atol=1e-6)


@pytest.mark.parametrize(
    ("sensors", "message"),
    [
        ([], "at least one"),
        ([CanRangefinder(1, 0.0), CanRangefinder(1, 90.0)], "share the id 0x1"),
        ([CanRangefinder(0x20000000, 0.0)], "outside"),
        ([CanRangefinder(2, float("nan"))], "non-finite"),
    ],
)
def test_bad_sensor_lists_are_user_errors(sensors: list, message: str) -> None:
    with can.Bus(interface="virtual", channel="can-ring-bad") as bus, pytest.raises(UserError, match=message):
        CanRangefinderRing(bus, sensors)


def test_a_bus_that_cannot_open_is_a_user_error() -> None:
    with pytest.raises(UserError, match="cannot open CAN bus no-such-interface:can0"):
        CanRangefinderRing.open("no-such-interface", "can0", RING)


def test_open_from_the_companion_config_with_an_injected_clock() -> None:
    config = CanConfig(
        interface="virtual",
        channel="can-ring-config",
        max_range=3.0,
        stale_after=0.1,
        sensors=(CanSensorConfig(can_id=0x21, yaw_deg=30.0), CanSensorConfig(can_id=0x22, yaw_deg=-30.0)),
    )
    now = [10.0]
    with (
        can.Bus(interface="virtual", channel="can-ring-config") as sensor_bus,
        open_can_ring(config, clock=lambda: now[0]) as ring,
    ):
        assert ring.max_range == 3.0 and ring.stale_after == 0.1
        sensor_bus.send(benewake_frame(0x21, 2.0))
        assert ring.read_available() == []
        now[0] = 10.2  # the first reading is now too old
        sensor_bus.send(benewake_frame(0x22, 2.0))
        assert ring.read_available() == [] and ring.counters.stale == 1
        sensor_bus.send(benewake_frame(0x21, 4.0))  # beyond max_range 3 m: no point
        [cloud] = ring.read_available()
    np.testing.assert_allclose(cloud, [[2 * np.cos(np.radians(30)), -1.0, 0.0]], atol=1e-6)
