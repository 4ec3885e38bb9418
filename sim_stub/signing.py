"""MAVLink 2 message signing as PX4 >= 1.18 enforces it (``MockVehicle(signing=…)``).

Follows PX4's ``src/modules/mavlink/mavlink_sign_control.cpp`` (``MavlinkSignControl``:
``check_for_signing``, ``accept_unsigned``), PX4's user guide page "MAVLink Message Signing"
(``docs/en/mavlink/message_signing.md``) and the MAVLink C library's signature check
(``mavlink_signature_check`` in ``mavlink_helpers.h``) that PX4 links. Cited "PX4 source":

* **No key** (``signing=True``: a PX4 >= 1.18 with an empty SD card): nothing is signed, every
  message is accepted; the first SETUP_SIGNING with a non-blank key enables signing.
* **A key** (SETUP_SIGNING accepted, or ``signing=KEY``: the key file on the SD card): every
  outgoing MAVLink 2 packet carries the 13-byte signature (link id, 48-bit timestamp in 10 µs
  units since 2015-01-01 00:00 UTC, the first 6 bytes of SHA-256(key ‖ packet ‖ link id ‖
  timestamp)); an incoming packet is accepted only if its signature verifies with the key,
  apart from the unsigned allow-list HEARTBEAT, RADIO_STATUS, ADSB_VEHICLE, COLLISION
  (:data:`UNSIGNED_ALLOWED`).
* **Replay**: per stream (source sysid, compid, link id) a timestamp not newer than the last
  accepted one is rejected; a new stream is accepted only if its timestamp is at most one
  minute older than the vehicle's own (the MAVLink C library's rule). The vehicle's timestamp
  follows the newest accepted one and advances with every signed packet it sends.
* **SETUP_SIGNING** (id 256): rejected while armed; applied only if broadcast or addressed to
  this vehicle; with a key already set it must itself be signed with that key (it passes the
  check above, like any other message); a blank key (all zeros, timestamp 0) disables signing
  and is accepted only signed. PX4 sends no answer (there is no ACK for SETUP_SIGNING).

What is dropped is counted by reason in :attr:`SigningState.dropped`: ``unsigned``,
``bad_signature``, ``stale`` (replayed or older timestamp), ``setup_armed``,
``setup_blank_unsigned``. A dropped packet does nothing else: in particular it does not make
the mock answer (stream to) its sender.
"""

from __future__ import annotations

import hashlib
import struct
import time
from collections import Counter
from collections.abc import Callable

__all__ = [
    "EPOCH_2015_UNIX_S",
    "MSG_SETUP_SIGNING",
    "SigningState",
    "UNSIGNED_ALLOWED",
    "signing_timestamp_now",
]

#: HEARTBEAT, RADIO_STATUS, ADSB_VEHICLE, COLLISION: accepted unsigned (PX4's allow-list).
UNSIGNED_ALLOWED: frozenset[int] = frozenset({0, 109, 246, 247})
MSG_SETUP_SIGNING = 256
#: 2015-01-01 00:00:00 UTC, the origin of MAVLink signing timestamps.
EPOCH_2015_UNIX_S = 1420070400
_NEW_STREAM_WINDOW = 6_000_000  # one minute in 10 µs units (MAVLink C library)
_TS = struct.Struct("<Q")
_CRC = struct.Struct("<H")


def signing_timestamp_now(unix_s: float | None = None) -> int:
    """The MAVLink signing timestamp of ``unix_s`` (default: now): 10 µs units since 2015."""
    t = time.time() if unix_s is None else unix_s
    return max(0, int((t - EPOCH_2015_UNIX_S) * 100_000))


