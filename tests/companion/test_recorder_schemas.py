"""The recorder's Foxglove schemas are Foxglove's: field for field against the protobuf descriptors
that Foxglove's own SDK (``foxglove-sdk``) ships, and every message builder's output validates
against the schema its channel declares."""

from __future__ import annotations

import json

import foxglove.messages as foxglove_messages
import jsonschema
import numpy as np
import pytest
from google.protobuf import descriptor_pb2

from companion.recording import messages as m
from companion.recording import schemas as s

# protobuf FieldDescriptorProto types -> JSON Schema type
_DOUBLE, _FLOAT, _INT32, _FIXED32, _UINT32, _STRING, _MESSAGE, _BYTES, _ENUM = 1, 2, 5, 7, 13, 9, 11, 12, 14
_BOOL = 8
_REPEATED = 3


def _descriptors(name: str) -> tuple[dict, dict]:
    """All message and enum descriptors of Foxglove's schema ``name`` (by full name)."""
    fds = descriptor_pb2.FileDescriptorSet.FromString(getattr(foxglove_messages, name).get_schema().data)
    msgs, enums = {}, {}
    for f in fds.file:
        for msg in f.message_type:
            msgs[f".{f.package}.{msg.name}"] = msg
            for e in msg.enum_type:
                enums[f".{f.package}.{msg.name}.{e.name}"] = e
        for e in f.enum_type:
            enums[f".{f.package}.{e.name}"] = e
    return msgs, enums


def _check(ours: dict, proto, msgs: dict, enums: dict, where: str) -> None:
    if proto.name in ("Timestamp", "Duration"):  # Foxglove's JSON encoding of google.protobuf's
        assert set(ours["properties"]) == {"sec", "nsec"}, where
        return
    assert set(ours["properties"]) == {f.name for f in proto.field}, where
    for f in proto.field:
        mine = ours["properties"][f.name]
        here = f"{where}.{f.name}"
        if f.label == _REPEATED:
            assert mine["type"] == "array", here
            mine = mine["items"]
        if f.type in (_DOUBLE, _FLOAT):
            assert mine["type"] == "number", here
        elif f.type in (_INT32, _FIXED32, _UINT32):
            assert mine["type"] == "integer", here
        elif f.type == _STRING:
            assert mine["type"] == "string", here
        elif f.type == _BOOL:
            assert mine["type"] == "boolean", here
        elif f.type == _BYTES:
            assert mine == {"type": "string", "contentEncoding": "base64"}, here
        elif f.type == _ENUM:
            values = [v.number for v in enums[f.type_name].value]
            assert mine["type"] == "integer", here
            assert (mine["minimum"], mine["maximum"]) == (min(values), max(values)), here
        elif f.type == _MESSAGE:
            _check(mine, msgs[f.type_name], msgs, enums, here)
        else:
            raise AssertionError(f"{here}: protobuf type {f.type} not handled")


@pytest.mark.parametrize("name", sorted(s.FOXGLOVE_SCHEMAS))
def test_foxglove_schema_matches_foxglove_sdk(name):
    short = name.split(".", 1)[1]
    msgs, enums = _descriptors(short)
    _check(s.FOXGLOVE_SCHEMAS[name], msgs[f".foxglove.{short}"], msgs, enums, name)


def test_a_wrong_field_name_is_caught():
    """The comparison can fail: a schema with a misspelt field does not pass."""
    msgs, enums = _descriptors("LaserScan")
    wrong = dict(s.FOXGLOVE_SCHEMAS["foxglove.LaserScan"])
    wrong["properties"] = {("range" if k == "ranges" else k): v for k, v in wrong["properties"].items()}
    with pytest.raises(AssertionError):
        _check(wrong, msgs[".foxglove.LaserScan"], msgs, enums, "LaserScan")


