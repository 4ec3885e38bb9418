"""PX4 specifics on the wire: custom_mode encoding, MAV_RESULT / landed-state / MAV_STATE names,
SYS_STATUS health bits. Pure functions and tables, no I/O.

PX4 packs its flight mode into HEARTBEAT.custom_mode as ``main << 16 | sub << 24`` (see
``px4_custom_mode.h``); the captures in ``tests/data/px4_sitl`` show ``50593792`` = main 4 / sub 3 =
AUTO.LOITER ("Hold", the boot mode), ``393216`` = main 6 = OFFBOARD and ``196608`` = main 3 =
POSCTL (offboard-loss failsafe). A mode is selected with MAV_CMD_DO_SET_MODE(param1 = 1
(MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), param2 = main, param3 = sub).

Flight-mode names follow MAVSDK's ``FlightMode`` enum (``HOLD``, ``OFFBOARD``, ``POSCTL``,
``LAND``, ``TAKEOFF`` …) so both link backends report the same strings; :func:`px4_mode_name`
gives PX4's own dotted name (``AUTO.LOITER``).
"""

from __future__ import annotations

__all__ = [
    "PX4_MAIN_MODES",
    "PX4_AUTO_SUB_MODES",
    "FLIGHT_MODES",
    "MAV_RESULT_NAMES",
    "LANDED_STATE_NAMES",
    "MAV_STATE_NAMES",
    "HEALTH_REQUIRED_BITS",
    "PREARM_CHECK_BIT",
    "decode_custom_mode",
    "encode_custom_mode",
    "px4_mode_name",
    "flight_mode_name",
    "mode_for_flight_mode",
    "result_name",
    "landed_state_name",
    "system_status_name",
    "health_problems",
]

#: PX4 main modes (px4_custom_mode.h, PX4_CUSTOM_MAIN_MODE_*).
PX4_MAIN_MODES: dict[int, str] = {
    1: "MANUAL",
    2: "ALTCTL",
    3: "POSCTL",
    4: "AUTO",
    5: "ACRO",
    6: "OFFBOARD",
    7: "STABILIZED",
    8: "RATTITUDE",
    9: "SIMPLE",
    10: "TERMINATION",
}
#: PX4 AUTO sub modes (PX4_CUSTOM_SUB_MODE_AUTO_*).
PX4_AUTO_SUB_MODES: dict[int, str] = {
    1: "READY",
    2: "TAKEOFF",
    3: "LOITER",
    4: "MISSION",
    5: "RTL",
    6: "LAND",
    8: "FOLLOW_TARGET",
    9: "PRECLAND",
    10: "VTOL_TAKEOFF",
}
#: PX4 POSCTL sub modes.
PX4_POSCTL_SUB_MODES: dict[int, str] = {0: "POSCTL", 1: "ORBIT", 2: "SLOW"}

#: MAVSDK-style flight-mode name → (main, sub) to request it with DO_SET_MODE.
FLIGHT_MODES: dict[str, tuple[int, int]] = {
    "MANUAL": (1, 0),
    "ALTCTL": (2, 0),
    "POSCTL": (3, 0),
    "READY": (4, 1),
    "TAKEOFF": (4, 2),
    "HOLD": (4, 3),
    "MISSION": (4, 4),
    "RETURN_TO_LAUNCH": (4, 5),
    "LAND": (4, 6),
    "FOLLOW_ME": (4, 8),
    "PRECISION_LAND": (4, 9),
    "ACRO": (5, 0),
    "OFFBOARD": (6, 0),
    "STABILIZED": (7, 0),
    "RATTITUDE": (8, 0),
}
_NAME_BY_MAIN_SUB: dict[tuple[int, int], str] = {v: k for k, v in FLIGHT_MODES.items()}

MAV_RESULT_NAMES: dict[int, str] = {
    0: "ACCEPTED",
    1: "TEMPORARILY_REJECTED",
    2: "DENIED",
    3: "UNSUPPORTED",
    4: "FAILED",
    5: "IN_PROGRESS",
    6: "CANCELLED",
    7: "COMMAND_LONG_ONLY",
    8: "COMMAND_INT_ONLY",
    9: "COMMAND_UNSUPPORTED_MAV_FRAME",
}
#: MAV_LANDED_STATE → MAVSDK ``LandedState`` names (PX4 SITL only ever reported 1 and 2).
LANDED_STATE_NAMES: dict[int, str] = {
    0: "UNKNOWN",
    1: "ON_GROUND",
    2: "IN_AIR",
    3: "TAKING_OFF",
    4: "LANDING",
}
MAV_STATE_NAMES: dict[int, str] = {
    0: "UNINIT",
    1: "BOOT",
    2: "CALIBRATING",
    3: "STANDBY",
    4: "ACTIVE",
    5: "CRITICAL",
    6: "EMERGENCY",
    7: "POWEROFF",
    8: "FLIGHT_TERMINATION",
}