class SigningState:
    """One vehicle's signing state: the key (None: signing off), its own timestamp, the
    per-stream timestamps and the drop counters. ``wall``: the Unix time source."""

    def __init__(self, key: bytes | None = None,
                 wall: Callable[[], float] = time.time) -> None:
        if key is not None and (len(key) != 32 or not any(key)):
            raise ValueError("a signing key is 32 bytes, not all zero")
        self.key = key
        self._wall = wall
        self.timestamp = signing_timestamp_now(wall()) if key is not None else 0
        self.streams: dict[tuple[int, int, int], int] = {}
        self.dropped: Counter[str] = Counter()
        self.accepted_signed = 0
        self.key_changes = 0

    @property
    def active(self) -> bool:
        return self.key is not None

    # -- incoming ---------------------------------------------------------------------------------
    def verdict(self, raw: bytes, msgid: int, src_sys: int, src_comp: int) -> str | None:
        """None to accept packet ``raw`` (one complete frame), else the drop reason."""
        key = self.key
        if key is None:
            return None
        signed = len(raw) > 25 and raw[0] == 0xFD and raw[2] & 0x01
        if not signed:
            return None if msgid in UNSIGNED_ALLOWED else "unsigned"
        sig = raw[-13:]
        want = hashlib.sha256(key + raw[:-6]).digest()[:6]
        if want != sig[7:]:
            return None if msgid in UNSIGNED_ALLOWED else "bad_signature"
        ts = int.from_bytes(sig[1:7], "little")
        stream = (src_sys, src_comp, sig[0])
        last = self.streams.get(stream)
        if (ts + _NEW_STREAM_WINDOW < self.timestamp) if last is None else ts <= last:
            return None if msgid in UNSIGNED_ALLOWED else "stale"
        self.streams[stream] = ts
        if ts > self.timestamp:
            self.timestamp = ts
        self.accepted_signed += 1
        return None

    def setup_signing(self, msg: object, signed: bool, armed: bool) -> bool:
        """Apply a SETUP_SIGNING that passed :meth:`verdict` (PX4's ``check_for_signing``);
        True if the key changed."""
        if armed:
            self.dropped["setup_armed"] += 1
            return False
        key = bytes(msg.secret_key)  # type: ignore[attr-defined]
        initial = int(msg.initial_timestamp)  # type: ignore[attr-defined]
        if initial == 0 and not any(key):
            if self.key is None:
                return False
            if not signed:
                self.dropped["setup_blank_unsigned"] += 1
                return False
            self.key = None
            self.timestamp = 0
            self.key_changes += 1
            return True
        if len(key) != 32:
            return False
        same = key == self.key
        self.key = key
        now = signing_timestamp_now(self._wall())
        self.timestamp = max(initial, now, self.timestamp if same else 0)
        self.key_changes += 1
        return True

    # -- outgoing ---------------------------------------------------------------------------------
    def frame(self, seq: int, sysid: int, compid: int, id3: bytes, crc_byte: bytes,
              payload: bytes, link_id: int, crc16: Callable[[bytes, int], int]) -> bytes:
        """One signed MAVLink 2 packet (incompat flag 0x01, CRC, 13-byte signature)."""
        assert self.key is not None
        body = bytes((len(payload), 1, 0, seq, sysid, compid)) + id3 + payload
        head = b"\xfd" + body + _CRC.pack(crc16(crc_byte, crc16(body, 0xFFFF)))
        self.timestamp += 1
        tail = bytes((link_id,)) + _TS.pack(self.timestamp)[:6]
        return head + tail + hashlib.sha256(self.key + head + tail).digest()[:6]

    # -- the vehicle's hook -----------------------------------------------------------------------
    def filter(self, packets: list, *, armed: bool, sysid: int, compid: int) -> tuple[list, bool]:
        """The packets of a datagram that pass (signature, replay), with SETUP_SIGNING applied
        and removed; and whether the key changed (the vehicle then re-arms its encoders)."""
        kept = []
        changed = False
        for pk in packets:
            why = self.verdict(pk.raw, pk.msgid, pk.src_system, pk.src_component)
            if why is not None:
                self.dropped[why] += 1
                continue
            if pk.msgid == MSG_SETUP_SIGNING:
                m = pk.msg
                tsys = int(m.target_system)  # type: ignore[attr-defined]
                tcomp = int(m.target_component)  # type: ignore[attr-defined]
                if tsys in (0, sysid) and tcomp in (0, compid):
                    signed = len(pk.raw) > 25 and bool(pk.raw[2] & 0x01)
                    changed = self.setup_signing(m, signed, armed) or changed
                continue  # never handled further (nor forwarded, as PX4)
            kept.append(pk)
        return kept, changed
