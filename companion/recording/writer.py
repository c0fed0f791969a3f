"""The MCAP writer thread: files, rotation, the size budget, and failing without harm.

The loop only ever calls :meth:`McapSink.submit`, which puts a small tuple into a bounded queue and
returns at once: when the queue is full the record is dropped and counted, the loop never waits.
Everything slow (JSON encoding, compression, the disk) happens in this thread. Any error writing
(disk full, directory gone or read-only) stops the recording for good: :attr:`McapSink.failure`
says why, the loop side reports it once (log line and STATUSTEXT) and the flight goes on.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from companion.recording.messages import nanoseconds, to_json
from companion.recording.schemas import METADATA_NAME, Channel, schema_bytes

log = logging.getLogger(__name__)

#: Recording files in the directory look like this (the budget only ever deletes these).
FILE_GLOB = "flight-*.mcap"
#: Uncompressed bytes per MCAP chunk. Smaller chunks reach the disk sooner (less lost in a crash).
CHUNK_SIZE = 128 * 1024
#: A chunk in progress is written out at least this often, s.
FLUSH_PERIOD = 1.0
_STOP = object()


class McapSink:
    """Writes records to ``flight-<start>-<pid>-<part>.mcap`` files in ``directory``.

    :param directory: created if missing
    :param budget_bytes: all ``flight-*.mcap`` files there stay below this; oldest deleted first
    :param file_bytes: a file is finished and the next part started before it grows past this
    :param metadata: written into every file (each part can be read on its own)
    :param queue_size: records waiting; more are dropped and counted in :attr:`dropped`
    :param metadata_name: name of the metadata record holding ``metadata``
    :raises OSError: the directory cannot be made, or the first file cannot be opened
    """

    def __init__(self, directory: str | Path, budget_bytes: int, file_bytes: int, metadata: dict[str, str],
                 queue_size: int = 512, metadata_name: str = METADATA_NAME) -> None:
        if file_bytes < 4 * CHUNK_SIZE:
            raise ValueError(f"file size {file_bytes} B is below 4 chunks of {CHUNK_SIZE} B")
        self.directory = Path(directory)
        self.budget_bytes = int(budget_bytes)
        self.file_bytes = int(file_bytes)
        self.metadata = dict(metadata)
        self.metadata_name = metadata_name
        self.dropped = 0
        self.written = 0
        self.deleted: list[Path] = []
        self.files: list[Path] = []
        self.failure: str | None = None  # why it stopped, with the file: for the log
        self.failure_reason: str | None = None  # the same, short: for the pilot's STATUSTEXT
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=queue_size)
        self._name = time.strftime("flight-%Y%m%d-%H%M%S", time.gmtime()) + f"-{os.getpid()}"
        self._stream: Any = None
        self._writer: Writer | None = None
        self._channels: dict[str, int] = {}
        self._last_flush = time.monotonic()
        self.directory.mkdir(parents=True, exist_ok=True)
        self._open_next()  # at start-up: an unwritable directory shows at once
        self._thread = threading.Thread(target=self._run, name="flight-recorder", daemon=True)
        self._thread.start()

    @property
    def current(self) -> Path | None:
        """The file being written (None once stopped)."""
        return self.files[-1] if self._writer is not None and self.files else None

    # ---- the loop's side -----------------------------------------------------------------

    def submit(self, channel: Channel, t: float, build: Callable[..., dict[str, Any]], *args: Any,
               seq: int = 0) -> None:
        """Queue one message at clock time ``t``; ``build(t, *args)`` makes its JSON object later, in
        the writer thread."""
        if self.failure is not None:
            return
        try:
            self._queue.put_nowait((channel, t, seq, build, args))
        except queue.Full:
            self.dropped += 1

    def close(self, timeout: float = 5.0) -> None:
        """Write what is queued, finish the file, stop the thread (at most ``timeout`` s)."""
        if self._thread.is_alive():
            try:
                self._queue.put(_STOP, timeout=timeout)
            except queue.Full:
                self.failure = self.failure or "closed with a full queue"
            self._thread.join(timeout)

    # ---- the writer thread ---------------------------------------------------------------

    def _run(self) -> None:
        try:
            while True:
                try:
                    item = self._queue.get(timeout=FLUSH_PERIOD / 2)
                except queue.Empty:
                    item = None
                if item is _STOP:
                    break
                if item is not None:
                    self._write(*item)
                if time.monotonic() - self._last_flush >= FLUSH_PERIOD:
                    self._writer.flush()  # type: ignore[union-attr]
                    self._last_flush = time.monotonic()
            self._finish()
        except Exception as exc:  # disk full, directory removed, ...: stop recording, never the flight
            self.failure = _describe(exc, self.current)
            self.failure_reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else self.failure
            log.warning("flight recorder stopped: %s", self.failure)
            self._abandon()

    def _write(self, channel: Channel, t: float, seq: int, build: Callable[..., dict[str, Any]],
               args: tuple[Any, ...]) -> None:
        writer = self._writer
        assert writer is not None
        channel_id = self._channels.get(channel.topic)
        if channel_id is None:
            schema_id = writer.register_schema(channel.schema, "jsonschema", schema_bytes(channel.schema))
            channel_id = writer.register_channel(channel.topic, "json", schema_id)
            self._channels[channel.topic] = channel_id
        data = to_json(build(t, *args))
        ns = nanoseconds(t)
        writer.add_message(channel_id, log_time=ns, publish_time=ns, data=data, sequence=seq)
        self.written += 1
        if self._stream.tell() + CHUNK_SIZE >= self.file_bytes:
            self._finish()
            self._open_next()

    def _open_next(self) -> None:
        path = self.directory / f"{self._name}-{len(self.files):03d}.mcap"
        self._make_room(self.file_bytes)
        self._stream = open(path, "wb")  # noqa: SIM115 - lives until rotation or close
        self.files.append(path)
        writer = Writer(self._stream, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD)
        writer.start(profile="", library="lidar-avoid")
        writer.add_metadata(self.metadata_name, self.metadata)
        self._writer = writer
        self._channels = {}
        self._last_flush = time.monotonic()

    def _finish(self) -> None:
        if self._writer is not None:
            self._writer.finish()
            self._stream.close()
            self._writer = None

    def _abandon(self) -> None:
        """After a failure: release the file without writing anything more (the disk may be full)."""
        self._writer = None
        if self._stream is not None:
            with contextlib.suppress(OSError):
                self._stream.close()

    def _make_room(self, needed: int) -> None:
        """Delete the oldest recordings until ``needed`` more bytes fit in the budget."""
        files = sorted(self.directory.glob(FILE_GLOB), key=lambda p: (p.stat().st_mtime, p.name))
        sizes = {p: p.stat().st_size for p in files}
        total = sum(sizes.values())
        for path in files:
            if total + needed <= self.budget_bytes:
                break
            path.unlink()
            total -= sizes[path]
            self.deleted.append(path)
            log.info("flight recorder: deleted %s (%d B) to stay within the budget", path.name, sizes[path])


def _describe(exc: BaseException, path: Path | None) -> str:
    """One line: what failed and where (``No space left on device: /var/log/.../flight-....mcap``)."""
    if isinstance(exc, OSError) and exc.strerror:
        where = exc.filename or path
        return f"{exc.strerror}: {where}" if where else exc.strerror
    return f"{type(exc).__name__}: {exc}"
