"""Lidar co-simulation: the vehicle's pose → ray-cast VLP-16 revolution → real UDP data packets.

Every 100 ms (10 Hz, like the sensor) the pose is read, one revolution is cast from the sensor's
mount point and encoded into the 75 VLP-16 packets a sensor at 600 rpm sends (0.2° apart; a coarser
cast, e.g. 1°, is sent as those firings too, see :func:`as_sensor_firings`, because the companion
accepts only turns a real VLP-16 can make), which are then sent spread over the revolution's
100 ms, as the spinning sensor does. The companion cuts revolutions
where the azimuth wraps, so a revolution is complete when the next one's first packet arrives,
right after its own last packet: the send time of each revolution's last packet is recorded so
the harness can measure latency from "scan complete" to "setpoint received".

A world with moving obstacles is cast at the world's time (``world_time``, seconds since the flight's
clock zero) that the revolution ends at, each column with the obstacles where they are when it fires
(:meth:`flightsim.envs.raycast.VLP16Raycaster.cast`).
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.lidar.vlp16_packet import encode_packets
from companion.perception.scan import ScanConfig
from flightsim.envs.raycast import LidarConfig, VLP16Raycaster
from flightsim.worlds.world import World

log = logging.getLogger(__name__)

#: azimuth between firings of a VLP-16 at 600 rpm (10 Hz), degrees
SENSOR_STEP_DEG = 0.2


def as_sensor_firings(azimuth_deg: np.ndarray, ranges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A cast coarser than the sensor's 0.2° as the firings a VLP-16 at 600 rpm sends.

    Each column is repeated at 0.2° steps just before its own azimuth (1° column α: α − 0.8, …,
    α − 0.2, α), so every repeat falls into the same 1° scan bin as the column and the scan equals
    the coarse cast's; a cast at 0.2° or finer is returned as it is.
    """
    repeats = round(360.0 / SENSOR_STEP_DEG / len(azimuth_deg))
    if repeats <= 1:
        return azimuth_deg, ranges
    offsets = SENSOR_STEP_DEG * np.arange(repeats - 1, -1, -1)
    firings = (np.asarray(azimuth_deg, dtype=np.float64)[:, None] - offsets[None, :]).reshape(-1) % 360.0
    return firings, np.repeat(ranges, repeats, axis=0)

REVOLUTION_S = 0.1
#: don't sleep for less than this between packets (the OS would oversleep); send a few together
MIN_SLEEP_S = 0.002


@dataclass
class CosimStats:
    """What the co-simulation did (read by the harness after or during a flight)."""

    revolutions: int = 0
    packets: int = 0
    #: clock time of the last packet of each revolution (the revolution is complete from here)
    revolution_ends: list[float] = field(default_factory=list)
    cast_seconds_max: float = 0.0
    late_revolutions: int = 0


class LidarCosim:
    """Stream a simulated VLP-16 from a moving vehicle to a UDP address in real time.

    :param world: the room to cast into
    :param pose: returns the vehicle's current state (position ENU, ``rotation()`` body FLU → world)
    :param target: (host, port) the companion listens on
    :param lidar: ray-caster settings (0.2° columns like the real sensor, or 1° to save CPU)
    :param scan: the companion's scan config; its mount transform places the sensor on the body
    :param clock: monotonic clock shared with the harness (for latency figures)
    :param world_time: seconds since the world's start (where its moving obstacles are); None: a
        static world's 0
    """

    def __init__(
        self,
        world: World,
        pose: Callable[[], Any],
        target: tuple[str, int],
        *,
        lidar: LidarConfig | None = None,
        scan: ScanConfig | None = None,
        clock: Callable[[], float] = time.monotonic,
        world_time: Callable[[], float] | None = None,
    ) -> None:
        self.world = world
        self.world_time = world_time
        self.pose = pose
        self.target = target
        self.caster = VLP16Raycaster(lidar or LidarConfig(azimuth_step_deg=0.2))
        scan = scan or ScanConfig()
        self.mount_xyz = np.asarray(scan.mount_xyz, dtype=float)
        self.mount_rotation = np.asarray(scan.rotation(), dtype=float)
        self.clock = clock
        self.stats = CosimStats()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        #: cleared by a test to stop the stream (the lidar "dies"); set again to resume
        self.streaming = threading.Event()
        self.streaming.set()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None

    def revolution_packets(self, state: Any, world_time: float = 0.0) -> list[bytes]:
        """Cast one revolution from ``state`` and encode it (pure apart from the caster's cache).

        :param world_time: when the revolution ends, seconds since the world's start
        """
        rotation = state.rotation()
        position = np.asarray(state.position, dtype=float) + rotation @ self.mount_xyz
        grid = self.caster.cast(self.world, position, rotation @ self.mount_rotation, time=world_time)
        past_hour_us = (time.time() % 3600.0) * 1e6
        azimuth, ranges = as_sensor_firings(grid.azimuth_deg, grid.ranges)
        return encode_packets(azimuth, ranges, start_timestamp_us=past_hour_us)

    def send_raw(self, data: bytes) -> None:
        """Send arbitrary bytes to the companion's lidar port (fault injection)."""
        self.sock.sendto(data, self.target)

    def start(self) -> LidarCosim:
        self._thread = threading.Thread(target=self._run, name="lidar-cosim", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.sock.close()

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException as exc:  # reported by the harness
            log.exception("lidar co-simulation stopped")
            self.error = exc

    def _loop(self) -> None:
        start = self.clock()
        while not self._stop.is_set():
            if not self.streaming.is_set():
                self._stop.wait(0.01)
                start = self.clock()
                continue
            t0 = self.clock()
            # the revolution is sent over the next 100 ms: it ends then
            ends = self.world_time() + REVOLUTION_S if self.world_time is not None else 0.0
            packets = self.revolution_packets(self.pose(), ends)
            cast = self.clock() - t0
            self.stats.cast_seconds_max = max(self.stats.cast_seconds_max, cast)
            n = len(packets)
            for i, packet in enumerate(packets):
                wait = start + REVOLUTION_S * (i + 1) / n - self.clock()
                if wait > MIN_SLEEP_S:
                    time.sleep(wait)
                # nobody listening yet (ICMP unreachable): the sensor doesn't care either
                with contextlib.suppress(OSError):
                    self.sock.sendto(packet, self.target)
            self.stats.revolution_ends.append(self.clock())
            self.stats.packets += n
            self.stats.revolutions += 1
            start += REVOLUTION_S
            behind = self.clock() - start
            if behind > REVOLUTION_S:  # the machine stalled: skip ahead rather than burst
                self.stats.late_revolutions += 1
                start = self.clock()
