"""Autopilot parameters the companion relies on: the parameter files, and check/apply over MAVLink.

Three layers, so each can be used (and tested) alone:

- files: :func:`load_param_file` reads ``firmware_params/ardupilot-copter.parm`` (``NAME VALUE``,
  ``#`` comments, comma accepted: the format mavparm and Mission Planner use) or
  ``firmware_params/px4.params`` (QGroundControl's tab-separated ``sysid compid NAME VALUE TYPE``).
  Strict where mavparm is lenient: a malformed line is a :class:`UserError` naming file and line,
  never a printed warning and a skipped line.
- comparison (pure): :func:`compare_parameter` decides whether what the autopilot holds is what
  the file wants, in the parameter's own type.
- wire: :class:`MavlinkParamClient` reads and writes one parameter at a time over a pymavlink
  connection (PARAM_REQUEST_READ / PARAM_SET / PARAM_VALUE), with bounded timeouts and retries.

The float field of PARAM_VALUE/PARAM_SET is encoded differently by the two firmwares (see
:mod:`companion.param_codec`); the encoding is taken from the autopilot's AUTOPILOT_VERSION
capabilities, not from ``--autopilot``, so COM_OBL_RC_ACT = 5.0 written C-cast style to a
bytewise PX4 (which stores 1084227584) is caught instead of reading back a reassuring 5.0.
"""

from __future__ import annotations

import argparse
import enum
import math
import os
import re
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from companion.connection import ensure_port_free, parse_connection
from companion.errors import UserError
from companion.param_codec import INT_TYPES, REAL32, decode_param_value, encode_param_value

AUTOPILOTS = ("ardupilot", "px4")
PARAM_FILE_NAMES = {"ardupilot": "ardupilot-copter.parm", "px4": "px4.params"}
# Where the parameter files are looked for when --file is not given: the source checkout, then
# the copy the install step puts next to the config.
PARAM_FILE_DIRS = (
    Path(__file__).resolve().parents[1] / "firmware_params",
    Path("/etc/lidar-avoid/firmware_params"),
)

# MAV_PARAM_TYPE values a file may name (MAVLink common.xml); 64-bit types cannot travel in the
# float field and are refused.
PARAM_TYPE_NAMES = {
    1: "UINT8",
    2: "INT8",
    3: "UINT16",
    4: "INT16",
    5: "UINT32",
    6: "INT32",
    9: "REAL32",
}
# Parameters that only take effect after an autopilot reboot. ArduPilot: PRXn_TYPE is
# @RebootRequired; serial ports are configured by the serial manager at boot only. PX4: the
# MAV_n_* and SER_*_BAUD definitions carry reboot_required.
REBOOT_PATTERNS = {
    "ardupilot": (re.compile(r"SERIAL\d+_\w+"), re.compile(r"PRX\d+_TYPE")),
    "px4": (re.compile(r"MAV_\d+_\w+"), re.compile(r"SER_\w+_BAUD")),
}
_NAME = re.compile(r"[A-Za-z0-9_]{1,16}")
REFUSED = object()  # the autopilot said it does not know the parameter
#: The firmware parameter (deg/s) that caps the yaw rate the autopilot flies for a companion's
#: setpoint. ArduCopter 4.8 holds 1.05 rad/s when 1.5 is asked: ATC_RATE_WPY_MAX, 60°/s by default
#: (../shared/fixtures/autopilot-response); PX4 offboard is bounded by MC_YAWRATE_MAX (200°/s).
YAW_RATE_LIMIT_PARAMS = {"ardupilot": "ATC_RATE_WPY_MAX", "px4": "MC_YAWRATE_MAX"}
# MAVLink component id of an onboard computer; the companion's identity on the link.
COMPANION_SYSTEM_ID = 1
COMPANION_COMPONENT_ID = 191


@dataclass(frozen=True)
class WantedParam:
    """One line of a parameter file.

    :param name: parameter name as the firmware spells it
    :param value: the wanted value
    :param param_type: MAV_PARAM_TYPE named by the file (PX4 files), None when the file does not
        say (ArduPilot files: the autopilot's own type is used)
    :param line: 1-based line number, for messages
    :param source: the file it came from
    """

    name: str
    value: float
    param_type: int | None
    line: int
    source: str


