"""Parameter files: what the companion wants the autopilot to hold, as the firmware's tools write it.

:func:`load_param_file` reads ``firmware_params/ardupilot-copter.parm`` (``NAME VALUE``, ``#``
comments, comma accepted: the format mavparm and Mission Planner use) or
``firmware_params/px4.params`` (QGroundControl's tab-separated ``sysid compid NAME VALUE TYPE``).
Strict where mavparm is lenient: a malformed line is a :class:`UserError` naming file and line,
never a printed warning and a skipped line. Pure: no MAVLink here (:mod:`companion.params.check` checks
and applies what it reads).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

from companion.common.errors import UserError
from companion.params.codec import INT_TYPES

AUTOPILOTS = ("ardupilot", "px4")
PARAM_FILE_NAMES = {"ardupilot": "ardupilot-copter.parm", "px4": "px4.params"}
# Where the parameter files are looked for when --file is not given: the source checkout, then
# the copy the install step puts next to the config.
PARAM_FILE_DIRS = (
    Path(__file__).resolve().parents[2] / "firmware_params",
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
#: what a parameter name may be (MAVLink param_id: 16 characters at most)
PARAM_NAME = re.compile(r"[A-Za-z0-9_]{1,16}")


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
    if not PARAM_NAME.fullmatch(name):
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
