"""Parameter files, comparison, and `avoid-companion params check|apply` against a real MAVLink peer.

The peer is a pymavlink UDP endpoint on loopback in a thread, serving the simulated autopilot's
parameter table (ArduPilot C-cast or PX4 bytewise personality), sending HEARTBEATs and answering
the AUTOPILOT_VERSION request, so every byte the companion exchanges is real MAVLink 2.
"""

from __future__ import annotations

import math
import os
import struct
import threading
import time
from pathlib import Path

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from companion.__main__ import main
from companion.common.errors import UserError
from companion.params.check import (
    Status,
    compare_parameter,
    needs_reboot,
    read_and_compare,
    run_params,
    values_match,
    yaw_rate_limit,
)
from companion.params.client import MavlinkParamClient, open_connection, wait_for_autopilot
from companion.params.codec import encode_param_value
from companion.params.files import WantedParam, default_param_file, load_param_file
from flightsim.sitl.sim_autopilot.params import ParameterTable, default_table

REPO = Path(__file__).resolve().parents[2]
INT8, INT32, REAL32 = mavlink.MAV_PARAM_TYPE_INT8, mavlink.MAV_PARAM_TYPE_INT32, mavlink.MAV_PARAM_TYPE_REAL32
FAST = ["--timeout", "0.3", "--retries", "1", "--heartbeat-timeout", "5"]


class ParamPeer(threading.Thread):
    """A simulated autopilot's MAVLink side: heartbeat, AUTOPILOT_VERSION, parameter protocol.

    :param version: "yes" answers MAV_CMD_REQUEST_MESSAGE; "legacy" rejects it and answers only
        MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES; "no" answers neither
    """

    def __init__(self, table: ParameterTable, version: str = "yes") -> None:
        super().__init__(daemon=True)
        self.table = table
        self.version = version
        os.environ["MAVLINK20"] = "1"  # pymavlink picks the wire protocol from the environment
        self.autopilot = mavlink.MAV_AUTOPILOT_PX4 if table.bytewise else mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
        self.conn = mavutil.mavlink_connection(
            "udpin:127.0.0.1:0", source_system=1, source_component=1, dialect="common"
        )
        self.url = f"udpout:127.0.0.1:{self.conn.port.getsockname()[1]}"
        self.received: list[str] = []
        self._halt = threading.Event()

    def run(self) -> None:
        next_beat = 0.0
        while not self._halt.is_set():
            if self.conn.clients and time.monotonic() >= next_beat:
                self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, self.autopilot, 0, 0, 0)
                next_beat = time.monotonic() + 0.2
            msg = self.conn.recv_match(blocking=True, timeout=0.05)
            if msg is None or msg.get_type() == "BAD_DATA":
                continue
            self.received.append(msg.get_type())
            for reply in self.table.handle(msg):
                self.conn.mav.send(reply)
            if msg.get_type() == "COMMAND_LONG":
                self._command(msg)

    def _command(self, msg) -> None:
        wants_version = msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE and int(msg.param1) == 148
        legacy = msg.command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES
        answer = (self.version == "yes" and wants_version) or (self.version == "legacy" and legacy)
        result = mavlink.MAV_RESULT_ACCEPTED if answer else mavlink.MAV_RESULT_UNSUPPORTED
        self.conn.mav.command_ack_send(msg.command, result)
        if answer:
            caps = self.table.protocol_capabilities
            self.conn.mav.autopilot_version_send(caps, 0, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0)

    def stop(self) -> None:
        self._halt.set()
        self.join(timeout=2)
        self.conn.close()


@pytest.fixture
def peer_factory():
    peers: list[ParamPeer] = []

    def make(personality: str, version: str = "yes", table: ParameterTable | None = None) -> ParamPeer:
        peer = ParamPeer(table or default_table(personality), version)
        peer.start()
        peers.append(peer)
        return peer

    yield make
    for peer in peers:
        peer.stop()


