"""The loop's side of the flight recorder: turn what the loop's parts saw into queued records.

Every ``on_*`` method runs in the loop thread and does nearly nothing: it takes the clock (the
loop's own, so recorded times line up with the loop's decisions) and holds the record, a tuple of
references, until :meth:`FlightRecorder.flush` hands them to :meth:`McapSink.submit`. The taps
flush once the iteration's time-critical messages are out (after the setpoint, OBSTACLE_DISTANCE,
HEARTBEAT), so the writer thread encodes while the loop waits for the next revolution instead
of competing with it for the interpreter lock between the last packet and the setpoint. The
arrays held are never changed afterwards by the loop (each scan, observation and cloud is a fresh
array), so nothing is copied here.

The parts report through the taps of :mod:`companion.recording.taps`; the goal and waypoints of
the navigation work, and anything else worth recording, go through :meth:`FlightRecorder.record`
(a topic with its own JSON schema in ``schemas.OWN_SCHEMAS``).
"""

from __future__ import annotations

import hashlib
import json
import logging
import sys
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from companion.perception.scan import N_BINS
from companion.recording import messages as m
from companion.recording import schemas as s
from companion.recording.writer import McapSink

log = logging.getLogger(__name__)

#: MAV_SEVERITY_WARNING, for the "recording stopped" STATUSTEXT.
WARNING = 4
#: Vehicle status and counters are recorded at most this often, s.
STATUS_PERIOD = 0.1
COUNTERS_PERIOD = 1.0
#: Longest the loop waits for the interpreter lock while the writer thread runs, s.
SWITCH_INTERVAL = 0.0005
#: Records held between flushes at most (more are dropped and counted), and held at most this long, s.
MAX_HELD = 256
MAX_HOLD_TIME = 0.5
_LOG_LEVEL = {0: 4, 1: 4, 2: 4, 3: 4, 4: 3, 5: 2, 6: 2, 7: 1}  # MAV_SEVERITY -> foxglove.LogLevel


