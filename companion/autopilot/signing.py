"""MAVLink 2 message signing: the key file, and signing switched on for one pymavlink parser.

The key file holds the 32-byte secret as 64 hexadecimal digits on one line (whitespace around it
is ignored). It must be readable by its owner only (mode 0600 or 0400): the key lets anyone who
has it command the vehicle. ``python -c "import hashlib; print(hashlib.sha256(b'PASSPHRASE')
.hexdigest())"`` gives the key MAVProxy's ``signing setup PASSPHRASE`` and Mission Planner install
from the same passphrase (both hash it with SHA-256).

pymavlink's own ``check_signature`` records a stream's timestamp *before* it compares the
signature, so one forged frame with a far-future timestamp and the autopilot's ids makes every
later genuine frame "old" and rejected. :func:`enable_signing` installs a check that compares the
signature first and only then advances the stream's timestamp (MAVLink's signing specification).
"""

from __future__ import annotations

import hashlib
import hmac
import os
import stat
import struct
import time
from collections.abc import Callable, Collection
from pathlib import Path
from typing import Any

from pymavlink.generator.mavcrc import x25crc

from companion.common.errors import UserError

#: Length of the MAVLink 2 signing secret, bytes.
KEY_LENGTH = 32
#: Signing timestamps count 10 µs units since 2015-01-01 00:00 UTC.
SIGNING_EPOCH = 1420070400
#: A stream not seen before is accepted when its timestamp is at most this far behind ours (1 min).
NEW_STREAM_TOLERANCE = 6000 * 1000

_TIMESTAMP = struct.Struct("<IH")
#: MAVLink 2 frame: magic, length, incompat flags, compat flags, seq, system, component, msgid (3)
_V2_MAGIC = 0xFD
_V2_HEADER = 10
_IFLAG_SIGNED = 0x01


def load_signing_key(path: str | Path, setting: str = "autopilot.signing_key") -> bytes:
    """Read a signing key file: 64 hex digits, owner-only permissions.

    :param setting: the config key or option that named the file, for the error message
    :raises UserError: one line naming the file and what is wrong with it
    """
    path = Path(path)
    where = f"{setting}: {path}"
    try:
        st = path.stat()
        if not stat.S_ISREG(st.st_mode):
            raise UserError(f"{where}: not a regular file")
        if st.st_mode & 0o077:
            raise UserError(
                f"{where}: readable or writable by group/others (mode {stat.S_IMODE(st.st_mode):04o}); "
                f"run chmod 600 {path}"
            )
        raw = path.read_bytes()
    except OSError as exc:
        raise UserError(f"{where}: cannot read: {exc.strerror or exc}") from None
    try:
        text = raw.decode("ascii").strip()
        key = bytes.fromhex(text)
    except (UnicodeDecodeError, ValueError):
        raise UserError(f"{where}: expected {2 * KEY_LENGTH} hexadecimal digits on one line") from None
    if len(key) != KEY_LENGTH:
        raise UserError(f"{where}: expected {2 * KEY_LENGTH} hexadecimal digits, found {len(text)}")
    if key == bytes(KEY_LENGTH):
        raise UserError(f"{where}: an all-zero key means 'signing off' to the autopilot; use a random key")
    return key


def write_signing_key(path: str | Path, key: bytes | None = None) -> bytes:
    """Create a key file (owner-only, refusing to overwrite one) holding ``key`` or a random key."""
    key = os.urandom(KEY_LENGTH) if key is None else key
    if len(key) != KEY_LENGTH:
        raise ValueError(f"a signing key is {KEY_LENGTH} bytes")
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(key.hex() + "\n")
    return key


def signing_timestamp(now: float | None = None) -> int:
    """The signing timestamp for wall-clock ``now`` (10 µs units since 2015)."""
    now = time.time() if now is None else now
    return int(max(now - SIGNING_EPOCH, 0.0) * 100_000)


