"""End-to-end latency of the real companion process: VLP-16 packets in → setpoint bytes out.

Starts ``avoid-companion run`` as a subprocess (ArduPilot link over UDP loopback, VLP-16 source on
UDP loopback, a small ONNX policy under the default config: a goal-layout model) and plays ArduPilot
to it from this process with the process tests' peer (tests/companion/mavlink_peer.py ``AutopilotPeer``:
armed, GUIDED, hovering at 1.5 m, with ATTITUDE + LOCAL_POSITION_NED, the measured velocity without
which a goal policy never engages). Each revolution is 75 real VLP-16 data packets at
0.2° (28,800 returns); its azimuth wraps inside the last packet, so the companion can finish the
revolution only once that packet is in. Per revolution this script records

    last packet sent → SET_POSITION_TARGET_LOCAL_NED received   (the latency the companion adds)
    first packet sent → setpoint received                         (including the packets' own transfer)

The arrival time is the kernel's receive timestamp of the setpoint datagram (SO_TIMESTAMPNS), so
this script's own scheduling delays do not count against the companion; send times are taken just
before each ``sendto``. ``--realtime`` runs the companion SCHED_FIFO as its systemd unit does.
Prints p50/p99/max over ``--revolutions`` (default 1,000), plus the companion's resident
memory (VmRSS, and the peak VmHWM) and its CPU time per revolution. ``--pacing sensor`` (default)
spreads the 75 packets over the revolution as the sensor does (one every 1.33 ms at 10 Hz);
``--pacing burst`` sends them back to back, the worst case where all decoding follows the last one.
Targets (issue 3): p99 ≤ 2 ms, resident memory ≤ 150 MB. ``--recording compare`` measures the
flight recorder's cost in the same run: four alternating blocks of ``--revolutions``/4 without and
with ``[recorder]`` on (as shipped: no point cloud; ``--cloud-decimation N`` adds one), then the
ratio of the two p99s; ``--shield compare`` the same for the shield's lane (the default) against
its ±30° sectors (the vehicle hovers here, so the lane sweeps the nose alone, not a travel arc:
``bench/bench_shield.py`` times both with motion); ``--tracking compare`` the same for the scan
tracker (``[tracking]``) off and on, in a scene with something to track (four pillars and a walker
crossing 3 m ahead at 1 m/s, before the room's walls) and a fixed goal 30 m ahead, so that the
tracker has the autopilot's position (without a goal source it tracks nothing) and the route's
map runs in both.

    /work/venv/bin/python bench/bench_companion.py [--revolutions 1000] [--rate 10]
        [--pacing sensor|burst] [--decoder numpy|velodyne-decoder] [--realtime]
        [--recording off|on|compare] [--cloud-decimation N] [--shield lane|sectors|compare]
        [--tracking compare]
"""

from __future__ import annotations

import argparse
import os
import re
import select
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from companion.lidar.vlp16_packet import PACKET_DURATION_US, encode_packets  # noqa: E402
from tests.companion.mavlink_peer import SETPOINT, SO_TIMESTAMPNS, AutopilotPeer, free_udp_port  # noqa: E402
from tests.onnx_models import write_policy  # noqa: E402

FIRINGS = 1800  # 0.2° steps: 75 packets, 28,800 returns
STEP_DEG = 0.2


#: (forward, right) m of the pillars of ``--tracking compare``'s scene, and their radius
PILLARS = ((2.0, 1.5), (-1.0, 2.5), (-2.5, -1.0), (1.5, -3.0))
PILLAR_RADIUS = 0.3


def _circle(azimuth: np.ndarray, forward: float, right: float, radius: float) -> np.ndarray:
    """Range along each azimuth (degrees clockwise from the front) to a circle centred (forward,
    right) m from the sensor, inf where the ray misses it."""
    a = np.radians(azimuth)
    along = forward * np.cos(a) + right * np.sin(a)
    inside = radius**2 - (right * np.cos(a) - forward * np.sin(a)) ** 2
    return np.where((inside > 0.0) & (along > 0.0), along - np.sqrt(np.maximum(inside, 0.0)), np.inf)


