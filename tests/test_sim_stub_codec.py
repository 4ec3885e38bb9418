"""sim_stub's MAVLink codec against the captured PX4 bytes (no sockets)."""

from __future__ import annotations

import json

import pytest
from pymavlink.dialects.v20 import common as mav

from sim_stub.captures import CAPTURE_DIR, CAPTURE_NAMES, read_tlog
from sim_stub.codec import EXTRA_SPECS, SPECS, DatagramParser, Encoder, fast_decoder

needs_captures = pytest.mark.skipif(
    not (CAPTURE_DIR / "README.md").exists(), reason=f"captures not found in {CAPTURE_DIR}"
)
_BY_ID = {s.msgid: s for s in SPECS.values()}


@needs_captures
@pytest.mark.parametrize("name", CAPTURE_NAMES)
def test_encoder_reproduces_every_captured_px4_packet_byte_for_byte(name: str) -> None:
    """Decode each PX4 packet to field values, re-encode with the mock's encoder (same seq):
    identical bytes, i.e. same layout, zero-truncation and CRC (incl. the 5 ids pymavlink's
    common dialect lacks)."""
    done = 0
    for _, pkt in read_tlog(CAPTURE_DIR / f"{name}_vehicle_to_gcs.tlog"):
        msgid = pkt[7] | (pkt[8] << 8) | (pkt[9] << 16)
        spec = _BY_ID[msgid]  # every message type PX4 sent is one the mock can send
        payload = pkt[10:-2]
        values = spec.struct.unpack(payload + bytes(spec.struct.size - len(payload)))
        enc = Encoder(pkt[5], pkt[6])
        enc.seq = pkt[4]
        assert enc.frame(spec, spec.struct.pack(*values)) == pkt, spec.name
        done += 1
    assert done > 10000


@needs_captures
@pytest.mark.parametrize("name", CAPTURE_NAMES)
def test_parser_reads_both_directions_of_the_captures_without_errors(name: str) -> None:
    parser = DatagramParser()
    for direction in ("gcs_to_vehicle", "vehicle_to_gcs"):
        unknown = 0
        for _, pkt in read_tlog(CAPTURE_DIR / f"{name}_{direction}.tlog"):
            packets, malformed, unk = parser.parse(pkt)
            assert malformed == 0
            unknown += unk
            assert len(packets) + unk == 1
        if direction == "gcs_to_vehicle":
            assert unknown == 0


@needs_captures
def test_garbage_datagrams_of_the_capture_are_malformed() -> None:
    g = json.loads((CAPTURE_DIR / "rejections_garbage_datagrams.json").read_text())
    parser = DatagramParser()
    for h in g["datagrams_hex"]:
        packets, malformed, unknown = parser.parse(bytes.fromhex(h))
        assert (packets, malformed, unknown) == ([], 1, 0)


def _heartbeat(seq: int = 0) -> bytes:
    m = mav.MAVLink(None, 255, 190)
    m.seq = seq
    return m.heartbeat_encode(6, 8, 0, 0, 0).pack(m)


def test_parser_handles_truncated_concatenated_and_foreign_datagrams() -> None:
    parser = DatagramParser()
    hb = _heartbeat()
    assert parser.parse(hb)[1:] == (0, 0) and len(parser.parse(hb)[0]) == 1
    # two packets in one datagram
    packets, malformed, _ = parser.parse(hb + _heartbeat(1))
    assert len(packets) == 2 and malformed == 0
    # truncated anywhere
    for n in range(1, len(hb)):
        packets, malformed, _ = parser.parse(hb[:n])
        assert packets == [] and malformed == 1
    # bad CRC
    bad = bytearray(hb)
    bad[-1] ^= 0xFF
    assert parser.parse(bytes(bad)) == ([], 1, 0)
    # a valid packet followed by garbage: the packet is kept, the datagram counted malformed
    packets, malformed, _ = parser.parse(hb + b"\x00garbage")
    assert len(packets) == 1 and malformed == 1
    # a well-framed packet of an unknown message id (CRC cannot be checked): counted unknown
    body = bytes((1, 0, 0, 0, 255, 190)) + (60000).to_bytes(3, "little") + b"\x01"
    assert parser.parse(b"\xfd" + body + b"\x00\x00") == ([], 0, 1)
    # MAVLink 1 framing is understood too
    m1 = mav.MAVLink(None, 255, 190)
    m1.WIRE_PROTOCOL_VERSION = "1.0"
    v1 = mav.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(m1, force_mavlink1=True)
    packets, malformed, _ = parser.parse(v1)
    assert len(packets) == 1 and malformed == 0 and packets[0].msg.get_type() == "HEARTBEAT"


def test_every_spec_encodes_like_pymavlink() -> None:
    """Same named field values through the mock's layout and through pymavlink's own packer give
    identical packets (guards the wire order the mock derives from pymavlink's dialect)."""
    m = mav.MAVLink(None, 1, 1)
    for spec in SPECS.values():
        if spec.msgid in EXTRA_SPECS:
            continue
        cls = getattr(mav, f"MAVLink_{spec.name.lower()}_message")
        values: dict[str, object] = {}
        for k, (name, n) in enumerate(zip(spec.fields, spec.lengths, strict=True)):
            ftype = cls.fieldtypes[cls.fieldnames.index(name)]
            if ftype == "char":
                values[name] = b"abc"
            elif ftype in ("float", "double"):
                values[name] = [0.5 * (k + j) for j in range(n)] if n > 1 else 0.25 * k
            else:
                values[name] = [(k + j) % 100 for j in range(n)] if n > 1 else k % 100
        m.seq = 7
        ref = cls(**values).pack(m)
        enc = Encoder(1, 1)
        enc.seq = 7
        assert enc.frame(spec, spec.pack(**values)) == bytes(ref), spec.name


def test_fast_decoder_zero_extends_truncated_payloads() -> None:
    dec = fast_decoder("HEARTBEAT")
    d = dec(b"\x01")
    assert d["custom_mode"] == 1 and d["type"] == 0
