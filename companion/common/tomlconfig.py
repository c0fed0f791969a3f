"""Load a (nested) dataclass from TOML with strict checking, and write one back (:func:`toml_dumps`).

Every program has one config dataclass. An unknown key, a wrong type, a float that is NaN or
infinite, or a value outside the range declared in the field's metadata
(``metadata={"min": 0, "max": 10}``, on a list: for every item) raises
:class:`UserError` naming the dotted key, so a typo in a config file stops start-up instead of
silently falling back to a default.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from companion.common.errors import UserError
from companion.common.userfile import load_user_file

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

T = TypeVar("T")


def load_toml(path: str | Path) -> dict[str, Any]:
    """Read a TOML file; a file that cannot be read or parsed, whatever the reason, is a
    :class:`UserError` naming it (:func:`companion.common.userfile.load_user_file`)."""
    return load_user_file(path, "config file", tomllib.loads)


def _check_value(key: str, value: Any, tp: Any) -> Any:
    """Return ``value`` converted to ``tp`` or raise naming ``key``."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _check_value(key, value, arg)
            except UserError as exc:
                errors.append(str(exc))
        raise UserError(errors[0] if errors else f"{key}: invalid value {value!r}")
    if origin is typing.Literal:
        allowed = typing.get_args(tp)
        if value not in allowed:
            raise UserError(f"{key}: must be one of {', '.join(map(repr, allowed))}, got {value!r}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise UserError(f"{key}: expected a list, got {type(value).__name__}")
        args = typing.get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise UserError(f"{key}: expected {len(args)} values, got {len(value)}")
            items = [
                _check_value(f"{key}[{i}]", v, a) for i, (v, a) in enumerate(zip(value, args, strict=True))
            ]
        else:
            item_tp = args[0] if args else Any
            items = [_check_value(f"{key}[{i}]", v, item_tp) for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise UserError(f"{key}: expected a table, got {type(value).__name__}")
        return from_dict(tp, value, prefix=f"{key}.")
    if tp is Any:
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise UserError(f"{key}: expected a number, got {type(value).__name__} {value!r}")
        if not math.isfinite(value):  # NaN compares false with every bound, inf passes one side
            raise UserError(f"{key}: expected a finite number, got {value}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise UserError(f"{key}: expected an integer, got {type(value).__name__} {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise UserError(f"{key}: expected true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise UserError(f"{key}: expected a string, got {type(value).__name__} {value!r}")
        return value
    if isinstance(tp, type) and not isinstance(value, tp):
        raise UserError(f"{key}: expected {tp.__name__}, got {type(value).__name__}")
    return value


def _check_range(key: str, value: Any, meta: typing.Mapping[str, Any]) -> None:
    """The field's ``min``/``max``; on a list or tuple they bound every item."""
    lo, hi = meta.get("min"), meta.get("max")
    if isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            _check_range(f"{key}[{i}]", item, meta)
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        if lo is not None and value < lo:
            raise UserError(f"{key}: {value} is below the minimum {lo}")
        if hi is not None and value > hi:
            raise UserError(f"{key}: {value} is above the maximum {hi}")


def from_dict(cls: type[T], data: dict[str, Any], prefix: str = "") -> T:
    """Build dataclass ``cls`` from ``data``, checking keys, types and ranges.

    :param cls: the dataclass type (nested dataclass fields become TOML tables)
    :param data: the parsed TOML (or override) mapping
    :param prefix: dotted path of ``data`` inside the whole file, for messages
    """
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise UserError(f"{prefix}{unknown[0]}: unknown config key")
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        key = f"{prefix}{name}"
        checked = _check_value(key, value, hints[name])
        _check_range(key, checked, fields[name].metadata)
        kwargs[name] = checked
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as exc:  # __post_init__ cross-field checks
        raise UserError(f"{prefix.rstrip('.') or cls.__name__}: {exc}") from None


def to_dict(obj: Any) -> dict[str, Any]:
    """The dataclass as plain TOML-able values (tuples become lists)."""

    def plain(v: Any) -> Any:
        if isinstance(v, (tuple, list)):
            return [plain(x) for x in v]
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items() if x is not None}
        return v

    return plain(dataclasses.asdict(obj))


def toml_dumps(data: dict[str, Any]) -> str:
    """Serialise a config dict (tables, arrays of tables, scalars, scalar lists) as TOML."""

    def scalar(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, float)):
            return repr(v) if math.isfinite(v) else ("nan" if math.isnan(v) else ("inf" if v > 0 else "-inf"))
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(scalar(x) for x in v) + "]"
        raise TypeError(f"cannot write {type(v).__name__} to TOML")

    lines: list[str] = []

    def table(prefix: str, d: dict[str, Any]) -> None:
        subs = []
        for k, v in d.items():
            if isinstance(v, dict):
                subs.append((k, v))
            elif isinstance(v, (list, tuple)) and v and all(isinstance(x, dict) for x in v):
                subs.append((k, list(v)))
            else:
                lines.append(f"{k} = {scalar(v)}")
        for k, v in subs:
            name = f"{prefix}.{k}" if prefix else k
            if isinstance(v, list):
                for item in v:
                    lines.extend(["", f"[[{name}]]"])
                    table(name, item)
            else:
                lines.extend(["", f"[{name}]"])
                table(name, v)

    table("", data)
    return "\n".join(lines).lstrip() + "\n"


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Apply ``a.b=value`` command-line overrides (value parsed as TOML) to ``data``."""
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in data.items()}
    for item in overrides:
        if "=" not in item:
            raise UserError(f"override {item!r}: expected key=value")
        key, raw = item.split("=", 1)
        try:
            value = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw  # a bare word is a string
        node = out
        parts = key.strip().split(".")
        for part in parts[:-1]:
            child = node.get(part, {})
            if not isinstance(child, dict):
                raise UserError(f"override {key}: {part} is not a table")
            node[part] = dict(child)
            node = node[part]
        node[parts[-1]] = value
    return out
