"""The simulated autopilot's parameter table answers like ArduPilot (C cast) and PX4 (bytewise)."""

from __future__ import annotations

import struct

import pytest
from pymavlink.dialects.v20 import common as mavlink

from companion.params.codec import decode_param_value, encode_param_value
from flightsim.sitl.sim_autopilot.params import ParameterTable, default_table

INT8 = mavlink.MAV_PARAM_TYPE_INT8
INT32 = mavlink.MAV_PARAM_TYPE_INT32
REAL32 = mavlink.MAV_PARAM_TYPE_REAL32


def wire(msg: mavlink.MAVLink_message) -> mavlink.MAVLink_message:
    """Pack and decode, so the handler sees exactly what a socket would deliver."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    return mav.decode(bytearray(msg.pack(mav)))


def read(name: str, system: int = 1, component: int = 1) -> mavlink.MAVLink_message:
    return wire(mavlink.MAVLink_param_request_read_message(system, component, name.encode(), -1))


def set_(name: str, field: float, param_type: int) -> mavlink.MAVLink_message:
    return wire(mavlink.MAVLink_param_set_message(1, 1, name.encode(), field, param_type))


def test_read_by_name_returns_value_type_index_and_count():
    table = default_table("ardupilot")
    (reply,) = table.handle(read("AVOID_MARGIN"))
    reply = wire(reply)
    assert reply.get_type() == "PARAM_VALUE"
    assert reply.param_id == "AVOID_MARGIN"
    assert reply.param_value == pytest.approx(2.0)
    assert reply.param_type == REAL32
    assert reply.param_count == len(table.names())
    assert table.names()[reply.param_index] == "AVOID_MARGIN"


def test_read_by_index_and_list_cover_every_parameter():
    table = default_table("px4")
    names = table.names()
    by_index = wire(mavlink.MAVLink_param_request_read_message(1, 1, b"", 2))
    assert [m.param_id for m in map(wire, table.handle(by_index))] == [names[2]]
    listing = [wire(m) for m in table.handle(wire(mavlink.MAVLink_param_request_list_message(1, 0)))]
    assert [m.param_id for m in listing] == names
    assert [m.param_index for m in listing] == list(range(len(names)))


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_unknown_name_read_gets_no_reply(personality):
    assert default_table(personality).handle(read("NO_SUCH_PARAM")) == []


def test_unknown_name_set_ardupilot_silent_px4_statustext():
    assert default_table("ardupilot").handle(set_("NO_SUCH_PARAM", 1.0, REAL32)) == []
    (reply,) = default_table("px4").handle(set_("NO_SUCH_PARAM", 1.0, REAL32))
    reply = wire(reply)
    assert reply.get_type() == "STATUSTEXT"
    assert reply.text == "[pm] unknown param: NO_SUCH_PARAM"


def test_unknown_index_px4_statustext():
    msg = wire(mavlink.MAVLink_param_request_read_message(1, 1, b"", 999))
    (reply,) = default_table("px4").handle(msg)
    assert wire(reply).text == "[pm] unknown param ID: 999"
    assert default_table("ardupilot").handle(msg) == []


def test_requests_for_another_system_or_component_are_ignored():
    table = default_table("ardupilot")
    assert table.handle(read("AVOID_MARGIN", system=2)) == []
    assert table.handle(read("AVOID_MARGIN", component=191)) == []
    assert len(table.handle(read("AVOID_MARGIN", component=0))) == 1


def test_ardupilot_set_casts_float_to_integer_type_and_echoes():
    table = default_table("ardupilot")
    (echo,) = table.handle(set_("PRX1_TYPE", 2.0, INT8))
    echo = wire(echo)
    assert table.get("PRX1_TYPE") == 2
    assert (echo.param_id, echo.param_value, echo.param_type) == ("PRX1_TYPE", 2.0, INT8)
    # AP_Param::set_float adds 0.01 away from zero then truncates: 1.995 -> 2, -1.995 -> -2
    table.handle(set_("AVOID_BEHAVE", 0.995, INT8))
    assert table.get("AVOID_BEHAVE") == 1
    table.handle(set_("AVOID_BEHAVE", -1.995, INT8))
    assert table.get("AVOID_BEHAVE") == -2
    table.handle(set_("AVOID_BEHAVE", 1000.0, INT8))  # clamped to int8
    assert table.get("AVOID_BEHAVE") == 127


def test_ardupilot_ignores_nan():
    table = default_table("ardupilot")
    assert table.handle(set_("GUID_TIMEOUT", float("nan"), REAL32)) == []
    assert table.get("GUID_TIMEOUT") == 3.0


def test_px4_bytewise_set_stores_the_bytes():
    table = default_table("px4")
    field = encode_param_value(5, INT32, bytewise=True)
    (echo,) = table.handle(set_("COM_OBL_RC_ACT", field, INT32))
    assert table.get("COM_OBL_RC_ACT") == 5
    echo = wire(echo)
    assert decode_param_value(echo.param_value, INT32, bytewise=True) == 5
    assert struct.pack("<f", echo.param_value) == struct.pack("<i", 5)


def test_px4_trap_plain_float_stores_a_meaningless_integer_but_reads_back_as_the_float():
    """COM_OBL_RC_ACT = 5.0 sent C-cast style: PX4 keeps the bytes of 5.0f as an int32."""
    table = default_table("px4")
    (echo,) = table.handle(set_("COM_OBL_RC_ACT", 5.0, INT32))
    assert table.get("COM_OBL_RC_ACT") == struct.unpack("<i", struct.pack("<f", 5.0))[0] == 1084227584
    echo = wire(echo)
    assert echo.param_value == 5.0  # the naive read-back looks right ...
    assert decode_param_value(echo.param_value, INT32, bytewise=True) == 1084227584  # ... and is not


def test_px4_real32_set_is_a_plain_float():
    table = default_table("px4")
    table.handle(set_("COM_OF_LOSS_T", 0.5, REAL32))
    assert table.get("COM_OF_LOSS_T") == 0.5


def test_capabilities_advertise_the_encoding():
    assert default_table("px4").protocol_capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    ardupilot = default_table("ardupilot").protocol_capabilities
    assert not ardupilot & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
    assert ardupilot & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST


def test_non_parameter_messages_get_no_reply():
    hb = wire(mavlink.MAVLink_heartbeat_message(18, 8, 0, 0, 0, 3))
    assert default_table("ardupilot").handle(hb) == []


def test_defaults_are_firmware_defaults_not_the_wanted_values():
    ardupilot = default_table("ardupilot")
    assert ardupilot.get("PRX1_TYPE") == 0 and ardupilot.get("GUID_TIMEOUT") == 3.0
    px4 = default_table("px4")
    assert px4.get("COM_OBL_RC_ACT") == 0 and px4.get("COM_OF_LOSS_T") == 1.0
    assert px4.param_type("CP_DIST") == REAL32 and px4.param_type("MAV_1_CONFIG") == INT32


def test_bad_table_definitions_are_rejected():
    with pytest.raises(ValueError, match="16 characters"):
        ParameterTable({"A_VERY_LONG_PARAMETER": (1, INT32)}, bytewise=True)
    with pytest.raises(ValueError, match="MAV_PARAM_TYPE"):
        ParameterTable({"X": (1, 99)}, bytewise=True)
    with pytest.raises(ValueError, match="personality"):
        default_table("betaflight")