class FlightRecorder:
    """Records one run of the companion.

    :param sink: the writer (None: recording could not start; ``notice`` says why)
    :param clock: the loop's clock
    :param max_range: metres a scan value of 1.0 stands for (LaserScan ranges are metres)
    :param mount_pose: the lidar's pose in the body frame (Foxglove pose), for the point cloud
    :param cloud_decimation: 0 = no cloud; N = every N-th point
    """

    def __init__(self, sink: McapSink | None, clock: Callable[[], float], max_range: float,
                 mount_pose: dict[str, Any], cloud_decimation: int = 0, notice: str = "") -> None:
        self.sink = sink
        self._clock = clock
        self.max_range = max_range
        self.mount_pose = mount_pose
        self.cloud_decimation = cloud_decimation
        self._notices: list[str] = [notice] if notice else []
        self._failure_reported = False
        self._counter_sources: dict[str, Mapping[str, int]] = {}
        self._cloud_seq = 0
        self._pending_clouds: list[int] = []
        self._scan_seq = 0
        self._stacked: tuple[float, int, int | None, bool, np.ndarray, np.ndarray] | None = None
        self.last_frame: np.ndarray | None = None
        self._shield_reset = True
        self._last_status = -float("inf")
        self._last_counters = -float("inf")
        self._held: list[tuple[Any, ...]] = []
        self._held_since = 0.0
        self.held_dropped = 0

    @property
    def active(self) -> bool:
        return self.sink is not None and self.sink.failure is None

    def _hold(self, channel: s.Channel, t: float, build: Callable[..., dict[str, Any]], *args: Any,
              seq: int = 0) -> None:
        if len(self._held) >= MAX_HELD:
            self.held_dropped += 1
            return
        if not self._held:
            self._held_since = self._clock()
        self._held.append((channel, t, build, args, seq))

    def flush(self) -> None:
        """Hand the held records to the writer thread (call when nothing time-critical is pending)."""
        held, self._held = self._held, []
        sink = self.sink
        if sink is None:
            return
        for channel, t, build, args, seq in held:
            sink.submit(channel, t, build, *args, seq=seq)

    def flush_if_stale(self) -> None:
        """Flush records held longer than :data:`MAX_HOLD_TIME` (an iteration that sent nothing)."""
        if self._held and self._clock() - self._held_since >= MAX_HOLD_TIME:
            self.flush()

    def watch_counters(self, **sources: Mapping[str, int]) -> None:
        """Counter dicts recorded once a second (copied in the loop thread, then queued)."""
        self._counter_sources.update(sources)

    def record(self, channel: s.Channel, build: Callable[..., dict[str, Any]], *args: Any) -> None:
        """Any other record: ``build(t, *args)`` gives its JSON object (in the writer thread).

        The extension point for goal and waypoints: a ``Channel`` whose schema is in
        ``schemas.OWN_SCHEMAS`` (or added with ``schemas.register_schema``), and a builder function.
        """
        if self.active:
            self._hold(channel, self._clock(), build, *args)

    # ---- what the taps report ----------------------------------------------------------------

    def on_clouds(self, clouds: list[np.ndarray]) -> None:
        """The revolutions one read of the lidar completed, oldest first."""
        self._pending_clouds = []
        for cloud in clouds:
            self._cloud_seq += 1
            self._pending_clouds.append(self._cloud_seq)
            if self.cloud_decimation and self.active:
                points = cloud if self.cloud_decimation == 1 else cloud[:: self.cloud_decimation]
                self._hold(s.CLOUD, self._clock(), m.point_cloud, points, self.mount_pose,
                           seq=self._cloud_seq)

    def on_stacked(self, frame: np.ndarray, obs: np.ndarray, reset: bool) -> None:
        """A frame went into the frame stack (``reset``: the stack started over with it); its scan
        (the frame's first :data:`~companion.perception.scan.N_BINS` values) is recorded as the LaserScan, the
        whole frame inside the observation."""
        self._scan_seq += 1
        cloud_seq = self._pending_clouds.pop(0) if self._pending_clouds else None
        self._stacked = (self._clock(), self._scan_seq, cloud_seq, reset, np.asarray(frame)[:N_BINS], obs)
        self.last_frame = frame

    def on_action(self, action: np.ndarray | None, fault: str | None = None) -> None:
        """The policy answered the stacked observation (or faulted)."""
        stacked, self._stacked = self._stacked, None
        if stacked is None or not self.active:
            return
        t, seq, cloud_seq, reset, scan, obs = stacked
        self._hold(s.SCAN, t, m.laser_scan, scan, self.max_range, seq=seq)
        self._hold(s.POLICY, t, _policy_step, seq, cloud_seq, reset, obs, action, fault, seq=seq)

    def on_shield_reset(self) -> None:
        self._shield_reset = True

    def on_shield(self, requested: Any, scan: np.ndarray, dt: float, output: Any, limits: list[str],
                  extra: dict[str, Any] | None) -> None:
        # the shield judges the newest frame's scan: that frame itself (scan only) or a view of it
        last = self.last_frame
        scan_seq = self._scan_seq if last is not None and (scan is last or scan.base is last) else None
        reset, self._shield_reset = self._shield_reset, False
        if self.active:
            self._hold(s.SHIELD, self._clock(), _shield_step, scan_seq, float(dt), reset, requested,
                       output, limits, extra)

    def on_tracks(self, scan: np.ndarray, pose: tuple[float, float, float] | None, time: float, fresh: bool,
                  output: Any) -> None:
        """The tracker took ``scan`` at ``pose`` and ``time`` (``fresh``: with no state before) and said
        ``output`` (:class:`~companion.perception.tracking.TrackerOutput`): its tracks are copied
        now, as the tracker goes on changing them. Nothing is recorded for an update that changed
        nothing (no pose, nothing to forget)."""
        if not self.active or (pose is None and fresh):
            return
        rows, bins = track_rows(output)
        where = None if pose is None else tuple(float(v) for v in pose)
        t = float(time)
        self._hold(s.TRACKS, t, _tracks, where, fresh, None if pose is None else scan, rows, bins)
        self._hold(s.TRACK_SCENE, t, m.scene_update, where, rows)

    def on_setpoint(self, forward: float, yaw_rate: float, lateral: float = 0.0,
                    vertical: float = 0.0) -> None:
        if self.active:
            self._hold(s.SETPOINT, self._clock(), _setpoint, float(forward), float(yaw_rate), float(lateral),
                       float(vertical))

    def on_statustext(self, text: str, severity: int) -> None:
        if self.active:
            self._hold(s.LOG, self._clock(), _log, text, severity)

    def on_transition(self, transition: Any, counters: Mapping[str, int]) -> None:
        if self.active:
            self._hold(s.TRANSITION, transition.time, _transition, transition, dict(counters))

    def on_status(self, status: Any) -> None:
        """The link's vehicle status (recorded at most every :data:`STATUS_PERIOD`), and the counters."""
        now = self._clock()
        if not self.active:
            return
        if now - self._last_status >= STATUS_PERIOD:
            self._last_status = now
            self._hold(s.VEHICLE, now, _vehicle, m.plain(status))  # now: the link updates it in place
        if now - self._last_counters >= COUNTERS_PERIOD:
            self._last_counters = now
            counts = {k: dict(v) for k, v in self._counter_sources.items()}
            counts["recorder"] = self.stats()
            self._hold(s.COUNTERS, now, _counters, counts)

    # ---- health ------------------------------------------------------------------------------

    def stats(self) -> dict[str, int]:
        sink = self.sink
        if sink is None:
            return {}
        return {"written": sink.written, "dropped": sink.dropped + self.held_dropped,
                "files": len(sink.files), "deleted": len(sink.deleted)}

    def take_notices(self) -> list[str]:
        """Lines for the pilot (STATUSTEXT): recording could not start, or stopped. Each once."""
        sink = self.sink
        if sink is not None and sink.failure is not None and not self._failure_reported:
            self._failure_reported = True
            self._notices.append(f"recording stopped: {sink.failure_reason}"[:200])
        out, self._notices = self._notices, []
        return out

    def close(self) -> None:
        if self.sink is not None:
            self.flush()
            self.sink.close()
            log.info("flight recorder: %s, files %s", " ".join(f"{k}={v}" for k, v in self.stats().items()),
                     ", ".join(str(p) for p in self.sink.files))


