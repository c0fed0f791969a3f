"""The flight recorder's writer: rotation, the size budget, drops, a full disk, an unwritable
directory; the loop's side (taps, the pilot's notice); replay finding the first difference.

Real files, a real tmpfs for the full disk (mounted when the tests run as root, as they do here and
in CI), the real companion process for the unwritable directory.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from companion.perception.scan import N_BINS
from companion.recording import schemas as s
from companion.recording.messages import point_cloud
from companion.recording.reader import read_recording, setpoints
from companion.recording.recorder import FlightRecorder
from companion.recording.taps import tap_parts
from companion.recording.writer import CHUNK_SIZE, FILE_GLOB, McapSink
from tests.companion.companion_process import (
    WEST_AND_UP,
    LidarSender,
    free_udp_port,
    start_companion,
    stop,
    write_config,
)
from tests.companion.mavlink_peer import SETPOINT, SimulatedAutopilot
from tests.onnx_models import write_policy

REPO = Path(__file__).resolve().parents[2]
POSE = {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}


def noise_cloud(seed: int, n: int = 4000) -> np.ndarray:
    """Incompressible points: file sizes then follow the data, not zstd's luck."""
    return np.random.default_rng(seed).normal(size=(n, 3)).astype(np.float32)


@contextlib.contextmanager
def tiny_tmpfs(path: Path, size_kb: int) -> Iterator[Path]:
    """A real, small filesystem that fills up (needs root to mount)."""
    path.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size_kb}k", "tmpfs", str(path)], capture_output=True, text=True
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({done.stderr.strip() or 'not root'})")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


def test_files_rotate_and_the_directory_stays_within_the_budget(tmp_path):
    old = tmp_path / "flight-20200101-000000-1-000.mcap"  # an earlier flight's recording
    old.write_bytes(b"x" * 900_000)
    os.utime(old, (1, 1))
    keep = tmp_path / "notes.txt"  # not a recording: never deleted
    keep.write_text("pilot notes")
    budget, file_bytes = 3_000_000, 4 * CHUNK_SIZE + 100_000
    sink = McapSink(tmp_path, budget, file_bytes, {"format": "1"}, queue_size=10_000)
    for i in range(150):  # ~7 MB of clouds: more than twice the budget
        sink.submit(s.CLOUD, 100.0 + i * 0.1, point_cloud, noise_cloud(i), POSE, seq=i + 1)
    sink.close()
    assert sink.failure is None and sink.dropped == 0 and sink.written == 150
    assert len(sink.files) >= 5, "rotation did not happen"
    assert old in sink.deleted and not old.exists() and keep.exists()
    remaining = sorted(tmp_path.glob(FILE_GLOB))
    assert sum(p.stat().st_size for p in remaining) <= budget
    assert all(p.stat().st_size <= file_bytes + 20_000 for p in remaining)  # + the summary section
    # each remaining part is a whole MCAP file on its own, with the metadata
    seqs = []
    for p in remaining:
        with open(p, "rb") as f:
            reader = make_reader(f)
            assert [md.name for md in reader.iter_metadata()] == [s.METADATA_NAME]
            seqs += [msg.sequence for _, _, msg in reader.iter_messages()]
    assert seqs == list(range(seqs[0], 151)), "the newest records are kept, in order, without a gap"


def test_a_full_queue_drops_and_counts_and_never_blocks(tmp_path):
    release = threading.Event()

    def slow(t, i):  # the writer thread stalls (a slow disk)
        release.wait(5)
        return {"timestamp": {"sec": 0, "nsec": 0}, "forward": float(i), "yaw_rate": 0.0}

    sink = McapSink(tmp_path, 10**8, 10**7, {}, queue_size=8)
    for i in range(200):
        sink.submit(s.SETPOINT, float(i), slow, i)  # would hang here if submit waited
    release.set()
    sink.close()
    assert sink.dropped >= 200 - 8 - 1
    assert sink.dropped + sink.written == 200


def test_a_full_disk_stops_recording_with_its_reason_and_keeps_what_was_written(tmp_path):
    with tiny_tmpfs(tmp_path / "disk", 600) as disk:
        sink = McapSink(disk, 10**9, 10**8, {"format": "1"}, queue_size=10_000)
        for i in range(400):
            sink.submit(s.CLOUD, 1.0 + i * 0.1, point_cloud, noise_cloud(i, 1000), POSE, seq=i + 1)
        deadline = time.monotonic() + 20
        while sink.failure is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert sink.failure is not None and "No space left on device" in sink.failure
        written = sink.written
        sink.submit(s.CLOUD, 99.0, point_cloud, noise_cloud(0), POSE)  # after the failure: ignored
        sink.close()
        assert sink.written == written
        rec = read_recording(sink.files[0])
        assert rec.truncated and 0 < len(rec.topic(s.CLOUD.topic)) < 400