class Status(enum.Enum):
    """Outcome for one parameter of a check or an apply."""

    OK = "ok"
    DIFFERS = "differs"
    UNKNOWN = "unknown to the autopilot"  # silent for this name while it answers others
    NO_REPLY = "no reply, link lost"  # silent for everything: no verdict on the parameter
    ABSENT_ALLOWED = "absent, allowed"  # unknown, and listed in --allow-missing
    TYPE_MISMATCH = "type mismatch"
    CHANGED = "changed"
    FAILED = "set failed"


@dataclass(frozen=True)
class ParamResult:
    """What the autopilot holds for one wanted parameter.

    :param actual: the decoded value the autopilot reported (None: no reply)
    :param actual_type: its MAV_PARAM_TYPE (None: no reply)
    :param before: for apply, the value before it was set
    :param needs_reboot: for apply, the parameter changed and only takes effect after a reboot
    """

    wanted: WantedParam
    status: Status
    actual: float | None = None
    actual_type: int | None = None
    before: float | None = None
    needs_reboot: bool = False

    @property
    def name(self) -> str:
        return self.wanted.name

    @property
    def ok(self) -> bool:
        """The autopilot now holds the wanted value (or lacks it, and the user allowed that)."""
        return self.status in (Status.OK, Status.CHANGED, Status.ABSENT_ALLOWED)


# ---------------------------------------------------------------------------------------- files


def default_param_file(autopilot: str) -> Path:
    """The parameter file for ``autopilot`` from the checkout or the installed copy."""
    name = PARAM_FILE_NAMES[autopilot]
    for directory in PARAM_FILE_DIRS:
        if (directory / name).is_file():
            return directory / name
    searched = ", ".join(str(d / name) for d in PARAM_FILE_DIRS)
    raise UserError(f"no {autopilot} parameter file found (looked for {searched}); pass --file")


def load_param_file(path: str | os.PathLike[str], autopilot: str) -> list[WantedParam]:
    """Read a parameter file in the format of ``autopilot``'s tools.

    :param path: the file
    :param autopilot: ``"ardupilot"`` (``.parm``: NAME VALUE) or ``"px4"`` (QGroundControl ``.params``)
    :raises UserError: unreadable file, malformed line (named by line number), unknown type,
        duplicate or no parameters
    """
    if autopilot not in AUTOPILOTS:
        raise UserError(f"unknown autopilot {autopilot!r} (expected one of {', '.join(AUTOPILOTS)})")
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot read parameter file {path}: {exc}") from exc
    parse = parse_parm_text if autopilot == "ardupilot" else parse_qgc_params_text
    params = parse(text, str(path))
    if not params:
        raise UserError(f"{path}: no parameters in the file")
    seen: dict[str, int] = {}
    for p in params:
        if p.name in seen:
            raise UserError(f"{path}:{p.line}: {p.name} already set on line {seen[p.name]}")
        seen[p.name] = p.line
    return params


def parse_parm_text(text: str, source: str) -> list[WantedParam]:
    """ArduPilot ``.parm``: ``NAME VALUE`` or ``NAME,VALUE``; ``#`` starts a comment anywhere."""
    params = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.replace(",", " ").split()
        if len(fields) != 2:
            raise UserError(f"{source}:{number}: expected 'NAME VALUE', got {raw.strip()!r}")
        name = _check_name(fields[0], source, number).upper()
        params.append(WantedParam(name, _parse_number(fields[1], source, number), None, number, source))
    return params


def parse_qgc_params_text(text: str, source: str) -> list[WantedParam]:
    """QGroundControl ``.params``: ``VEHICLE<TAB>COMPONENT<TAB>NAME<TAB>VALUE<TAB>TYPE``, ``#`` lines."""
    params = []
    for number, raw in enumerate(text.splitlines(), start=1):
        if not raw.strip() or raw.lstrip().startswith("#"):
            continue
        fields = raw.rstrip("\r\n").split("\t")
        if len(fields) != 5:
            raise UserError(
                f"{source}:{number}: expected 5 tab-separated fields "
                f"(Vehicle-Id Component-Id Name Value Type), got {raw.strip()!r}"
            )
        for label, text_id in (("vehicle id", fields[0]), ("component id", fields[1])):
            if not text_id.strip().isdigit():
                raise UserError(f"{source}:{number}: {label} {text_id!r} is not a number")
        name = _check_name(fields[2].strip(), source, number)
        value = _parse_number(fields[3].strip(), source, number)
        type_text = fields[4].strip()
        if not type_text.isdigit() or int(type_text) not in PARAM_TYPE_NAMES:
            known = ", ".join(f"{k} = {v}" for k, v in PARAM_TYPE_NAMES.items())
            raise UserError(f"{source}:{number}: {name}: unknown parameter type {type_text!r} ({known})")
        param_type = int(type_text)
        if param_type in INT_TYPES and value != math.floor(value):
            raise UserError(
                f"{source}:{number}: {name} is {PARAM_TYPE_NAMES[param_type]} but the value {fields[3]} "
                "is not an integer"
            )
        params.append(WantedParam(name, value, param_type, number, source))
    return params


