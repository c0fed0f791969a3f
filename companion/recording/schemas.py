"""The recording's channels: topic, schema name and JSON Schema of each.

Messages are JSON (MCAP message encoding ``json``, schema encoding ``jsonschema``), which
Foxglove reads natively and the pure-Python ``mcap`` package writes without code generation.
Where Foxglove has a standard message (LaserScan, PointCloud, PoseInFrame, FrameTransform, Log,
SceneUpdate),
the channel uses it under its Foxglove name, so Foxglove's 3D, Plot and Log panels understand it;
the field names and types follow Foxglove's definitions (``tests/companion/test_recorder_schemas.py``
checks them against the protobuf descriptors the ``foxglove-sdk`` package ships). The companion's
own records (policy step, shield, setpoint, supervisor, vehicle status, counters, tracks) have
``lidar_avoid.*`` schemas defined here.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

#: MCAP metadata record name holding the recording's context (config, model digest, ...).
METADATA_NAME = "lidar_avoid"
#: Version of this recording layout (in the metadata); replay refuses others.
FORMAT_VERSION = "1"
#: Body frame (FLU) the scan and the setpoints refer to, and the sensor frame of the point cloud.
BODY_FRAME = "base_link"
#: World frame of ground truth (flightsim's ENU room frame).
WORLD_FRAME = "world"


def _num() -> dict[str, Any]:
    return {"type": "number"}


def _int(minimum: int | None = 0) -> dict[str, Any]:
    return {"type": "integer"} if minimum is None else {"type": "integer", "minimum": minimum}


def _str() -> dict[str, Any]:
    return {"type": "string"}


def _bool() -> dict[str, Any]:
    return {"type": "boolean"}


def _array(items: dict[str, Any]) -> dict[str, Any]:
    return {"type": "array", "items": items}


def _obj(title: str | None = None, nullable: bool = False, **properties: dict[str, Any]) -> dict[str, Any]:
    schema: dict[str, Any] = {"type": ["object", "null"] if nullable else "object",
                              "properties": properties, "required": sorted(properties)}
    if title:
        schema["title"] = title
    return schema


def _bytes() -> dict[str, Any]:
    return {"type": "string", "contentEncoding": "base64"}


def _nullable(schema: dict[str, Any]) -> dict[str, Any]:
    return {"anyOf": [schema, {"type": "null"}]}


# Foxglove's building blocks.
TIME = _obj("time", sec=_int(), nsec={"type": "integer", "minimum": 0, "maximum": 999_999_999})
VECTOR3 = _obj("foxglove.Vector3", x=_num(), y=_num(), z=_num())
QUATERNION = _obj("foxglove.Quaternion", x=_num(), y=_num(), z=_num(), w=_num())
POSE = _obj("foxglove.Pose", position=VECTOR3, orientation=QUATERNION)
#: foxglove.NumericType: FLOAT32 is 7.
NUMERIC_TYPE = {"type": "integer", "minimum": 0, "maximum": 8}
FLOAT32 = 7
#: foxglove.LogLevel: INFO 2, WARNING 3, ERROR 4.
LOG_LEVEL = {"type": "integer", "minimum": 0, "maximum": 5}
#: google.protobuf.Duration as Foxglove's JSON has it (0: for ever)
DURATION = _obj("duration", sec=_int(None), nsec={"type": "integer", "minimum": 0, "maximum": 999_999_999})
COLOR = _obj("foxglove.Color", r=_num(), g=_num(), b=_num(), a=_num())
POINT3 = _obj("foxglove.Point3", x=_num(), y=_num(), z=_num())
#: foxglove.SceneEntityDeletion.Type: MATCHING_ID 0, ALL 1.
DELETE_ALL = 1
#: foxglove.LinePrimitive.Type: LINE_STRIP 0, LINE_LOOP 1, LINE_LIST 2.
_LINE_TYPE = {"type": "integer", "minimum": 0, "maximum": 2}
SCENE_ENTITY = _obj(
    "foxglove.SceneEntity", timestamp=TIME, frame_id=_str(), id=_str(), lifetime=DURATION,
    frame_locked=_bool(),
    metadata=_array(_obj("foxglove.KeyValuePair", key=_str(), value=_str())),
    arrows=_array(_obj("foxglove.ArrowPrimitive", pose=POSE, shaft_length=_num(), shaft_diameter=_num(),
                       head_length=_num(), head_diameter=_num(), color=COLOR)),
    cubes=_array(_obj("foxglove.CubePrimitive", pose=POSE, size=VECTOR3, color=COLOR)),
    spheres=_array(_obj("foxglove.SpherePrimitive", pose=POSE, size=VECTOR3, color=COLOR)),
    cylinders=_array(_obj("foxglove.CylinderPrimitive", pose=POSE, size=VECTOR3, bottom_scale=_num(),
                          top_scale=_num(), color=COLOR)),
    lines=_array(_obj("foxglove.LinePrimitive", type=_LINE_TYPE, pose=POSE, thickness=_num(),
                      scale_invariant=_bool(), points=_array(POINT3), color=COLOR, colors=_array(COLOR),
                      indices=_array(_int()))),
    triangles=_array(_obj("foxglove.TriangleListPrimitive", pose=POSE, points=_array(POINT3), color=COLOR,
                          colors=_array(COLOR), indices=_array(_int()))),
    texts=_array(_obj("foxglove.TextPrimitive", pose=POSE, billboard=_bool(), font_size=_num(),
                      scale_invariant=_bool(), color=COLOR, text=_str())),
    models=_array(_obj("foxglove.ModelPrimitive", pose=POSE, scale=VECTOR3, color=COLOR,
                       override_color=_bool(), url=_str(), media_type=_str(), data=_bytes())),
)

FOXGLOVE_SCHEMAS: dict[str, dict[str, Any]] = {
    "foxglove.LaserScan": _obj(
        "foxglove.LaserScan", timestamp=TIME, frame_id=_str(), pose=POSE, start_angle=_num(),
        end_angle=_num(), ranges=_array(_num()), intensities=_array(_num()),
    ),
    "foxglove.PointCloud": _obj(
        "foxglove.PointCloud", timestamp=TIME, frame_id=_str(), pose=POSE, point_stride=_int(),
        fields=_array(_obj("foxglove.PackedElementField", name=_str(), offset=_int(), type=NUMERIC_TYPE)),
        data=_bytes(),
    ),
    "foxglove.PoseInFrame": _obj("foxglove.PoseInFrame", timestamp=TIME, frame_id=_str(), pose=POSE),
    "foxglove.FrameTransform": _obj(
        "foxglove.FrameTransform", timestamp=TIME, parent_frame_id=_str(), child_frame_id=_str(),
        translation=VECTOR3, rotation=QUATERNION,
    ),
    "foxglove.Log": _obj(
        "foxglove.Log", timestamp=TIME, level=LOG_LEVEL, message=_str(), name=_str(), file=_str(),
        line=_int(),
    ),
    "foxglove.SceneUpdate": _obj(
        "foxglove.SceneUpdate",
        deletions=_array(_obj("foxglove.SceneEntityDeletion", timestamp=TIME,
                              type={"type": "integer", "minimum": 0, "maximum": 1}, id=_str())),
        entities=_array(SCENE_ENTITY),
    ),
}

#: A command, body frame FLU: m/s, rad/s, m/s to the left. Recordings made before ``lateral`` have
#: none in /shield (replay then compares forward and yaw rate alone).
COMMAND = _obj("lidar_avoid.Command", forward=_num(), yaw_rate=_num(), lateral=_num())
_COUNTS = {"type": "object", "additionalProperties": _int()}

OWN_SCHEMAS: dict[str, dict[str, Any]] = {
    # One per scan: what the policy was fed and what it answered. ``observation`` is the stacked
    # float32 scans (oldest first, little-endian, base64: exact, for a bit-for-bit replay).
    "lidar_avoid.PolicyStep": _obj(
        "lidar_avoid.PolicyStep", timestamp=TIME, seq=_int(), cloud_seq=_nullable(_int()),
        reset=_bool(), observation=_bytes(), action=_nullable(_array(_num())),
        fault=_nullable(_str()),
    ),
    # One per shielded policy setpoint: the shield's input, output and the limits that acted.
    "lidar_avoid.ShieldStep": _obj(
        "lidar_avoid.ShieldStep", timestamp=TIME, scan_seq=_nullable(_int()), dt=_num(),
        reset_before=_bool(), requested=COMMAND, output=COMMAND, limits=_array(_str()),
        extra=_nullable({"type": "object"}),
    ),
    # Every velocity setpoint that went to the autopilot (policy or zero), body frame FLU, m/s and
    # rad/s; ``vertical`` is the climb rate (up positive). Recordings made before it have no
    # ``vertical`` (reader.setpoints gives NaN: not recorded).
    "lidar_avoid.Setpoint": _obj("lidar_avoid.Setpoint", timestamp=TIME, forward=_num(), yaw_rate=_num(),
                                  lateral=_num(), vertical=_num()),
    "lidar_avoid.Transition": _obj(
        "lidar_avoid.Transition", timestamp=TIME, old=_str(), new=_str(), reason=_str(), counters=_COUNTS,
    ),
    # The link's VehicleStatus, every field as it is (None: not known).
    "lidar_avoid.VehicleStatus": {"title": "lidar_avoid.VehicleStatus", "type": "object",
                                  "properties": {"timestamp": TIME}, "required": ["timestamp"]},
    "lidar_avoid.Counters": _obj(
        "lidar_avoid.Counters", timestamp=TIME, companion=_COUNTS, supervisor=_COUNTS, shield=_COUNTS,
        link=_COUNTS, recorder=_COUNTS,
    ),
    # One per tracker update: its input (the time, the pose, or null when there was none and the
    # tracker reset; the scan as float32, base64: exact) and its output, the confirmed tracks (ground
    # frame, m and m/s; widths as seen, m) and the bins of moving returns. ``fresh``: the tracker had
    # no state before this update, so a replay can check the updates from here on. An update without
    # a pose on a tracker already fresh changes nothing and is not recorded.
    "lidar_avoid.Tracks": _obj(
        "lidar_avoid.Tracks", timestamp=TIME, time=_num(), fresh=_bool(),
        pose=_obj(None, nullable=True, x=_num(), y=_num(), yaw=_num()), scan=_nullable(_bytes()),
        tracks=_array(_obj("lidar_avoid.Track", id=_int(), x=_num(), y=_num(), vx=_num(), vy=_num(),
                           extent=_num(), widest=_num(), moving=_bool())),
        moving_bins=_array(_int()),
    ),
}


@dataclass(frozen=True)
class Channel:
    """One MCAP channel of the recording."""

    topic: str
    schema: str


SCAN = Channel("/scan", "foxglove.LaserScan")
CLOUD = Channel("/lidar/points", "foxglove.PointCloud")
POLICY = Channel("/policy", "lidar_avoid.PolicyStep")
SHIELD = Channel("/shield", "lidar_avoid.ShieldStep")
SETPOINT = Channel("/setpoint", "lidar_avoid.Setpoint")
TRANSITION = Channel("/supervisor/transition", "lidar_avoid.Transition")
VEHICLE = Channel("/vehicle/status", "lidar_avoid.VehicleStatus")
COUNTERS = Channel("/counters", "lidar_avoid.Counters")
LOG = Channel("/log", "foxglove.Log")
TRACKS = Channel("/tracks", "lidar_avoid.Tracks")
#: the same tracks to look at: a cylinder per track in the body frame, an arrow for a mover's velocity
TRACK_SCENE = Channel("/tracks/scene", "foxglove.SceneUpdate")
# Ground truth (flightsim only).
TRUTH_POSE = Channel("/truth/pose", "foxglove.PoseInFrame")
TRUTH_TF = Channel("/tf", "foxglove.FrameTransform")


def register_schema(name: str, schema: dict[str, Any]) -> None:
    """Add a schema for another channel (flightsim's ground truth; goal and waypoints, ...)."""
    OWN_SCHEMAS[name] = schema


def schema_json(name: str) -> dict[str, Any]:
    """The JSON Schema of ``name`` (Foxglove's or the project's own)."""
    if name in FOXGLOVE_SCHEMAS:
        return FOXGLOVE_SCHEMAS[name]
    return OWN_SCHEMAS[name]


def schema_bytes(name: str) -> bytes:
    """``name``'s JSON Schema as the bytes an MCAP schema record holds."""
    return json.dumps(schema_json(name), separators=(",", ":")).encode()