class FakeLink:
    """Stands in for the autopilot link in this unit test of the taps' pure bookkeeping."""

    def __init__(self):
        self.texts = []
        self.counters = {}
        self.status = type("Status", (), {"heartbeat_time": None})()

    def poll(self):
        return self.status

    def send_statustext(self, text, severity):
        self.texts.append((text, severity))

    def send_velocity(self, forward, yaw_rate, lateral=0.0, vertical=0.0):
        pass


def test_an_unusable_directory_is_told_to_the_pilot_once_the_autopilot_is_there():
    recorder = FlightRecorder(None, time.monotonic, 10.0, POSE, notice="recording off: Not a directory")
    link = FakeLink()
    tapped = tap_parts(recorder, link=link)["link"]
    tapped.poll()
    assert link.texts == [], "no autopilot yet: nobody to tell"
    link.status.heartbeat_time = 1.0
    tapped.poll()
    tapped.poll()
    assert link.texts == [("recording off: Not a directory", 4)]
    tapped.send_velocity(1.0, 0.0)  # recording is off: the taps pass everything through
    assert not recorder.active


def test_the_companion_flies_on_when_its_recording_directory_cannot_be_made(tmp_path):
    """The real process: the directory's parent is a file, so nothing can be written, even as root."""
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("")
    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    model = write_policy(tmp_path / "forward.onnx", kind="forward")
    config = write_config(
        tmp_path,
        model,
        lidar_port,
        mavlink_port,
        extra=f'[recorder]\nenabled = true\ndirectory = "{blocker}/flights"\n',
    )
    vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{mavlink_port}")
    proc = start_companion(config)
    lidar = LidarSender(lidar_port)
    try:
        lidar.on = True
        text = vehicle.wait_for("STATUSTEXT", timeout=40, condition=lambda msg: "recording off" in msg.text)
        assert text is not None and "Not a directory" in text.text
        assert vehicle.wait_for(SETPOINT, timeout=10) is not None
        t = time.monotonic()
        time.sleep(1.5)
        assert len(vehicle.times(SETPOINT, since=t)) >= 10
    finally:
        lidar.close()
        code, _, err = stop(proc)
        vehicle.close()
    assert code == 0, err[-3000:]


def _record_companion(
    tmp_path: Path,
    setpoints: int = 25,
    recorder: str = "",
    parts: int = 1,
    extra: str = "",
    kind: str = "steer",
    room_m: float | None = None,
    params: dict[str, float] | None = None,
    scene=None,
) -> list[Path]:
    """A short recording of the real companion process (constant lidar, the ``kind`` policy, config
    ``extra``), ended once the autopilot has had ``setpoints`` setpoints and the recorder has begun
    ``parts`` files (how fast a part fills depends on how well the cloud compresses); its files,
    oldest first.

    :param room_m: the lidar's round room's radius (default: the sender's 8 m)
    :param params: the autopilot's parameters (for a ``[params_check]`` in ``extra``)
    :param scene: the lidar's scene instead (:func:`revolution_packets`), asked once a revolution
    """
    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    model = write_policy(tmp_path / f"{kind}.onnx", kind=kind)
    recording = f'[recorder]\nenabled = true\ndirectory = "{tmp_path}/rec"\n{recorder}\n'
    config = write_config(tmp_path, model, lidar_port, mavlink_port, extra=recording + extra)
    vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{mavlink_port}")
    vehicle.params = dict(params or {})
    proc = start_companion(config)
    lidar = LidarSender(lidar_port)
    if room_m is not None:
        lidar.scene = lambda azimuth: np.full(azimuth.shape, room_m)
    if scene is not None:
        lidar.scene = scene
    try:
        lidar.on = True
        deadline = time.monotonic() + 40
        while (
            len(vehicle.times(SETPOINT)) < setpoints or len(list((tmp_path / "rec").glob(FILE_GLOB))) < parts
        ):
            assert time.monotonic() < deadline, "too few setpoints or recording parts from the companion"
            time.sleep(0.1)
    finally:
        lidar.close()
        code, _, err = stop(proc)
        vehicle.close()
    assert code == 0, err[-3000:]
    return sorted((tmp_path / "rec").glob(FILE_GLOB))


def _with_one_action_changed(src: Path, dst: Path, index: int) -> None:
    """Copy a recording, the ``index``-th policy action moved by one float32 ulp."""

    def change(topic: str, data: bytes, n: int) -> bytes:
        if topic != s.POLICY.topic or n != index:
            return data
        step = json.loads(data)
        step["action"][0] = float(np.nextafter(np.float32(step["action"][0]), np.float32(2)))
        return json.dumps(step).encode()

    _copy_recording(src, dst, change)


def _as_before_the_vertical_speed(src: Path, dst: Path) -> None:
    """Copy a recording as the recorder wrote it before setpoints had ``vertical``: without the
    field, under the schema of then."""

    def old_schema(name: str, data: bytes) -> bytes:
        if name != "lidar_avoid.Setpoint":
            return data
        schema = json.loads(data)
        del schema["properties"]["vertical"]
        schema["required"].remove("vertical")
        return json.dumps(schema).encode()

    def strip(topic: str, data: bytes, _n: int) -> bytes:
        if topic != s.SETPOINT.topic:
            return data
        msg = json.loads(data)
        del msg["vertical"]
        return json.dumps(msg).encode()

    _copy_recording(src, dst, strip, old_schema)