def _check_name(name: str, source: str, number: int) -> str:
    if not _NAME.fullmatch(name):
        raise UserError(f"{source}:{number}: {name!r} is not a parameter name (letters, digits, _; ≤ 16)")
    return name


def _parse_number(text: str, source: str, number: int) -> float:
    try:
        value = float(int(text, 16)) if text.lower().startswith("0x") else float(text)
    except ValueError:
        raise UserError(f"{source}:{number}: value {text!r} is not a number") from None
    if not math.isfinite(value):
        raise UserError(f"{source}:{number}: value {text!r} is not a finite number")
    return value


def needs_reboot(autopilot: str, name: str) -> bool:
    """Whether a change of ``name`` only takes effect after the autopilot reboots."""
    return any(p.fullmatch(name) for p in REBOOT_PATTERNS[autopilot])


# ----------------------------------------------------------------------------------- comparison


def values_match(wanted: float, actual: float, param_type: int) -> bool:
    """Equal as values of ``param_type``: integers exactly, REAL32 after rounding both to float32."""
    if param_type in INT_TYPES:
        return wanted == actual
    as_f32 = struct.unpack("<2f", struct.pack("<2f", wanted, actual))
    return as_f32[0] == as_f32[1] or math.isclose(as_f32[0], as_f32[1], rel_tol=1e-6, abs_tol=1e-9)


def compare_parameter(wanted: WantedParam, actual: tuple[float, int] | None) -> ParamResult:
    """Judge one parameter (pure).

    :param wanted: from the file
    :param actual: (decoded value, MAV_PARAM_TYPE) the autopilot reported, None for no reply
    """
    if actual is None:
        return ParamResult(wanted, Status.UNKNOWN)
    value, param_type = actual
    if wanted.param_type is not None and wanted.param_type != param_type:
        return ParamResult(wanted, Status.TYPE_MISMATCH, value, param_type)
    status = Status.OK if values_match(wanted.value, value, param_type) else Status.DIFFERS
    return ParamResult(wanted, status, value, param_type)


# ----------------------------------------------------------------------------------------- wire


@dataclass
class LinkStats:
    """What the parameter exchange cost, for the report: requests sent, retries, timeouts."""

    requests: int = 0
    retries: int = 0
    timeouts: int = 0


@dataclass
class AutopilotInfo:
    """The autopilot found on the link (from its HEARTBEAT)."""

    system_id: int
    component_id: int
    autopilot: int


