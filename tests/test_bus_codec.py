"""Wire formats of the MQTT bus (vtube_fleet.bus.codec) and its topic names."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from vtube_fleet.bus.codec import (
    PHASES,
    STATE_SIZE,
    CodecError,
    Command,
    MissionConfigMsg,
    Status,
    decode_command,
    decode_config,
    decode_state,
    decode_status,
    encode_command,
    encode_config,
    encode_state,
    encode_status,
)
from vtube_fleet.bus.topics import MissionTopics, TopicError
from vtube_fleet.errors import UserError
from vtube_fleet.state import NeighbourState, Phase

f32 = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False, width=32)


@given(
    vid=st.integers(0, 65535),
    seq=st.integers(0, 2**32 - 1),
    stamp=st.floats(0, 4e9, allow_nan=False),
    x=f32,
    y=f32,
    vx=f32,
    vy=f32,
    phase=st.sampled_from(list(Phase)),
)
def test_state_round_trip(vid, seq, stamp, x, y, vx, vy, phase):
    s = NeighbourState(vid, x, y, vx, vy, phase, stamp, seq)
    payload = encode_state(s)
    assert len(payload) == STATE_SIZE == 32
    assert decode_state(payload) == s


def test_state_float32_resolution():
    s = NeighbourState(1, 1234.5678, -987.6543, 1.23456, -0.5, Phase.IN_TUBE, 1.8e9 + 0.123456, 7)
    d = decode_state(encode_state(s))
    assert abs(d.x_m - s.x_m) < 1e-4 and abs(d.y_m - s.y_m) < 1e-4
    assert d.stamp_s == s.stamp_s  # float64: exact


def test_phase_codes_are_pinned():
    # Wire compatibility: existing codes never change (new phases are appended).
    assert PHASES[:11] == (
        Phase.CONNECTING,
        Phase.READY,
        Phase.ARMING,
        Phase.TAKEOFF,
        Phase.IN_TUBE,
        Phase.EXITED,
        Phase.HOLDING,
        Phase.LANDING,
        Phase.LANDED,
        Phase.LOST,
        Phase.FAILED,
    )


@pytest.mark.parametrize(
    "payload, match",
    [
        (b"", "0 bytes"),
        (b"\x01" * 31, "31 bytes"),
        (struct.pack("<BBHIdffff", 2, 0, 1, 1, 1.0, 0, 0, 0, 0), "version 2"),
        (struct.pack("<BBHIdffff", 1, 200, 1, 1, 1.0, 0, 0, 0, 0), "phase code 200"),
        (struct.pack("<BBHIdffff", 1, 0, 1, 1, 1.0, math.nan, 0, 0, 0), "non-finite"),
    ],
)
def test_state_rejects_malformed(payload, match):
    with pytest.raises(CodecError, match=match):
        decode_state(payload)


def test_state_encode_rejects_out_of_range_id():
    with pytest.raises(CodecError, match="cannot encode"):
        encode_state(NeighbourState(70000, 0, 0, 0, 0, Phase.READY, 1.0, 0))


def test_control_messages_round_trip():
    st_ = Status(3, "refused", "abc", "run1", 12.5, "config hash differs", "joined")
    assert decode_status(encode_status(st_)) == st_
    cmd = Command("start", "demo", "run1", "abc", 1700000000123, 1700000000.1)
    assert decode_command(encode_command(cmd)) == cmd
    cfg = MissionConfigMsg("demo", "run1", "abc", 8, 1.5, "mock_fleet.toml", 0.15, 3.5)
    assert decode_config(encode_config(cfg)) == cfg
    assert len(encode_command(cmd)) < 150  # compact JSON


@pytest.mark.parametrize(
    "decoder, payload, match",
    [
        (decode_status, b"\xff\xfe", "not JSON"),
        (decode_status, b"[1, 2]", "not a JSON object"),
        (decode_status, b'{"v": 9, "status": "online"}', "version 9"),
        (decode_status, b'{"v": 1, "status": "dancing", "id": 1, "t": 0}', "unknown status"),
        (decode_status, b'{"v": 1, "status": "online", "id": "1", "t": 0}', "'id'"),
        (decode_command, b'{"v": 1, "cmd": "selfdestruct"}', "unknown command"),
        (
            decode_command,
            b'{"v": 1, "cmd": "start", "mission": "m", "run": "r", "hash": "h",'
            b' "seq": true, "t": 0}',
            "'seq'",
        ),
        (decode_config, b'{"v": 1, "mission": "m"}', "'run'"),
    ],
)
def test_control_rejects_malformed(decoder, payload, match):
    with pytest.raises(CodecError, match=match):
        decoder(payload)


def test_encode_rejects_unknown_names():
    with pytest.raises(CodecError):
        encode_status(Status(1, "sleepy"))
    with pytest.raises(CodecError):
        encode_command(Command("fly-home", "m", "r", "h", 1, 0.0))


# -- topics ---------------------------------------------------------------------------------
def test_topic_names_and_classification():
    t = MissionTopics("mock-fleet_1.2")
    assert t.state(3) == "vtube/mock-fleet_1.2/state/0/0/3"
    assert t.state(3, (-2, 5)) == "vtube/mock-fleet_1.2/state/-2/5/3"
    assert t.cell_states((4, -1)) == "vtube/mock-fleet_1.2/state/4/-1/+"
    assert t.status(3) == "vtube/mock-fleet_1.2/status/3"
    assert t.last(3) == "vtube/mock-fleet_1.2/last/3"
    assert t.all_states == "vtube/mock-fleet_1.2/state/+/+/+"
    assert t.classify(t.state(12)) == ("state", 12)
    assert t.classify(t.state(12, (-3, 7))) == ("state", 12)
    assert t.classify("vtube/mock-fleet_1.2/state/1/x/3") == ("unknown", None)
    assert t.classify("vtube/mock-fleet_1.2/state/3") == ("unknown", None)
    assert t.classify(t.status(0)) == ("status", 0)
    assert t.classify(t.last(5)) == ("last", 5)
    assert t.classify(t.config) == ("config", None)
    assert t.classify(t.cmd) == ("cmd", None)
    assert t.classify("vtube/mock-fleet_1.2/status/x1") == ("unknown", None)
    assert t.classify("vtube/other/state/1") == ("unknown", None)


@pytest.mark.parametrize("bad", ["", "a/b", "a+b", "#", "with space", "x" * 65])
def test_bad_mission_ids_are_user_errors(bad):
    with pytest.raises(TopicError, match="not usable as an MQTT topic level") as info:
        MissionTopics(bad)
    assert isinstance(info.value, UserError)
