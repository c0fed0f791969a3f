"""Run the real ``avoid-companion run`` in a subprocess, feed it VLP-16 packets, listen to systemd.

Shared by the process-level tests (test_app, test_isolation) and the bench.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from companion.autopilot.mavlink_adapter import mavlink
from companion.lidar.vlp16_packet import FIRINGS_PER_PACKET, PACKET_DURATION_US, encode_packets
from tests.companion.mavlink_peer import SETPOINT, SimulatedAutopilot, free_udp_port

REPO = Path(__file__).resolve().parents[2]


def revolution_packets(index: int, step_deg: float = 0.2, range_m: float = 8.0,
                       scene: Callable[[np.ndarray], np.ndarray] | None = None) -> list[bytes]:
    """The packets of one whole revolution, laid out so the azimuth wraps inside the last packet.

    Revolutions of consecutive ``index`` continue each other, so each one completes the previous.
    The default 0.2° step is the VLP-16's at 600 rpm (75 packets): the companion drops turns no
    VLP-16 can make (1° = 15 packets a turn would be 2,400 rpm).

    :param range_m: every laser's range, metres (a round room)
    :param scene: instead, the range of each azimuth (degrees clockwise from the front), metres
    """
    n = round(360 / step_deg)
    start = step_deg * (FIRINGS_PER_PACKET // 2)  # the wrap falls half-way through the last packet
    azimuth = (start + step_deg * np.arange(n)) % 360.0
    per_azimuth = np.full(n, range_m) if scene is None else scene(azimuth)
    ranges = np.repeat(per_azimuth[:, None], 16, axis=1)
    first_stamp = index * (n // FIRINGS_PER_PACKET) * PACKET_DURATION_US
    return encode_packets(azimuth, ranges, start_timestamp_us=first_stamp)


class LidarSender:
    """Sends revolutions to the companion's VLP-16 port at ``rate_hz`` from a thread while ``on``."""

    def __init__(self, port: int, rate_hz: float = 10.0, step_deg: float = 0.2) -> None:
        self.address = ("127.0.0.1", port)
        self.scene: Callable[[np.ndarray], np.ndarray] | None = None  # see revolution_packets
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.period = 1.0 / rate_hz
        self.step_deg = step_deg
        self.on = False
        self.sent: list[float] = []  # monotonic time each revolution's last packet left
        self._index = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            if self.on:
                self.send_one()

    def send_one(self) -> None:
        for packet in revolution_packets(self._index, self.step_deg, scene=self.scene):
            self.sock.sendto(packet, self.address)
        self.sent.append(time.monotonic())
        self._index += 1

    def garbage(self) -> None:
        """Malformed datagrams: too short, wrong flag, random bytes of the right length."""
        rng = np.random.default_rng(7)
        self.sock.sendto(b"\x00" * 100, self.address)
        self.sock.sendto(b"\xff" * 1206, self.address)
        self.sock.sendto(rng.integers(0, 256, 1206, dtype=np.uint8).tobytes(), self.address)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.sock.close()


class NotifySocket:
    """An AF_UNIX datagram socket standing in for systemd's NOTIFY_SOCKET."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.setblocking(False)
        self.received: list[tuple[float, str]] = []

    def drain(self) -> list[str]:
        while True:
            try:
                self.received.append((time.monotonic(), self.sock.recv(4096).decode()))
            except BlockingIOError:
                return [m for _, m in self.received]

    def wait_for(self, text: str, timeout: float = 10.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(text in m for m in self.drain()):
                return True
            time.sleep(0.01)
        return False

    def close(self) -> None:
        self.sock.close()


def write_config(tmp_path: Path, model: Path, lidar_port: int, mavlink_port: int, extra: str = "",
                 autopilot: str = "ardupilot", sensor_ip: str = "") -> Path:
    """A companion config for loopback: VLP-16 on ``lidar_port``, the autopilot via udpin ``mavlink_port``."""
    path = tmp_path / "companion.toml"
    connect = f"udpin://127.0.0.1:{mavlink_port}" if autopilot == "px4" else f"udpin:127.0.0.1:{mavlink_port}"
    path.write_text(
        f"""
[lidar.velodyne]
host = "127.0.0.1"
port = {lidar_port}
sensor_ip = "{sensor_ip}"

[policy]
model = "{model}"

[supervisor]
recover_scans = 5
climb_settled_time = 0.3

[autopilot]
type = "{autopilot}"
connect = "{connect}"

