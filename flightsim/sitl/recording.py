"""The recording of a SITL flight: the companion's own MCAP plus the simulator's ground truth, in one file.

The companion process records itself exactly as on the drone (``[recorder]``, switched on by
:meth:`FlightRecording.companion_overrides`), plus about :data:`CLOUD_POINTS` points of each
revolution: every point at 1° (so a replay starts from the clouds), every 5th at 0.2° (a whole
0.2° cloud is ~3 MB/s of MCAP; the replay then starts from the recorded scans).
Beside it this module records what only the simulator knows, from the harness's physics hook:
the vehicle's true pose (``/truth/pose``, and ``/tf`` world → base_link so Foxglove's 3D panel
places the scan in the room), its true velocity and clearance (``/truth/state``), and the world
itself (metadata ``lidar_avoid_truth``). Both use the same monotonic clock, so when the flight
ends :func:`merge_recordings` interleaves them into ``flight.mcap``.
"""

from __future__ import annotations

import heapq
import json
import logging
import math
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from companion.recording import messages as m
from companion.recording import schemas as s
from companion.recording.writer import FILE_GLOB, McapSink
from flightsim.worlds.world import World, world_to_dict

log = logging.getLogger(__name__)

TRUTH_METADATA = "lidar_avoid_truth"
TRUTH_STATE = s.Channel("/truth/state", "lidar_avoid.TruthState")
s.register_schema("lidar_avoid.TruthState", {
    "title": "lidar_avoid.TruthState", "type": "object",
    "properties": {"timestamp": s.TIME, "position": s.VECTOR3, "velocity": s.VECTOR3,
                   "speed": {"type": "number"}, "yaw": {"type": "number"},
                   "clearance": {"type": ["number", "null"]}},
    "required": ["timestamp", "position", "velocity", "speed", "yaw", "clearance"],
})
#: Points per revolution the companion records (at most; a divisor of the revolution's).
CLOUD_POINTS = 6000
#: Ground truth is recorded at most this often (the physics runs at 120 Hz), s.
TRUTH_PERIOD = 0.05
_BUDGET = 50 * 10**9  # the workdir holds one flight: no deletion


class FlightRecording:
    """Ground truth of one SITL flight, merged with the companion's recording at the end.

    :param workdir: the flight's working directory; the result is ``workdir/flight.mcap``
    :param world: the room (stored in the recording, so a report needs nothing else)
    :param lidar_step_deg: the lidar's azimuth step (16 channels × 360°/step points per revolution)
    """

    def __init__(self, workdir: Path, world: World, lidar_step_deg: float = 1.0) -> None:
        # absolute: the companion takes a relative recorder directory relative to its config file
        self.companion_dir = Path(workdir).resolve() / "recording"
        self.truth_dir = Path(workdir) / "truth"
        self.path = Path(workdir) / "flight.mcap"
        self.world = world
        #: monotonic time of the world's start (where its moving obstacles are); the harness sets it
        self.t0 = 0.0
        self._last = -math.inf
        self._merged: Path | None = None
        self.cloud_decimation = max(1, math.ceil(16 * 360 / lidar_step_deg / CLOUD_POINTS))
        for d in (self.companion_dir, self.truth_dir):  # a reused workdir: this flight only
            shutil.rmtree(d, ignore_errors=True)
        self.sink = McapSink(self.truth_dir, _BUDGET, _BUDGET // 10,
                             {"format": s.FORMAT_VERSION, "world": json.dumps(world_to_dict(world))},
                             queue_size=4096, metadata_name=TRUTH_METADATA)

    def companion_overrides(self, overrides: dict[str, Any]) -> dict[str, Any]:
        """The companion config overrides with the recorder on (the caller's own recorder keys win)."""
        recorder = {"enabled": True, "directory": str(self.companion_dir),
                    "cloud_decimation": self.cloud_decimation}
        return {**overrides, "recorder": {**recorder, **overrides.get("recorder", {})}}

    def on_state(self, t: float, state: Any) -> None:
        """The simulated vehicle's state at monotonic time ``t`` (physics thread: queue and go)."""
        if t - self._last < TRUTH_PERIOD:
            return
        self._last = t
        position = np.asarray(state.position, dtype=float)
        clearance = self.world.clearance_at(position, t - self.t0)
        q = m.quaternion_from_rpy(float(state.roll), float(state.pitch), float(state.yaw))
        pose = m.identity_pose(tuple(position), q)
        self.sink.submit(s.TRUTH_POSE, t, _pose_in_frame, pose)
        self.sink.submit(s.TRUTH_TF, t, _transform, pose)
        self.sink.submit(TRUTH_STATE, t, _truth_state, position, np.asarray(state.velocity, dtype=float),
                         float(state.yaw), clearance)

    def close(self) -> Path | None:
        """Finish the ground truth and merge it with the companion's files into :attr:`path` (the
        parts are deleted once merged). Closing again does nothing."""
        if self._merged is not None:
            return self._merged
        self.sink.close()
        sources = sorted(self.companion_dir.glob(FILE_GLOB)) + list(self.sink.files)
        try:
            merge_recordings(sources, self.path)
        except Exception as exc:  # a damaged part must not cost the flight's report: keep the parts
            log.warning("could not merge the flight recording %s: %s", self.path, exc)
            return None
        for source in sources:
            source.unlink()
        self._merged = self.path
        return self.path


