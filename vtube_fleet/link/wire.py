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

Wire formats and CRC extras come from pymavlink's dialect classes, so they cannot drift from it
(tests/test_link_wire.py compares both paths byte for byte).
"""

from __future__ import annotations

import binascii
import struct
from collections import namedtuple
from collections.abc import Iterable
from typing import Any

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


class _Spec:
    __slots__ = ("msgid", "struct", "size", "extra", "tuple", "zeros")

    def __init__(self, cls: Any) -> None:
        self.msgid = int(cls.id)
        self.struct = struct.Struct(cls.unpacker.format)
        self.size = self.struct.size
        self.extra = bytes((cls.crc_extra,))
        self.tuple = namedtuple(f"Fast_{cls.msgname}", cls.ordered_fieldnames)  # noqa: PYI024
        self.zeros = bytes(self.size)


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
