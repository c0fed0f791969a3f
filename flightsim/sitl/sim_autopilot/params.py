"""The simulated autopilot's parameter table and its side of the MAVLink parameter protocol.

Pure logic: :meth:`ParameterTable.handle` takes a decoded pymavlink message and returns the
messages to send back; the caller owns the socket. It answers the way the real firmwares do
(checked against their sources):

- ArduPilot (``GCS_Param.cpp``): a read or set of an unknown name gets no reply at all; a set
  casts the float to the parameter's own integer type (adding 0.01 away from zero first, then
  truncating, like ``AP_Param::set_float``) and is echoed as PARAM_VALUE; NaN/Inf is ignored.
- PX4 (``mavlink_parameters.cpp``): integer parameters travel bytewise in the float field, and
  PARAM_SET copies the field's four bytes into the parameter whatever ``param_type`` says, so
  5.0 sent as a float to an INT32 parameter stores 1084227584. A read of an unknown name gets no
  reply; a set of an unknown name gets only a STATUSTEXT ``[pm] unknown param: NAME``; a read of an
  unknown index gets ``[pm] unknown param ID: N``.

The default tables hold each firmware's DEFAULT values for the parameters the companion relies
on (see ``firmware_params/``), so ``avoid-companion params check`` fails against a fresh simulator
and ``params apply`` fixes it, as on a new flight controller.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

from companion.params.codec import INT_TYPES, REAL32, decode_param_value, encode_param_value

INT8 = mavlink.MAV_PARAM_TYPE_INT8
INT32 = mavlink.MAV_PARAM_TYPE_INT32

# Integer range of each MAVLink integer parameter type, for ArduPilot's clamp on set.
_INT_LIMITS = {
    mavlink.MAV_PARAM_TYPE_UINT8: (0, 2**8 - 1),
    mavlink.MAV_PARAM_TYPE_INT8: (-(2**7), 2**7 - 1),
    mavlink.MAV_PARAM_TYPE_UINT16: (0, 2**16 - 1),
    mavlink.MAV_PARAM_TYPE_INT16: (-(2**15), 2**15 - 1),
    mavlink.MAV_PARAM_TYPE_UINT32: (0, 2**32 - 1),
    mavlink.MAV_PARAM_TYPE_INT32: (-(2**31), 2**31 - 1),
}


@dataclass
class Parameter:
    """One entry of the table: its value (of its own type) and its MAV_PARAM_TYPE."""

    value: float
    param_type: int


class ParameterTable:
    """Named parameters of one simulated autopilot, in a fixed order (the order gives the index).

    :param params: name -> (value, MAV_PARAM_TYPE); names are at most 16 characters
    :param bytewise: PX4 personality (integers bytewise in the float field) when True,
        ArduPilot (C cast) when False
    :param system_id: the autopilot's MAVLink system id; requests for another system are ignored
    :param component_id: the autopilot's component id (requests to it or to 0 = all are answered)
    """

    def __init__(
        self,
        params: dict[str, tuple[float, int]],
        bytewise: bool,
        system_id: int = 1,
        component_id: int = 1,
    ) -> None:
        for name, (_, param_type) in params.items():
            if len(name) > 16:
                raise ValueError(f"parameter name longer than 16 characters: {name}")
            if param_type not in INT_TYPES and param_type != REAL32:
                raise ValueError(f"{name}: unsupported MAV_PARAM_TYPE {param_type}")
        self._params = {name: Parameter(float(v), t) for name, (v, t) in params.items()}
        self._names = list(self._params)
        self.bytewise = bytewise
        self.system_id = system_id
        self.component_id = component_id

    @property
    def protocol_capabilities(self) -> int:
        """The parameter-encoding bits of AUTOPILOT_VERSION.capabilities for this personality."""
        encoding = (
            mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
            if self.bytewise
            else mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
        )
        return encoding | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2

    def names(self) -> list[str]:
        """Parameter names in index order."""
        return list(self._names)

    def get(self, name: str) -> float | None:
        """The stored value of ``name`` (of the parameter's own type), None when unknown."""
        entry = self._params.get(name)
        return None if entry is None else entry.value

    def param_type(self, name: str) -> int | None:
        """The MAV_PARAM_TYPE of ``name``, None when unknown."""
        entry = self._params.get(name)
        return None if entry is None else entry.param_type

    def set(self, name: str, value: float) -> None:
        """Set a known parameter directly (the simulator's own side, not over MAVLink)."""
        entry = self._params[name]
        entry.value = float(round(value)) if entry.param_type in INT_TYPES else _as_float32(value)

    def handle(self, msg: mavlink.MAVLink_message) -> list[mavlink.MAVLink_message]:
        """Answer one parameter-protocol message; anything else (or addressed elsewhere) gets []."""
        kind = msg.get_type()
        if kind not in ("PARAM_REQUEST_READ", "PARAM_REQUEST_LIST", "PARAM_SET"):
            return []
        if msg.target_system != self.system_id or msg.target_component not in (0, self.component_id):
            return []
        if kind == "PARAM_REQUEST_LIST":
            return [self._value_message(name) for name in self._names]
        if kind == "PARAM_REQUEST_READ":
            return self._handle_read(msg)
        return self._handle_set(msg)

    def _handle_read(self, msg: mavlink.MAVLink_param_request_read_message) -> list[mavlink.MAVLink_message]:
        if msg.param_index >= 0:
            if msg.param_index < len(self._names):
                return [self._value_message(self._names[msg.param_index])]
            if self.bytewise:
                return [_statustext(f"[pm] unknown param ID: {msg.param_index}")]
            return []
        name = _param_id(msg.param_id)
        return [self._value_message(name)] if name in self._params else []

    def _handle_set(self, msg: mavlink.MAVLink_param_set_message) -> list[mavlink.MAVLink_message]:
        name = _param_id(msg.param_id)
        entry = self._params.get(name)
        if entry is None:
            return [_statustext(f"[pm] unknown param: {name}")] if self.bytewise else []
        if self.bytewise:
            # PX4: param_set() copies the four bytes of the field, whatever msg.param_type says.
            entry.value = decode_param_value(msg.param_value, entry.param_type, bytewise=True)
        else:
            if not math.isfinite(msg.param_value):
                return []
            entry.value = _ardupilot_set_float(msg.param_value, entry.param_type)
        return [self._value_message(name)]

    def _value_message(self, name: str) -> mavlink.MAVLink_param_value_message:
        entry = self._params[name]
        field = encode_param_value(entry.value, entry.param_type, self.bytewise)
        return mavlink.MAVLink_param_value_message(
            name.encode("ascii"), field, entry.param_type, len(self._names), self._names.index(name)
        )


def _param_id(raw: str | bytes) -> str:
    """A param_id field as text, without the NUL padding."""
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", errors="replace")
    return raw.split("\0", 1)[0]


def _as_float32(value: float) -> float:
    return float(struct.unpack("<f", struct.pack("<f", value))[0])


def _ardupilot_set_float(value: float, param_type: int) -> float:
    """``AP_Param::set_float``: floats kept; integers nudged 0.01 away from zero, clamped, truncated."""
    if param_type == REAL32:
        return _as_float32(value)
    low, high = _INT_LIMITS[param_type]
    nudged = value + math.copysign(0.01, value) if value != 0 else 0.0
    return float(math.trunc(min(max(nudged, low), high)))


def _statustext(text: str) -> mavlink.MAVLink_statustext_message:
    return mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_INFO, text.encode("ascii")[:50])