class MavlinkParamClient:
    """One-parameter-at-a-time access to an autopilot's parameters over a pymavlink connection.

    :param conn: a ``mavutil`` connection (``mavlink_connection(...)``)
    :param target_system: the autopilot's system id
    :param target_component: the autopilot's component id
    :param timeout: seconds to wait for each reply
    :param retries: extra attempts after the first before a parameter counts as not answered
    :param bytewise: value encoding (see :meth:`detect_bytewise`, which sets it)
    """

    def __init__(
        self,
        conn: Any,
        target_system: int,
        target_component: int,
        timeout: float = 1.0,
        retries: int = 2,
        bytewise: bool = False,
    ) -> None:
        self.conn = conn
        self.target_system = target_system
        self.target_component = target_component
        self.timeout = timeout
        self.retries = retries
        self.bytewise = bytewise
        self.stats = LinkStats()
        self.encoding_source = "not detected"

    def detect_bytewise(self, heartbeat_autopilot: int | None = None) -> bool:
        """Ask for AUTOPILOT_VERSION and take the encoding from its capability bits.

        Sends MAV_CMD_REQUEST_MESSAGE (falls back to the older MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES
        when the autopilot rejects it). With no answer at all, the HEARTBEAT's autopilot field decides
        (PX4 → bytewise), and :attr:`encoding_source` says so.

        :param heartbeat_autopilot: MAV_AUTOPILOT from the autopilot's HEARTBEAT, for the fallback
        """
        mav = self.conn.mav
        mavlink = _mavlink_module()
        use_legacy = False
        for attempt in range(self.retries + 1):
            self._count_attempt(attempt)
            if use_legacy:
                mav.command_long_send(
                    self.target_system,
                    self.target_component,
                    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
                    0,
                    1,
                    0,
                    0,
                    0,
                    0,
                    0,
                    0,
                )
            else:
                mav.command_long_send(
                    self.target_system,
                    self.target_component,
                    mavlink.MAV_CMD_REQUEST_MESSAGE,
                    0,
                    mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                    0,
                    0,
                    0,
                    0,
                    0,
                    0,
                )
            deadline = time.monotonic() + self.timeout
            while (msg := self._recv(["AUTOPILOT_VERSION", "COMMAND_ACK"], deadline)) is not None:
                if msg.get_type() == "AUTOPILOT_VERSION":
                    self.bytewise = bool(
                        msg.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
                    )
                    self.encoding_source = "AUTOPILOT_VERSION capabilities"
                    return self.bytewise
                if (
                    msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE
                    and msg.result != mavlink.MAV_RESULT_ACCEPTED
                ):
                    use_legacy = True  # an older firmware: ask the deprecated way on the next attempt
                    break
            else:
                self.stats.timeouts += 1
        self.bytewise = heartbeat_autopilot == mavlink.MAV_AUTOPILOT_PX4
        self.encoding_source = "HEARTBEAT autopilot type (no AUTOPILOT_VERSION reply)"
        return self.bytewise

    def read(self, name: str) -> tuple[float, int] | None:
        """The parameter's decoded value and MAV_PARAM_TYPE, None when the autopilot never answers.

        Both firmwares stay silent for a name they do not know, so "no answer after all retries"
        is how an unknown parameter shows up.
        """
        for attempt in range(self.retries + 1):
            self._count_attempt(attempt)
            self.conn.mav.param_request_read_send(
                self.target_system, self.target_component, name.encode("ascii"), -1
            )
            reply = self._wait_param_value(name)
            if reply is not None:
                return reply
            self.stats.timeouts += 1
        return None

    def link_alive(self) -> bool:
        """Does the autopilot answer at all? Asks for its first parameter by index.

        Both firmwares stay silent for a name they do not know, exactly as a dead link does; an
        answer to this request tells the two apart.
        """
        for attempt in range(self.retries + 1):
            self._count_attempt(attempt)
            self.conn.mav.param_request_read_send(self.target_system, self.target_component, b"", 0)
            if self._recv(["PARAM_VALUE"], time.monotonic() + self.timeout) is not None:
                return True
            self.stats.timeouts += 1
        return False

    def write(self, name: str, value: float, param_type: int) -> tuple[float, int] | None:
        """Send PARAM_SET and wait for the PARAM_VALUE echo; None when none comes (or PX4 says unknown).

        :param value: the value in the parameter's own type
        :param param_type: the parameter's MAV_PARAM_TYPE (as the autopilot reports it)
        """
        field_value = encode_param_value(value, param_type, self.bytewise)
        for attempt in range(self.retries + 1):
            self._count_attempt(attempt)
            self.conn.mav.param_set_send(
                self.target_system, self.target_component, name.encode("ascii"), field_value, param_type
            )
            # PX4 answers a set of a name it does not know with this STATUSTEXT and nothing else
            reply = self._wait_param_value(name, refused_text=f"unknown param: {name}")
            if reply is REFUSED:
                return None
            if reply is not None:
                return reply
            self.stats.timeouts += 1
        return None

    def _count_attempt(self, attempt: int) -> None:
        self.stats.requests += 1
        if attempt:
            self.stats.retries += 1

    def _recv(self, types: list[str], deadline: float) -> Any:
        """Next message of ``types`` from the target system before ``deadline``, else None."""
        while (remaining := deadline - time.monotonic()) > 0:
            msg = self.conn.recv_match(type=types, blocking=True, timeout=remaining)
            if msg is not None and msg.get_srcSystem() == self.target_system:
                return msg
        return None

    def _wait_param_value(self, name: str, refused_text: str | None = None) -> Any:
        """The (value, type) of the next PARAM_VALUE for ``name``; :data:`REFUSED` or None on timeout."""
        deadline = time.monotonic() + self.timeout
        while (msg := self._recv(["PARAM_VALUE", "STATUSTEXT"], deadline)) is not None:
            if msg.get_type() == "STATUSTEXT":
                if refused_text is not None and msg.text.endswith(refused_text):
                    return REFUSED
                continue
            if msg.param_id == name:
                return decode_param_value(msg.param_value, msg.param_type, self.bytewise), msg.param_type
        return None