# ---- record builders (writer thread) ---------------------------------------------------------


def track_rows(output: Any) -> tuple[list[m.TrackRow], list[int]]:
    """A tracker update's output (:class:`~companion.perception.tracking.TrackerOutput`) as /tracks
    holds it: a row per confirmed track, and the moving bins. Replay compares its own by these."""
    moving = {track.track_id for track in output.moving}
    rows = [(int(track.track_id), *(float(v) for v in track.state), float(track.extent), float(track.widest),
             track.track_id in moving) for track in output.tracks]
    return rows, np.flatnonzero(output.moving_bins).tolist()


def _policy_step(t: float, seq: int, cloud_seq: int | None, reset: bool, obs: np.ndarray,
                 action: np.ndarray | None, fault: str | None) -> dict[str, Any]:
    return {"timestamp": m.stamp(t), "seq": seq, "cloud_seq": cloud_seq, "reset": reset,
            "observation": m.pack_f32(obs),
            "action": None if action is None else [float(a) for a in np.asarray(action, np.float32)],
            "fault": fault}


def _shield_step(t: float, scan_seq: int | None, dt: float, reset: bool, requested: Any, output: Any,
                 limits: list[str], extra: dict[str, Any] | None) -> dict[str, Any]:
    return {"timestamp": m.stamp(t), "scan_seq": scan_seq, "dt": dt, "reset_before": reset,
            "requested": m.command(requested.forward, requested.yaw_rate, requested.lateral),
            "output": m.command(output.forward, output.yaw_rate, output.lateral), "limits": limits,
            "extra": None if not extra else m.plain(extra)}


def _tracks(t: float, pose: tuple[float, float, float] | None, fresh: bool, scan: np.ndarray | None,
            rows: list[m.TrackRow], bins: list[int]) -> dict[str, Any]:
    return {"timestamp": m.stamp(t), "time": t, "fresh": fresh,
            "pose": None if pose is None else dict(zip(("x", "y", "yaw"), pose, strict=True)),
            "scan": None if scan is None else m.pack_f32(scan),
            "tracks": [dict(zip(m.TRACK_FIELDS, row, strict=True)) for row in rows],
            "moving_bins": bins}


