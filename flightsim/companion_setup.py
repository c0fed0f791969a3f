"""What a SITL flight hands the companion process: a free loopback port and its config, built from
the companion's own dataclasses (written with :func:`companion.tomlconfig.toml_dumps`)."""

from __future__ import annotations

import dataclasses
import socket
from pathlib import Path
from typing import Any

from companion.config import CompanionConfig


def free_udp_port() -> int:
    """A UDP port nobody on loopback uses right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


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