def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# ---------------------------------------------------------------------------------------- files


def test_repository_files_parse_with_their_types():
    parm = REPO / "firmware_params/ardupilot-copter.parm"
    ardupilot = {p.name: p for p in load_param_file(parm, "ardupilot")}
    assert ardupilot["SERIAL2_BAUD"].value == 921 and ardupilot["PRX1_TYPE"].value == 0
    assert ardupilot["ATC_RATE_WPY_MAX"].value == 86  # the policy's 1.5 rad/s
    assert {"SERIAL2_PROTOCOL", "GUID_TIMEOUT"} <= set(ardupilot)
    assert all(p.param_type is None for p in ardupilot.values())
    px4 = {p.name: p for p in load_param_file(REPO / "firmware_params/px4.params", "px4")}
    assert px4["COM_OBL_RC_ACT"].value == 5 and px4["COM_OBL_RC_ACT"].param_type == INT32
    assert px4["MAV_1_CONFIG"].value == 102 and px4["CP_DIST"].param_type == REAL32
    assert px4["CP_DIST"].value == -1.0 and px4["MC_YAWRATE_MAX"].value >= 86
    assert {"MAV_1_MODE", "MAV_1_FORWARD", "SER_TEL2_BAUD", "COM_OF_LOSS_T"} <= set(px4)


def test_every_file_parameter_exists_in_the_simulated_firmware():
    """The sim table (firmware defaults) and the files name the same parameters, with the same types."""
    for personality, name in (("ardupilot", "ardupilot-copter.parm"), ("px4", "px4.params")):
        table = default_table(personality)
        for p in load_param_file(REPO / "firmware_params" / name, personality):
            assert table.get(p.name) is not None, p.name
            assert p.param_type in (None, table.param_type(p.name)), p.name


def test_yaw_rate_limit_read_from_a_check_report():
    from companion.params.check import CheckReport, ParamResult

    def report(name, actual):
        wanted = WantedParam(name, 86.0, None, 1, "f")
        return CheckReport([ParamResult(wanted, Status.DIFFERS, actual, REAL32)], False, "test")

    assert yaw_rate_limit(report("ATC_RATE_WPY_MAX", 60.0), "ardupilot") == pytest.approx(math.radians(60.0))
    assert yaw_rate_limit(report("ATC_RATE_WPY_MAX", 0.0), "ardupilot") is None  # 0: no cap of its own
    assert yaw_rate_limit(report("ATC_RATE_WPY_MAX", None), "ardupilot") is None  # no reply
    assert yaw_rate_limit(report("MC_YAWRATE_MAX", 200.0), "px4") == pytest.approx(math.radians(200.0))
    assert yaw_rate_limit(report("GUID_TIMEOUT", 1.0), "ardupilot") is None  # not in the file


def test_default_file_is_the_checkout_copy():
    assert default_param_file("px4") == REPO / "firmware_params/px4.params"


def test_parm_accepts_commas_trailing_comments_and_hex(tmp_path):
    path = write(tmp_path, "a.parm", "# header\n\nFOO_BAR,1.5  # why\nbaz 0x10\n")
    params = load_param_file(path, "ardupilot")
    assert [(p.name, p.value, p.line) for p in params] == [("FOO_BAR", 1.5, 3), ("BAZ", 16.0, 4)]


