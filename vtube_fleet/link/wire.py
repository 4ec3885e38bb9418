"""A struct fast path for the hot MAVLink 2 messages of the ``mavlink`` backend.

At 1,000 vehicles one supervisor receives ~50,000 LOCAL_POSITION_NED per second and sends
20,000 SET_POSITION_TARGET_LOCAL_NED; pymavlink's generic path (a byte-by-byte parser, a message
object per packet, a header object per packed message) costs ~25 µs per packet there. This
module handles exactly one *unsigned* MAVLink 2 frame per datagram with one precompiled
``struct.Struct`` per message id and the CRC-16/MCRF4XX in C (``fastcrc``, the implementation
pymavlink itself uses; ``binascii.crc_hqx`` on bit-reversed bytes if it is missing):

* :meth:`WireCodec.unpack` returns a named tuple with pymavlink's field names (so the link's
  handlers take either) or None for anything it does not fully accept: another framing, signed
  or flagged frames, a length that does not match the datagram, an unknown id, a payload longer
  than the dialect's, a bad CRC. The caller then hands the datagram to pymavlink, which counts
  and reports it as before; the fast path never decides that a packet is bad.
* :meth:`WireCodec.pack` builds the frame pymavlink's ``msg.pack`` builds, byte for byte
  (trailing zero bytes of the payload stripped, at least one kept; incompat/compat flags 0).
* :meth:`WireCodec.pack_many` builds N such frames of one id at once (a fleet's setpoints in
  a tick): the frames as rows of one numpy record array, the CRC of all of them from
  per-position tables (:class:`_CrcTables`: CRC-16/MCRF4XX is affine over GF(2), so the CRC of
  a frame is a constant XOR one table entry per byte), the same bytes as :meth:`~WireCodec.pack`.

Wire formats and CRC extras come from pymavlink's dialect classes, so they cannot drift from it
(tests/test_link_wire.py compares both paths byte for byte).
"""

from __future__ import annotations

import binascii
import struct
from collections import namedtuple
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

__all__ = ["WireCodec", "mcrf4xx"]

_REV8 = bytes(int(f"{i:08b}"[::-1], 2) for i in range(256))


def _rev16(x: int) -> int:
    return _REV8[x >> 8] | (_REV8[x & 0xFF] << 8)