def _pose_in_frame(t: float, pose: dict[str, Any]) -> dict[str, Any]:
    return {"timestamp": m.stamp(t), "frame_id": s.WORLD_FRAME, "pose": pose}


def _transform(t: float, pose: dict[str, Any]) -> dict[str, Any]:
    return {"timestamp": m.stamp(t), "parent_frame_id": s.WORLD_FRAME, "child_frame_id": s.BODY_FRAME,
            "translation": pose["position"], "rotation": pose["orientation"]}


def _truth_state(t: float, position: np.ndarray, velocity: np.ndarray, yaw: float,
                 clearance: float) -> dict[str, Any]:
    return {"timestamp": m.stamp(t), "position": dict(zip("xyz", map(float, position), strict=True)),
            "velocity": dict(zip("xyz", map(float, velocity), strict=True)),
            "speed": float(np.linalg.norm(velocity[:2])), "yaw": yaw,
            "clearance": m.finite_or_none(clearance)}


def merge_recordings(sources: list[Path], out: Path) -> None:
    """Interleave the messages of ``sources`` by log time into one MCAP file; keep every metadata record."""
    handles = [open(p, "rb") for p in sources]  # noqa: SIM115 - closed below
    writer = Writer(str(out), compression=CompressionType.ZSTD)
    writer.start(profile="", library="lidar-avoid")
    schema_ids: dict[tuple[str, bytes], int] = {}
    channel_ids: dict[tuple[str, int], int] = {}
    try:
        readers = [make_reader(f) for f in handles]
        seen_metadata: set[str] = set()
        for reader in readers:
            for meta in reader.iter_metadata():
                if meta.name not in seen_metadata:
                    seen_metadata.add(meta.name)
                    writer.add_metadata(meta.name, dict(meta.metadata))

        def stream(i: int) -> Iterator[tuple[int, int, int, Any, Any, Any]]:
            for n, (schema, channel, message) in enumerate(readers[i].iter_messages(log_time_order=True)):
                yield message.log_time, i, n, schema, channel, message

        for *_, schema, channel, message in heapq.merge(*(stream(i) for i in range(len(readers)))):
            key = (schema.name, schema.data)
            if key not in schema_ids:
                schema_ids[key] = writer.register_schema(schema.name, schema.encoding, schema.data)
            ckey = (channel.topic, schema_ids[key])
            if ckey not in channel_ids:
                channel_ids[ckey] = writer.register_channel(channel.topic, channel.message_encoding,
                                                            schema_ids[key])
            writer.add_message(channel_ids[ckey], log_time=message.log_time, data=message.data,
                               publish_time=message.publish_time, sequence=message.sequence)
    finally:
        for f in handles:
            f.close()
        writer.finish()