[runtime]
log_interval = 2.0
{extra}
"""
    )
    return path


def realtime_prefix(priority: int = 20) -> list[str]:
    """``chrt --fifo PRIORITY`` where this user may (root or CAP_SYS_NICE), otherwise nothing.

    20 is the companion's priority in systemd/lidar-avoid-companion.service.
    """
    command = ["chrt", "--fifo", str(priority)]
    try:
        allowed = subprocess.run([*command, "true"], capture_output=True).returncode == 0
    except OSError:
        allowed = False
    return command if allowed else []


def start_companion(config: Path, notify: Path | None = None, extra_env: dict[str, str] | None = None,
                    python_args: tuple[str, ...] = (), realtime: bool = False,
                    log: Path | None = None) -> subprocess.Popen[str]:
    """``avoid-companion run --config config`` in a subprocess.

    :param realtime: SCHED_FIFO 20 as deployed, where permitted
    :param log: write its log (stderr) to this file instead of a pipe: a pipe nobody reads before
        the end fills after 64 KiB, and the companion then blocks on its next log line
    """
    env = dict(os.environ)
    env.pop("NOTIFY_SOCKET", None)
    if notify is not None:
        env["NOTIFY_SOCKET"] = str(notify)
        env["WATCHDOG_USEC"] = "1000000"
    env.update(extra_env or {})
    stderr = log.open("w") if log is not None else None
    try:
        return subprocess.Popen(
            [*(realtime_prefix() if realtime else []), sys.executable, *python_args, "-m", "companion",
             "run", "--config", str(config)],
            cwd=REPO,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE if stderr is None else stderr,
            text=True,
        )
    finally:
        if stderr is not None:
            stderr.close()  # the child has its own copy


def favoured_prefix() -> list[str]:
    """``nice -n -10`` where this user may: a larger share of a loaded machine's processor, without
    the real-time priority that would starve the kernel's own threads (ksoftirqd delivers loopback
    datagrams once the softirq load is high)."""
    command = ["nice", "-n", "-10"]
    try:
        allowed = subprocess.run([*command, "true"], capture_output=True).returncode == 0
    except OSError:
        allowed = False
    return command if allowed and os.geteuid() == 0 else []


def start_lidar_traffic(port: int, *args: str, favoured: bool = False) -> subprocess.Popen[str]:
    """tests/companion/lidar_flood.py in its own process (``--play ...`` or ``--flood ...``).

    :param favoured: ``nice -n -10`` where permitted, so that a loaded machine cannot keep the
        sensor's pace or the flood's rate from being what the test says
    """
    prefix = favoured_prefix() if favoured else []
    return subprocess.Popen(
        [*prefix, sys.executable, "-m", "tests.companion.lidar_flood", "--port", str(port), *args],
        cwd=REPO, stdout=subprocess.PIPE, text=True)


def run_to_exit(args: list[str], timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion", *args], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout)


def stop(proc: subprocess.Popen[str], timeout: float = 10.0) -> tuple[int, str, str]:
    """SIGTERM, wait, return (exit status, stdout, stderr); kill if it does not stop."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
    return proc.returncode, out, err


#: config extra: a fixed waypoint 5 m west of the origin and 2 m above the :class:`Flight`'s 1.5 m
WEST_AND_UP = """
[goal]
source = "fixed"
max_vertical_speed = 0.5
[[goal.waypoints]]
north = 0.0
east = -5.0
down = -3.5
"""


class Flight:
    """The companion process with a config, a peer autopilot hovering at 1.5 m, the lidar on.

    :param position: the peer's LOCAL_POSITION_NED (north, east, down), None: over the origin
    :param autopilot: the peer's MAV_AUTOPILOT; a PX4 peer starts in OFFBOARD
    """

    def __init__(self, config: Path, lidar_port: int, mavlink_port: int,
                 position: tuple[float, float, float] | None = (0.0, 0.0, -1.5),
                 autopilot: int = mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA) -> None:
        self.vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{mavlink_port}", autopilot=autopilot)
        self.vehicle.local_position = position
        self.proc = start_companion(config)
        self.lidar = LidarSender(lidar_port)
        self.lidar.on = True

    @classmethod
    def with_model(cls, tmp_path: Path, kind: str, extra: str = "") -> Flight:
        """A test model of ``kind`` (tests/onnx_models.py) under the default config + ``extra``."""
        from tests.onnx_models import write_policy

        lidar_port, mavlink_port = free_udp_port(), free_udp_port()
        model = write_policy(tmp_path / f"{kind}.onnx", kind=kind)
        config = write_config(tmp_path, model, lidar_port, mavlink_port, extra=extra)
        return cls(config, lidar_port, mavlink_port)

    def setpoints(self, since: float = 0.0) -> list[Any]:
        return self.vehicle.messages(SETPOINT, since=since)

    def texts(self, since: float = 0.0) -> list[str]:
        """The companion's STATUSTEXTs received at or after ``since`` (monotonic)."""
        return [m.text for m in self.vehicle.messages("STATUSTEXT", since=since)]

    def settled(self, condition: Callable[[Any], bool], what: str, window: float = 0.6) -> Any:
        """Wait until every setpoint of the last ``window`` s satisfies ``condition``; return the last."""
        def check() -> Any:
            recent = self.setpoints(since=time.monotonic() - window)
            return recent[-1] if len(recent) >= 3 and all(condition(m) for m in recent) else None

        return wait_until(check, 20.0, what)

    def close(self) -> None:
        self.lidar.close()
        if self.proc.poll() is None:
            print(stop(self.proc)[2][-5000:])
        self.vehicle.close()


__all__ = ["WEST_AND_UP", "Flight", "LidarSender", "NotifySocket", "free_udp_port", "revolution_packets",
           "run_to_exit", "start_companion", "start_lidar_traffic", "stop", "write_config"]


def wait_until(condition: Callable[[], Any], timeout: float = 10.0, what: str = "condition") -> Any:
    """Poll ``condition()`` every 10 ms until it is truthy and return it; AssertionError naming ``what``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.01)
    raise AssertionError(f"timed out waiting for {what}")