def _with_one_lateral_changed(src: Path, dst: Path, index: int) -> None:
    """Copy a recording, the ``index``-th shield output's sideways part moved by one float64 ulp."""

    def change(topic: str, data: bytes, n: int) -> bytes:
        if topic != s.SHIELD.topic or n != index:
            return data
        step = json.loads(data)
        step["output"]["lateral"] = float(np.nextafter(step["output"]["lateral"], 2.0))
        return json.dumps(step).encode()

    _copy_recording(src, dst, change)


def _as_before_the_lateral(src: Path, dst: Path) -> None:
    """Copy a recording as the recorder wrote it before /shield had ``lateral``: the requested and
    output commands without it, under the schema of then."""

    def old_schema(name: str, data: bytes) -> bytes:
        if name != "lidar_avoid.ShieldStep":
            return data
        schema = json.loads(data)
        for part in ("requested", "output"):
            del schema["properties"][part]["properties"]["lateral"]
            schema["properties"][part]["required"].remove("lateral")
        return json.dumps(schema).encode()

    def strip(topic: str, data: bytes, _n: int) -> bytes:
        if topic != s.SHIELD.topic:
            return data
        msg = json.loads(data)
        for part in ("requested", "output"):
            del msg[part]["lateral"]
        return json.dumps(msg).encode()

    _copy_recording(src, dst, strip, old_schema)


def _as_before_the_yaw_cap(src: Path, dst: Path) -> None:
    """Copy a recording as the recorder wrote it before the metadata had the yaw cap read."""

    def old_metadata(name: str, metadata: dict[str, str]) -> dict[str, str]:
        return {k: v for k, v in metadata.items() if name != s.METADATA_NAME or k != "autopilot_yaw_rate"}

    _copy_recording(src, dst, lambda _topic, data, _n: data, metadata=old_metadata)


def _copy_recording(
    src: Path, dst: Path, message, schema=lambda _name, data: data, metadata=lambda _name, md: md
) -> None:
    """Copy an MCAP file record by record: ``message(topic, data, n)`` (n: the topic's n-th message,
    from 1), ``schema(name, data)`` and ``metadata(name, map)`` give what is written."""
    with open(src, "rb") as f, open(dst, "wb") as out:
        reader = make_reader(f)
        writer = Writer(out)
        writer.start()
        for md in reader.iter_metadata():
            writer.add_metadata(md.name, metadata(md.name, dict(md.metadata)))
        ids: dict[str, int] = {}
        counts: dict[str, int] = {}
        for mcap_schema, channel, msg in reader.iter_messages():
            if channel.topic not in ids:
                sid = writer.register_schema(
                    mcap_schema.name, mcap_schema.encoding, schema(mcap_schema.name, mcap_schema.data)
                )
                ids[channel.topic] = writer.register_channel(channel.topic, channel.message_encoding, sid)
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            data = message(channel.topic, msg.data, counts[channel.topic])
            writer.add_message(ids[channel.topic], msg.log_time, data, msg.publish_time, msg.sequence)
        writer.finish()


