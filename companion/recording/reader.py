"""Read a recording back: every JSON message by topic, in log-time order, and the metadata.

Reads the file as a stream, record by record, so a file whose end never got written (power cut,
full disk) still gives everything up to its last whole chunk; :attr:`Recording.truncated` says so.
"""

from __future__ import annotations

import json
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from companion.common.errors import UserError
from companion.recording.schemas import SETPOINT

#: the columns of :func:`setpoints` after the log time (``lidar_avoid.Setpoint`` fields)
SETPOINT_FIELDS = ("forward", "yaw_rate", "lateral", "vertical")


@dataclass
class Recording:
    """One MCAP file, decoded.

    :param messages: topic -> [(log time s, message)], log-time order
    :param sequences: topic -> the MCAP sequence number of each of those messages
    :param schemas: topic -> schema name
    :param metadata: metadata record name -> its key/value map
    :param truncated: the file ends before its footer (the rest was not written)
    """

    path: Path
    messages: dict[str, list[tuple[float, dict[str, Any]]]] = field(default_factory=dict)
    sequences: dict[str, list[int]] = field(default_factory=dict)
    schemas: dict[str, str] = field(default_factory=dict)
    schema_data: dict[str, bytes] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    truncated: bool = False

    def topic(self, name: str) -> list[tuple[float, dict[str, Any]]]:
        return self.messages.get(name, [])


def read_recording(path: str | Path) -> Recording:
    """Decode ``path`` (:class:`UserError` naming it when it is not an MCAP file or cannot be read)."""
    path = Path(path)
    rec = Recording(path)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    by_topic: dict[str, list[tuple[int, int, int, dict[str, Any]]]] = defaultdict(list)
    order = 0
    try:
        with open(path, "rb") as f:
            try:
                for record in StreamReader(f, validate_crcs=True).records:
                    if isinstance(record, Schema):
                        schemas[record.id] = record
                    elif isinstance(record, Channel):
                        channels[record.id] = record
                    elif isinstance(record, Metadata):
                        rec.metadata[record.name] = dict(record.metadata)
                    elif isinstance(record, Message):
                        channel = channels[record.channel_id]
                        if channel.message_encoding != "json":
                            continue
                        order += 1
                        by_topic[channel.topic].append(
                            (record.log_time, order, record.sequence, json.loads(record.data)))
            except Exception as exc:  # a cut-off or damaged tail: keep what came before
                if not by_topic and not rec.metadata:
                    raise UserError(f"{path}: not a readable MCAP recording ({exc})") from None
                rec.truncated = True
    except OSError as exc:
        raise UserError(f"cannot read {path}: {exc.strerror or exc}") from None
    for channel in channels.values():
        schema = schemas.get(channel.schema_id)
        if schema is not None:
            rec.schemas[channel.topic] = schema.name
            rec.schema_data[channel.topic] = schema.data
    for topic, rows in by_topic.items():
        rows.sort(key=lambda r: (r[0], r[1]))
        rec.messages[topic] = [(ns * 1e-9, msg) for ns, _, _, msg in rows]
        rec.sequences[topic] = [seq for _, _, seq, _ in rows]
    return rec


def setpoints(rec: Recording) -> np.ndarray:
    """Every setpoint the companion sent: rows of (log time s, forward, yaw rate, lateral, vertical).

    A field the recording lacks is NaN, never 0: recordings made before the vertical speed was
    recorded have none, and their flights may have climbed toward a waypoint's height.
    """
    def value(v: Any) -> float:
        return np.nan if v is None else float(v)

    rows = [(t, *(value(msg.get(k)) for k in SETPOINT_FIELDS)) for t, msg in rec.topic(SETPOINT.topic)]
    return np.array(rows, dtype=np.float64).reshape(-1, 1 + len(SETPOINT_FIELDS))
