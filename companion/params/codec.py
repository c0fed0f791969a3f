"""MAVLink parameter values on the wire: the float field and its two encodings.

PARAM_VALUE and PARAM_SET carry every value in a float32 field. ArduPilot casts the value to
float (C cast). PX4 advertises MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE and puts the bytes
of an integer parameter into the field unchanged: sending 5 as 5.0 to PX4 stores the integer
whose bytes spell 5.0f (1084227584), and a naive read-back still shows 5.0. Both the companion's
parameter check and the simulated autopilot use these functions.
"""

from __future__ import annotations

import struct

from pymavlink.dialects.v20 import common as mavlink

INT_TYPES = {
    mavlink.MAV_PARAM_TYPE_UINT8: "<B",
    mavlink.MAV_PARAM_TYPE_INT8: "<b",
    mavlink.MAV_PARAM_TYPE_UINT16: "<H",
    mavlink.MAV_PARAM_TYPE_INT16: "<h",
    mavlink.MAV_PARAM_TYPE_UINT32: "<I",
    mavlink.MAV_PARAM_TYPE_INT32: "<i",
}
REAL32 = mavlink.MAV_PARAM_TYPE_REAL32


def encode_param_value(value: float, param_type: int, bytewise: bool) -> float:
    """The float to put in PARAM_SET/PARAM_VALUE for ``value`` of ``param_type``."""
    if param_type not in INT_TYPES:
        return float(struct.unpack("<f", struct.pack("<f", value))[0])
    if not bytewise:
        return float(round(value))
    raw = struct.pack(INT_TYPES[param_type], round(value)).ljust(4, b"\0")
    return float(struct.unpack("<f", raw)[0])


def decode_param_value(field: float, param_type: int, bytewise: bool) -> float:
    """The parameter's value (of its own type) from the float field of a PARAM_VALUE."""
    if param_type not in INT_TYPES:
        return float(field)
    if not bytewise:
        return float(round(field))
    fmt = INT_TYPES[param_type]
    raw = struct.pack("<f", field)[: struct.calcsize(fmt)]
    return float(struct.unpack(fmt, raw)[0])
