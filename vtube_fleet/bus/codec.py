"""Wire formats of the MQTT bus: a compact binary state, small JSON control messages.

State payload (``vtube/<m>/state/<id>`` and ``vtube/<m>/last/<id>``), little-endian, 32 bytes::

    offset size type  field
    0      1    u8    format version (STATE_VERSION = 1)
    1      1    u8    phase code (index into PHASES)
    2      2    u16   vehicle id
    4      4    u32   seq (per-vehicle counter, wraps at 2**32)
    8      8    f64   stamp_s: wall-clock time (time.time()) the position was measured
    16     4    f32   x_m   tube frame
    20     4    f32   y_m
    24     4    f32   vx_m_s
    28     4    f32   vy_m_s

float32 keeps 0.1 mm resolution up to 1.6 km from the tube origin, ample for metre-scale
clearances. Status, config and command messages are rare (on change / once per mission), so
they are compact JSON objects with a ``"v"`` version field, readable with ``mosquitto_sub``.

Every decoder raises :class:`CodecError` (a ``ValueError``) naming what is wrong; the bus logs
and drops such messages (malformed network input never stops an agent).
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from typing import Any

from vtube_fleet.state import NeighbourState, Phase

__all__ = [
    "STATE_VERSION",
    "CONTROL_VERSION",
    "PHASES",
    "STATE_SIZE",
    "CodecError",
    "encode_state",
    "decode_state",
    "STATUSES",
    "Status",
    "encode_status",
    "decode_status",
    "Command",
    "COMMANDS",
    "encode_command",
    "decode_command",
    "MissionConfigMsg",
    "encode_config",
    "decode_config",
    "ClockMsg",
    "ClockOffset",
    "encode_clock",
    "decode_clock",
]

STATE_VERSION = 1
CONTROL_VERSION = 1
#: Phase codes on the wire: the index in this tuple (append only; never reorder).
PHASES: tuple[Phase, ...] = tuple(Phase)
_PHASE_CODE = {p: i for i, p in enumerate(PHASES)}

_STATE = struct.Struct("<BBHIdffff")
STATE_SIZE = _STATE.size  # 32


class CodecError(ValueError):
    """A payload that is not a valid message of the expected kind and version."""


# -- state --------------------------------------------------------------------------------------
def encode_state(state: NeighbourState) -> bytes:
    """Pack ``state`` into the 32-byte wire format."""
    try:
        return _STATE.pack(
            STATE_VERSION,
            _PHASE_CODE[Phase(state.phase)],
            state.vehicle_id,
            state.seq & 0xFFFFFFFF,
            state.stamp_s,
            state.x_m,
            state.y_m,
            state.vx_m_s,
            state.vy_m_s,
        )
    except (struct.error, KeyError, ValueError) as exc:
        raise CodecError(f"cannot encode {state!r}: {exc}") from None


def decode_state(payload: bytes) -> NeighbourState:
    """Unpack a state payload; :class:`CodecError` on a wrong size, version or phase code."""
    if len(payload) != STATE_SIZE:
        raise CodecError(f"state payload has {len(payload)} bytes, expected {STATE_SIZE}")
    version, phase, vid, seq, stamp, x, y, vx, vy = _STATE.unpack(payload)
    if version != STATE_VERSION:
        raise CodecError(f"state payload version {version}, this build reads {STATE_VERSION}")
    if phase >= len(PHASES):
        raise CodecError(f"state payload phase code {phase} unknown (max {len(PHASES) - 1})")
    # (one sum first: it is finite unless a term is, or the sum overflowed)
    if not math.isfinite(stamp + x + y + vx + vy) and not all(
        math.isfinite(v) for v in (stamp, x, y, vx, vy)
    ):
        raise CodecError(f"state payload of vehicle {vid} has non-finite numbers")
    return NeighbourState(
        vehicle_id=vid,
        x_m=x,
        y_m=y,
        vx_m_s=vx,
        vy_m_s=vy,
        phase=PHASES[phase],
        stamp_s=stamp,
        seq=seq,
    )


# -- JSON control messages ------------------------------------------------------------------------
def _dumps(obj: dict[str, Any]) -> bytes:
    return json.dumps(obj, separators=(",", ":"), sort_keys=True).encode()


def _loads(payload: bytes, what: str) -> dict[str, Any]:
    try:
        obj = json.loads(payload.decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CodecError(f"{what} payload is not JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise CodecError(f"{what} payload is not a JSON object: {payload[:60]!r}")
    if obj.get("v") != CONTROL_VERSION:
        raise CodecError(f"{what} payload version {obj.get('v')!r}, expected {CONTROL_VERSION}")
    return obj


def _field(obj: dict[str, Any], key: str, typ: type | tuple[type, ...], what: str) -> Any:
    value = obj.get(key)
    if isinstance(value, bool) or not isinstance(value, typ):
        raise CodecError(f"{what} payload: field {key!r} = {value!r} has the wrong type")
    return value


#: Agent presence values: ``online`` (connected; with its config hash and the run it joined),
#: ``offline`` (left cleanly), ``refused`` (will not fly this run: ``detail`` says why), ``lost``
#: (the broker published the last will: the connection dropped unexpectedly).
STATUSES = ("online", "offline", "refused", "lost")


@dataclass(frozen=True, slots=True)
class Status:
    """Presence of one agent (retained; the last will says ``lost``)."""

    vehicle_id: int
    status: str
    config_hash: str = ""
    run_id: str = ""  # the coordinator run this agent accepted ("" before any)
    stamp_s: float = 0.0  # 0 in a last will (its payload is fixed at connect time)
    detail: str = ""
    #: Where the agent's procedure is: "" (waiting for a mission), "joined" (accepted the
    #: run), "ready", "at_altitude" (climbed; waits for the fleet to fly the response check
    #: together), "checked" (flew it; waits for the fleet to enter the tube together),
    #: "in_tube", "waiting" / "waiting again" (trapped in the tube, docs/fleet.md "Waiting for
    #: a way"), "exited", "done".
    stage: str = ""
    #: The agent's clock offset to the coordinator's, as it measured it (None: not measured).
    clock: ClockOffset | None = None


def encode_status(status: Status) -> bytes:
    if status.status not in STATUSES:
        raise CodecError(f"unknown status {status.status!r}; expected one of {STATUSES}")
    obj: dict[str, Any] = {
        "v": CONTROL_VERSION,
        "id": status.vehicle_id,
        "status": status.status,
        "hash": status.config_hash,
        "run": status.run_id,
        "t": status.stamp_s,
        "detail": status.detail,
        "stage": status.stage,
    }
    c = status.clock
    if c is not None:
        obj["clock"] = {"offset_s": c.offset_s, "delay_s": c.delay_s, "samples": c.samples}
    return _dumps(obj)


def decode_status(payload: bytes) -> Status:
    obj = _loads(payload, "status")
    st = _field(obj, "status", str, "status")
    if st not in STATUSES:
        raise CodecError(f"status payload: unknown status {st!r}")
    clock = None
    c = obj.get("clock")
    if c is not None:
        if not isinstance(c, dict):
            raise CodecError(f"status payload: field 'clock' = {c!r} is not an object")
        clock = ClockOffset(_finite(c.get("offset_s"), "status clock offset_s"),
                            _nonneg(c.get("delay_s"), "delay_s"),
                            _field(c, "samples", int, "status clock"))
    return Status(
        vehicle_id=_field(obj, "id", int, "status"),
        status=st,
        config_hash=str(obj.get("hash", "")),
        run_id=str(obj.get("run", "")),
        stamp_s=float(_field(obj, "t", (int, float), "status")),
        detail=str(obj.get("detail", "")),
        stage=str(obj.get("stage", "")),
        clock=clock,
    )


#: Fleet commands a coordinator may publish.
COMMANDS = ("start", "abort")


@dataclass(frozen=True, slots=True)
class Command:
    """A fleet command (retained on ``vtube/<m>/cmd``) for one coordinator run.

    Agents obey only commands whose ``run_id`` is the run they joined, so a retained command
    left over from an earlier run of the same mission never starts anybody. ``seq`` grows
    with every command (milliseconds since the epoch), so a command re-published after a broker
    restart is recognised as already handled.
    """

    command: str
    mission_id: str
    run_id: str
    config_hash: str
    seq: int
    stamp_s: float


def encode_command(cmd: Command) -> bytes:
    if cmd.command not in COMMANDS:
        raise CodecError(f"unknown command {cmd.command!r}; expected one of {COMMANDS}")
    return _dumps(
        {
            "v": CONTROL_VERSION,
            "cmd": cmd.command,
            "mission": cmd.mission_id,
            "run": cmd.run_id,
            "hash": cmd.config_hash,
            "seq": cmd.seq,
            "t": cmd.stamp_s,
        }
    )


def decode_command(payload: bytes) -> Command:
    obj = _loads(payload, "command")
    name = _field(obj, "cmd", str, "command")
    if name not in COMMANDS:
        raise CodecError(f"command payload: unknown command {name!r}; expected one of {COMMANDS}")
    return Command(
        command=name,
        mission_id=_field(obj, "mission", str, "command"),
        run_id=_field(obj, "run", str, "command"),
        config_hash=_field(obj, "hash", str, "command"),
        seq=_field(obj, "seq", int, "command"),
        stamp_s=float(_field(obj, "t", (int, float), "command")),
    )


@dataclass(frozen=True, slots=True)
class MissionConfigMsg:
    """The retained mission announcement of one coordinator run.

    Agents compare ``config_hash`` with the hash of their own mission file and refuse to fly
    on a difference; ``run_id`` is new for every ``mission start``. The run's bus parameters,
    the same for every agent: ``max_age_s`` (oldest neighbour state used as a live position,
    budgeted in the safety margin), ``cell_m`` (spatial cell size; 0 = no cells) and
    ``delta_m`` (the fleet's safety budget δ, the same partition for every agent; each agent
    refuses if its own link and estimate need more; 0 = none announced).
    """

    mission_id: str
    run_id: str
    config_hash: str
    vehicles: int
    stamp_s: float
    source: str = ""  # the coordinator's mission file name, for error messages
    max_age_s: float = 0.0
    cell_m: float = 0.0
    delta_m: float = 0.0


def encode_config(cfg: MissionConfigMsg) -> bytes:
    return _dumps(
        {
            "v": CONTROL_VERSION,
            "mission": cfg.mission_id,
            "run": cfg.run_id,
            "hash": cfg.config_hash,
            "vehicles": cfg.vehicles,
            "t": cfg.stamp_s,
            "source": cfg.source,
            "max_age_s": cfg.max_age_s,
            "cell_m": cfg.cell_m,
            "delta_m": cfg.delta_m,
        }
    )


def decode_config(payload: bytes) -> MissionConfigMsg:
    obj = _loads(payload, "config")
    return MissionConfigMsg(
        mission_id=_field(obj, "mission", str, "config"),
        run_id=_field(obj, "run", str, "config"),
        config_hash=_field(obj, "hash", str, "config"),
        vehicles=_field(obj, "vehicles", int, "config"),
        stamp_s=float(_field(obj, "t", (int, float), "config")),
        source=str(obj.get("source", "")),
        max_age_s=float(_field(obj, "max_age_s", (int, float), "config")),
        cell_m=float(_field(obj, "cell_m", (int, float), "config")),
        delta_m=_nonneg(obj.get("delta_m", 0.0), "delta_m"),
    )


# -- clock --------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class ClockMsg:
    """One timestamp round trip between an agent and the coordinator (NTP's four stamps,
    wall clock, s): the agent sends ``t1_s`` (its clock) on ``clock/ask/<id>``; the coordinator
    answers on ``clock/echo/<id>`` with ``t2_s`` (its clock when the ask arrived) and ``t3_s``
    (its clock when it answered); the agent notes t4 when the echo arrives. ``nonce`` pairs an
    echo with its ask."""

    vehicle_id: int
    nonce: int
    t1_s: float
    t2_s: float = 0.0
    t3_s: float = 0.0


def encode_clock(msg: ClockMsg) -> bytes:
    return _dumps({"v": CONTROL_VERSION, "id": msg.vehicle_id, "n": msg.nonce, "t1": msg.t1_s,
                   "t2": msg.t2_s, "t3": msg.t3_s})


def decode_clock(payload: bytes) -> ClockMsg:
    obj = _loads(payload, "clock")
    return ClockMsg(
        vehicle_id=_field(obj, "id", int, "clock"),
        nonce=_field(obj, "n", int, "clock"),
        t1_s=_finite(obj.get("t1"), "clock t1"),
        t2_s=_finite(obj.get("t2", 0.0), "clock t2"),
        t3_s=_finite(obj.get("t3", 0.0), "clock t3"),
    )


@dataclass(frozen=True, slots=True)
class ClockOffset:
    """An agent's clock against the coordinator's, from the round trip of least delay out of
    ``samples`` (NTP): ``offset_s`` = the agent's clock − the coordinator's (positive: the
    agent's runs ahead), ``delay_s`` the round trip without the coordinator's own time. The true
    offset lies within ``offset_s`` ± ``delay_s`` / 2 (the two legs of the trip may differ by
    all of it), so the agent's clock is at most :attr:`bound_s` from the coordinator's."""

    offset_s: float
    delay_s: float
    samples: int = 1

    @classmethod
    def from_stamps(cls, t1_s: float, t2_s: float, t3_s: float, t4_s: float) -> ClockOffset:
        """One round trip: t1 ask sent, t2 ask received (coordinator), t3 echo sent
        (coordinator), t4 echo received: offset = ((t1 − t2) + (t4 − t3)) / 2 (the agent's
        minus the coordinator's), delay = (t4 − t1) − (t3 − t2)."""
        return cls(((t1_s - t2_s) + (t4_s - t3_s)) / 2.0, (t4_s - t1_s) - (t3_s - t2_s))

    @property
    def bound_s(self) -> float:
        """|offset| + delay / 2: how far the agent's clock may be from the coordinator's."""
        return abs(self.offset_s) + 0.5 * max(self.delay_s, 0.0)

    def describe(self) -> str:
        ms = round(1000.0 * self.offset_s, 1) + 0.0  # (+ 0.0: never "-0.0")
        return (f"clock offset {ms:+.1f} ms to the coordinator's (round trip "
                f"{1000 * self.delay_s:.1f} ms, best of {self.samples}: within "
                f"{1000 * self.bound_s:.1f} ms)")


def _finite(v: Any, name: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise CodecError(f"{name} must be a finite number, got {v!r}")
    return float(v)


def _nonneg(v: Any, name: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
        raise CodecError(f"config: {name} must be a finite number >= 0, got {v!r}")
    return float(v)