@pytest.mark.parametrize(
    ("autopilot", "text", "message"),
    [
        ("ardupilot", "A 1\nB\n", r"a\.parm:2: expected 'NAME VALUE'"),
        ("ardupilot", "A 1 2\n", r"a\.parm:1: expected 'NAME VALUE'"),
        ("ardupilot", "A one\n", r"a\.parm:1: value 'one' is not a number"),
        ("ardupilot", "A nan\n", r"a\.parm:1: value 'nan' is not a finite number"),
        ("ardupilot", "A-B 1\n", r"a\.parm:1: 'A-B' is not a parameter name"),
        ("ardupilot", "A 1\nA 2\n", r"a\.parm:2: A already set on line 1"),
        ("ardupilot", "# nothing\n", r"no parameters"),
        ("px4", "1 1 A 1 6\n", r"a\.parm:1: expected 5 tab-separated fields"),
        ("px4", "1\t1\tA\t1\t8\n", r"a\.parm:1: A: unknown parameter type '8'"),
        ("px4", "1\t1\tA\t1\tINT\n", r"unknown parameter type 'INT'"),
        ("px4", "1\t1\tA\t1.5\t6\n", r"a\.parm:1: A is INT32 but the value 1.5 is not an integer"),
        ("px4", "x\t1\tA\t1\t6\n", r"vehicle id 'x' is not a number"),
    ],
)
def test_bad_file_lines_name_file_and_line(tmp_path, autopilot, text, message):
    with pytest.raises(UserError, match=message):
        load_param_file(write(tmp_path, "a.parm", text), autopilot)


def test_missing_file_is_a_user_error(tmp_path):
    with pytest.raises(UserError, match="cannot read parameter file"):
        load_param_file(tmp_path / "nope.params", "px4")


def test_bad_file_through_the_cli_is_one_line_exit_2(tmp_path, capsys):
    path = write(tmp_path, "bad.params", "1\t1\tCP_DIST\t1.0\n")
    code = main(cli("check", "px4", "udpin:127.0.0.1:0", "--file", str(path)))
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and "bad.params:1: expected 5 tab-separated fields" in err


def test_unopenable_connection_is_a_user_error(capsys):
    code = main(["params", "check", "--autopilot", "ardupilot", "--connect", "/dev/no-such-tty"])
    assert code == 2
    assert "cannot open MAVLink connection '/dev/no-such-tty'" in capsys.readouterr().err


# ----------------------------------------------------------------------------------- comparison


def wanted(name: str, value: float, param_type: int | None = None) -> WantedParam:
    return WantedParam(name, value, param_type, 1, "test")


def test_compare_integer_and_float_values():
    assert compare_parameter(wanted("A", 5), (5.0, INT32)).status is Status.OK
    assert compare_parameter(wanted("A", 5), (4.0, INT32)).status is Status.DIFFERS
    # 0.1 travels as float32: 0.10000000149011612 must count as 0.1
    f32 = struct.unpack("<f", struct.pack("<f", 0.1))[0]
    assert compare_parameter(wanted("A", 0.1), (f32, REAL32)).status is Status.OK
    assert compare_parameter(wanted("A", 0.1), (0.2, REAL32)).status is Status.DIFFERS
    assert not values_match(2.5, 2.0, INT8)


def test_compare_unknown_and_type_mismatch():
    assert compare_parameter(wanted("A", 1), None).status is Status.UNKNOWN
    result = compare_parameter(wanted("A", 1.0, REAL32), (1.0, INT32))
    assert result.status is Status.TYPE_MISMATCH and not result.ok
    assert compare_parameter(wanted("A", 1.0, None), (1.0, INT32)).ok  # .parm files take the autopilot's type


def test_reboot_required_parameters():
    assert needs_reboot("ardupilot", "SERIAL2_BAUD") and needs_reboot("ardupilot", "PRX1_TYPE")
    assert not needs_reboot("ardupilot", "AVOID_MARGIN")
    assert needs_reboot("px4", "MAV_1_CONFIG") and needs_reboot("px4", "SER_TEL2_BAUD")
    assert not needs_reboot("px4", "COM_OBL_RC_ACT")


# ------------------------------------------------------------------------------ over the wire


def cli(action: str, personality: str, url: str, *extra: str) -> list[str]:
    return ["params", action, "--autopilot", personality, "--connect", url, *FAST, *extra]