def _mavlink_module() -> Any:
    from pymavlink.dialects.v20 import common

    return common


def read_and_compare(
    client: MavlinkParamClient, wanted: WantedParam, allow_missing: frozenset[str]
) -> ParamResult:
    """Read one parameter and judge it; an unanswered name is told apart from a lost link."""
    actual = client.read(wanted.name)
    if actual is not None:
        return compare_parameter(wanted, actual)
    if not client.link_alive():
        return ParamResult(wanted, Status.NO_REPLY)
    return ParamResult(wanted, Status.ABSENT_ALLOWED if wanted.name in allow_missing else Status.UNKNOWN)


def check_parameters(
    client: MavlinkParamClient, wanted: list[WantedParam], allow_missing: frozenset[str] = frozenset()
) -> list[ParamResult]:
    """Read every wanted parameter and compare it (nothing is written)."""
    return [read_and_compare(client, w, allow_missing) for w in wanted]


def apply_parameters(
    client: MavlinkParamClient,
    wanted: list[WantedParam],
    autopilot: str,
    allow_missing: frozenset[str] = frozenset(),
) -> list[ParamResult]:
    """Set every parameter that differs, then read it back to verify.

    A parameter is written in the type the autopilot reports for it; one the autopilot does not
    know, or whose type differs from the file's, is reported and not written.
    """
    results = []
    for w in wanted:
        before = read_and_compare(client, w, allow_missing)
        if before.status is not Status.DIFFERS:
            results.append(before)
            continue
        param_type = before.actual_type if before.actual_type is not None else REAL32
        client.write(w.name, w.value, param_type)
        after = compare_parameter(w, client.read(w.name))  # read-back, not the echo, decides
        changed = after.status is Status.OK
        results.append(
            ParamResult(
                w,
                Status.CHANGED if changed else Status.FAILED,
                after.actual,
                after.actual_type if after.actual_type is not None else param_type,
                before=before.actual,
                needs_reboot=changed and needs_reboot(autopilot, w.name),
            )
        )
    return results


# ------------------------------------------------------------------------------------ connection


def open_connection(url: str, baud: int) -> Any:
    """A MAVLink 2 pymavlink connection as the companion (system 1, component 191).

    :param url: mavutil connection string: ``udpin:0.0.0.0:14550``, ``udpout:HOST:PORT``,
        ``tcp:HOST:PORT``, a serial device such as ``/dev/ttyTHS1``
    :param baud: serial baud rate (ignored for network links)
    """
    os.environ["MAVLINK20"] = "1"  # pymavlink picks the wire protocol from the environment
    from pymavlink import mavutil

    try:
        return mavutil.mavlink_connection(
            url,
            baud=baud,
            source_system=COMPANION_SYSTEM_ID,
            source_component=COMPANION_COMPONENT_ID,
            dialect="common",
            autoreconnect=False,
        )
    except Exception as exc:  # pymavlink raises whatever the transport raises (OSError, SerialException…)
        raise UserError(f"cannot open MAVLink connection {url!r}: {exc}") from exc


def wait_for_autopilot(conn: Any, timeout: float) -> AutopilotInfo:
    """Wait for an autopilot HEARTBEAT, sending the companion's own heartbeat meanwhile.

    Sending first matters on ``udpout:`` links, where the autopilot learns our address from it.

    :raises UserError: no autopilot heartbeat within ``timeout`` seconds
    """
    mavlink = _mavlink_module()
    deadline = time.monotonic() + timeout
    next_beat = 0.0
    while (now := time.monotonic()) < deadline:
        if now >= next_beat:
            conn.mav.heartbeat_send(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0
            )
            next_beat = now + 0.5
        msg = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=min(0.5, deadline - now))
        if msg is not None and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID:
            return AutopilotInfo(msg.get_srcSystem(), msg.get_srcComponent(), msg.autopilot)
    raise UserError(f"no autopilot HEARTBEAT within {timeout:g} s; check --connect and the wiring")


