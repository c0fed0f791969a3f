"""What a SITL flight hands the companion process: a free loopback port and its config, built from
the companion's own dataclasses (written with :func:`companion.common.tomlconfig.toml_dumps`).

The start-up parameter check is the example config's, the one a drone starts from: the companion in
SITL reads the autopilot's parameters, and its yaw-rate cap, as it does on the drone."""

from __future__ import annotations

import dataclasses
import random
import socket
from collections.abc import Container
from pathlib import Path
from typing import Any

from companion.config import CompanionConfig, ParamsCheckConfig, load_config

#: the config a drone's companion starts from (config/companion.example.toml in the checkout)
EXAMPLE_CONFIG = Path(__file__).resolve().parents[2] / "config" / "companion.example.toml"

#: Linux's default ephemeral range, for systems that do not publish theirs
DEFAULT_EPHEMERAL = (32768, 60999)
_handed_out: set[int] = set()


def ephemeral_range() -> tuple[int, int]:
    """The ports the kernel hands out to sockets bound to port 0 or sending unbound."""
    try:
        low, high = (int(v) for v in Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
    except (OSError, ValueError):
        return DEFAULT_EPHEMERAL
    return low, high


def free_port(kind: int = socket.SOCK_DGRAM, avoid: Container[int] = ()) -> int:
    """A loopback port nobody uses now, and one the kernel will not give another socket meanwhile.

    A port the kernel picked (bind to 0) is ephemeral: between closing the probe and the
    listener binding it, any socket of the flight that sends unbound (the lidar stream, the
    ground-station relay) may be handed the same port, and the companion then refuses a link
    whose port is in use. Ports below the ephemeral range are only ever taken on purpose; each
    is handed out once per process, so two asked in a row differ.

    :param kind: ``socket.SOCK_DGRAM`` (UDP) or ``socket.SOCK_STREAM`` (TCP)
    :param avoid: ports never to hand out, such as those another program takes for itself later
    """
    low, high = ephemeral_range()
    span = range(1024, low) if low > 2048 else range(high + 1, 65536)
    ports = [port for port in span if port not in _handed_out and port not in avoid]
    for port in random.SystemRandom().sample(ports, min(500, len(ports))):
        with socket.socket(socket.AF_INET, kind) as probe:
            try:
                probe.bind(("127.0.0.1", port))
            except OSError:
                continue
        _handed_out.add(port)
        return port
    raise RuntimeError(f"no free loopback port in {span.start}-{span.stop - 1}")


def free_udp_port() -> int:
    """A UDP port nobody on loopback uses now, outside the ephemeral range (see :func:`free_port`)."""
    return free_port(socket.SOCK_DGRAM)


def free_tcp_port(avoid: Container[int] = ()) -> int:
    """A TCP port nobody on loopback uses now, outside the ephemeral range and ``avoid`` (see
    :func:`free_port`)."""
    return free_port(socket.SOCK_STREAM, avoid)


def example_params_check() -> ParamsCheckConfig:
    """The example config's ``[params_check]``: the drone's start-up parameter check (the default
    check where the example is not installed)."""
    if not EXAMPLE_CONFIG.is_file():
        return ParamsCheckConfig()
    return load_config(EXAMPLE_CONFIG).params_check


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
        params_check=example_params_check(),
    )
    for section, values in (overrides or {}).items():
        cfg = dataclasses.replace(cfg, **{section: dataclasses.replace(getattr(cfg, section), **values)})
    return cfg
