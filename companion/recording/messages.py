"""Record → JSON message, one function per channel. Pure: the writer thread calls these, never the loop.

Times are seconds of the clock the loop runs on (``time.monotonic`` on the drone); MCAP log times
are the same instants in integer nanoseconds.
"""

from __future__ import annotations

import base64
import dataclasses
import enum
import json
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from companion.recording.schemas import BODY_FRAME, DELETE_ALL, FLOAT32

#: LaserScan bin i covers [i°, i+1°): its bearing is the bin centre.
_BIN_CENTRE = math.radians(0.5)


def nanoseconds(t: float) -> int:
    """Clock seconds as MCAP log time (integer ns, never negative)."""
    return max(0, round(t * 1e9))


def stamp(t: float) -> dict[str, int]:
    """Clock seconds as a Foxglove ``time``."""
    ns = nanoseconds(t)
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def seconds(stamp_: Mapping[str, int]) -> float:
    """A Foxglove ``time`` back to clock seconds."""
    return stamp_["sec"] + stamp_["nsec"] * 1e-9


class Base64(bytes):
    """A JSON string field given as its base64 bytes; :func:`to_json` writes it without the JSON
    encoder (which would scan a 460 kB cloud character by character: 7 ms against 0.1 ms)."""


def pack_f32(values: np.ndarray) -> Base64:
    """float32 little-endian, base64: exact, compact."""
    return Base64(base64.b64encode(np.ascontiguousarray(values, dtype="<f4").tobytes()))


def to_json(message: dict[str, Any]) -> bytes:
    """``message`` as compact JSON bytes; :class:`Base64` fields (top level) are spliced in as strings."""
    raw = {k: v for k, v in message.items() if isinstance(v, Base64)}
    rest = {k: v for k, v in message.items() if not isinstance(v, Base64)} if raw else message
    text = json.dumps(rest, separators=(",", ":")).encode()
    if not raw:
        return text
    parts = [text[:-1]] + [b'%s"%s":"%s"' % (b"," if (i or rest) else b"", k.encode(), v)
                           for i, (k, v) in enumerate(raw.items())]
    return b"".join(parts) + b"}"


def unpack_f32(text: str) -> np.ndarray:
    return np.frombuffer(base64.b64decode(text), dtype="<f4").astype(np.float32)


def finite_or_none(x: Any) -> float | None:
    """JSON has no NaN/Inf: an unusable number is recorded as null."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def plain(value: Any) -> Any:
    """Any status-like value as JSON: dataclasses as objects, enums by name, non-finite as null."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, enum.Enum):
        return value.name
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return finite_or_none(value)
    if isinstance(value, np.ndarray):
        return [plain(v) for v in value.tolist()]
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    return str(value)


def identity_pose(xyz: tuple[float, float, float] = (0.0, 0.0, 0.0),
                  quaternion: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)) -> dict[str, Any]:
    return {"position": dict(zip("xyz", map(float, xyz), strict=True)),
            "orientation": dict(zip("xyzw", map(float, quaternion), strict=True))}


def quaternion_from_rpy(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of the rotation roll about x, then pitch about y, then yaw about z (extrinsic ZYX)."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)


def laser_scan(t: float, scan: np.ndarray, max_range: float) -> dict[str, Any]:
    """foxglove.LaserScan of one 360-bin scan, metres, bins counter-clockwise from the nose."""
    n = len(scan)
    step = 2 * math.pi / n
    return {
        "timestamp": stamp(t), "frame_id": BODY_FRAME, "pose": identity_pose(),
        "start_angle": _BIN_CENTRE, "end_angle": _BIN_CENTRE + step * (n - 1),
        "ranges": np.round(np.asarray(scan, dtype=np.float64) * max_range, 4).tolist(), "intensities": [],
    }


def point_cloud(t: float, points: np.ndarray, mount_pose: dict[str, Any]) -> dict[str, Any]:
    """foxglove.PointCloud of sensor-frame points (x, y, z float32), placed at the sensor's mount."""
    return {
        "timestamp": stamp(t), "frame_id": BODY_FRAME, "pose": mount_pose, "point_stride": 12,
        "fields": [{"name": a, "offset": 4 * i, "type": FLOAT32} for i, a in enumerate("xyz")],
        "data": pack_f32(np.asarray(points, dtype=np.float32).reshape(-1, 3)),
    }


def command(forward: float, yaw_rate: float, lateral: float) -> dict[str, float | None]:
    """``lidar_avoid.Command``: a body-frame command, sideways part included."""
    return {"forward": finite_or_none(forward), "yaw_rate": finite_or_none(yaw_rate),
            "lateral": finite_or_none(lateral)}


def log(t: float, level: int, text: str, name: str = "companion") -> dict[str, Any]:
    """foxglove.Log."""
    return {"timestamp": stamp(t), "level": level, "message": text, "name": name, "file": "", "line": 0}


#: a track as the recorder holds it: id, ground-frame x, y (m), vx, vy (m/s), seen width and widest
#: width (m), moving; /tracks names them so
TrackRow = tuple[int, float, float, float, float, float, float, bool]
TRACK_FIELDS = ("id", "x", "y", "vx", "vy", "extent", "widest", "moving")
_MOVING_COLOR = {"r": 0.95, "g": 0.25, "b": 0.2, "a": 0.85}
_STILL_COLOR = {"r": 0.6, "g": 0.6, "b": 0.6, "a": 0.5}


def scene_update(t: float, pose: tuple[float, float, float] | None, tracks: list[TrackRow]) -> dict[str, Any]:
    """foxglove.SceneUpdate of one tracker update: every earlier entity deleted, then a cylinder per
    confirmed track (its widest width, 1 m tall about the scan's plane; red when it moves, grey
    when not) and an arrow along a mover's velocity, 1 s of it, in the body frame at ``pose``
    (the vehicle's ground-frame x, y, yaw the tracks were placed from; None: nothing tracked)."""
    entities = []
    if pose is not None:
        x0, y0, yaw = pose
        c, s = math.cos(yaw), math.sin(yaw)
        for track_id, x, y, vx, vy, _extent, widest, moving in tracks:
            dx, dy = x - x0, y - y0
            forward, left = c * dx + s * dy, -s * dx + c * dy
            v_forward, v_left = c * vx + s * vy, -s * vx + c * vy
            color = _MOVING_COLOR if moving else _STILL_COLOR
            size = max(widest, 0.1)
            at = identity_pose((forward, left, 0.0))
            arrows = []
            speed = math.hypot(v_forward, v_left)
            if moving:
                heading = quaternion_from_rpy(0.0, 0.0, math.atan2(v_left, v_forward))
                arrows.append({"pose": identity_pose((forward, left, 0.0), heading), "shaft_length": speed,
                               "shaft_diameter": 0.05, "head_length": 0.15, "head_diameter": 0.12,
                               "color": color})
            entities.append({
                "timestamp": stamp(t), "frame_id": BODY_FRAME, "id": f"track-{track_id}",
                "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": False,
                "metadata": [{"key": "moving", "value": str(moving).lower()},
                             {"key": "speed", "value": f"{speed:.2f} m/s"}],
                "arrows": arrows, "cubes": [], "spheres": [],
                "cylinders": [{"pose": at, "size": {"x": size, "y": size, "z": 1.0}, "bottom_scale": 1.0,
                               "top_scale": 1.0, "color": color}],
                "lines": [], "triangles": [], "texts": [], "models": [],
            })  # fmt: skip
    return {"deletions": [{"timestamp": stamp(t), "type": DELETE_ALL, "id": ""}], "entities": entities}
