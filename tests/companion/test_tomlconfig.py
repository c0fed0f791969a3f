"""Strict config loading: every mistake names its key."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import pytest

from companion.common.errors import UserError
from companion.common.tomlconfig import apply_overrides, from_dict, load_toml, to_dict
from companion.perception.scan import ScanConfig


@dataclass(frozen=True)
class Inner:
    rate: float = field(default=10.0, metadata={"min": 1.0, "max": 50.0})
    name: str = "x"


@dataclass(frozen=True)
class Outer:
    inner: Inner = Inner()
    scan: ScanConfig = ScanConfig()
    mode: Literal["warn", "refuse"] = "warn"
    count: int = 3
    flag: bool = False
    path: str | None = None


def test_defaults_and_nested_tables() -> None:
    cfg = from_dict(Outer, {"inner": {"rate": 20}, "scan": {"mount_xyz": [0.1, 0, 0.05]}, "mode": "refuse"})
    assert cfg.inner.rate == 20.0 and isinstance(cfg.inner.rate, float)
    assert cfg.scan.mount_xyz == (0.1, 0.0, 0.05)
    assert cfg.mode == "refuse"
    assert from_dict(Outer, to_dict(cfg)) == cfg


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"inner": {"rte": 1.0}}, "inner.rte: unknown config key"),
        ({"inner": {"rate": "fast"}}, "inner.rate: expected a number"),
        ({"inner": {"rate": 99.0}}, "inner.rate: 99.0 is above the maximum 50.0"),
        ({"count": 2.5}, "count: expected an integer"),
        ({"flag": 1}, "flag: expected true or false"),
        ({"mode": "ignore"}, "mode: must be one of"),
        ({"scan": {"mount_xyz": [0, 0]}}, "scan.mount_xyz: expected 3 values"),
        ({"scan": {"min_range": 4.0, "max_range": 2.0}}, "scan: min_range 4.0 must be below"),
        ({"inner": 3}, "inner: expected a table"),
    ],
)
def test_mistakes_name_the_key(data: dict, message: str) -> None:
    with pytest.raises(UserError, match=message.replace(".", r"\.").replace("(", r"\(")):
        from_dict(Outer, data)


def test_load_toml_errors_are_user_errors(tmp_path) -> None:
    with pytest.raises(UserError, match="not found"):
        load_toml(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("a = [1,\n")
    with pytest.raises(UserError, match="not valid TOML"):
        load_toml(bad)


def test_overrides_parse_values_as_toml() -> None:
    data = apply_overrides({"inner": {"rate": 10.0}}, ["inner.rate=20", "mode=refuse", "inner.name='y'"])
    cfg = from_dict(Outer, data)
    assert cfg.inner.rate == 20.0 and cfg.mode == "refuse" and cfg.inner.name == "y"
    with pytest.raises(UserError, match="expected key=value"):
        apply_overrides({}, ["novalue"])