def _mcrf4xx_hqx(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/MCRF4XX (reflected CCITT) through the non-reflected ``binascii.crc_hqx``."""
    return _rev16(binascii.crc_hqx(bytes(data).translate(_REV8), _rev16(crc)))


try:  # the C CRC pymavlink uses when installed
    from fastcrc.crc16 import mcrf4xx as _mcrf4xx_c

    def mcrf4xx(data: bytes, crc: int = 0xFFFF) -> int:
        """CRC-16/MCRF4XX of ``data`` starting from ``crc`` (MAVLink's X.25 checksum)."""
        return _mcrf4xx_c(bytes(data), crc)
except ImportError:  # pragma: no cover - depends on the environment
    mcrf4xx = _mcrf4xx_hqx

_HEADER = struct.Struct("<BBBBBBBHB")  # magic, len, incompat, compat, seq, sys, comp, id16, id8
_CRC = struct.Struct("<H")


#: struct format character → numpy dtype (little-endian, as MAVLink's wire format)
_NP_TYPES = {"B": "u1", "b": "i1", "H": "<u2", "h": "<i2", "I": "<u4", "i": "<i4",
             "Q": "<u8", "q": "<i8", "f": "<f4", "d": "<f8"}
_HEADER_FIELDS = [("magic", "u1"), ("len", "u1"), ("incompat_flags", "u1"),
                  ("compat_flags", "u1"), ("seq", "u1"), ("src_system", "u1"),
                  ("src_component", "u1"), ("msgid_lo", "<u2"), ("msgid_hi", "u1")]


def _crc_step(crc: np.ndarray, byte: np.ndarray | int) -> np.ndarray:
    """One byte of CRC-16/MCRF4XX (pymavlink's ``x25crc.accumulate``), elementwise."""
    tmp = (byte ^ (crc & 0xFF)) & 0xFF
    tmp = (tmp ^ (tmp << 4)) & 0xFF
    return ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF


class _CrcTables:
    """CRC-16/MCRF4XX of ``n``-byte inputs as XORs: the register update is affine over GF(2),
    so ``crc(b) = crc(0…0) ^ XOR_p table[p, b_p]`` with ``table[p, v]`` the CRC from a zero
    register of ``v`` at position p and zeros elsewhere."""

    def __init__(self, n: int) -> None:
        table = np.empty((n, 256), np.uint16)
        cur = _crc_step(np.zeros(256, np.uint32), np.arange(256, dtype=np.uint32))
        for p in range(n - 1, -1, -1):
            table[p] = cur
            cur = _crc_step(cur, 0)
        self.table = table
        self.zero = mcrf4xx(bytes(n))
        self._positions = np.arange(n)

    def crc(self, data: np.ndarray) -> np.ndarray:
        """The CRC of each row of ``data`` ((N, n) uint8)."""
        return np.bitwise_xor.reduce(self.table[self._positions, data], axis=1) ^ np.uint16(
            self.zero)


class _Spec:
    __slots__ = ("msgid", "struct", "size", "extra", "tuple", "zeros", "frame_dtype",
                 "_crc_tables")

    def __init__(self, cls: Any) -> None:
        self.msgid = int(cls.id)
        self.struct = struct.Struct(cls.unpacker.format)
        self.size = self.struct.size
        self.extra = bytes((cls.crc_extra,))
        self.tuple = namedtuple(f"Fast_{cls.msgname}", cls.ordered_fieldnames)  # noqa: PYI024
        self.zeros = bytes(self.size)
        #: one whole unstripped frame: header, payload (wire order), CRC
        self.frame_dtype = np.dtype(
            _HEADER_FIELDS
            + [(name, _NP_TYPES[c]) for name, c in
               zip(cls.ordered_fieldnames, cls.unpacker.format[1:], strict=True)]
            + [("crc", "<u2")])
        self._crc_tables: _CrcTables | None = None

    @property
    def crc_tables(self) -> _CrcTables:
        """Over header bytes 1..9, the payload and the CRC extra (made on first use)."""
        if self._crc_tables is None:
            self._crc_tables = _CrcTables(9 + self.size + 1)
        return self._crc_tables


class WireCodec:
    """Unpack/pack the message ids ``msgids`` (of pymavlink's ``common`` dialect) directly.

    Only message types without arrays or char fields are accepted (their decoded values are then
    exactly the struct's, as in pymavlink)."""

    def __init__(self, msgids: Iterable[int]) -> None:
        self._specs: dict[int, _Spec] = {}
        for msgid in msgids:
            cls = mavlink2.mavlink_map[msgid]
            if any(cls.array_lengths) or "char" in cls.fieldtypes:
                raise ValueError(f"{cls.msgname}: arrays and strings are not on the fast path")
            self._specs[msgid] = _Spec(cls)

    @property
    def msgids(self) -> frozenset[int]:
        return frozenset(self._specs)

    def unpack(self, data: bytes) -> Any | None:
        """The message of a datagram that is exactly one valid unsigned MAVLink 2 frame of a
        known id, as a named tuple (pymavlink's field names, wire order); None otherwise."""
        n = len(data)
        if n < 12 or data[0] != 0xFD or data[2] or data[3] or n != data[1] + 12:
            return None
        spec = self._specs.get(data[7] | (data[8] << 8) | (data[9] << 16))
        if spec is None or data[1] > spec.size:
            return None
        crc = mcrf4xx(spec.extra, mcrf4xx(data[1:n - 2]))
        if crc != (data[n - 2] | (data[n - 1] << 8)):
            return None
        payload = data[10:n - 2]
        if len(payload) < spec.size:  # MAVLink 2 strips trailing zero bytes
            payload = payload + spec.zeros[len(payload):]
        return spec.tuple._make(spec.struct.unpack(payload))

    def pack(self, msgid: int, seq: int, src_system: int, src_component: int,
             *values: Any) -> bytes:
        """One unsigned MAVLink 2 frame of ``msgid`` with ``values`` in wire order
        (``ordered_fieldnames``), as pymavlink's ``msg.pack(mav)`` builds it."""
        spec = self._specs[msgid]
        payload = spec.struct.pack(*values).rstrip(b"\x00") or b"\x00"
        head = _HEADER.pack(0xFD, len(payload), 0, 0, seq, src_system, src_component,
                            msgid & 0xFFFF, msgid >> 16)
        body = head + payload
        return body + _CRC.pack(mcrf4xx(spec.extra, mcrf4xx(body[1:])))

    def pack_many(self, msgid: int, seq: np.ndarray, src_system: np.ndarray | int,
                  src_component: np.ndarray | int, values: Mapping[str, Any]) -> list[bytes]:
        """N frames of ``msgid`` at once, each the bytes :meth:`pack` builds for its row:
        ``seq`` (N,), the source ids (N,) or scalars, ``values`` by pymavlink field name, each
        an (N,) array or a scalar (missing fields are 0). Rows whose payload ends in a zero
        byte (MAVLink 2 strips those) are packed one by one."""
        spec = self._specs[msgid]
        n = len(seq)
        rec = np.zeros(n, spec.frame_dtype)
        rec["magic"] = 0xFD
        rec["len"] = spec.size
        rec["seq"] = seq
        rec["src_system"] = src_system
        rec["src_component"] = src_component
        rec["msgid_lo"] = msgid & 0xFFFF
        rec["msgid_hi"] = msgid >> 16
        for name, col in values.items():
            rec[name] = col
        raw = rec.view(np.uint8).reshape(n, spec.frame_dtype.itemsize)
        last = 10 + spec.size  # the CRC's offset
        tables = spec.crc_tables
        body = np.empty((n, tables.table.shape[0]), np.uint8)
        body[:, :-1] = raw[:, 1:last]
        body[:, -1] = spec.extra[0]
        rec["crc"] = tables.crc(body)
        size = spec.frame_dtype.itemsize
        blob = raw.tobytes()
        frames = [blob[k:k + size] for k in range(0, n * size, size)]
        for k in np.flatnonzero(raw[:, last - 1] == 0).tolist():
            row = rec[k]
            frames[k] = self.pack(msgid, int(row["seq"]), int(row["src_system"]),
                                  int(row["src_component"]),
                                  *(row[f].item() for f in spec.tuple._fields))
        return frames