def _replay(path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "companion", "replay", str(path), *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_replay_matches_bit_for_bit_and_finds_a_one_ulp_difference(tmp_path):
    (path,) = _record_companion(tmp_path)
    rec = read_recording(path)
    assert not rec.truncated
    assert len(rec.topic(s.POLICY.topic)) >= 20 and len(rec.topic(s.SHIELD.topic)) >= 10
    # the scans the replay starts from (no cloud recorded) are the recorded observations' newest
    same = _replay(path)
    assert same.returncode == 0, same.stdout + same.stderr
    assert "matches bit for bit" in same.stdout and "from the recorded scans" in same.stdout

    tampered = tmp_path / "tampered.mcap"
    _with_one_action_changed(path, tampered, index=7)
    diff = _replay(tampered)
    assert diff.returncode == 1, diff.stdout + diff.stderr
    assert "first difference" in diff.stdout and "action 7:" in diff.stdout

    other = write_policy(tmp_path / "forward.onnx", kind="forward")
    plot = tmp_path / "whatif.png"
    what_if = _replay(path, "--policy", str(other), "--plot", str(plot))
    assert what_if.returncode == 0, what_if.stdout + what_if.stderr
    assert "what-if: forward.onnx" in what_if.stdout and "largest differences" in what_if.stdout
    assert plot.stat().st_size > 10_000


def test_replay_builds_the_shield_for_the_recorded_autopilot_and_the_yaw_cap_read_from_it(tmp_path):
    """ArduPilot, whose ATC_RATE_WPY_MAX the start-up check reads as 45 deg/s (neither the firmware
    default 60 nor the policy's 86), and a policy asking full speed and full yaw rate in a 2 m room:
    the read yaw cap and ArduPilot's stopping distance both bind, and the replay, building its shield
    from the recording, matches bit for bit. Without the recorded cap (a recording made before it
    was recorded) the replay assumes the firmware default, as the companion does when it reads none."""
    (tmp_path / "copter.parm").write_text("ATC_RATE_WPY_MAX 86\n")
    check = '[params_check]\nmode = "warn"\nfile = "copter.parm"\ntimeout = 5.0\n'
    (path,) = _record_companion(
        tmp_path,
        setpoints=30,
        extra=check,
        kind="forward_left",
        room_m=2.0,
        params={"ATC_RATE_WPY_MAX": 45.0},
    )
    rec = read_recording(path)
    assert json.loads(rec.metadata[s.METADATA_NAME]["config"])["autopilot"]["type"] == "ardupilot"
    assert float(rec.metadata[s.METADATA_NAME]["autopilot_yaw_rate"]) == math.radians(45.0)
    steps = [msg for _, msg in rec.topic(s.SHIELD.topic)]
    assert len(steps) >= 20 and steps[-1]["requested"]["yaw_rate"] == 1.5
    assert steps[-1]["output"]["yaw_rate"] == math.radians(45.0)
    assert "stopping_distance" in steps[-1]["limits"]
    held = {step["output"]["forward"] for step in steps[-5:]}  # the speed the stopping distance allows
    assert len(held) == 1 and 1.0 < held.pop() < steps[-1]["requested"]["forward"]

    same = _replay(path)
    assert same.returncode == 0 and "matches bit for bit" in same.stdout, same.stdout + same.stderr

    before = tmp_path / "before-yaw-cap.mcap"
    _as_before_the_yaw_cap(path, before)
    default = _replay(before)
    assert default.returncode == 1, default.stdout + default.stderr
    assert "first difference" in default.stdout and "shield output recorded" in default.stdout


def test_the_shield_record_carries_the_sideways_part_and_older_recordings_replay_as_before(tmp_path):
    """A sideways policy: /shield records the lateral speed asked and let through, the replay checks
    it (one ulp off is found), and the same recording as the recorder wrote it before ``lateral``
    existed still replays bit for bit, comparing what it holds."""
    (path,) = _record_companion(tmp_path, kind="slide_left")
    rec = read_recording(path)
    schema = json.loads(rec.schema_data[s.SHIELD.topic])
    assert all("lateral" in schema["properties"][part]["required"] for part in ("requested", "output"))
    steps = [msg for _, msg in rec.topic(s.SHIELD.topic)]
    assert len(steps) >= 10 and all(step["requested"]["lateral"] == 1.0 for step in steps)
    lateral = [step["output"]["lateral"] for step in steps]
    assert 0.0 < lateral[0] < lateral[1] < lateral[-1] == 1.0  # ramped up at max_accel
    same = _replay(path)
    assert same.returncode == 0 and "matches bit for bit" in same.stdout, same.stdout + same.stderr

    tampered = tmp_path / "tampered.mcap"
    _with_one_lateral_changed(path, tampered, index=3)
    diff = _replay(tampered)
    assert diff.returncode == 1, diff.stdout + diff.stderr
    assert "shield output recorded" in diff.stdout and repr(lateral[2]) in diff.stdout

    before = tmp_path / "before-lateral.mcap"
    _as_before_the_lateral(path, before)
    old = _replay(before)
    assert old.returncode == 0 and "matches bit for bit" in old.stdout, old.stdout + old.stderr
    other = write_policy(tmp_path / "forward.onnx", kind="forward")
    what_if = _replay(before, "--policy", str(other), "--plot", str(tmp_path / "whatif.png"))
    assert what_if.returncode == 0, what_if.stdout + what_if.stderr
    assert "lateral not recorded" in what_if.stdout


def test_setpoints_record_the_vertical_speed_and_older_recordings_read_as_before(tmp_path):
    """A fixed waypoint 2 m above: the climb the link sends (vz, down-positive) is in the setpoint
    record, and the report shows it. The same recording as the recorder wrote it before
    ``vertical`` existed still replays bit for bit, and reads with the vertical speed unknown."""
    from flightsim.sitl.recording_report import flight_series, summary

    (path,) = _record_companion(tmp_path, extra=WEST_AND_UP)
    rec = read_recording(path)
    assert rec.schemas[s.SETPOINT.topic] == "lidar_avoid.Setpoint"
    assert "vertical" in json.loads(rec.schema_data[s.SETPOINT.topic])["required"]
    sent = setpoints(rec)
    assert sent.shape[1] == 5 and not np.isnan(sent).any()
    # 2 m below the waypoint: a climb at goal.max_vertical_speed (0.5 m/s) beside the policy's command
    assert np.sum(np.isclose(sent[:, 4], 0.5)) >= 10 and sent[:, 4].min() >= 0.0
    assert "vertical setpoint: climb up to 0.50 m/s" in "\n".join(summary(flight_series(rec)))

    before = tmp_path / "before-vertical.mcap"
    _as_before_the_vertical_speed(path, before)
    old = read_recording(before)
    assert len(setpoints(old)) == len(sent) and np.isnan(setpoints(old)[:, 4]).all()
    np.testing.assert_array_equal(setpoints(old)[:, :4], sent[:, :4])
    assert "vertical setpoint: not recorded" in "\n".join(summary(flight_series(old)))
    replay = _replay(before)
    assert replay.returncode == 0 and "matches bit for bit" in replay.stdout, replay.stdout + replay.stderr


def test_replay_of_a_file_that_is_not_a_recording_is_one_line_and_exit_2(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    done = subprocess.run(
        [sys.executable, "-m", "companion", "replay", str(junk)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert done.stderr.strip().count("\n") == 0 and "junk.mcap" in done.stderr


def test_recorder_config_is_checked_and_its_directory_is_relative_to_the_config(tmp_path, monkeypatch):
    from companion.common.errors import UserError
    from companion.config import default_recording_directory, load_config

    model = write_policy(tmp_path / "forward.onnx", kind="forward")
    path = tmp_path / "c.toml"
    path.write_text(f'[policy]\nmodel = "{model}"\n[recorder]\nenabled = true\n')
    assert load_config(path).recorder.directory == str(default_recording_directory())
    with pytest.raises(UserError, match=r"recorder.*file_mb"):
        load_config(
            path, ['recorder.directory="flights"', "recorder.file_mb=500.0", "recorder.budget_mb=100.0"]
        )
    path.write_text(f'[policy]\nmodel = "{model}"\n[recorder]\nenabled = true\ndirectory = "flights"\n')
    monkeypatch.chdir(tmp_path.parent)
    assert load_config(path).recorder.directory == str(tmp_path / "flights")


def test_the_recorder_and_replay_need_neither_foxglove_nor_matplotlib(tmp_path):
    """foxglove-sdk is an extra and matplotlib the simulator's: the companion's install has neither."""
    script = tmp_path / "blocked.py"
    script.write_text(
        "import importlib.abc, sys\n"
        "class Block(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('foxglove', 'matplotlib', 'jsonschema', 'flightsim'):\n"
        "            raise ImportError(name + ' is blocked')\n"
        "sys.meta_path.insert(0, Block())\n"
        "import companion.app, companion.replay, companion.recording.reader\n"
        "print('imported')\n"
    )
    done = subprocess.run([sys.executable, str(script)], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and "imported" in done.stdout, done.stderr


def test_a_later_part_of_a_rotated_recording_replays_on_its_own(tmp_path):
    """A part that starts mid-flight: the frame stack is taken from its first observation, and
    shield steps are checked from the shield's first reset in the part on (its state before the
    part is not in it)."""
    parts = _record_companion(
        tmp_path, setpoints=60, recorder="file_mb = 1.0\ncloud_decimation = 1\n", parts=4
    )

    def starts_mid_flight(path: Path) -> bool:
        steps = read_recording(path).topic(s.POLICY.topic)
        return bool(steps) and not steps[0][1]["reset"]

    # a whole 0.2° cloud fills a 1 MB part in a few revolutions: the first parts may hold the start's resets
    middle = next((p for p in parts[1:-1] if starts_mid_flight(p)), None)
    assert middle is not None, "no finished part starts mid-flight"
    done = _replay(middle)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "from the recorded clouds" in done.stdout and "matches bit for bit" in done.stdout
    assert "not checked" in done.stdout


def test_a_recording_from_before_the_goal_layout_replays_as_scan_only(tmp_path):
    """Recordings whose config has no policy.observation were made with scan-only models."""
    from types import SimpleNamespace

    from companion.replay import recorded_config

    def recording(policy: dict) -> SimpleNamespace:
        meta = {"format": s.FORMAT_VERSION, "config": json.dumps({"policy": {"model": "m.onnx", **policy}})}
        return SimpleNamespace(path=tmp_path / "f.mcap", metadata={s.METADATA_NAME: meta})

    assert recorded_config(recording({}))[0].policy.observation == "scan"
    assert recorded_config(recording({"observation": "goal"}))[0].policy.observation == "goal"


def test_the_recorded_yaw_cap_reads_back_exactly_and_is_none_when_not_read_or_not_recorded(tmp_path):
    from types import SimpleNamespace

    from companion.common.errors import UserError
    from companion.replay import recorded_autopilot_yaw_rate

    def recording(**meta: str) -> SimpleNamespace:
        return SimpleNamespace(path=tmp_path / "f.mcap", metadata={s.METADATA_NAME: meta})

    cap = math.radians(75.0)
    assert recorded_autopilot_yaw_rate(recording(autopilot_yaw_rate=repr(cap))) == cap
    assert recorded_autopilot_yaw_rate(recording(autopilot_yaw_rate="")) is None  # nothing was read
    assert recorded_autopilot_yaw_rate(recording()) is None  # recorded before the key existed
    with pytest.raises(UserError, match=r"f\.mcap: recorded autopilot_yaw_rate 'fast'"):
        recorded_autopilot_yaw_rate(recording(autopilot_yaw_rate="fast"))


def test_the_recorded_stopping_model_is_the_replays_and_older_recordings_get_the_limits_they_flew(tmp_path):
    """A recording replays with the stopping model its shield assumed, whatever this version's
    AUTOPILOT_LIMITS say (ArduPilot's changed from 0.7 s and 2.5 m/s² to the envelope's, issue 66)."""
    from types import SimpleNamespace

    from companion.common.errors import UserError
    from companion.replay import STOPPING_BEFORE_RECORDED, recorded_config
    from companion.safety.shield import AUTOPILOT_LIMITS

    def shield(autopilot: str, shield: dict | None = None, **meta: str):
        config = {"policy": {"model": "m.onnx"}, "autopilot": {"type": autopilot}, "shield": shield or {}}
        meta = {"format": s.FORMAT_VERSION, "config": json.dumps(config), **meta}
        rec = SimpleNamespace(path=tmp_path / "f.mcap", metadata={s.METADATA_NAME: meta})
        got = recorded_config(rec)[0].shield
        return got.max_decel, got.reaction_time

    assert shield("ardupilot", shield_stopping="3.0 1.1") == (3.0, 1.1)
    assert shield("ardupilot") == STOPPING_BEFORE_RECORDED["ardupilot"] == (2.5, 0.7)  # before the key
    assert shield("px4") == (AUTOPILOT_LIMITS["px4"].decel, AUTOPILOT_LIMITS["px4"].reaction_time)
    assert shield("ardupilot", shield_stopping="") == (0.0, 0.0)  # not given: this version's limits
    assert shield("px4", {"max_decel": 2.0}, shield_stopping="1.2 0.8") == (2.0, 0.8)  # the config's wins
    with pytest.raises(UserError, match=r"f\.mcap: recorded shield_stopping 'fast'"):
        shield("ardupilot", shield_stopping="fast")


# ---- what-if with shield settings changed (--set) ----------------------------------------------

#: the real ArduPilot/PX4 SITL flights with ground truth (``../shared`` beside the repository), as
#: tests/companion/test_envelope.py finds them
FLIGHTS = Path(os.environ.get("LIDAR_AVOID_SHARED", Path(__file__).resolve().parents[3] / "shared")) / (
    "fixtures/real-sitl-flights"
)
#: one of the four flights that ended in contact (flights.csv: collision True)
COLLISION_FLIGHT = "ardupilot-project-nav-narrow-gap.mcap"
#: the model the shared flights were flown with
FLOWN_MODEL = REPO / "models" / "policy.onnx"


def test_replay_set_takes_shield_keys_through_the_config_checks_and_names_a_bad_one():
    from companion.common.errors import UserError
    from companion.config import CompanionConfig
    from companion.replay import with_settings

    config = CompanionConfig()
    assert with_settings(config, []) == config  # the round trip through the loader changes nothing
    gated = with_settings(config, ["shield.backup_gate=true", "shield.max_speed = 1.5"])
    assert gated.shield.backup_gate is True and gated.shield.max_speed == 1.5
    assert config.shield.backup_gate is False and gated.policy == config.policy
    refused = {
        "shield.backup_gat=true": r"^--set shield\.backup_gat: unknown config key$",
        "shield.backup_gate=maybe": r"^--set shield\.backup_gate: expected true or false, got 'maybe'$",
        "shield.max_speed=fast": r"^--set shield\.max_speed: expected a number",
        "shield.max_speed=-1.0": r"^--set shield\.max_speed: -1\.0 is below the minimum",
        "policy.stack=2": r"^--set policy\.stack=2: expected shield\.KEY=VALUE",
        "shield.backup_gate": r"^--set shield\.backup_gate: expected shield\.KEY=VALUE",
    }
    for item, message in refused.items():
        with pytest.raises(UserError, match=message):
            with_settings(config, [item])


def test_the_contact_and_the_approach_figures_follow_the_harness_rule_and_the_last_seconds():
    from companion.replay import (
        CONTACT_RADIUS_M,
        TRUTH_STATE_TOPIC,
        Contact,
        Step,
        approach_figures,
        first_contact,
        least_clearance,
    )
    from flightsim.sitl.recording import TRUTH_STATE
    from flightsim.worlds.world import DEFAULT_VEHICLE_RADIUS

    assert CONTACT_RADIUS_M == DEFAULT_VEHICLE_RADIUS and TRUTH_STATE.topic == TRUTH_STATE_TOPIC

    def truth(t: float, clearance: float | None, z: float = 1.5) -> tuple[float, dict]:
        return t, {"clearance": clearance, "position": {"x": 0.0, "y": 0.0, "z": z}}

    # on the ground (the floor is near) and unknown do not count; the first in the air below 0.25 m does
    samples = [truth(1.0, 0.1, z=0.2), truth(2.0, None), truth(3.0, 0.26), truth(4.0, 0.24), truth(5.0, 0.2)]
    assert first_contact(samples) == Contact(4.0, 0.24)
    assert first_contact(samples[:3]) is None and least_clearance(samples[:3]) == 0.26

    def step(t: float, recorded: tuple[float, float], new: tuple[float, float]) -> Step:
        return Step(t, (recorded[0], 0.3, recorded[1]), (new[0], 0.3, new[1]), 1.0, [], [])

    steps = [
        step(1.0, (1.0, 0.0), (0.5, 0.0)),  # less, long before: the first
        step(7.5, (1.0, 0.0), (1.0, 0.0)),  # before the last 2 s
        step(8.5, (0.6, 0.8), (0.0, 0.6)),  # speed 1.0 vs 0.6: less
        step(9.0, (2.0, float("nan")), (2.0, 0.0)),  # lateral not recorded: 2.0 vs 2.0
        step(9.5, (-0.3, 0.4), (-0.3, 0.4)),  # 0.5 vs 0.5
        step(10.5, (3.0, 0.0), (0.0, 0.0)),  # after the contact: not counted
    ]
    a = approach_figures(steps, contact_t=10.0, window=2.0)
    assert a.first_less_s == pytest.approx(9.0) and a.last_less_s == pytest.approx(1.5)
    assert (a.less_in_window, a.in_window) == (1, 3)
    assert a.recorded_mean == pytest.approx((1.0 + 2.0 + 0.5) / 3) and a.recorded_max == 2.0
    assert a.new_mean == pytest.approx((0.6 + 2.0 + 0.5) / 3) and a.new_max == 2.0
    same = approach_figures([step(9.0, (1.0, 0.0), (1.0 - 1e-9, 0.0))], contact_t=10.0)
    assert same.first_less_s is None and same.less_in_window == 0  # float noise is not less


def test_replay_with_the_backup_gate_on_a_real_collision_flight_asks_less_before_the_contact(tmp_path):
    """The shared ArduPilot SITL flight that hit the narrow gap's wall: replayed as flown it matches
    bit for bit; with ``--set shield.backup_gate=true`` the gate asks for less speed on the way in
    (open loop: on the recorded path); with the gate as recorded (off) nothing differs; a bad key is
    one line naming it."""
    if not FLIGHTS.is_dir():
        pytest.skip(f"the real SITL recordings are not here: {FLIGHTS}")
    import re

    from companion.recording.recorder import file_digest

    flight = FLIGHTS / COLLISION_FLIGHT
    assert file_digest(FLOWN_MODEL) == read_recording(flight).metadata[s.METADATA_NAME]["model_sha256"]
    model = ("--policy", str(FLOWN_MODEL))

    same = _replay(flight, *model)
    assert same.returncode == 0 and "matches bit for bit" in same.stdout, same.stdout + same.stderr

    gated = _replay(flight, *model, "--set", "shield.backup_gate=true", "--plot", str(tmp_path / "gate.png"))
    assert gated.returncode == 0, gated.stdout + gated.stderr
    out = gated.stdout
    assert "what-if: shield.backup_gate=true" in out and "gate_slowed" in out
    assert "heading: not in the recording" in out  # neither /shield nor /vehicle/status holds it
    line = re.search(
        r"contact at t=([\d.]+) s .*first asked for less speed ([\d.]+) s before it .* on (\d+) of (\d+) "
        r"setpoints; .*mean ([\d.]+) vs ([\d.]+) m/s, max ([\d.]+) vs ([\d.]+) m/s",
        out,
    )
    assert line, out
    contact, first, less, count, rec_mean, new_mean, rec_max, new_max = map(float, line.groups())
    assert contact == pytest.approx(16.27, abs=0.05)  # the truth's first sample inside 0.25 m
    assert first > 3.0 and less >= count / 2
    assert new_mean < 0.6 * rec_mean and new_max <= rec_max

    ungated = _replay(flight, *model, "--set", "shield.backup_gate=false", "--plot", str(tmp_path / "no.png"))
    assert ungated.returncode == 0, ungated.stdout + ungated.stderr
    assert "|Δ forward| mean 0.000 max 0.000 m/s" in ungated.stdout
    assert "never asked for less speed" in ungated.stdout and "heading:" not in ungated.stdout

    bad = _replay(flight, *model, "--set", "shield.backup_gat=true")
    assert bad.returncode == 2 and bad.stdout == ""
    assert bad.stderr.strip().splitlines()[-1].endswith("--set shield.backup_gat: unknown config key")


class _Walker:
    """A walker 0.3 m in radius crossing 3 m ahead of a vehicle facing north, from 2 m west to 2 m
    east at 1 m/s and round again, in a round room of 8 m: each call is the next revolution's ranges
    (azimuth degrees clockwise from the front)."""

    def __init__(self) -> None:
        self.revolution = 0

    def __call__(self, azimuth_deg: np.ndarray) -> np.ndarray:
        east = -2.0 + (0.1 * self.revolution) % 4.0
        self.revolution += 1
        a = np.radians(azimuth_deg)
        north_dir, east_dir = np.cos(a), np.sin(a)
        along = 3.0 * north_dir + east * east_dir  # the ray's nearest approach to the walker's centre
        miss = (3.0 * east_dir - east * north_dir) ** 2
        inside = 0.3**2 - miss
        hit = np.where((inside > 0.0) & (along > 0.0), along - np.sqrt(np.maximum(inside, 0.0)), np.inf)
        return np.minimum(hit, 8.0)


def _with_one_track_moved(src: Path, dst: Path) -> None:
    """Copy a recording, the first moving track's x moved by one float64 ulp."""
    done = False

    def change(topic: str, data: bytes, _n: int) -> bytes:
        nonlocal done
        msg = json.loads(data)
        if topic != s.TRACKS.topic or done or not any(track["moving"] for track in msg["tracks"]):
            return data
        track = next(track for track in msg["tracks"] if track["moving"])
        track["x"] = float(np.nextafter(track["x"], math.inf))
        done = True
        return json.dumps(msg).encode()

    _copy_recording(src, dst, change)


def test_the_tracks_are_recorded_each_scan_and_replay_reproduces_them(tmp_path):
    """A walker crosses in front of the companion's vehicle (a fixed goal: the autopilot's position
    places the scans): every scan's tracker update goes to /tracks, with the walker moving and its
    bins marked, and to /tracks/scene; the replay runs the tracker again on what /tracks holds and
    matches it bit for bit, and finds a track moved by one ulp."""
    (path,) = _record_companion(tmp_path, setpoints=40, extra=WEST_AND_UP, scene=_Walker())
    rec = read_recording(path)
    updates = [msg for _, msg in rec.topic(s.TRACKS.topic)]
    assert len(updates) >= 30 and updates[0]["fresh"] and all(msg["pose"] for msg in updates)
    movers = [track for msg in updates for track in msg["tracks"] if track["moving"]]
    assert len(movers) >= 5, updates[-1]
    # the walker crosses at 1 m/s to the east (ENU x), 3 m north of the origin (y)
    assert np.median([t["vx"] for t in movers]) == pytest.approx(1.0, abs=0.3)
    assert np.median([t["y"] for t in movers]) == pytest.approx(3.0, abs=0.3)
    assert all(msg["moving_bins"] for msg in updates if any(t["moving"] for t in msg["tracks"]))
    scenes = [msg for _, msg in rec.topic(s.TRACK_SCENE.topic)]
    assert len(scenes) == len(updates) and any(e["arrows"] for msg in scenes for e in msg["entities"])
    same = _replay(path)
    assert same.returncode == 0, same.stdout + same.stderr
    assert f"{len(updates)} tracker updates" in same.stdout and "track matches bit for bit" in same.stdout

    tampered = tmp_path / "tampered.mcap"
    _with_one_track_moved(path, tampered)
    diff = _replay(tampered)
    assert diff.returncode == 1, diff.stdout + diff.stderr
    assert "first difference" in diff.stdout and "tracks recorded" in diff.stdout


def test_the_gated_shield_is_given_the_walker_and_replay_gives_it_again(tmp_path):
    """With the backup gate on, every shield call carries the tracker's moving bins and movers (the
    walker among them, in the body axes), and replay hands the recorded ones back to the shield as it
    took them: its outputs match bit for bit."""
    gate = WEST_AND_UP + "[shield]\nbackup_gate = true\n"
    (path,) = _record_companion(tmp_path, setpoints=40, extra=gate, scene=_Walker())
    steps = [msg for _, msg in read_recording(path).topic(s.SHIELD.topic)]
    assert steps and all(len(msg["extra"]["moving_bins"]) == N_BINS for msg in steps)
    movers = [m for msg in steps for m in msg["extra"]["movers"]]
    assert len(movers) >= 5, steps[-1]["extra"]
    # the walker crosses at 1 m/s: in the body axes, whichever way the vehicle faces
    assert np.median([np.hypot(*m["velocity"]) for m in movers]) == pytest.approx(1.0, abs=0.3)
    same = _replay(path)
    assert same.returncode == 0, same.stdout + same.stderr
    assert "shield output" in same.stdout and "matches bit for bit" in same.stdout, same.stdout


def test_without_tracking_or_a_position_no_tracks_are_recorded(tmp_path):
    """``[tracking] enabled = false``; and the default without a goal source (no position asked
    for): nothing tracked, no /tracks."""
    for name in ("off", "no-goal"):
        (tmp_path / name).mkdir()
    (off,) = _record_companion(
        tmp_path / "off", extra=WEST_AND_UP + "[tracking]\nenabled = false\n", scene=_Walker()
    )
    (no_goal,) = _record_companion(tmp_path / "no-goal", scene=_Walker())
    for path in (off, no_goal):
        assert read_recording(path).topic(s.TRACKS.topic) == []