def enable_signing(
    mav: Any,
    key: bytes,
    link_id: int = 0,
    accept_unsigned: Collection[int] | Callable[[int], bool] = (),
    initial_timestamp: int | None = None,
) -> None:
    """Sign everything ``mav`` sends with ``key`` and drop incoming frames not signed with it.

    :param mav: a pymavlink ``MAVLink`` object (parser and encoder of one link)
    :param link_id: the signature's link id (one per link of a system)
    :param accept_unsigned: message ids still accepted unsigned (ArduPilot: RADIO_STATUS), or a
        predicate on the message id
    :param initial_timestamp: first signing timestamp (default: now)
    """
    signing = mav.signing
    signing.secret_key = bytes(key)
    signing.sign_outgoing = True
    signing.link_id = link_id
    signing.timestamp = signing_timestamp() if initial_timestamp is None else initial_timestamp
    signing.stream_timestamps = {}
    accept = accept_unsigned if callable(accept_unsigned) else frozenset(accept_unsigned).__contains__
    signing.allow_unsigned_callback = lambda _mav, msg_id: bool(accept(msg_id))
    mav.check_signature = lambda msgbuf, src_system, src_component: _check_signature(
        signing, msgbuf, src_system, src_component
    )


def disable_signing(mav: Any) -> None:
    """Back to unsigned MAVLink 2 (what SETUP_SIGNING with an all-zero key asks for)."""
    signing = mav.signing
    signing.secret_key = None
    signing.sign_outgoing = False
    signing.allow_unsigned_callback = None
    signing.stream_timestamps = {}
    mav.__dict__.pop("check_signature", None)


def _check_signature(signing: Any, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
    """MAVLink 2 signature check: signature first, then the stream's timestamp must move forward."""
    expected = hashlib.sha256(signing.secret_key + bytes(msgbuf[:-6])).digest()[:6]
    if not hmac.compare_digest(expected, bytes(msgbuf[-6:])):
        return False
    low, high = _TIMESTAMP.unpack(bytes(msgbuf[-12:-6]))
    timestamp = low + (high << 32)
    stream = (msgbuf[-13], src_system, src_component)
    last = signing.stream_timestamps.get(stream)
    if last is not None and timestamp <= last:
        return False  # a replay, or a frame older than one already accepted
    if last is None and timestamp + NEW_STREAM_TOLERANCE < signing.timestamp:
        return False  # a new stream more than a minute in the past: a replay
    signing.stream_timestamps[stream] = timestamp
    signing.timestamp = max(signing.timestamp, timestamp)
    return True


class FrameSigner:
    """Signs finished MAVLink 2 frames someone else encoded (MAVSDK's), as pymavlink would have.

    :param key: the 32-byte secret
    :param link_id: the signature's link id
    """

    def __init__(self, key: bytes, link_id: int = 0) -> None:
        self._key = bytes(key)
        self._link_id = link_id
        self._timestamp = signing_timestamp()

    def sign(self, frame: bytes, crc_extra: int) -> bytes | None:
        """``frame`` with the signed flag, its CRC recomputed and the 13-byte signature appended.

        :param crc_extra: the message's CRC_EXTRA byte (from the dialect)
        :return: None for a frame that cannot be signed (MAVLink 1)
        """
        if len(frame) < _V2_HEADER + 2 or frame[0] != _V2_MAGIC:
            return None
        length = frame[1]
        body = bytearray(frame[: _V2_HEADER + length])
        body[2] |= _IFLAG_SIGNED
        crc = x25crc(bytes(body[1:]) + bytes([crc_extra])).crc
        # one tick past both the last timestamp used and the clock: strictly increasing per link
        self._timestamp = max(self._timestamp + 1, signing_timestamp())
        stamp = self._timestamp
        out = body + struct.pack("<HB", crc, self._link_id) + _TIMESTAMP.pack(stamp & 0xFFFFFFFF, stamp >> 32)
        return bytes(out + hashlib.sha256(self._key + out).digest()[:6])