@pytest.mark.parametrize("personality", ["ardupilot", "px4"])
def test_check_fails_on_fresh_autopilot_apply_fixes_check_passes(peer_factory, capsys, personality):
    peer = peer_factory(personality)
    assert main(cli("check", personality, peer.url)) == 1
    out = capsys.readouterr().out
    first = "ATC_RATE_WPY_MAX" if personality == "ardupilot" else "COM_OBL_RC_ACT"
    row = next(line for line in out.splitlines() if line.startswith(first))
    assert row.split()[1:4] == (["86", "60", "NO"] if personality == "ardupilot" else ["5", "0", "NO"])
    encoding = "bytewise" if personality == "px4" else "C cast"
    assert f"value encoding: {encoding} (from AUTOPILOT_VERSION capabilities)" in out
    assert "PARAM_SET" not in peer.received  # check never writes

    assert main(cli("apply", personality, peer.url)) == 0
    out = capsys.readouterr().out
    if personality == "ardupilot":
        assert "changed SERIAL2_BAUD: 57 -> 921 (needs reboot)" in out
        assert "changed ATC_RATE_WPY_MAX: 60 -> 86" in out and "WPY_MAX: 60 -> 86 (needs reboot)" not in out
        assert peer.table.get("ATC_RATE_WPY_MAX") == 86 and peer.table.get("GUID_TIMEOUT") == 1.0
    else:
        assert "changed COM_OBL_RC_ACT: 0 -> 5" in out
        assert "changed MAV_1_CONFIG: 0 -> 102 (needs reboot)" in out
        assert peer.table.get("COM_OBL_RC_ACT") == 5  # the integer 5, not the bytes of 5.0f
        assert peer.table.get("COM_OF_LOSS_T") == 0.5
    assert "reboot the autopilot for" in out

    assert main(cli("check", personality, peer.url)) == 0
    assert "NO" not in capsys.readouterr().out


def test_plain_float_to_bytewise_autopilot_is_detected_as_wrong(peer_factory, capsys):
    """COM_OBL_RC_ACT = 5.0 written C-cast style to PX4 stores 1084227584; the check catches it."""
    peer = peer_factory("px4")
    conn = open_connection(peer.url, 921600)
    try:
        info = wait_for_autopilot(conn, 5)
        naive = MavlinkParamClient(conn, info.system_id, info.component_id, timeout=0.5, bytewise=False)
        echo = naive.write("COM_OBL_RC_ACT", 5, INT32)
        assert echo == (5.0, INT32)  # the naive read-back looks right
    finally:
        conn.close()
    assert peer.table.get("COM_OBL_RC_ACT") == 1084227584
    assert main(cli("check", "px4", peer.url)) == 1
    row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("COM_OBL_RC_ACT"))
    assert row.split()[1:4] == ["5", "1084227584", "NO"]


def test_unknown_parameter_is_reported_by_name_with_bounded_retries(peer_factory, tmp_path, capsys):
    peer = peer_factory("px4")
    path = write(tmp_path, "x.params", "1\t1\tNO_SUCH_PARAM\t1\t6\n1\t1\tCP_DIST\t-1.0\t9\n")
    started = time.monotonic()
    assert main(cli("apply", "px4", peer.url, "--file", str(path))) == 1
    elapsed = time.monotonic() - started
    out = capsys.readouterr().out
    assert "NO_SUCH_PARAM" in out and "NO (unknown to the autopilot)" in out
    assert "unknown to this autopilot (it answers other names): NO_SUCH_PARAM;" in out
    assert "1/2 parameters as wanted" in out
    # 1 version request + 2 attempts (retries 1) for the unknown name + 1 read by index (answered:
    # the link is alive, so the name is unknown) + 1 read of CP_DIST
    assert "link: 5 requests, 1 retries, 2 timeouts" in out
    assert peer.received.count("PARAM_REQUEST_READ") == 4
    assert "PARAM_SET" not in peer.received  # an unknown name is never written
    assert elapsed < 3


