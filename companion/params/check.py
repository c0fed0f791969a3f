"""Autopilot parameters the companion relies on: ``avoid-companion params check|apply``, and the
start-up check.

Three layers, each usable (and tested) alone: the files (:mod:`companion.params.files`: what the
autopilot should hold), the comparison here (pure: :func:`compare_parameter` decides whether what
the autopilot holds is what the file wants, in the parameter's own type), and the wire
(:mod:`companion.params.client`: one parameter at a time over MAVLink). This module joins them:
check or apply a whole file, and the report.

The float field of PARAM_VALUE/PARAM_SET is encoded differently by the two firmwares (see
:mod:`companion.params.codec`); the encoding is taken from the autopilot's AUTOPILOT_VERSION
capabilities, not from ``--autopilot``, so COM_OBL_RC_ACT = 5.0 written C-cast style to a
bytewise PX4 (which stores 1084227584) is caught instead of reading back a reassuring 5.0.
"""

from __future__ import annotations

import argparse
import enum
import math
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from companion.autopilot.connection import ensure_port_free, parse_connection
from companion.common.errors import UserError
from companion.params.client import (
    LinkStats,
    MavlinkParamClient,
    mavlink_common,
    open_connection,
    wait_for_autopilot,
)
from companion.params.codec import INT_TYPES, REAL32
from companion.params.files import (
    AUTOPILOTS,
    PARAM_NAME,
    PARAM_TYPE_NAMES,
    WantedParam,
    default_param_file,
    load_param_file,
)

# Parameters that only take effect after an autopilot reboot. ArduPilot: PRXn_TYPE is
# @RebootRequired; serial ports are configured by the serial manager at boot only. PX4: the
# MAV_n_* and SER_*_BAUD definitions carry reboot_required.
REBOOT_PATTERNS = {
    "ardupilot": (re.compile(r"SERIAL\d+_\w+"), re.compile(r"PRX\d+_TYPE")),
    "px4": (re.compile(r"MAV_\d+_\w+"), re.compile(r"SER_\w+_BAUD")),
}
#: The firmware parameter (deg/s) that caps the yaw rate the autopilot flies for a companion's
#: setpoint. ArduCopter 4.8 holds 1.05 rad/s when 1.5 is asked: ATC_RATE_WPY_MAX, 60°/s by default
#: (../shared/fixtures/autopilot-response); PX4 offboard is bounded by MC_YAWRATE_MAX (200°/s).
YAW_RATE_LIMIT_PARAMS = {"ardupilot": "ATC_RATE_WPY_MAX", "px4": "MC_YAWRATE_MAX"}


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
    mavlink = mavlink_common()
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
    bad = sorted(n for n in names if not PARAM_NAME.fullmatch(n))
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
