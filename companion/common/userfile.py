"""Reading a file the user names (config, world, model): whatever is wrong with it is one line.

The path may be missing, a directory, a symlink loop, unreadable, a FIFO or device, huge, not UTF-8,
not the format, or nested deeper than any parser recurses: each becomes a :class:`UserError` naming
the file and the problem (the command-line fronts print it and exit 2), never a traceback or a hang.
"""

from __future__ import annotations

import errno
import json
import os
import stat
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from companion.common.errors import UserError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

T = TypeVar("T")

#: Text files (configs, worlds) are small; anything larger is not one of them.
MAX_TEXT_BYTES = 16 << 20

_OS_PROBLEMS = {
    errno.ENOENT: "file not found",
    errno.EISDIR: "is a directory, not a file",
    errno.ELOOP: "is a symlink loop",
    errno.EACCES: "permission denied",
    errno.EPERM: "permission denied",
    errno.ENOTDIR: "a part of the path is not a directory",
    errno.ENAMETOOLONG: "the name is too long",
}


def read_user_bytes(path: str | Path, what: str, max_bytes: int = MAX_TEXT_BYTES) -> bytes:
    """The whole content of a regular file.

    :param path: the file
    :param what: what it is, for the message ("config file", "world", "policy model")
    :param max_bytes: refuse larger files
    :raises UserError: "{what} {path}: {problem}"
    """
    path = Path(path)
    try:
        # O_NONBLOCK: opening a FIFO must not wait for a writer (it is refused right after)
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise UserError(f"{what} {path}: {_os_problem(exc)}") from None
    try:
        info = os.fstat(fd)
        if stat.S_ISDIR(info.st_mode):
            raise UserError(f"{what} {path}: is a directory, not a file")
        if not stat.S_ISREG(info.st_mode):
            raise UserError(f"{what} {path}: is not a regular file")
        if info.st_size > max_bytes:
            raise UserError(f"{what} {path}: is {info.st_size} bytes, larger than the {max_bytes} allowed")
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(max_bytes + 1)
    except OSError as exc:
        raise UserError(f"{what} {path}: {_os_problem(exc)}") from None
    finally:
        os.close(fd)
    if len(data) > max_bytes:  # it grew while being read
        raise UserError(f"{what} {path}: larger than the {max_bytes} bytes allowed")
    return data


def read_user_text(path: str | Path, what: str, max_bytes: int = MAX_TEXT_BYTES) -> str:
    """:func:`read_user_bytes`, decoded as UTF-8 (a BOM is not allowed: neither TOML nor JSON has one)."""
    data = read_user_bytes(path, what, max_bytes)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserError(
            f"{what} {path}: not UTF-8 text (byte {data[exc.start]:#04x} at offset {exc.start})"
        ) from None


def load_user_file(
    path: str | Path, what: str, parse: Callable[[str], T], max_bytes: int = MAX_TEXT_BYTES
) -> T:
    """Read a UTF-8 text file and parse it; any failure is one line naming the file.

    :param parse: e.g. ``json.loads`` or ``tomllib.loads``; a ValueError it raises (as
        JSONDecodeError and TOMLDecodeError are) is the user's mistake, its text the problem
    :raises UserError: "{what} {path}: {problem}"
    """
    text = read_user_text(path, what, max_bytes)
    try:
        return parse(text)
    except RecursionError:  # 100,000 nested brackets: every recursive parser gives up
        raise UserError(f"{what} {path}: nested too deeply to parse") from None
    except ValueError as exc:
        raise UserError(f"{what} {path}: {_parse_problem(exc)}") from None


def _os_problem(exc: OSError) -> str:
    return _OS_PROBLEMS.get(exc.errno or 0, f"cannot read ({exc.strerror or exc})")


def _parse_problem(exc: ValueError) -> str:
    if isinstance(exc, json.JSONDecodeError):
        return f"invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}"
    if isinstance(exc, tomllib.TOMLDecodeError):
        return f"not valid TOML: {exc}"
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