def revolution(index: int, objects: bool = False) -> list[bytes]:
    """75 packets of one whole revolution; the wrap falls inside the last packet (its 13th firing).

    :param objects: pillars and a walker crossing 3 m ahead at 1 m/s (4 m and round again) before
        the walls
    """
    azimuth = (STEP_DEG * 12 + STEP_DEG * np.arange(FIRINGS)) % 360.0
    per_azimuth = 5.0 + 3.0 * np.sin(np.radians(azimuth))
    if objects:
        for forward, right in PILLARS:
            per_azimuth = np.minimum(per_azimuth, _circle(azimuth, forward, right, PILLAR_RADIUS))
        walker = -2.0 + (0.1 * index) % 4.0
        per_azimuth = np.minimum(per_azimuth, _circle(azimuth, 3.0, walker, 0.3))
    ranges = np.repeat(per_azimuth[:, None], 16, axis=1)
    return encode_packets(azimuth, ranges, start_timestamp_us=index * 75 * PACKET_DURATION_US)


def proc_status(pid: int) -> dict[str, int]:
    """VmRSS / VmHWM of a process in kB."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(value.split()[0])
    return out


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


class Autopilot:
    """This process's end of the MAVLink link: plays an ArduPilot Copter, catches setpoints.

    The status streams are the process tests' (:class:`AutopilotPeer`, what ``SimulatedAutopilot``
    sends every period), so the bench engages under whatever the companion's default config needs:
    a goal policy flies only on a fresh measured velocity, LOCAL_POSITION_NED turned into the body
    frame by a fresh ATTITUDE heading. Single-threaded (unlike ``SimulatedAutopilot``, whose thread
    would stamp setpoints late by its GIL waits): it sends between revolutions only and reads the
    setpoint's kernel receive timestamp itself.
    """

    def __init__(self, port: int) -> None:
        self.peer = AutopilotPeer(f"udpout:127.0.0.1:{port}")  # ArduPilot Copter, system 1 component 1
        self.conn = self.peer.conn
        self.sock = self.conn.port
        self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        self.last_status = 0.0

    def status(self) -> None:
        """Heartbeat and status streams, at most every 0.1 s (between revolutions only): armed,
        GUIDED, in the air at 1.5 m, climb settled, hovering (zero velocity, heading north)."""
        now = time.monotonic()
        if now - self.last_status < 0.1:
            return
        self.last_status = now
        self.peer.heartbeat()
        self.peer.flying()

    def wait_setpoint(self, timeout: float) -> float | None:
        """When a SET_POSITION_TARGET_LOCAL_NED datagram reached this socket (kernel receive
        timestamp, CLOCK_REALTIME seconds: not delayed by this process's own scheduling), or None.
        """
        deadline = time.monotonic() + timeout
        parser = self.conn.mav
        while (remaining := deadline - time.monotonic()) > 0:
            if not select.select([self.sock], [], [], remaining)[0]:
                return None
            data, ancillary, _flags, _addr = self.sock.recvmsg(4096, 64)
            arrived = time.time()
            for level, kind, payload in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    seconds, nanoseconds = struct.unpack("qq", payload[:16])
                    arrived = seconds + nanoseconds * 1e-9
            for msg in parser.parse_buffer(data) or ():
                if msg.get_type() == SETPOINT:
                    return arrived
        return None

    def drain(self) -> None:
        while select.select([self.sock], [], [], 0)[0]:
            self.sock.recvfrom(4096)


def percentiles(values_ms: list[float]) -> str:
    a = np.asarray(values_ms)
    return f"p50 {np.percentile(a, 50):.3f} ms  p99 {np.percentile(a, 99):.3f} ms  max {a.max():.3f} ms"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--revolutions", type=int, default=1000)
    parser.add_argument("--rate", type=float, default=10.0, help="revolutions per second (VLP-16: 5-20)")
    parser.add_argument("--decoder", default="numpy", choices=("numpy", "velodyne-decoder"))
    parser.add_argument(
        "--realtime", action="store_true",
        help="run the companion SCHED_FIFO priority 20, as systemd/lidar-avoid-companion.service does "
             "(needs root; keeps other load on the machine from delaying it)",
    )
    parser.add_argument(
        "--pacing", default="sensor", choices=("sensor", "burst"),
        help="sensor: packets spread over the revolution as the VLP-16 sends them; "
             "burst: all 75 at once (worst case: everything is decoded after the last packet)",
    )
    parser.add_argument(
        "--recording", default="off", choices=("off", "on", "compare"),
        help="the flight recorder ([recorder]) off, on, or compare: alternate blocks without and with "
             "it in this run, and print the p99 ratio",
    )
    parser.add_argument("--cloud-decimation", type=int, default=0,
                        help="recorder.cloud_decimation when recording (0: no cloud, as shipped)")
    parser.add_argument(
        "--shield", default="lane", choices=("lane", "sectors", "compare"),
        help="the shield's forward cap over its lane ([shield] lane_half_width, the default) or the "
             "±30° sectors (lane_half_width = 0), or compare: alternate blocks of both in this run",
    )
    parser.add_argument(
        "--tracking", default="default", choices=("default", "compare"),
        help="compare: alternate blocks with [tracking] off and on in this run, in a scene with "
             "pillars and a walker and a fixed goal (the tracker needs the autopilot's position)",
    )
    args = parser.parse_args()
    compared = [args.recording == "compare", args.shield == "compare", args.tracking == "compare"]
    if sum(compared) > 1:
        parser.error("compare one thing at a time: --recording, --shield or --tracking compare")
    if args.recording == "compare":
        variants = {"recording off": Variant(False, args.shield), "recording on": Variant(True, args.shield)}
    elif args.shield == "compare":
        on = args.recording == "on"
        variants = {"shield sectors": Variant(on, "sectors"), "shield lane": Variant(on, "lane")}
    elif args.tracking == "compare":
        on = args.recording == "on"
        variants = {"tracking off": Variant(on, args.shield, tracking=False),
                    "tracking on": Variant(on, args.shield, tracking=True)}
    else:
        variant = Variant(args.recording == "on", args.shield)
        print_result(args, run_companion(args, args.revolutions, variant), f", {variant}")
        return 0
    # Alternate blocks, so load that comes and goes on the machine falls on both alike.
    blocks = 4
    results: dict[str, list[Result]] = {label: [] for label in variants}
    for i in range(blocks):
        label = list(variants)[i % 2]
        results[label].append(run_companion(args, args.revolutions // blocks, variants[label]))
    merged = {label: Result.merge(parts) for label, parts in results.items()}
    for label in variants:
        print_result(args, merged[label], f", {label}")
    (base, base_result), (other, other_result) = merged.items()
    a, b = (float(np.percentile(r.from_last, 99)) for r in (base_result, other_result))
    print(f"{other} against {base}: p99 last packet -> setpoint {b:.3f} ms / {a:.3f} ms = {b / a:.2f}x; "
          f"records dropped {other_result.dropped}")
    return 0


@dataclass(frozen=True)
class Variant:
    """What one companion run is configured with: the flight recorder on or off, the shield's
    forward cap (``lane``: the default; ``sectors``: ``[shield] lane_half_width = 0``), and the
    scan tracker (None: the default config, without a goal source and the scene without objects;
    False/True: ``[tracking] enabled``, with a fixed goal and the scene with pillars and a walker)."""

    recording: bool
    shield: str
    tracking: bool | None = None

    def __str__(self) -> str:
        tracking = "" if self.tracking is None else f", tracking {'on' if self.tracking else 'off'}"
        return f"recording {'on' if self.recording else 'off'}, shield {self.shield}{tracking}"


@dataclass
class Result:
    """One companion run's measurements."""

    from_last: list[float]
    from_first: list[float]
    missed: int
    cpu: float
    memory: dict[str, int]
    dropped: int = 0

    @staticmethod
    def merge(parts: list[Result]) -> Result:
        return Result(
            [x for p in parts for x in p.from_last], [x for p in parts for x in p.from_first],
            sum(p.missed for p in parts), sum(p.cpu for p in parts),
            {k: max(p.memory[k] for p in parts) for k in parts[0].memory}, sum(p.dropped for p in parts),
        )


def run_companion(args: argparse.Namespace, revolutions: int, variant: Variant) -> Result:
    """Start the companion, engage it, measure ``revolutions`` revolutions, stop it."""
    tmp = Path(tempfile.mkdtemp(prefix="bench-companion-"))
    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    model = write_policy(tmp / "steer.onnx", kind="steer")
    config = tmp / "companion.toml"
    recorder = (f'[recorder]\nenabled = true\ndirectory = "{tmp / "flights"}"\n'
                f"cloud_decimation = {args.cloud_decimation}\n" if variant.recording else "")
    shield = "[shield]\nlane_half_width = 0.0\n" if variant.shield == "sectors" else ""
    tracking = ""
    if variant.tracking is not None:  # a fixed goal 30 m north: the autopilot's position is asked for
        tracking = (f"[tracking]\nenabled = {str(variant.tracking).lower()}\n"
                    "[goal]\nsource = \"fixed\"\n[[goal.waypoints]]\nnorth = 30.0\ndown = -1.5\n")
    config.write_text(
        f'[lidar.velodyne]\nhost = "127.0.0.1"\nport = {lidar_port}\ndecoder = "{args.decoder}"\n'
        f'[policy]\nmodel = "{model}"\n'
        "[supervisor]\nclimb_settled_time = 0.3\n"
        f'[autopilot]\nconnect = "udpin:127.0.0.1:{mavlink_port}"\n'
        "[runtime]\nlog_interval = 3600.0\n" + recorder + shield + tracking
    )
    autopilot = Autopilot(mavlink_port)
    command = [sys.executable, "-m", "companion", "run", "--config", str(config)]
    if args.realtime:
        command = ["chrt", "--reset-on-fork", "--fifo", "20", *command]  # as the unit: ResetOnFork
    proc = subprocess.Popen(
        command,
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )
    lidar = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    target = ("127.0.0.1", lidar_port)
    period = 1.0 / args.rate
    from_last: list[float] = []
    from_first: list[float] = []
    missed = 0
    engaged = False
    index = 0
    cpu_start = 0.0
    try:
        time.sleep(1.0)  # model load, sockets bound
        deadline = time.monotonic() + 30
        while len(from_last) < revolutions:
            if proc.poll() is not None:
                raise SystemExit(f"companion exited: {proc.communicate()[1][-2000:]}")
            packets = revolution(index, objects=variant.tracking is not None)
            index += 1
            autopilot.status()
            autopilot.drain()  # heartbeats, OBSTACLE_DISTANCE, ... of the previous revolution
            start = time.monotonic()
            t_first = time.time()  # CLOCK_REALTIME, the clock of the kernel receive timestamps
            gap = period / len(packets) if args.pacing == "sensor" else 0.0
            t_last = t_first
            for i, packet in enumerate(packets):
                if gap:
                    while time.time() < t_first + i * gap:
                        pass  # spin: sleep() is far too coarse for 1.3 ms gaps
                # Stamped before the call: on loopback the receiver may run inside this sendto.
                t_last = time.time()
                lidar.sendto(packet, target)
            arrived = autopilot.wait_setpoint(timeout=0.05)
            if not engaged:
                if arrived is not None:
                    engaged = True
                    cpu_start = cpu_seconds(proc.pid)
                    print(f"engaged after {index} revolutions; measuring {revolutions}", flush=True)
                elif time.monotonic() > deadline:
                    proc.terminate()
                    raise SystemExit("the companion never engaged: " + proc.communicate()[1][-2000:])
            elif arrived is None:
                missed += 1
            else:
                from_last.append((arrived - t_last) * 1e3)
                from_first.append((arrived - t_first) * 1e3)
            if not gap:
                time.sleep(max(0.0, period - (time.monotonic() - start)))
        cpu = cpu_seconds(proc.pid) - cpu_start
        memory = proc_status(proc.pid)
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            _, log = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            log = ""
        lidar.close()
    dropped = re.findall(r"flight recorder: written=\d+ dropped=(\d+)", log)
    return Result(from_last, from_first, missed, cpu, memory, int(dropped[-1]) if dropped else 0)


def print_result(args: argparse.Namespace, result: Result, label: str = "") -> None:
    from_last, from_first, missed, cpu, memory = (result.from_last, result.from_first, result.missed,
                                                   result.cpu, result.memory)

    n = len(from_last)
    print(f"companion end to end, {n} revolutions of 28,800 points (75 VLP-16 packets), "
          f"{args.rate:g} Hz, {args.pacing} pacing, decoder {args.decoder}"
          f"{', companion SCHED_FIFO 20' if args.realtime else ''}{label}; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs:")
    print(f"  last packet -> setpoint:  {percentiles(from_last)}   (target p99 <= 2 ms)")
    if from_last:  # against the 100 ms scan period the same setpoints have to fit in
        p99 = float(np.percentile(from_last, 99))
        period = 1.0 / args.rate
        print(f"  p99 / scan period {period * 1e3:.0f} ms: {p99 / (period * 1e3):.1%} of the period")
    print(f"  first packet -> setpoint: {percentiles(from_first)}")
    print(f"  setpoints missing: {missed}")
    print(f"  CPU time per revolution: {cpu / max(n + missed, 1) * 1e3:.2f} ms")
    print(f"  resident memory: {memory['VmRSS'] / 1024:.1f} MB (peak {memory['VmHWM'] / 1024:.1f} MB)"
          "   (target <= 150 MB)")



if __name__ == "__main__":
    sys.exit(main())