#: SYS_STATUS bits that must be healthy (MAV_SYS_STATUS_SENSOR_*: gyro, accel, mag, GPS).
HEALTH_REQUIRED_BITS: dict[int, str] = {
    0x01: "gyro",
    0x02: "accel",
    0x04: "mag",
    0x20: "gps",
}
#: MAV_SYS_STATUS_PREARM_CHECK. PX4 (captures) sets it only in the *health* field, not in
#: present/enabled; it is set once the pre-arm checks pass (about 3-4 s after boot).
PREARM_CHECK_BIT = 0x1000_0000


def decode_custom_mode(custom_mode: int) -> tuple[int, int]:
    """(main, sub) of a PX4 HEARTBEAT.custom_mode: ``main = (cm >> 16) & 0xFF``,
    ``sub = (cm >> 24) & 0xFF``."""
    return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF


def encode_custom_mode(main: int, sub: int = 0) -> int:
    """Inverse of :func:`decode_custom_mode`: ``encode_custom_mode(4, 3) == 50593792``."""
    return ((main & 0xFF) << 16) | ((sub & 0xFF) << 24)


def px4_mode_name(custom_mode: int) -> str:
    """PX4's dotted name, e.g. ``AUTO.LOITER``, ``OFFBOARD``, ``POSCTL``; unknown values give
    ``MODE(main=…, sub=…)``."""
    main, sub = decode_custom_mode(custom_mode)
    main_name = PX4_MAIN_MODES.get(main)
    if main_name is None:
        return f"MODE(main={main}, sub={sub})"
    if main == 4:
        sub_name = PX4_AUTO_SUB_MODES.get(sub)
        return f"AUTO.{sub_name}" if sub_name else f"AUTO.SUB{sub}"
    if main == 3 and sub:
        return f"POSCTL.{PX4_POSCTL_SUB_MODES.get(sub, f'SUB{sub}')}"
    return main_name


def flight_mode_name(custom_mode: int) -> str:
    """MAVSDK-style flight-mode name: AUTO.LOITER → ``HOLD``, AUTO.LAND → ``LAND``, OFFBOARD →
    ``OFFBOARD`` …; anything without a MAVSDK name gives :func:`px4_mode_name`."""
    main, sub = decode_custom_mode(custom_mode)
    if main != 4:
        sub = 0  # POSCTL's ORBIT/SLOW and others: MAVSDK reports the main mode
    return _NAME_BY_MAIN_SUB.get((main, sub)) or px4_mode_name(custom_mode)


def mode_for_flight_mode(name: str) -> tuple[int, int]:
    """(main, sub) for a MAVSDK-style name (also accepts PX4's ``AUTO.LOITER`` spelling)."""
    key = name.upper()
    if key in FLIGHT_MODES:
        return FLIGHT_MODES[key]
    for cm_main, main_name in PX4_MAIN_MODES.items():
        if key == main_name:
            return cm_main, 0
    if key.startswith("AUTO."):
        for sub, sub_name in PX4_AUTO_SUB_MODES.items():
            if key == f"AUTO.{sub_name}":
                return 4, sub
    raise ValueError(f"unknown PX4 flight mode {name!r}; known: {', '.join(FLIGHT_MODES)}")


def result_name(result: int) -> str:
    """MAV_RESULT name without prefix, e.g. ``TEMPORARILY_REJECTED``."""
    return MAV_RESULT_NAMES.get(result, f"MAV_RESULT({result})")


def landed_state_name(state: int) -> str:
    return LANDED_STATE_NAMES.get(state, f"LANDED_STATE({state})")


def system_status_name(status: int) -> str:
    return MAV_STATE_NAMES.get(status, f"MAV_STATE({status})")


def health_problems(health: int) -> list[str]:
    """Names of what is not healthy in SYS_STATUS.onboard_control_sensors_health (empty list =
    healthy).

    A sensor in :data:`HEALTH_REQUIRED_BITS` counts when its health bit is 0 (PX4 sets the health
    bits of absent sensors to 1, so present/enabled need not be consulted); ``prearm`` when the
    PREARM_CHECK health bit is 0.
    """
    problems = [name for bit, name in HEALTH_REQUIRED_BITS.items() if not health & bit]
    if not health & PREARM_CHECK_BIT:
        problems.append("prearm")
    return problems