def test_type_mismatch_is_reported_and_not_written(peer_factory, tmp_path, capsys):
    peer = peer_factory("px4")
    path = write(tmp_path, "x.params", "1\t1\tCP_DIST\t2\t6\n")
    assert main(cli("apply", "px4", peer.url, "--file", str(path))) == 1
    out = capsys.readouterr().out
    assert "NO (type mismatch): file says INT32, autopilot REAL32" in out
    assert peer.table.get("CP_DIST") == -1.0 and "PARAM_SET" not in peer.received


@pytest.mark.parametrize(
    ("version", "source"),
    [
        ("legacy", "AUTOPILOT_VERSION capabilities"),
        ("no", "HEARTBEAT autopilot type (no AUTOPILOT_VERSION reply)"),
    ],
)
def test_encoding_without_request_message(peer_factory, version, source):
    peer = peer_factory("px4", version=version)
    conn = open_connection(peer.url, 921600)
    try:
        wanted_list = load_param_file(REPO / "firmware_params/px4.params", "px4")
        report = run_params(conn, "px4", wanted_list, apply=True, timeout=0.3, retries=1, heartbeat_timeout=5)
    finally:
        conn.close()
    assert report.bytewise and report.encoding_source == source
    assert report.ok and peer.table.get("COM_OBL_RC_ACT") == 5


def test_file_for_the_other_firmware_is_refused(peer_factory, capsys):
    peer = peer_factory("px4")
    assert main(cli("check", "ardupilot", peer.url)) == 2
    assert "--autopilot ardupilot, but the autopilot on the link identifies as px4" in capsys.readouterr().err


def test_write_to_unknown_name_on_px4_returns_at_once(peer_factory):
    """PX4's STATUSTEXT '[pm] unknown param: NAME' ends the wait without using up the retries."""
    peer = peer_factory("px4")
    conn = open_connection(peer.url, 921600)
    try:
        info = wait_for_autopilot(conn, 5)
        client = MavlinkParamClient(
            conn, info.system_id, info.component_id, timeout=2.0, retries=3, bytewise=True
        )
        started = time.monotonic()
        assert client.write("NO_SUCH_PARAM", 1, INT32) is None
        assert time.monotonic() - started < 1.5
        assert client.stats.requests == 1
        assert client.write("CP_DIST", 1.5, REAL32) == (1.5, REAL32)
        assert encode_param_value(1.5, REAL32, True) == 1.5
    finally:
        conn.close()


@pytest.mark.parametrize(
    ("personality", "link", "scheme"),
    [("ardupilot", "tcpin:127.0.0.1:0", "tcp"), ("px4", "udpin:127.0.0.1:0", "udpout")],
)
def test_against_the_simulated_autopilot(capsys, personality, link, scheme):
    """The whole simulated flight controller (flightsim.sitl.sim_autopilot), not only its table."""
    from flightsim.sitl.sim_autopilot.server import SimAutopilotServer

    with SimAutopilotServer(personality, [link]) as server:
        host, port = server.endpoint.address(0)
        url = f"{scheme}:{host}:{port}"
        assert main(cli("check", personality, url)) == 1
        assert main(cli("apply", personality, url)) == 0
        assert main(cli("check", personality, url)) == 0
        wanted_file = "ardupilot-copter.parm" if personality == "ardupilot" else "px4.params"
        for p in load_param_file(REPO / "firmware_params" / wanted_file, personality):
            assert server.autopilot.params.get(p.name) == pytest.approx(p.value), p.name
    assert "value encoding: " + ("bytewise" if personality == "px4" else "C cast") in capsys.readouterr().out


# ------------------------------------------------------- unknown names, lost links, --allow-missing


def _px4_sitl_table() -> ParameterTable:
    """PX4 at defaults without the TELEM2 parameters, as a PX4 SITL (no such serial port) has it."""
    from flightsim.sitl.sim_autopilot.params import PX4_DEFAULTS

    sitl = {k: v for k, v in PX4_DEFAULTS.items() if k not in ("MAV_1_CONFIG", "SER_TEL2_BAUD")}
    return ParameterTable(sitl, bytewise=True)