def _setpoint(t: float, forward: float, yaw_rate: float, lateral: float, vertical: float) -> dict[str, Any]:
    return {"timestamp": m.stamp(t), **m.command(forward, yaw_rate, lateral), "vertical": vertical}


def _log(t: float, text: str, severity: int) -> dict[str, Any]:
    return m.log(t, _LOG_LEVEL.get(severity, 2), text)


def _transition(t: float, transition: Any, counters: dict[str, int]) -> dict[str, Any]:
    return {"timestamp": m.stamp(t), "old": transition.old.value, "new": transition.new.value,
            "reason": transition.reason, "counters": counters}


def _vehicle(t: float, status: dict[str, Any]) -> dict[str, Any]:
    return {"timestamp": m.stamp(t), **status}


def _counters(t: float, counts: dict[str, dict[str, int]]) -> dict[str, Any]:
    return {"timestamp": m.stamp(t), **{k: counts.get(k, {}) for k in
                                          ("companion", "supervisor", "shield", "link", "recorder")}}


# ---- start-up --------------------------------------------------------------------------------


def file_digest(path: str | Path) -> str:
    """sha256 of a file (the model), so a replay knows whether it runs the recorded model."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def open_recorder(
    config: Any, config_dict: dict[str, Any], clock: Callable[[], float],
    autopilot_yaw_rate: float | None = None,
    shield_stopping: tuple[float, float] | None = None,
) -> FlightRecorder | None:
    """The recorder for ``config`` (a :class:`companion.config.CompanionConfig`), or None when off.

    A directory that cannot be written does not stop the companion: the recorder comes back
    inactive, with a notice for the pilot.

    :param autopilot_yaw_rate: the yaw cap the start-up check read from the autopilot, rad/s (None:
        not read); the config does not hold it, and the replay's shield needs it
    :param shield_stopping: the shield's stopping model, (deceleration m/s², reaction time s): the
        config's ``max_decel`` and ``reaction_time``, or where they are 0 the autopilot's limits of
        this version (:data:`companion.safety.shield.AUTOPILOT_LIMITS`), which a later one may change
    """
    rc = config.recorder
    if not rc.enabled:
        return None
    x, y, z = config.scan.mount_xyz
    roll, pitch, yaw = (np.radians(v) for v in config.scan.mount_rpy_deg)
    mount = m.identity_pose((x, y, z), m.quaternion_from_rpy(float(roll), float(pitch), float(yaw)))
    metadata = {
        "format": s.FORMAT_VERSION,
        "config": json.dumps(config_dict),
        "model_sha256": file_digest(config.policy.model),
        "cloud_decimation": str(rc.cloud_decimation),
        # exact (repr); "": not read, the shield assumed the firmware default
        "autopilot_yaw_rate": "" if autopilot_yaw_rate is None else repr(float(autopilot_yaw_rate)),
        # exact (repr), "decel reaction_time"; "": not given
        "shield_stopping": " ".join(repr(float(v)) for v in shield_stopping) if shield_stopping else "",
        "clock": "time.monotonic",
        "clock_at_start": repr(clock()),
        "wall_time_at_start": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    try:
        sink = McapSink(rc.directory, int(rc.budget_mb * 1e6), int(rc.file_mb * 1e6), metadata, rc.queue_size)
    except OSError as exc:
        reason = f"{exc.strerror or exc}: {exc.filename or rc.directory}"
        log.warning("flight recorder: recording off, %s", reason)
        return FlightRecorder(None, clock, config.scan.max_range, mount,
                              notice=f"recording off: {exc.strerror or exc}")
    # The writer thread holds the interpreter lock while it encodes; the loop, woken by a packet,
    # must not wait CPython's default 5 ms for it. 0.5 ms bounds that wait (bench_companion.py).
    sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL))
    log.info("flight recorder: writing %s", sink.current)
    return FlightRecorder(sink, clock, config.scan.max_range, mount, rc.cloud_decimation)
