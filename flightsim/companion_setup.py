"""What a SITL flight hands the companion process: a free loopback port and its config file, built
from the companion's own dataclasses and written as TOML."""

from __future__ import annotations

import dataclasses
import json
import math
import socket
from pathlib import Path
from typing import Any

from companion.config import CompanionConfig


def free_udp_port() -> int:
    """A UDP port nobody on loopback uses right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


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


def companion_config(
    *,
    autopilot_type: str,
    connect: str,
    lidar_port: int,
    policy: Path,
    overrides: dict[str, Any] | None = None,
) -> CompanionConfig:
    """The companion's config for a SITL flight, built from its own dataclasses (not hand-written TOML)."""
    base = CompanionConfig()
    cfg = dataclasses.replace(
        base,
        lidar=dataclasses.replace(
            base.lidar, velodyne=dataclasses.replace(base.lidar.velodyne, host="127.0.0.1", port=lidar_port)
        ),
        policy=dataclasses.replace(base.policy, model=str(policy)),
        autopilot=dataclasses.replace(base.autopilot, type=autopilot_type, connect=connect),
    )
    for section, values in (overrides or {}).items():
        cfg = dataclasses.replace(cfg, **{section: dataclasses.replace(getattr(cfg, section), **values)})
    return cfg