# Firmware DEFAULTS of the parameters the companion relies on (firmware_params/ holds the wanted
# values). Types and defaults as in ArduPilot's @Param tables (AP_SerialManager, ArduCopter
# Parameters.cpp, AP_Proximity_Params, AC_Avoid) and PX4's parameter definitions (mavlink
# module.yaml, serial params, commander_params.c, collisionprevention_params.c).
ARDUPILOT_DEFAULTS: dict[str, tuple[float, int]] = {
    "SERIAL2_PROTOCOL": (2, INT8),
    "SERIAL2_BAUD": (57, INT32),
    "GUID_TIMEOUT": (3.0, REAL32),
    "PRX1_TYPE": (0, INT8),
    "AVOID_ENABLE": (3, INT8),
    "AVOID_MARGIN": (2.0, REAL32),
    "AVOID_BEHAVE": (0, INT8),
    "ATC_RATE_WPY_MAX": (60.0, REAL32),
}

PX4_DEFAULTS: dict[str, tuple[float, int]] = {
    "MAV_1_CONFIG": (0, INT32),
    "MAV_1_MODE": (2, INT32),
    "MAV_1_FORWARD": (0, INT32),
    "SER_TEL2_BAUD": (921600, INT32),
    "COM_OF_LOSS_T": (1.0, REAL32),
    "COM_OBL_RC_ACT": (0, INT32),
    "COM_RC_OVERRIDE": (1, INT32),
    "CP_DIST": (-1.0, REAL32),
    "MC_YAWRATE_MAX": (200.0, REAL32),
}


def default_table(personality: str, system_id: int = 1, component_id: int = 1) -> ParameterTable:
    """A fresh table at firmware defaults.

    :param personality: ``"ardupilot"`` or ``"px4"``
    """
    if personality == "ardupilot":
        return ParameterTable(
            ARDUPILOT_DEFAULTS, bytewise=False, system_id=system_id, component_id=component_id
        )
    if personality == "px4":
        return ParameterTable(PX4_DEFAULTS, bytewise=True, system_id=system_id, component_id=component_id)
    raise ValueError(f"unknown autopilot personality: {personality!r} (ardupilot or px4)")
