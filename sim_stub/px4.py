"""PX4 conventions as seen on the wire: modes, base_mode flags, parameters, STATUSTEXT, events.

Everything here is either measured in the captures (``tests/data/px4_sitl/``, summarised in
``docs/sim_stub.md``, cited as "capture") or taken from PX4 source at the captured era (cited as
"PX4 source") where the captures do not show it. Pure data and pure functions, no I/O.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

__all__ = [
    "MAV_RESULT_ACCEPTED",
    "MAV_RESULT_TEMPORARILY_REJECTED",
    "MAV_RESULT_DENIED",
    "MAV_RESULT_UNSUPPORTED",
    "MAV_RESULT_FAILED",
    "MAV_STATE_UNINIT",
    "MAV_STATE_STANDBY",
    "MAV_STATE_ACTIVE",
    "MAV_STATE_CRITICAL",
    "LANDED_ON_GROUND",
    "LANDED_IN_AIR",
    "FLAG_CUSTOM",
    "FLAG_STABILIZE",
    "FLAG_GUIDED",
    "FLAG_AUTO",
    "FLAG_MANUAL",
    "FLAG_ARMED",
    "Mode",
    "MODES",
    "MODE_BY_NAME",
    "mode_from_custom",
    "mode_from_set_mode",
    "custom_mode",
    "base_mode",
    "Param",
    "PARAM_DEFAULTS",
    "PARAM_REAL32",
    "PARAM_INT32",
    "param_to_wire",
    "param_from_wire",
    "param_table",
    "statustext_chunks",
    "EventTemplate",
    "EVENTS",
    "HEALTH_BURST_NOT_READY",
    "HEALTH_BURST_READY",
    "HEALTH_BURST_NO_OFFBOARD",
    "SENSORS_BOOT",
    "SENSORS_NO_GPS",
    "SENSORS_READY",
    "SENSOR_PREARM",
    "ARM_REASON",
]

# --- MAVLink enums used here ------------------------------------------------------------------
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_TEMPORARILY_REJECTED = 1
MAV_RESULT_DENIED = 2
MAV_RESULT_UNSUPPORTED = 3
MAV_RESULT_FAILED = 4

MAV_STATE_UNINIT = 0
MAV_STATE_STANDBY = 3
MAV_STATE_ACTIVE = 4
MAV_STATE_CRITICAL = 5

LANDED_ON_GROUND = 1
LANDED_IN_AIR = 2  # capture: 3 (TAKEOFF) and 4 (LANDING) were never reported

SEV_CRITICAL = 2
SEV_INFO = 6

FLAG_CUSTOM = 0x01
FLAG_AUTO = 0x04
FLAG_GUIDED = 0x08
FLAG_STABILIZE = 0x10
FLAG_MANUAL = 0x40
FLAG_ARMED = 0x80


# --- modes ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Mode:
    """A PX4 navigation state as MAVLink shows it.

    ``name``: mock-wide name ("OFFBOARD", "AUTO.LOITER", ...); ``label``: PX4's nav_state name
    used in "Switching to <label> is currently not available"; ``flags``: base_mode flags besides
    CUSTOM/ARMED (capture: AUTO.LOITER 29 = CUSTOM|AUTO|GUIDED|STABILIZE, POSCTL 209 armed =
    ARMED|MANUAL|STABILIZE|CUSTOM; OFFBOARD's STABILIZE flag depends on the setpoints, see
    :func:`base_mode`); ``standard_mode``: CURRENT_MODE.standard_mode (capture: POSCTL 1, others
    seen 0); ``needs``: what the mode needs to run ("position", "offboard", "manual", "mission").
    """

    name: str
    main: int
    sub: int
    label: str
    flags: int
    standard_mode: int
    needs: str

    @property
    def custom_mode(self) -> int:
        return custom_mode(self.main, self.sub)


def custom_mode(main: int, sub: int = 0) -> int:
    """PX4 custom_mode: main mode in bits 16..23, sub mode in bits 24..31 (capture)."""
    return ((main & 0xFF) << 16) | ((sub & 0xFF) << 24)


_MANUAL_FLAGS = FLAG_MANUAL | FLAG_STABILIZE
_AUTO_FLAGS = FLAG_AUTO | FLAG_GUIDED | FLAG_STABILIZE

MODES: tuple[Mode, ...] = (
    Mode("MANUAL", 1, 0, "Manual", _MANUAL_FLAGS, 0, "manual"),
    Mode("ALTCTL", 2, 0, "Altitude", _MANUAL_FLAGS, 4, "manual"),
    Mode("POSCTL", 3, 0, "Position", _MANUAL_FLAGS, 1, "manual"),
    Mode("AUTO.TAKEOFF", 4, 2, "Takeoff", _AUTO_FLAGS, 8, "position"),
    Mode("AUTO.LOITER", 4, 3, "Hold", _AUTO_FLAGS, 0, "position"),
    Mode("AUTO.MISSION", 4, 4, "Mission", _AUTO_FLAGS, 6, "mission"),
    Mode("AUTO.RTL", 4, 5, "Return", _AUTO_FLAGS, 5, "position"),
    Mode("AUTO.LAND", 4, 6, "Land", _AUTO_FLAGS, 7, "position"),
    Mode("AUTO.FOLLOW_TARGET", 4, 8, "Follow Target", _AUTO_FLAGS, 0, "unsupported"),
    Mode("AUTO.PRECLAND", 4, 9, "Precision Landing", _AUTO_FLAGS, 0, "unsupported"),
    Mode("ACRO", 5, 0, "Acro", FLAG_MANUAL, 0, "manual"),
    Mode("OFFBOARD", 6, 0, "Offboard", FLAG_STABILIZE, 0, "offboard"),
    Mode("STABILIZED", 7, 0, "Stabilized", _MANUAL_FLAGS, 0, "manual"),
)
MODE_BY_NAME = {m.name: m for m in MODES}
_MODE_BY_CUSTOM = {m.custom_mode: m for m in MODES}


def mode_from_custom(cm: int) -> Mode | None:
    """The :class:`Mode` of a HEARTBEAT custom_mode, or None if PX4 has no such mode."""
    return _MODE_BY_CUSTOM.get(cm & 0xFFFF0000)


def mode_from_set_mode(main: int, sub: int) -> Mode | None:
    """Mode selected by DO_SET_MODE(CUSTOM, main, sub) as PX4's commander maps it.

    POSCTL ignores the sub mode (POSCTL_SLOW is not modelled), AUTO with sub 0 is MISSION, an
    unknown AUTO sub mode is None ("Unsupported auto mode").
    """
    if main in (1, 2, 3, 5, 6, 7):
        return _MODE_BY_CUSTOM.get(custom_mode(main, 0))
    if main == 4:
        return _MODE_BY_CUSTOM.get(custom_mode(4, sub if sub else 4))
    return None


def base_mode(mode: Mode, armed: bool, offboard_has_setpoint: bool = True) -> int:
    """HEARTBEAT base_mode as the captures show it.

    OFFBOARD reports 17 (CUSTOM|STABILIZE) once any setpoint has configured the offboard control
    mode, and 1 (CUSTOM only) while no setpoint was ever received (capture 1d).
    """
    flags = mode.flags
    if mode.name == "OFFBOARD" and not offboard_has_setpoint:
        flags = 0
    return FLAG_CUSTOM | flags | (FLAG_ARMED if armed else 0)


# --- arming / disarming reasons (PX4 arm_disarm_reason_t as seen in EVENT arguments) ---------
ARM_REASON = {
    "external command": 4,  # capture: "Armed by external command", EVENT argument 04
    "landing": 6,  # capture: "Disarmed by landing", argument 06
    "auto preflight disarming": 7,  # capture: argument 07
}


# --- parameters -------------------------------------------------------------------------------
PARAM_INT32 = 6
PARAM_REAL32 = 9


@dataclass(frozen=True)
class Param:
    """A PX4 parameter default: ``name`` (≤ 16 chars), ``value``, MAVLink ``type`` (6 or 9)."""

    name: str
    value: float
    type: int


def _p(name: str, value: float, type_: int = PARAM_REAL32) -> Param:
    return Param(name, float(value), type_)


# Values read from real PX4 in the captures are marked (capture); the rest are PX4 defaults of
# the same era (PX4 source / parameter reference) that the mock's behaviour uses.
PARAM_DEFAULTS: tuple[Param, ...] = (
    _p("CAL_BARO0_ID", 6620172, PARAM_INT32),  # capture (unsolicited at ~5.5 s)
    _p("CAL_BARO0_OFF", 0.0),  # capture: varies per run (-3.66 .. 1.22)
    _p("CAL_BARO0_PRIO", 50, PARAM_INT32),  # capture
    _p("COM_ARM_WO_GPS", 1, PARAM_INT32),  # capture
    _p("COM_DISARM_LAND", 2.0),  # capture
    _p("COM_DISARM_PRFLT", 10.0),  # capture
    _p("COM_DL_LOSS_T", 10, PARAM_INT32),  # capture
    _p("COM_FAIL_ACT_T", 5.0),  # capture
    _p("COM_OBL_RC_ACT", 0, PARAM_INT32),  # capture: 0 = Position mode
    _p("COM_OF_LOSS_T", 1.0),  # capture
    _p("COM_RCL_EXCEPT", 0, PARAM_INT32),  # capture
    _p("COM_RC_IN_MODE", 1, PARAM_INT32),  # capture
    _p("COM_SPOOLUP_TIME", 1.0),
    _p("GF_ACTION", 2, PARAM_INT32),  # PX4 source: geofence_params.yaml default Hold
    # PX4 source: src/modules/navigator/geofence_params.yaml, "Disabled if 0" (the mock does
    # not enforce a ceiling; the fleet's audit refuses a set one below the mission altitude)
    _p("GF_MAX_VER_DIST", 0.0),
    _p("MAV_SYS_ID", 1, PARAM_INT32),  # set to instance+1 per vehicle
    _p("MIS_TAKEOFF_ALT", 2.5),
    _p("MPC_ACC_DOWN_MAX", 3.0),
    _p("MPC_ACC_HOR", 3.0),
    _p("MPC_ACC_UP_MAX", 4.0),
    # PX4 source: src/modules/mc_pos_control/multicopter_autonomous_params.yaml (MPC_JERK_AUTO,
    # auto modes) and multicopter_position_mode_params.yaml (MPC_JERK_MAX, Position mode);
    # answered only: offboard velocity setpoints bypass PX4's jerk-limited trajectory
    _p("MPC_JERK_AUTO", 4.0),
    _p("MPC_JERK_MAX", 8.0),
    _p("MPC_LAND_SPEED", 0.7),
    _p("MPC_TKO_RAMP_T", 3.0),
    _p("MPC_TKO_SPEED", 1.5),
    _p("MPC_XY_CRUISE", 5.0),
    _p("MPC_XY_P", 0.95),
    _p("MPC_XY_VEL_MAX", 12.0),
    _p("MPC_YAWRAUTO_MAX", 45.0),
    _p("MPC_Z_P", 1.0),
    # PX4 source: src/modules/mc_pos_control/multicopter_position_control_limits_params.yaml;
    # in offboard PX4 clips the vertical velocity setpoint to [-UP, DN] (commander.py _limit)
    _p("MPC_Z_VEL_MAX_DN", 1.5),
    _p("MPC_Z_VEL_MAX_UP", 3.0),
    _p("NAV_DLL_ACT", 0, PARAM_INT32),  # capture
    _p("NAV_RCL_ACT", 2, PARAM_INT32),  # capture
    _p("RTL_DESCEND_ALT", 30.0),
    _p("RTL_RETURN_ALT", 60.0),
    _p("SYS_AUTOSTART", 10040, PARAM_INT32),  # sihsim_quadx
)


def param_table(overrides: dict[str, float] | None = None, sysid: int = 1) -> dict[str, Param]:
    """The mock's parameter set (sorted by name as PX4 sorts), with ``overrides`` applied.

    An override of an unknown name raises ``KeyError`` naming it.
    """
    table = {p.name: p for p in PARAM_DEFAULTS}
    table["MAV_SYS_ID"] = Param("MAV_SYS_ID", float(sysid), PARAM_INT32)
    for name, value in (overrides or {}).items():
        if name not in table:
            raise KeyError(f"unknown parameter {name!r} (the mock models {len(table)} parameters)")
        p = table[name]
        table[name] = Param(name, float(value), p.type)
    return dict(sorted(table.items()))


_F = struct.Struct("<f")
_I = struct.Struct("<i")


def param_to_wire(p: Param) -> float:
    """PARAM_VALUE.param_value: REAL32 as is; INT32 bytewise in the float (capture: 1 → 1.4e-45)."""
    if p.type == PARAM_INT32:
        return _F.unpack(_I.pack(int(p.value)))[0]
    return p.value


def param_from_wire(value: float, type_: int) -> float:
    """Inverse of :func:`param_to_wire` for PARAM_SET: INT32 is read back bytewise."""
    if type_ == PARAM_INT32:
        return float(_I.unpack(_F.pack(value))[0])
    return float(value)


# --- STATUSTEXT -------------------------------------------------------------------------------
def statustext_chunks(text: str) -> list[bytes]:
    """Split a PX4 text (already ending in ``\\t``) into 50-byte STATUSTEXT chunks (capture).

    The first chunks are exactly 50 bytes and not NUL-terminated; the last one is shorter. A text
    of a multiple of 50 bytes gets an empty terminating chunk.
    """
    raw = text.encode("utf-8")
    if len(raw) <= 50:
        return [raw]
    chunks = [raw[i : i + 50] for i in range(0, len(raw), 50)]
    if len(chunks[-1]) == 50:
        chunks.append(b"")
    return chunks


# --- EVENT (msgid 410) templates --------------------------------------------------------------
@dataclass(frozen=True)
class EventTemplate:
    """An EVENT as PX4 sent it in the captures: 32-bit id, log_levels byte, raw argument bytes.

    The mock does not decode PX4's event metadata; it re-sends the events at the same triggers
    with the same ids and arguments, so the EVENT/CURRENT_EVENT_SEQUENCE stream looks alike.
    """

    event_id: int
    log_levels: int
    args: bytes


def _ev(event_id: str, levels: int, args: str = "") -> EventTemplate:
    return EventTemplate(
        int.from_bytes(bytes.fromhex(event_id), "little"), levels, bytes.fromhex(args)
    )


EVENTS = {
    "boot": _ev("ef5b1201", 0x66, "ea070b1515310c"),
    "arming_denied": _ev("9d080201", 0x62),
    "armed": _ev("f3ca9001", 0x66, "04"),
    "takeoff": _ev("69454101", 0x66),
    "landing": _ev("ac389601", 0x66),
    "disarmed": _ev("7767f401", 0x66, "06"),
    "failsafe": _ev("d0dbde01", 0x42, "0000060002"),
}
# health/arming-check reports (capture: 8 at ~2.2 s, 4-5 when ready, 5 when the offboard signal
# is lost)
HEALTH_BURST_NOT_READY = (
    _ev("e093a801", 0x88, "000000120180000000803b0180803b0180"),
    _ev("b91bd301", 0x33, "7c007e0011"),
    _ev("73c29801", 0x33, "3800000018"),
    _ev("d9c20501", 0x66, "0800000014"),
    _ev("c71d2f01", 0x33, "0040000014"),
    _ev("29ed0601", 0x44, "ffffffff07"),
    _ev("7bc96701", 0x66, "ffffffff0c"),
    _ev("27371d01", 0x88, "00020c0238"),
)
HEALTH_BURST_READY = (
    _ev("e093a801", 0x88, "000000000080000000b07b7f80b07b7f80"),
    _ev("d9c20501", 0x66, "0800000014"),
    _ev("29ed0601", 0x44, "ffffffff07"),
    _ev("27371d01", 0x88, "000a1c0238"),
)
HEALTH_BURST_NO_OFFBOARD = (
    _ev("e093a801", 0x88, "000000100080000000b03b7f80b03b7f80"),
    _ev("d9c20501", 0x66, "0800000014"),
    _ev("c71d2f01", 0x33, "0040000014"),
    _ev("29ed0601", 0x44, "ffffffff07"),
    _ev("27371d01", 0x88, "000a1c0238"),
)

# --- SYS_STATUS sensor bits (capture, three phases) -------------------------------------------
# (present, enabled, health); PREARM_CHECK (0x10000000) is added to health when arming is allowed.
SENSORS_BOOT = (0, 0, 52545599)  # first ~2.4 s
SENSORS_NO_GPS = (50348047, 50413583, 52463679)  # ~2.4 s .. ready
SENSORS_READY = (50348079, 50413615, 52480063)  # from ready on (GPS present)
SENSOR_PREARM = 0x10000000


# Boot timeline, seconds after start (capture: first packet 0.37-0.44 s, HEARTBEAT 1.3-1.45 s,
# GLOBAL_POSITION_INT 2.9-3.2 s, system_status STANDBY between the 3.4 s and 4.4 s heartbeats,
# health reports at ~4.3 s, unsolicited CAL_BARO0_* at ~5.5 s).
BOOT = {
    "time_boot_zero": 0.22,  # time_boot_ms 0 (capture: first GPS_RAW_INT at 0.39 s has 164 ms)
    "event_boot": 0.44,
    "origin": 1.38,  # GPS_GLOBAL_ORIGIN (sent once) and home become valid
    "health_report": 2.25,
    "sensors": 2.40,
    "logger": 2.70,
    "global_position": 2.95,
    "ready": 4.30,
    "cal_baro": 5.55,
}

# Takeoff/landing timing (capture, see dynamics fit): spool-up COM_SPOOLUP_TIME (1 s), then the
# takeoff ramp: "Takeoff detected"/IN_AIR 0.9 s and lift-off 2.0 s after the ramp starts (capture:
# "Takeoff detected" 1.7-2.0 s and lift-off ~3.0 s after ARM with a climb command waiting);
# "Landing detected" 1.5 s after touchdown (capture: 1.0-2.0 s).
TAKEOFF_DETECT_S = 0.9
LIFTOFF_S = 2.0
LAND_DETECT_S = 1.5
# after a disarm by landing PX4 re-reports its health once (capture: 3.83 s and 3.92 s later; the
# cause is not visible on the link)
HEALTH_AFTER_LANDING_S = 3.87
TAKEOFF_ACCEPT_M = 0.8  # NAV_MC_ALT_RAD: takeoff counts as done within this of the target
MAX_STREAM_HZ = 500.0  # SET_MESSAGE_INTERVAL requests above this rate are capped (mock)
# hard speed caps whatever the parameters say (PX4 parameter metadata maxima of MPC_XY_VEL_MAX,
# MPC_Z_VEL_MAX_UP, MPC_Z_VEL_MAX_DN)
XY_SPEED_CAP, UP_SPEED_CAP, DOWN_SPEED_CAP = 20.0, 8.0, 4.0

#: Boot stages in order (keys of :data:`BOOT`) the heartbeat builder walks through.
BOOT_STAGES = ("event_boot", "origin", "health_report", "logger", "ready", "cal_baro")
