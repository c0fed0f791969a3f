"""Connection strings: both spellings for both autopilots, normalised in one place; bad ports and busy
ports are one line, exit 2.

The busy-port tests hold the port with real sockets and real companion processes on loopback.
"""

from __future__ import annotations

import socket
import time

import pytest

from companion.__main__ import main
from companion.autopilot.connection import Connection, ensure_port_free, parse_connection
from companion.common.errors import UserError
from companion.config import AutopilotConfig
from tests.companion.companion_process import free_udp_port, run_to_exit, start_companion, stop, write_config
from tests.onnx_models import write_policy


@pytest.mark.parametrize(
    ("text", "kind", "pymavlink", "mavsdk"),
    [
        ("udpin:0.0.0.0:14540", "udpin", "udpin:0.0.0.0:14540", "udpin://0.0.0.0:14540"),
        ("udpin://0.0.0.0:14540", "udpin", "udpin:0.0.0.0:14540", "udpin://0.0.0.0:14540"),
        ("udp://0.0.0.0:14540", "udpin", "udpin:0.0.0.0:14540", "udpin://0.0.0.0:14540"),
        ("udpout:10.0.0.2:14550", "udpout", "udpout:10.0.0.2:14550", "udpout://10.0.0.2:14550"),
        ("tcp:127.0.0.1:5760", "tcpout", "tcp:127.0.0.1:5760", "tcpout://127.0.0.1:5760"),
        ("tcpout://127.0.0.1:5760", "tcpout", "tcp:127.0.0.1:5760", "tcpout://127.0.0.1:5760"),
        ("tcpin://0.0.0.0:5760", "tcpin", "tcpin:0.0.0.0:5760", "tcpin://0.0.0.0:5760"),
        ("/dev/ttyTHS1", "serial", "/dev/ttyTHS1", "serial:///dev/ttyTHS1:57600"),
        ("serial:///dev/ttyTHS1:921600", "serial", "/dev/ttyTHS1", "serial:///dev/ttyTHS1:921600"),
        ("serial_flowcontrol:///dev/ttyUSB0:115200", "serial", "/dev/ttyUSB0",
         "serial_flowcontrol:///dev/ttyUSB0:115200"),
    ],
)  # fmt: skip
def test_both_spellings_give_the_same_link(text, kind, pymavlink, mavsdk):
    link = parse_connection(text, default_baud=57600)
    assert link.kind == kind and link.pymavlink == pymavlink and link.mavsdk == mavsdk
    assert parse_connection(link.mavsdk, 57600) == link  # the MAVSDK form parses back to the same link
    if kind != "serial":
        assert parse_connection(link.pymavlink, 57600) == link


def test_serial_baud_in_the_string_wins_over_the_default():
    assert parse_connection("serial:///dev/ttyTHS1:921600", 57600) == Connection(
        "serial", "/dev/ttyTHS1", baud=921600
    )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("udpin:0.0.0.0:99999", "port '99999' is not a port number 1-65535"),
        ("udpin://0.0.0.0:0", "port '0' is not a port number"),
        ("udpin:0.0.0.0:port", "port 'port' is not a port number"),
        ("udpin::14550", "expected HOST:PORT"),
        ("http://x:80", "unknown scheme 'http'"),
        ("localhost", "expected udpin:HOST:PORT"),
        ("serial:///dev/ttyTHS1:fast", "baud 'fast' is not a number"),
        ("serial://ttyTHS1:921600", "expected /dev/DEVICE[:BAUD]"),
        ("", "empty MAVLink connection"),
    ],
)
def test_bad_strings_name_what_is_wrong(text, message):
    with pytest.raises(UserError, match=message.replace("[", r"\[").replace("(", r"\(")):
        parse_connection(text)


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4"])
@pytest.mark.parametrize(
    "connect", ["udpin:0.0.0.0:14540", "udpin://0.0.0.0:14540", "serial:///dev/ttyTHS1:921600"]
)
def test_the_companion_config_takes_either_spelling_for_either_autopilot(autopilot, connect):
    config = AutopilotConfig(type=autopilot, connect=connect)
    assert config.link == parse_connection(connect)


def test_a_held_udp_port_is_refused_even_when_the_holder_set_so_reuseaddr():
    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as pymavlink's udpin does
    holder.bind(("127.0.0.1", 0))
    port = holder.getsockname()[1]
    try:
        for text in (f"udpin:127.0.0.1:{port}", f"udpin://0.0.0.0:{port}"):
            with pytest.raises(UserError, match=f"port {port} is already in use"):
                ensure_port_free(parse_connection(text))
    finally:
        holder.close()
    ensure_port_free(parse_connection(f"udpin:127.0.0.1:{port}"))  # free again


def _one_line(stderr: str) -> str:
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    return lines[0]


def test_bad_port_in_the_companion_config_is_one_line_exit_2(tmp_path):
    model = write_policy(tmp_path / "m.onnx")
    config = write_config(tmp_path, model, free_udp_port(), free_udp_port())
    result = run_to_exit(["run", "--config", str(config), 'autopilot.connect="udpin:0.0.0.0:99999"'])
    assert result.returncode == 2
    line = _one_line(result.stderr)
    assert line.startswith("avoid-companion: error: autopilot") and "'99999' is not a port number" in line


def test_params_bad_port_is_one_line_exit_2(capsys):
    assert main(["params", "check", "--autopilot", "px4", "--connect", "udpin:0.0.0.0:99999"]) == 2
    line = _one_line(capsys.readouterr().err)
    expected = "MAVLink connection 'udpin:0.0.0.0:99999': port '99999' is not a port number 1-65535"
    assert line == f"avoid-companion: error: {expected}"


@pytest.mark.parametrize("autopilot", ["ardupilot", "px4"])
def test_a_second_companion_on_the_same_mavlink_port_refuses_to_start(tmp_path, autopilot):
    model = write_policy(tmp_path / "m.onnx")
    mavlink_port = free_udp_port()
    first_dir, second_dir = tmp_path / "first", tmp_path / "second"
    first_dir.mkdir()
    second_dir.mkdir()
    first = start_companion(
        write_config(first_dir, model, free_udp_port(), mavlink_port, autopilot=autopilot)
    )
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and first.poll() is None:
            probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            try:
                probe.bind(("127.0.0.1", mavlink_port))
            except OSError:
                break  # the first companion holds its MAVLink port
            finally:
                probe.close()
            time.sleep(0.1)
        assert first.poll() is None, first.communicate()[1]
        # the second one: its own lidar port, the same MAVLink port
        config = write_config(second_dir, model, free_udp_port(), mavlink_port, autopilot=autopilot)
        result = run_to_exit(["run", "--config", str(config)])
        assert result.returncode == 2
        line = result.stderr.strip().splitlines()[-1]
        assert (
            line.startswith("avoid-companion: error: ") and f"port {mavlink_port} is already in use" in line
        )
        assert "Traceback" not in result.stderr
        assert first.poll() is None  # the first one flies on
    finally:
        stop(first)