@dataclass
class CheckReport:
    """The outcome of a whole check or apply run."""

    results: list[ParamResult]
    bytewise: bool
    encoding_source: str
    stats: LinkStats = field(default_factory=LinkStats)

    @property
    def ok(self) -> bool:
        return all(r.ok for r in self.results)


def run_params(
    conn: Any,
    autopilot: str,
    wanted: list[WantedParam],
    apply: bool = False,
    timeout: float = 1.0,
    retries: int = 2,
    heartbeat_timeout: float = 10.0,
    allow_missing: frozenset[str] = frozenset(),
) -> CheckReport:
    """Check (or apply) ``wanted`` on the autopilot at the other end of ``conn``.

    This is what the companion's start-up check calls, before its own link takes the port.

    :param autopilot: ``"ardupilot"`` or ``"px4"``: which firmware the file was written for
    :param allow_missing: names this autopilot may lack (a SITL has no TELEM2): absent is fine
    """
    info = wait_for_autopilot(conn, heartbeat_timeout)
    _check_firmware_family(autopilot, info.autopilot)
    client = MavlinkParamClient(conn, info.system_id, info.component_id, timeout, retries)
    client.detect_bytewise(info.autopilot)
    results = (
        apply_parameters(client, wanted, autopilot, allow_missing)
        if apply
        else check_parameters(client, wanted, allow_missing)
    )
    return CheckReport(results, client.bytewise, client.encoding_source, client.stats)


def yaw_rate_limit(report: CheckReport, autopilot: str) -> float | None:
    """The autopilot's yaw-rate cap as read in ``report``, rad/s; None when the parameter was not
    in the file, got no reply, or is 0 (ArduPilot: no cap of its own)."""
    name = YAW_RATE_LIMIT_PARAMS[autopilot]
    for r in report.results:
        if r.name == name and r.actual is not None and r.actual > 0:
            return math.radians(r.actual)
    return None