def test_built_messages_validate_against_their_channel_schemas():
    scan = np.linspace(0.1, 1.0, 360).astype(np.float32)
    cloud = np.random.default_rng(3).normal(size=(50, 3)).astype(np.float32)
    pose = m.identity_pose((1.0, 2.0, 0.1), m.quaternion_from_rpy(0.0, 0.1, 1.0))
    cases = [
        (s.SCAN, m.laser_scan(12.5, scan, 10.0)),
        (s.CLOUD, m.point_cloud(12.5, cloud, pose)),
        (s.LOG, m.log(12.5, 3, "avoid STANDBY->ACTIVE: engaged")),
    ]
    for channel, msg in cases:  # what is written: the JSON bytes, base64 fields spliced in as strings
        jsonschema.validate(json.loads(m.to_json(msg)), s.schema_json(channel.schema))
    scan_msg = cases[0][1]
    assert len(scan_msg["ranges"]) == 360 and scan_msg["ranges"][-1] == pytest.approx(10.0)
    assert scan_msg["start_angle"] == pytest.approx(np.radians(0.5))
    assert scan_msg["end_angle"] == pytest.approx(np.radians(359.5))
    assert np.array_equal(m.unpack_f32(json.loads(m.to_json(cases[1][1]))["data"]).reshape(-1, 3), cloud)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**scan_msg, "ranges": "far"}, s.schema_json("foxglove.LaserScan"))


def test_quaternion_from_rpy_is_a_unit_quaternion_with_the_right_yaw():
    x, y, z, w = m.quaternion_from_rpy(0.0, 0.0, np.pi / 2)
    assert (x, y) == (0.0, 0.0) and z == pytest.approx(np.sqrt(0.5)) and w == pytest.approx(np.sqrt(0.5))
    q = np.array(m.quaternion_from_rpy(0.3, -0.2, 2.0))
    assert np.linalg.norm(q) == pytest.approx(1.0)


def test_the_tracks_and_their_scene_validate_against_their_channel_schemas():
    """/tracks and /tracks/scene, as the recorder builds them from one tracker update: a mover ahead
    of a vehicle heading north, a pillar still; and an update without a pose (the tracker reset)."""
    from companion.perception.tracking import Track, TrackerOutput
    from companion.recording.recorder import _tracks, track_rows

    mover = Track(3, np.array([1.0, 4.0, 0.8, 0.0]), np.eye(4), 1.0, hits=5, extent=0.4, widest=0.5)
    pillar = Track(4, np.array([-2.0, 3.0, 0.0, 0.0]), np.eye(4), 1.0, hits=9, extent=0.5, widest=0.6)
    moving_bins = np.zeros(360, dtype=bool)
    moving_bins[[1, 2, 3]] = True
    rows, bins = track_rows(TrackerOutput([mover, pillar], [mover], moving_bins))
    assert rows[0] == (3, 1.0, 4.0, 0.8, 0.0, 0.4, 0.5, True) and rows[1][-1] is False and bins == [1, 2, 3]
    pose = (1.0, 2.0, np.pi / 2)
    scan = np.full(360, 0.5, dtype=np.float32)
    tracks = _tracks(12.5, pose, False, scan, rows, bins)
    scene = m.scene_update(12.5, pose, rows)
    for channel, msg in ((s.TRACKS, tracks), (s.TRACK_SCENE, scene)):
        jsonschema.validate(json.loads(m.to_json(msg)), s.schema_json(channel.schema))
    assert np.array_equal(m.unpack_f32(json.loads(m.to_json(tracks))["scan"]), scan)
    first = scene["entities"][0]
    assert first["frame_id"] == s.BODY_FRAME and first["id"] == "track-3"
    # 2 m ahead of the vehicle, moving to its right at 0.8 m/s: the arrow points right, 0.8 m long
    assert (
        first["cylinders"][0]["pose"]["position"]["x"],
        first["cylinders"][0]["pose"]["position"]["y"],
    ) == (
        pytest.approx(2.0),
        pytest.approx(0.0, abs=1e-9),
    )
    (arrow,) = first["arrows"]
    assert arrow["shaft_length"] == pytest.approx(0.8) and arrow["pose"]["orientation"]["z"] == pytest.approx(
        -np.sqrt(0.5)
    )
    assert scene["entities"][1]["arrows"] == [] and scene["deletions"][0]["type"] == s.DELETE_ALL
    reset = _tracks(12.6, None, False, None, [], [])
    jsonschema.validate(json.loads(m.to_json(reset)), s.schema_json(s.TRACKS.schema))
    assert m.scene_update(12.6, None, [])["entities"] == []
