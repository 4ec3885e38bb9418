"""PX4 custom_mode encoding and name tables (values from the captures in tests/data/px4_sitl)."""

from __future__ import annotations

import pytest

from vtube_fleet.link import px4


@pytest.mark.parametrize(
    "custom_mode, main, sub, flight_mode, px4_name",
    [
        (50593792, 4, 3, "HOLD", "AUTO.LOITER"),  # boot mode
        (393216, 6, 0, "OFFBOARD", "OFFBOARD"),
        (196608, 3, 0, "POSCTL", "POSCTL"),  # offboard-loss failsafe
        (px4.encode_custom_mode(4, 6), 4, 6, "LAND", "AUTO.LAND"),
        (px4.encode_custom_mode(4, 2), 4, 2, "TAKEOFF", "AUTO.TAKEOFF"),
        (px4.encode_custom_mode(4, 5), 4, 5, "RETURN_TO_LAUNCH", "AUTO.RTL"),
    ],
)
def test_captured_modes(custom_mode: int, main: int, sub: int, flight_mode: str,
                        px4_name: str) -> None:
    assert px4.decode_custom_mode(custom_mode) == (main, sub)
    assert px4.encode_custom_mode(main, sub) == custom_mode
    assert px4.flight_mode_name(custom_mode) == flight_mode
    assert px4.px4_mode_name(custom_mode) == px4_name
    assert px4.mode_for_flight_mode(flight_mode) == (main, sub)
    assert px4.mode_for_flight_mode(px4_name) == (main, sub)


def test_all_flight_modes_round_trip() -> None:
    for name, (main, sub) in px4.FLIGHT_MODES.items():
        assert px4.flight_mode_name(px4.encode_custom_mode(main, sub)) == name


def test_unknown_modes_are_named_not_raised() -> None:
    assert px4.px4_mode_name(px4.encode_custom_mode(42, 7)) == "MODE(main=42, sub=7)"
    assert px4.flight_mode_name(px4.encode_custom_mode(4, 77)) == "AUTO.SUB77"
    assert px4.flight_mode_name(px4.encode_custom_mode(3, 1)) == "POSCTL"  # orbit
    assert px4.px4_mode_name(px4.encode_custom_mode(3, 1)) == "POSCTL.ORBIT"
    with pytest.raises(ValueError, match="unknown PX4 flight mode 'WARP'"):
        px4.mode_for_flight_mode("WARP")


def test_result_and_state_names() -> None:
    assert px4.result_name(0) == "ACCEPTED"
    assert px4.result_name(1) == "TEMPORARILY_REJECTED"
    assert px4.result_name(3) == "UNSUPPORTED"
    assert px4.result_name(99) == "MAV_RESULT(99)"
    assert [px4.landed_state_name(i) for i in range(5)] == [
        "UNKNOWN", "ON_GROUND", "IN_AIR", "TAKING_OFF", "LANDING"
    ]
    assert px4.system_status_name(0) == "UNINIT"
    assert px4.system_status_name(5) == "CRITICAL"


def test_health_bits_from_captures() -> None:
    # SYS_STATUS.onboard_control_sensors_health seen in offboard_flight_i0
    assert px4.health_problems(0x320883F) == ["prearm"]  # t=2.0 s: pre-arm checks failing
    assert px4.health_problems(0x1320C83F) == []  # t=4.0 s: ready
    assert px4.health_problems(0x1000_0000) == ["gyro", "accel", "mag", "gps"]