def test_a_sitl_without_telem2_fails_strictly_and_passes_with_allow_missing(peer_factory, capsys):
    peer = peer_factory("px4", table=_px4_sitl_table())
    assert main(cli("apply", "px4", peer.url)) == 1  # strict by default: a real board must have them
    out = capsys.readouterr().out
    assert "MAV_1_CONFIG" in out and "NO (unknown to the autopilot)" in out
    assert "unknown to this autopilot (it answers other names): MAV_1_CONFIG, SER_TEL2_BAUD;" in out
    assert "--allow-missing MAV_1_CONFIG,SER_TEL2_BAUD accepts that" in out
    assert "differ from the file" not in out  # apply set everything else

    assert main(cli("check", "px4", peer.url, "--allow-missing", "MAV_1_CONFIG,SER_TEL2_BAUD")) == 0
    out = capsys.readouterr().out
    assert "absent, allowed by --allow-missing: MAV_1_CONFIG, SER_TEL2_BAUD" in out
    assert "unknown to this autopilot" not in out


def test_a_differing_value_and_an_unknown_name_are_told_apart(peer_factory, tmp_path, capsys):
    peer = peer_factory("px4", table=_px4_sitl_table())
    path = write(tmp_path, "x.params", "1\t1\tMAV_1_CONFIG\t102\t6\n1\t1\tCP_DIST\t2.0\t9\n")
    assert main(cli("check", "px4", peer.url, "--file", str(path))) == 1
    out = capsys.readouterr().out
    assert "differ from the file: CP_DIST" in out
    assert "unknown to this autopilot (it answers other names): MAV_1_CONFIG;" in out
    # an allowance covers a missing name only, never a wrong value
    assert (
        main(cli("check", "px4", peer.url, "--file", str(path), "--allow-missing", "MAV_1_CONFIG,CP_DIST"))
        == 1
    )
    assert "differ from the file: CP_DIST" in capsys.readouterr().out


def test_silence_from_a_lost_link_is_not_called_unknown(peer_factory):
    peer = peer_factory("px4")
    conn = open_connection(peer.url, 921600)
    try:
        info = wait_for_autopilot(conn, 5)
        client = MavlinkParamClient(
            conn, info.system_id, info.component_id, timeout=0.2, retries=0, bytewise=True
        )
        wanted_cp = wanted("CP_DIST", -1.0)
        assert read_and_compare(client, wanted("NO_SUCH_PARAM", 1), frozenset()).status is Status.UNKNOWN
        assert read_and_compare(client, wanted_cp, frozenset()).status is Status.OK
        peer.stop()  # the autopilot goes silent
        assert read_and_compare(client, wanted_cp, frozenset()).status is Status.NO_REPLY
        assert read_and_compare(client, wanted("NO_SUCH_PARAM", 1), frozenset({"NO_SUCH_PARAM"})).status is (
            Status.NO_REPLY
        )
    finally:
        conn.close()


@pytest.mark.parametrize("text", ["", "MAV 1", "A,,B=1"])
def test_allow_missing_takes_parameter_names_only(capsys, text):
    with pytest.raises(SystemExit):
        main(
            [
                "params",
                "check",
                "--autopilot",
                "px4",
                "--connect",
                "udpin:127.0.0.1:14550",
                "--allow-missing",
                text,
            ]
        )
    assert "is not a comma-separated list of parameter names" in capsys.readouterr().err


def test_params_take_the_mavsdk_spelling_too(peer_factory, capsys):
    """The PX4 companion's ``autopilot.connect`` (a MAVSDK URL) works as ``params --connect`` as is."""
    peer = peer_factory("px4")
    mavsdk_url = peer.url.replace("udpout:", "udpout://")
    assert main(cli("apply", "px4", mavsdk_url)) == 0
    assert "parameters as wanted" in capsys.readouterr().out
