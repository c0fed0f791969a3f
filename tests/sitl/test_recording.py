"""SITL flights with the flight recorder: the real companion process and the simulated ArduCopter on
loopback, the lidar as real VLP-16 packets.

1. A recorded flight reads back with the ``mcap`` reader, every message validates against the JSON
   Schema its channel carries, ground truth and the companion share one clock, the replay matches
   bit for bit (the autopilot's yaw cap binding: the replay's shield is ArduPilot's, as the
   companion's was), and ``avoid-sim report`` draws it.
2. The disk fills up in the middle of the flight (a real tmpfs, filled by this test while the
   companion is ACTIVE): a STATUSTEXT says recording stopped, and the setpoints keep flowing.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from pathlib import Path

import jsonschema
import pytest
from mcap.reader import make_reader

from companion.recording import schemas as s
from companion.recording.reader import read_recording
from flightsim.sitl.harness import FlightOptions, SitlFlight
from flightsim.sitl.recording import FlightRecording
from tests.companion.test_recorder import tiny_tmpfs
from tests.sitl.helpers import OPEN_ROOM, companion_counters, wait_for, write_constant_policy

pytestmark = pytest.mark.sitl
REPO = Path(__file__).resolve().parents[2]
COMPANION_TOPICS = {s.SCAN.topic, s.CLOUD.topic, s.POLICY.topic, s.SHIELD.topic, s.SETPOINT.topic,
                    s.TRANSITION.topic, s.VEHICLE.topic, s.COUNTERS.topic, s.LOG.topic}
TRUTH_TOPICS = {s.TRUTH_POSE.topic, s.TRUTH_TF.topic, "/truth/state"}


def _options(workdir: Path, turn: float = 0.4, **overrides) -> FlightOptions:
    workdir.mkdir(parents=True, exist_ok=True)
    return FlightOptions(
        autopilot="sim-ardupilot",
        world=OPEN_ROOM,
        policy=write_constant_policy(workdir / "circle.onnx", 0.5, turn),
        workdir=workdir,
        lidar_step_deg=1.0,
        companion_overrides={"runtime": {"log_interval": 1.0}, **overrides},
    )


def test_a_recorded_flight_reads_back_validates_and_replays_bit_for_bit(tmp_path):
    # 0.8 asks 1.2 rad/s, above ArduPilot's default ATC_RATE_WPY_MAX (60 deg/s): the shield caps it
    with SitlFlight(_options(tmp_path, turn=0.8)) as flight:
        flight.take_off()
        assert flight.wait_engaged(25.0), flight.companion_log()
        t = time.monotonic()
        wait_for(lambda: flight.recorder.setpoints_since(t) >= 40, 30, "40 setpoints while ACTIVE")
    path = flight.recording.path
    assert path.is_file()

    topics: dict[str, int] = {}
    times: dict[str, list[int]] = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        metadata = {md.name for md in reader.iter_metadata()}
        validators = {}
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            assert (schema.encoding, channel.message_encoding) == ("jsonschema", "json")
            if channel.topic not in validators:
                validators[channel.topic] = jsonschema.Draft202012Validator(json.loads(schema.data))
            topics[channel.topic] = topics.get(channel.topic, 0) + 1
            times.setdefault(channel.topic, []).append(message.log_time)
            validators[channel.topic].validate(json.loads(message.data))
    assert {s.METADATA_NAME, "lidar_avoid_truth"} <= metadata
    assert set(topics) >= COMPANION_TOPICS | TRUTH_TOPICS, topics
    # a goal policy gets no frame (no scan in the stack, no policy step) before a measured velocity
    # arrives; every revolution's cloud is recorded
    assert topics[s.CLOUD.topic] >= topics[s.SCAN.topic] == topics[s.POLICY.topic] >= 40
    # ground truth and the companion are on one clock: the truth covers the companion's flight
    assert times["/truth/state"][0] < times[s.SETPOINT.topic][0] < times[s.SETPOINT.topic][-1] \
        < times["/truth/state"][-1]
    yaw_rates = [msg["output"]["yaw_rate"] for _, msg in read_recording(path).topic(s.SHIELD.topic)]
    assert max(yaw_rates) == pytest.approx(math.radians(60.0))

    replay = subprocess.run([sys.executable, "-m", "companion", "replay", str(path)], cwd=REPO,
                            capture_output=True, text=True, timeout=300)
    assert replay.returncode == 0, replay.stdout + replay.stderr
    assert "from the recorded clouds" in replay.stdout and "matches bit for bit" in replay.stdout

    picture = tmp_path / "report.png"
    report = subprocess.run([sys.executable, "-m", "flightsim", "report", str(path), "--out", str(picture)],
                            cwd=REPO, capture_output=True, text=True, timeout=300)
    assert report.returncode == 0, report.stderr
    assert "ACTIVE" in report.stdout and picture.stat().st_size > 20_000


def test_a_relative_workdir_gives_the_companion_the_directory_the_merge_reads(tmp_path, monkeypatch):
    """``avoid-sim demo``'s default ``--out`` is relative: the companion resolves a relative recorder
    directory against its config file (in the workdir), so the directory it is given must be the
    absolute one the merge reads, or the merged recording holds the ground truth alone."""
    monkeypatch.chdir(tmp_path)
    recording = FlightRecording(Path("out/flight"), OPEN_ROOM)
    try:
        given = Path(recording.companion_overrides({})["recorder"]["directory"])
        assert given == tmp_path / "out" / "flight" / "recording"
        assert recording.companion_dir == given
    finally:
        recording.close()


def test_a_disk_that_fills_up_mid_flight_stops_recording_not_the_flight(tmp_path):
    with tiny_tmpfs(tmp_path / "disk", 64 * 1024) as disk:  # room for the take-off
        options = _options(tmp_path / "flight", recorder={"directory": str(disk / "flights")})
        with SitlFlight(options) as flight:
            flight.take_off()
            assert flight.wait_engaged(25.0), flight.companion_log()
            start = time.monotonic()
            wait_for(lambda: flight.recorder.setpoints_since(start) >= 10, 20, "setpoints while ACTIVE")
            # fill the disk: whatever the recorder writes next has no room
            filler = disk / "filler"
            # unbuffered: a buffered file keeps what did not fit and raises again when it is closed,
            # outside pytest.raises (8 of 132 fill levels of a 64 KiB tmpfs did)
            with open(filler, "wb", buffering=0) as f, pytest.raises(OSError, match="No space left"):
                while True:
                    f.write(b"\0" * 65536)
            full = time.monotonic()
            notice = wait_for(lambda: [t for t in flight.recorder.texts(full) if "recording stopped" in t],
                              15, "the 'recording stopped' STATUSTEXT")
            assert "No space left on device" in notice[0]
            after = time.monotonic()
            time.sleep(2.0)
            assert flight.recorder.setpoints_since(after) >= 15, "setpoints stopped with the recording"
            assert flight.companion_alive()
            assert not [t for t in flight.recorder.texts(full) if "->HOLD" in t or "->STANDBY" in t]
            assert "loop_faults" not in companion_counters(flight)