def _check_firmware_family(autopilot: str, heartbeat_autopilot: int) -> None:
    """Refuse a file for one firmware against the other (every parameter would look unknown)."""
    mavlink = _mavlink_module()
    says = {mavlink.MAV_AUTOPILOT_PX4: "px4", mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot"}
    found = says.get(heartbeat_autopilot)
    if found is not None and found != autopilot:
        raise UserError(f"--autopilot {autopilot}, but the autopilot on the link identifies as {found}")


# ------------------------------------------------------------------------------------------ CLI


def _positive_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not 0.05 <= value <= 60:
        raise argparse.ArgumentTypeError(f"{text} s is outside 0.05-60 s")
    return value


def _retries(text: str) -> int:
    if not text.isdigit() or int(text) > 10:
        raise argparse.ArgumentTypeError(f"{text!r} is not a retry count 0-10")
    return int(text)


def _names(text: str) -> frozenset[str]:
    names = frozenset(n.strip() for n in text.split(",") if n.strip())
    bad = sorted(n for n in names if not _NAME.fullmatch(n))
    if bad or not names:
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of parameter names")
    return names


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """``params check|apply``."""
    parser.add_argument(
        "action",
        choices=("check", "apply"),
        help="check: read and compare (exit 0 only if all match); apply: set what differs",
    )
    parser.add_argument(
        "--autopilot",
        choices=AUTOPILOTS,
        required=True,
        help="firmware the parameter file is for (picks the file format and default file)",
    )
    parser.add_argument(
        "--connect",
        required=True,
        metavar="URL",
        help="MAVLink connection, pymavlink or MAVSDK form: /dev/ttyTHS1, udpin:0.0.0.0:14550, "
        "udpin://0.0.0.0:14540, tcp:127.0.0.1:5760, serial:///dev/ttyTHS1:921600, ...",
    )
    parser.add_argument(
        "--file",
        metavar="F",
        help="parameter file (default: firmware_params/ardupilot-copter.parm or px4.params)",
    )
    parser.add_argument("--baud", type=int, default=921600, help="serial baud rate (default 921600)")
    parser.add_argument(
        "--allow-missing",
        type=_names,
        default=frozenset(),
        metavar="NAME,...",
        help="parameters this autopilot may lack, e.g. MAV_1_CONFIG,SER_TEL2_BAUD on a PX4 SITL "
        "(which has no TELEM2); without it every parameter of the file must exist",
    )
    parser.add_argument(
        "--timeout",
        type=_positive_seconds,
        default=1.0,
        metavar="S",
        help="seconds to wait for each reply (default 1)",
    )
    parser.add_argument(
        "--retries",
        type=_retries,
        default=2,
        metavar="N",
        help="extra attempts per parameter before it counts as unanswered (default 2)",
    )
    parser.add_argument(
        "--heartbeat-timeout",
        type=_positive_seconds,
        default=10.0,
        metavar="S",
        help="seconds to wait for the autopilot's heartbeat (default 10)",
    )


def command(args: argparse.Namespace) -> int:
    path = Path(args.file) if args.file else default_param_file(args.autopilot)
    wanted = load_param_file(path, args.autopilot)
    link = parse_connection(args.connect, args.baud)
    ensure_port_free(link)
    conn = open_connection(link.pymavlink, link.baud or args.baud)
    try:
        report = run_params(
            conn,
            args.autopilot,
            wanted,
            apply=args.action == "apply",
            timeout=args.timeout,
            retries=args.retries,
            heartbeat_timeout=args.heartbeat_timeout,
            allow_missing=args.allow_missing,
        )
    finally:
        conn.close()
    print(format_report(report, args.action, str(path)))
    return 0 if report.ok else 1


def format_value(value: float | None, param_type: int | None) -> str:
    """A value as a person would write it: integers without a decimal point, floats short."""
    if value is None:
        return "-"
    if param_type in INT_TYPES or (param_type is None and value == math.floor(value) and abs(value) < 1e15):
        return str(int(value))
    return f"{value:.7g}"


def format_report(report: CheckReport, action: str, source: str) -> str:
    """The table and summary ``params check|apply`` prints."""
    rows = [("name", "wanted", "actual", "ok")]
    for r in report.results:
        ptype = r.actual_type if r.actual_type is not None else r.wanted.param_type
        note = "yes" if r.ok else f"NO ({r.status.value})"
        if r.status is Status.TYPE_MISMATCH:
            note += (
                f": file says {PARAM_TYPE_NAMES.get(r.wanted.param_type or 0, '?')}, "
                f"autopilot {PARAM_TYPE_NAMES.get(r.actual_type or 0, r.actual_type)}"
            )
        rows.append((r.name, format_value(r.wanted.value, ptype), format_value(r.actual, ptype), note))
    widths = [max(len(row[i]) for row in rows) for i in range(3)]
    lines = [f"{a:<{widths[0]}}  {b:>{widths[1]}}  {c:>{widths[2]}}  {d}" for a, b, c, d in rows]
    encoding = "bytewise" if report.bytewise else "C cast"
    lines.append("")
    lines.append(f"file: {source}; value encoding: {encoding} (from {report.encoding_source})")
    good = sum(r.ok for r in report.results)
    lines.append(f"{good}/{len(report.results)} parameters as wanted")
    if action == "apply":
        changed = [r for r in report.results if r.status is Status.CHANGED]
        for r in changed:
            was = format_value(r.before, r.actual_type)
            lines.append(
                f"changed {r.name}: {was} -> {format_value(r.actual, r.actual_type)}"
                + (" (needs reboot)" if r.needs_reboot else "")
            )
        reboot = [r.name for r in changed if r.needs_reboot]
        if reboot:
            lines.append(f"reboot the autopilot for {', '.join(reboot)} to take effect")
    differ = [
        r.name for r in report.results if r.status in (Status.DIFFERS, Status.TYPE_MISMATCH, Status.FAILED)
    ]
    if differ:
        lines.append(f"differ from the file: {', '.join(differ)}")
    unknown = [r.name for r in report.results if r.status is Status.UNKNOWN]
    if unknown:
        lines.append(
            f"unknown to this autopilot (it answers other names): {', '.join(unknown)}; a SITL or a board "
            f"without that port lacks them: --allow-missing {','.join(unknown)} accepts that"
        )
    allowed = [r.name for r in report.results if r.status is Status.ABSENT_ALLOWED]
    if allowed:
        lines.append(f"absent, allowed by --allow-missing: {', '.join(allowed)}")
    lost = [r.name for r in report.results if r.status is Status.NO_REPLY]
    if lost:
        lines.append(f"no reply, and none to a request by index either (link lost?): {', '.join(lost)}")
    s = report.stats
    lines.append(f"link: {s.requests} requests, {s.retries} retries, {s.timeouts} timeouts")
    return "\n".join(lines)
